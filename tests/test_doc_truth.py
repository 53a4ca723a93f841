"""What the pages say a run does is what a run does (issue 92).

- The tags a page lists for a default run are the tags a default tiny run logs, and those it lists under `--diagnostics`
  are what that flag adds: `sac.py`, `pebble.py` and `r2n_pebble.py`, each page with the pages it inherits from.
- The checkpoint's keys each page names, and `state.pt`'s keys in docs/running.md, are the files' keys.
- The console lines docs/running.md shows are lines of the logs it cites, and a tiny run prints lines of their shape.
- docs/layout.md names every module of `r2n_harness` with what the scripts take from it, and its code block names
  exactly what `pebble.py`'s main block uses of the harness (every other script's, a part of it); every method flag
  (above `# Run settings`) is read by the script's own code, none by the harness alone.
- docs/testing.md has a row for every test file.

A page's tags are the first column of each table headed `tag` in its section "Explanation of the logged metrics": those
above a `### ... --diagnostics` heading are the default run's, those under it what `--diagnostics` adds. A row that
says "Meta-World only" may be missing from a cartpole run. `{net}` in a tag stands for each name the page gives after
"`net` in" (in the row, else in the section). One test per script runs its two tiny runs, so that pytest-xdist never
runs them twice."""
import ast
import glob
import os
import re
import sys
from concurrent.futures import ThreadPoolExecutor

import pytest
import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from test_scripts import DEVICE, ROOT, SPARSE_TINY, TINY, run_script, scalars  # noqa: E402

CODE = re.compile(r"`([^`]+)`")
SHORT = ["--total-timesteps", "800", "--eval-freq", "400"]  # a feedback round at 500, evaluations at 400 and 800
SAC_TINY = ["--env-id", "cartpole-swingup", "--noise", "0.9", "--learning-starts", "200", "--episode-length", "100",
            "--eval-episodes", "2", "--hidden-dim", "32", "--batch-size", "32", "--log-freq", "100", DEVICE, *SHORT]
ARGS = {"sac.py": SAC_TINY, "pebble.py": TINY + SHORT, "r2n_pebble.py": TINY + SPARSE_TINY + SHORT}
PAGES = {"sac.py": ["sac.md"], "pebble.py": ["sac.md", "pebble.md"],  # a page with the pages it says it adds to
         "r2n_pebble.py": ["sac.md", "pebble.md", "r2n_pebble.md"]}
# `--diagnostics`, with `--resumable --keep-state`, which add no tag: the same run gives `state.pt` and the console
DIAGNOSTICS = ["--diagnostics", "--resumable", "--keep-state"]


def page(name):
    with open(os.path.join(ROOT, "docs", name), encoding="utf-8") as f:
        return f.read()


def section(text, heading):
    """The text under the heading that starts with `heading` (its `#`s included), to the next heading of its level."""
    level = heading.split(" ")[0]
    lines, fenced, headings = text.split("\n"), False, []
    for i, line in enumerate(lines):  # a `#` in a code block is no heading
        fenced ^= line.startswith("```")
        if not fenced and re.match(r"#+ ", line):
            headings.append(i)
    (start,) = [i for i in headings if lines[i].startswith(heading)]
    end = next((i for i in headings if i > start and len(lines[i].split(" ")[0]) <= len(level)), len(lines))
    return "\n".join(lines[start + 1 : end])


def tables(text, header):
    """The rows (lists of cells) of each Markdown table in `text` whose first header cell is `header`."""
    rows, current = [], None
    for line in text.split("\n"):
        if not line.startswith("|"):
            current = None
            continue
        cells = [cell.strip() for cell in line.strip().strip("|").split("|")]
        if current is None:
            current = cells[0] == header
        elif current and not set(line) <= set("|-: "):
            rows.append(cells)
    return rows


def expand(tag, *contexts):
    """`features/{net}/chance` -> one tag per name the row or its section gives after "`net` in"."""
    match = re.search(r"\{(\w+)\}", tag)
    if not match:
        return [tag]
    for context in contexts:
        names = re.search(rf"`{match.group(1)}`\s+in\s+((?:`[^`]+`(?:,?\s+(?:and\s+)?)?)+)", context)
        if names:
            return [each for name in CODE.findall(names.group(1))
                    for each in expand(tag.replace(match.group(0), name, 1), *contexts)]
    raise AssertionError(f"{tag}: the page does not say what {match.group(0)} stands for")


def listed_tags(name, text=None):
    """{"default": (required, allowed), "diagnostics": (required, allowed)}: the tags page `name` (or `text`) lists."""
    metrics = section(page(name) if text is None else text, "## Explanation of the logged metrics")
    parts = re.split(r"\n###[^\n]*--diagnostics[^\n]*\n", metrics)
    assert len(parts) <= 2, f"{name}: one `### ... --diagnostics` subsection at most"
    listed = {}
    for kind, text in zip(("default", "diagnostics"), parts + [""]):
        required, allowed = set(), set()
        for row in tables(text, "tag"):
            tags = [each for tag in CODE.findall(row[0]) for each in expand(tag, " | ".join(row), metrics)]
            allowed.update(tags)
            if not any("Meta-World only" in cell for cell in row):
                required.update(tags)
        listed[kind] = required, allowed
    return listed


def checkpoint_keys(name):
    """The keys page `name` says the checkpoint holds (or adds to its parent's), with whether it says "holds"."""
    found = re.findall(r"checkpoint\s+`\w+\.cleanrl_model`\s+(holds|adds)\s+([^.:]*)", page(name))
    assert len(found) == 1, f"{name}: one sentence 'The checkpoint `X.cleanrl_model` holds/adds ...', found {found}"
    (verb, keys), = found
    return verb == "holds", set(CODE.findall(keys))


def tag_problems(script, kind, logged):
    """Where the tags of `script`'s `kind` run and its pages differ, one line each."""
    required, allowed = set(), set()
    for name in PAGES[script]:
        listed = listed_tags(name)
        for each in ("default", "diagnostics") if kind == "diagnostics" else ("default",):
            required |= listed[each][0]
            allowed |= listed[each][1]
    pages = " + ".join(PAGES[script])
    lists, do = ("lists", "does") if len(PAGES[script]) == 1 else ("list", "do")
    return ([f"{script} {kind}: {pages} {lists} {tag}, the run does not log it" for tag in sorted(required - logged)]
            + [f"{script} {kind}: the run logs {tag}, {pages} {do} not list it" for tag in sorted(logged - allowed)])


def two_runs(script, tmp_path):
    """`script`'s default tiny run and its `DIAGNOSTICS` run, side by side: kind -> (run folder, stdout)."""
    kinds = {"default": [], "diagnostics": DIAGNOSTICS}
    with ThreadPoolExecutor(2) as pool:
        futures = {kind: pool.submit(run_script, script, ARGS[script] + ["--run-name", kind, *extra], tmp_path)
                   for kind, extra in kinds.items()}
        return {kind: (str(tmp_path / "runs" / kind), future.result().stdout) for kind, future in futures.items()}


def console_lines():
    """The lines of docs/running.md's console block, and those of the logs the section cites."""
    text = section(page("running.md"), "### The console")
    (block,) = re.findall(r"```\n(.*?)```", text, re.DOTALL)
    logs = re.findall(r"\]\(\.\./(results/[^)]+\.txt)\)", text)
    assert logs, "the console section cites the logs its lines come from"
    cited = set()
    for log in logs:
        with open(os.path.join(ROOT, log), encoding="utf-8") as f:
            cited.update(f.read().split("\n"))
    return [line for line in block.split("\n") if line], cited


def shape(line):
    """A console line with its numbers, ETA, phase and return left out: what every such line shares."""
    if line.startswith("progress:"):
        fields = line.split(" | ")
        fields[1] = "PHASE"
        line = " | ".join(fields)
        line = re.sub(r"ETA \S+", "ETA T", re.sub(r"eval return \S+$", "eval return R", line))
    return re.sub(r"-?\d+(\.\d+)?", "N", line)


def phase(line):
    return line.split(" | ")[1]


def console_problems(script, stdout):
    """Where the console lines of `script`'s run and docs/running.md's block differ in shape."""
    shown, cited = console_lines()
    problems = [f"running.md shows {line!r}, which no cited log holds" for line in shown if line not in cited]
    printed = [line for line in stdout.split("\n") if line.startswith(("progress:", "step="))]
    assert any(line.startswith("progress:") for line in printed), f"{script}: no progress line"
    shapes = {shape(line) for line in shown}
    problems += [f"{script} prints {line!r}, unlike every line running.md shows" for line in printed
                 if shape(line) not in shapes]
    phases = {phase(line) for line in printed if line.startswith("progress:")}
    own = {phase(line) for line in shown if line.startswith("progress:") and shape(line) in {shape(p) for p in printed}}
    if phases != own:
        problems.append(f"{script} prints the phases {sorted(phases)}, running.md shows {sorted(own)} for its lines")
    return problems


def check_script(script, tmp_path):
    """Every difference between `script`'s two tiny runs and its pages, one line each (a page that cannot be read as
    this module's docstring says is one line too)."""
    runs = two_runs(script, tmp_path)

    def tags():
        return [line for kind, (folder, _) in runs.items() for line in tag_problems(script, kind, set(scalars(folder)))]

    def checkpoint():
        expected = set()
        for name in PAGES[script]:
            holds, keys = checkpoint_keys(name)
            assert holds == (name == PAGES[script][0]), f"{name}: its checkpoint sentence says 'holds' on sac.md only"
            expected |= keys
        saved = torch.load(os.path.join(runs["default"][0], f"{script[:-3]}.cleanrl_model"), weights_only=False)
        return [] if set(saved) == expected else [
            f"{script}'s checkpoint holds {sorted(saved)}, {' + '.join(PAGES[script])} say {sorted(expected)}"]

    def state():
        saved = torch.load(os.path.join(runs["diagnostics"][0], "state.pt"), weights_only=False)
        keys = {key for row in tables(section(page("running.md"), "## Resuming a run"), "key")
                for key in CODE.findall(row[0])}
        return [] if set(saved) == keys else [
            f"{script}'s state.pt holds {sorted(saved)}, running.md's table {sorted(keys)}"]

    def console():
        return console_problems(script, runs["diagnostics"][1])

    problems = []
    for part in (tags, checkpoint, state, console):
        try:
            problems += part()
        except (AssertionError, ValueError) as e:  # a page that cannot be read so
            problems.append(f"{part.__name__}: {type(e).__name__}: {e}")
    assert not problems, "\n".join(problems)


def test_the_sac_page_lists_what_a_run_logs_and_saves(tmp_path):
    check_script("sac.py", tmp_path)


def test_the_pebble_page_lists_what_a_run_logs_and_saves(tmp_path):
    check_script("pebble.py", tmp_path)


def test_the_r2n_pebble_page_lists_what_a_run_logs_and_saves(tmp_path):
    check_script("r2n_pebble.py", tmp_path)


def test_tag_tables_are_read_as_the_pages_mean_them():
    """The parsing on a page written for it: placeholders from the row or the section, optional rows, the split."""
    text = "\n".join([
        "## Explanation of the logged metrics", "", "For `net` in `actor`, `qf1` and `qf2`:", "",
        "| tag | when | what |", "|---|---|---|",
        "| `eval/episodic_return` | at every evaluation | the return |",
        "| `eval/success_rate` | Meta-World only | successes |",
        "| `sparse/{net}/degree`, `sparse/{net}/frac` | at every evaluation | for each `net` |", "",
        "### With `--diagnostics`", "",
        "| tag | when | what |", "|---|---|---|",
        "| `features/reward{e}/chance` | at every evaluation | for `e` in `0`, `1`, `2` |", "",
        "## Implementation details", "", "| tag | x |", "|---|---|", "| `not/a_tag` | x |",
    ])
    listed = listed_tags("example.md", text)
    nets = {f"sparse/{net}/{m}" for net in ("actor", "qf1", "qf2") for m in ("degree", "frac")}
    assert listed["default"] == ({"eval/episodic_return"} | nets, {"eval/episodic_return", "eval/success_rate"} | nets)
    members = {f"features/reward{e}/chance" for e in range(3)}
    assert listed["diagnostics"] == (members, members)
    assert shape("progress: step 5000/50000 (10%) | pre-training | 10 SPS | ETA 1h14m | feedback 0/1600 | "
                 "eval return 184.2") == shape("progress: step 0/800 (0%) | PbRL | 0 SPS | ETA ? | feedback 5/20 | "
                                               "eval return -")
    assert shape("step=400 eval_return=-1.50 SPS=90 eval_seconds=0.13") != shape(
        "step=400 eval_return=1.50 SPS=90 eval_seconds=0.13 feedback=5/20 labels=5")


def main_block(script):
    with open(os.path.join(ROOT, script), encoding="utf-8") as f:
        tree = ast.parse(f.read())
    (main,) = [node for node in tree.body if isinstance(node, ast.If) and "__main__" in ast.unparse(node.test)]
    return main


def harness_uses(script):
    """What `script`'s main block uses of the harness: `run.X` attributes, `harness("m")` modules, `harness("m").X`."""
    used = set()
    for node in ast.walk(main_block(script)):
        if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id == "run":
            used.add(f"run.{node.attr}")
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "harness":
            used.add(f'harness("{node.args[0].value}")')
        if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Call) \
                and getattr(node.value.func, "id", None) == "harness":
            used.add(f'harness("{node.value.args[0].value}").{node.attr}')
    return used


def layout_uses():
    """What docs/layout.md's code block says the main block uses of the harness, in the same three forms."""
    text = section(page("layout.md"), "## The run harness's package")
    (block,) = re.findall(r"```python\n(.*?)```", text, re.DOTALL)
    return (set(re.findall(r"\brun\.\w+", block)) | set(re.findall(r'harness\("\w+"\)(?:\.\w+)?', block))
            | set(re.findall(r'harness\("\w+"\)', block)))


SCRIPTS = ["sac.py", "anf_sac.py", "pebble.py", "r2n_pebble.py", "set_pebble.py", "static_pebble.py", "l1_pebble.py",
           "dropconnect_pebble.py", "surf.py", "r2n_surf.py", "rune.py", "r2n_rune.py"]


def test_layout_names_exactly_what_the_main_block_uses_of_the_harness():
    listed, used = layout_uses(), harness_uses("pebble.py")
    assert listed == used, (f"pebble.py's main block uses {sorted(used - listed)} that layout.md's block leaves out; "
                            f"layout.md names {sorted(listed - used)} that it does not use")
    beyond = {script: sorted(harness_uses(script) - listed) for script in SCRIPTS}
    assert not any(beyond.values()), f"main blocks that use what layout.md does not name: {beyond}"


def test_layouts_harness_table_names_every_module_and_what_the_scripts_take_from_it():
    import importlib

    rows = tables(section(page("layout.md"), "## The run harness's package"), "module")
    modules = {CODE.findall(row[0])[0]: row for row in rows}
    files = {os.path.basename(path) for path in glob.glob(os.path.join(ROOT, "r2n_harness", "*.py"))} - {"__init__.py"}
    assert set(modules) == files, f"layout.md's table names {sorted(modules)}, r2n_harness holds {sorted(files)}"
    problems = []
    for file, row in modules.items():
        module = importlib.import_module(f"r2n_harness.{file[:-3]}")
        named = {name for name in CODE.findall(row[-1]) if re.fullmatch(r"[A-Za-z_]\w*", name)}
        problems += [f"layout.md: {file} holds no {name}" for name in sorted(named) if not hasattr(module, name)]
        taken = {use.split(".")[-1] for script in SCRIPTS for use in harness_uses(script)
                 if use.startswith(f'harness("{file[:-3]}").')}
        problems += [f"layout.md: the row of {file} leaves out {name}, which a main block uses"
                     for name in sorted(taken - named)]
    assert not problems, "\n".join(problems)


def test_testing_md_has_a_row_for_every_test_file():
    rows = tables(section(page("testing.md"), "## What the suite covers"), "file")
    listed = {name for row in rows for name in CODE.findall(row[0])}
    files = {f"tests/{os.path.basename(path)}" for path in glob.glob(os.path.join(ROOT, "tests", "test_*.py"))}
    assert files <= listed, f"testing.md has no row for {sorted(files - listed)}"
    assert listed <= files, f"testing.md has rows for files that do not exist: {sorted(listed - files)}"


@pytest.mark.parametrize("script", SCRIPTS)
def test_every_method_flag_is_read_by_the_method(script):
    """layout.md: the method's flags come first in `Args` (a patch's own last, after `# X arguments`), each read by
    the script's own code (outside `Args` and `validate_args`), so that none is there for the harness alone; the run's
    flags follow `# Run settings`."""
    with open(os.path.join(ROOT, script), encoding="utf-8") as f:
        source = f.read()
    tree = ast.parse(source)
    (args,) = [node for node in tree.body if isinstance(node, ast.ClassDef) and node.name == "Args"]
    lines = source.split("\n")
    (settings,) = [i + 1 for i, line in enumerate(lines) if line.strip().startswith("# Run settings")]
    # a patch's own flags come last, under a comment of their own: `# ANF arguments`, `# L1 arguments`, ...
    patch = next((i + 1 for i in range(settings, args.end_lineno) if re.match(r"\s*# \S+ arguments", lines[i])),
                 args.end_lineno + 1)
    method = [node.target.id for node in args.body if isinstance(node, ast.AnnAssign)
              and not settings < node.lineno < patch]
    assert method and settings < args.end_lineno, f"{script}: `# Run settings` inside Args, after the method's flags"
    read = set()
    for node in tree.body:
        if node is args or getattr(node, "name", None) == "validate_args":
            continue
        for each in ast.walk(node):
            if isinstance(each, ast.Attribute):
                read.add(each.attr)
            elif isinstance(each, ast.Constant) and isinstance(each.value, str):
                read.add(each.value)
    unread = [name for name in method if name not in read]
    assert not unread, f"{script}: method flags that only validate_args or the harness read: {unread}"
