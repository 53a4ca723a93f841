"""The layout of issues 18 and 68: every script reads algorithm first, and what it needs to run is one short block, the
same everywhere; the run harness is the package `r2n_harness`, which only its flags import.

The `# RUN:` block (from that comment line to `if __name__ == "__main__":`) is byte-identical in the ten PbRL scripts;
sac.py and anf_sac.py keep a subset of its top-level definitions, in the same order, each byte-identical but
`log_evaluation` (no feedback counts). A fix to the block is made in pebble.py and copied; this test fails until every
copy is the same.
"""
import ast
import os
import re

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PBRL = ["pebble.py", "r2n_pebble.py", "set_pebble.py", "static_pebble.py", "l1_pebble.py", "dropconnect_pebble.py",
        "surf.py", "r2n_surf.py", "rune.py", "r2n_rune.py"]
ORACLES = ["sac.py", "anf_sac.py"]


def lines(script):
    with open(os.path.join(ROOT, script)) as f:
        return f.read().split("\n")


RUN = "# RUN:"  # the block's first line starts so


def plumbing(script):
    """The script's `# RUN:` block, as text."""
    text = lines(script)
    starts = [i for i, line in enumerate(text) if line.startswith(RUN)]
    main = [i for i, line in enumerate(text) if line.startswith("if __name__")]
    assert len(starts) == 1 and len(main) == 1 and starts[0] < main[0], f"{script}: one RUN block before main"
    return "\n".join(text[starts[0] : main[0]])


def definitions(source):
    """(name, source) of each top-level statement; assignments are named by their target."""
    tree = ast.parse(source)
    named = []
    for node in tree.body:
        name = getattr(node, "name", None) or ast.unparse(node.targets[0] if isinstance(node, ast.Assign) else node)
        named.append((name, ast.get_source_segment(source, node)))
    return named


@pytest.mark.parametrize("script", PBRL[1:])
def test_pbrl_plumbing_is_pebbles_byte_for_byte(script):
    assert plumbing(script) == plumbing("pebble.py"), f"{script}'s RUN block differs from pebble.py's"


@pytest.mark.parametrize("script", ORACLES)
def test_oracle_plumbing_is_a_subset_of_pebbles(script):
    reference = definitions(plumbing("pebble.py"))
    order = [name for name, _ in reference]
    own = definitions(plumbing(script))
    changed = [name for name, source in own if (name, source) not in reference and name != "log_evaluation"]
    assert not changed, f"{script}: plumbing definitions that are not pebble.py's, byte for byte: {changed}"
    positions = [order.index(name) for name, _ in own]
    assert positions == sorted(positions), f"{script}: plumbing definitions in another order than pebble.py's"
    assert len(own) < len(reference)


@pytest.mark.parametrize("script", PBRL + ORACLES)
def test_no_global_and_algorithm_first(script):
    text = lines(script)
    assert not [line for line in text if re.match(r"\s*global\s", line)], f"{script} uses `global`"
    order = [next(i for i, line in enumerate(text) if line.startswith(start))
             for start in ("class Args", "# ALGO LOGIC", RUN, "if __name__")]
    assert order == sorted(order), f"{script}: expected Args, ALGO LOGIC, RUN, then the main block"


def test_pebble_reads_algorithm_first():
    text = lines("pebble.py")
    first_network = next(i + 1 for i, line in enumerate(text) if re.match(r"class \w+\(nn\.Module\)", line))
    assert first_network < 200


def plumbing_calls(source: str) -> list:
    """(definition, name) for each name that a top-level definition between the first `# ALGO LOGIC` line and the
    `# RUN:` line uses (as a name or a string annotation) and that the `# RUN:` block defines."""
    text = source.split("\n")
    algo = next(i for i, line in enumerate(text) if line.startswith("# ALGO LOGIC")) + 1
    plumbing_start = next(i for i, line in enumerate(text) if line.startswith(RUN)) + 1
    main = next(i for i, line in enumerate(text) if line.startswith("if __name__")) + 1
    tree = ast.parse(source)
    defined = set()
    for node in tree.body:
        if plumbing_start <= node.lineno < main:
            targets = node.targets if isinstance(node, ast.Assign) else [node]
            defined |= {getattr(target, "name", None) or getattr(target, "id", None) for target in targets}
    calls = []
    for node in tree.body:
        if algo <= node.lineno < plumbing_start:
            used = {n.id for n in ast.walk(node) if isinstance(n, ast.Name)}
            used |= {n.value for n in ast.walk(node) if isinstance(n, ast.Constant) and isinstance(n.value, str)}
            calls += [(getattr(node, "name", node.lineno), name) for name in sorted(used & defined)]
    return calls


@pytest.mark.parametrize("script", PBRL + ORACLES)
def test_the_method_never_calls_the_plumbing(script):
    """Issue 42's seam: the method can be lifted out of its file without the `# RUN:` block."""
    with open(os.path.join(ROOT, script)) as f:
        assert plumbing_calls(f.read()) == [], f"{script}: the method uses the plumbing"


def test_the_seam_check_sees_a_plumbing_call_in_the_method():
    with open(os.path.join(ROOT, "pebble.py")) as f:
        source = f.read()
    back = "    rb.relabel(reward_model.mean_reward, args.relabel_batch_size)\n    return trained\n"
    assert source.count(back) == 1
    broken = source.replace(back, "    check_finite(trained, 0)\n" + back)
    assert plumbing_calls(broken) == [("feedback_round", "check_finite")]


@pytest.mark.parametrize("script", PBRL + ORACLES)
def test_no_line_over_100_characters(script):
    long = [i + 1 for i, line in enumerate(lines(script)) if len(line) > 100]
    assert not long, f"{script}: lines over 100 characters: {long[:10]}"


@pytest.mark.parametrize("script", PBRL + ORACLES)
def test_the_header_is_at_most_15_lines_and_points_home(script):
    """Everything above the first import (the pointer home, the docstring, a patch's comment) fits in 15 lines, and
    the first line names the project and the docs page, so that a copied file still says where it came from."""
    text = lines(script)
    header = next(i for i, line in enumerate(text) if line.startswith(("import ", "from ")))
    assert header <= 15, f"{script}: a header of {header} lines"
    assert text[0].startswith("# Docs: docs/NAME.md in r2n, the R2N paper's reference implementation"), text[0]
    assert os.path.exists(os.path.join(ROOT, "docs", script.replace(".py", ".md")))


def test_the_main_block_stays_short():
    """pebble.py's main block (`if __name__ == "__main__":` to the end) is setup and the loop; what it calls lives
    above it. A method's own main-block lines (R2N's sparse optimisers and connectivity tags, SURF's unlabelled
    buffer) come on top of these 200."""
    text = lines("pebble.py")
    main = next(i for i, line in enumerate(text) if line.startswith("if __name__"))
    assert len(text[main:]) - (text[-1] == "") <= 200


HARNESS_MODULES = {  # the run harness's package: what each module defines, and no script does
    "cuda_graph": ["CudaGraph", "WholeUpdate", "settle_step"],
    "external_teacher": ["ExternalTeacher", "check_labels_unchanged", "labels_problem", "queries_digest"],
    "preferences": ["read_preferences", "load_preferences", "add_preferences"],
    "resume": ["open_state", "state_of", "load_state_", "save_state", "restore_run", "state_due"],
    "query_log": ["QueryLog", "log_queries", "write_npz"],
    "diagnostics": ["log_reward_diagnostics", "input_layers", "relevant_weight_frac", "weight_shares"],
    "run": ["Run", "catch_stop_signals"],  # the progress line is each script's own (a copy prints it)
}


@pytest.mark.parametrize("script", PBRL + ORACLES)
def test_the_harness_lives_in_its_package_and_no_script_defines_it(script):
    """What only a flag needs is defined once, in `r2n_harness`, and reached through `harness(module)` in that flag's
    branch: no script defines it, and no script imports the package at its top."""
    import importlib

    tree = ast.parse(open(os.path.join(ROOT, script)).read())
    defined = {node.name for node in tree.body if isinstance(node, (ast.FunctionDef, ast.ClassDef))}
    for module, names in HARNESS_MODULES.items():
        package = importlib.import_module(f"r2n_harness.{module}")
        assert all(hasattr(package, name) for name in names), module
        assert not defined & set(names), f"{script} defines {defined & set(names)}, which r2n_harness.{module} holds"
    top_imports = [node for node in tree.body if isinstance(node, (ast.Import, ast.ImportFrom))]
    assert not [n for n in top_imports if "r2n_harness" in ast.dump(n)], f"{script} imports r2n_harness at its top"
