"""The documentation's links resolve: every relative link and every `#anchor` in README.md, docs/*.md and
results/**/*.md points at a file or folder that exists, and at a heading or `<a id>` that exists in that file.

Anchors follow GitHub's rule for headings: the heading's text as rendered (code, links and emphasis reduced to their
text), lowercased, every character that is not a letter, digit, space, hyphen or underscore removed, each space
turned into a hyphen; a slug seen before in the same file gets -1, -2, ... Explicit `<a id="...">` and
`<a name="...">` anchors count too. External links (http, https, mailto) are not checked."""
import glob
import os
import re
import subprocess
from urllib.parse import unquote

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

FENCE = re.compile(r"^ {0,3}(`{3,}|~{3,})")
CODE_SPAN = re.compile(r"(`+)(.+?)\1")
INLINE_LINK = re.compile(r"!?\[((?:[^\[\]]|\[[^\]]*\])*)\]\(\s*(<[^>]*>|[^)\s]+)(?:\s+(?:\"[^\"]*\"|'[^']*'))?\s*\)")
REFERENCE_DEFINITION = re.compile(r"^ {0,3}\[[^\]]+\]:\s*(<[^>]*>|\S+)")
HTML_LINK = re.compile(r"<(?:a|img)\b[^>]*?\b(?:href|src)\s*=\s*[\"']([^\"']*)[\"']", re.IGNORECASE)
HTML_ANCHOR = re.compile(r"<a\b[^>]*?\b(?:id|name)\s*=\s*[\"']([^\"']+)[\"']", re.IGNORECASE)
ATX_HEADING = re.compile(r"^ {0,3}#{1,6}(?:\s+(.*?))?(?:\s+#+)?\s*$")
SETEXT_UNDERLINE = re.compile(r"^ {0,3}(=+|-+)\s*$")
EXTERNAL = re.compile(r"^[a-z][a-z0-9+.-]*:", re.IGNORECASE)  # http:, https:, mailto:, ...


def prose_lines(text: str):
    """(line number, line) of the lines outside fenced code blocks."""
    fence = None
    for number, line in enumerate(text.split("\n"), 1):
        match = FENCE.match(line)
        if fence is None and match:
            fence = match.group(1)
        elif fence is not None and match and match.group(1)[0] == fence[0] and len(match.group(1)) >= len(fence) \
                and not line.strip().strip(fence[0]):
            fence = None
        elif fence is None:
            yield number, line


def heading_text(markdown: str) -> str:
    """A heading's text as GitHub renders it: code spans, links, images and HTML tags reduced to their text."""
    text = CODE_SPAN.sub(lambda m: m.group(2).strip(), markdown)
    text = INLINE_LINK.sub(lambda m: m.group(1), text)
    return re.sub(r"<[^>]+>", "", text)


def github_slug(text: str) -> str:
    """GitHub's anchor for a heading's rendered text (before duplicates get their -1, -2 suffix)."""
    return re.sub(r"[^\w\- ]", "", text.strip().lower()).replace(" ", "-")


def anchors(text: str) -> set:
    """Every anchor of a Markdown file: its headings' slugs (with GitHub's suffixes for repeats) and its explicit
    `<a id>` / `<a name>` anchors."""
    found, seen, previous = set(), {}, None
    for _, line in prose_lines(text):
        found.update(HTML_ANCHOR.findall(line))
        atx = ATX_HEADING.match(line)
        if atx or (previous and previous.strip() and SETEXT_UNDERLINE.match(line)
                   and not ATX_HEADING.match(previous) and not previous.lstrip().startswith(("|", "-", "*", ">"))):
            slug = github_slug(heading_text(atx.group(1) or "" if atx else previous))
            count = seen.get(slug, 0)
            seen[slug] = count + 1
            found.add(slug if count == 0 else f"{slug}-{count}")
        previous = line
    return found


def links(text: str):
    """(line number, target) of every link and image outside code: inline, reference definitions, HTML href/src."""
    for number, line in prose_lines(text):
        line = CODE_SPAN.sub("", line)
        for match in INLINE_LINK.finditer(line):
            yield number, match.group(2).strip("<>")
        match = REFERENCE_DEFINITION.match(line)
        if match:
            yield number, match.group(1).strip("<>")
        for target in HTML_LINK.findall(line):
            yield number, target


def problems(root: str, files: list) -> list:
    """One line per link of `files` (paths relative to `root`) that does not resolve: a missing file or folder, or an
    anchor that the target Markdown file does not have."""
    found, cache = [], {}

    def anchors_of(path):
        if path not in cache:
            with open(path, encoding="utf-8") as f:
                cache[path] = anchors(f.read())
        return cache[path]

    for name in files:
        source = os.path.join(root, name)
        with open(source, encoding="utf-8") as f:
            text = f.read()
        for number, target in links(text):
            if not target or EXTERNAL.match(target):
                continue
            path, _, anchor = target.partition("#")
            path = unquote(path.split("?")[0])
            if path.startswith("/"):  # GitHub resolves a leading / from the repository's root
                resolved = os.path.join(root, path.lstrip("/"))
            else:
                resolved = os.path.join(os.path.dirname(source), path) if path else source
            resolved = os.path.normpath(resolved)
            where = f"{name}:{number}: {target}"
            if not os.path.exists(resolved):
                found.append(f"{where}: no such file or folder {os.path.relpath(resolved, root)}")
            elif anchor and resolved.endswith(".md") and unquote(anchor) not in anchors_of(resolved):
                found.append(f"{where}: {os.path.relpath(resolved, root)} has no anchor #{anchor}")
    return found


def documentation_files(root: str) -> list:
    names = ["README.md"] + sorted(glob.glob("docs/*.md", root_dir=root))
    return names + sorted(glob.glob("results/**/*.md", root_dir=root, recursive=True))


def test_every_relative_link_and_anchor_of_the_docs_resolves():
    files = documentation_files(ROOT)
    assert "README.md" in files and any(name.startswith("docs/") for name in files), files
    assert sum(1 for name in files for _ in links(open(os.path.join(ROOT, name), encoding="utf-8").read())) > 100
    found = problems(ROOT, files)
    assert not found, "links that do not resolve:\n" + "\n".join(found)


def test_github_slugs():
    text = "\n".join([
        "# R2N: robust-to-noise preference-based RL, one file per algorithm",
        "## `r2n_surf.py`, `r2n_rune.py`",
        "## Reproducing the paper's main table",
        "## Two noisy environments: noise redrawn or stored",
        "### Cheetah study: results",
        "## Results", "## Results", "## Results",
        "## [`ene.py`](../ene.py) and its `NoiseSampler`",
        "## SAC's critic: $y = r + \\gamma$ (**soft**)",
        "Setext heading, with a comma",
        "----------------------------",
        "```bash", "# not a heading: a comment in code", "```",
        'Text with <a id="explicit-anchor"></a> an anchor, and <a name="named"></a> another.',
    ])
    assert anchors(text) == {
        "r2n-robust-to-noise-preference-based-rl-one-file-per-algorithm", "r2n_surfpy-r2n_runepy",
        "reproducing-the-papers-main-table", "two-noisy-environments-noise-redrawn-or-stored",
        "cheetah-study-results", "results", "results-1", "results-2", "enepy-and-its-noisesampler",
        "sacs-critic-y--r--gamma-soft", "setext-heading-with-a-comma", "explicit-anchor", "named",
    }


def test_a_broken_link_or_anchor_is_found(tmp_path):
    (tmp_path / "docs").mkdir()
    (tmp_path / "results" / "study").mkdir(parents=True)
    (tmp_path / "docs" / "page.md").write_text("# Page\n\n## A section\n\ntext\n")
    (tmp_path / "results" / "study" / "README.md").write_text(
        "# Study\n\n[up](../../README.md#the-landing-page) [page](../../docs/page.md#a-section)\n")
    (tmp_path / "README.md").write_text("\n".join([
        "# The landing page",
        "[fine](docs/page.md) [fine too](docs/page.md#a-section) [here](#the-landing-page) [folder](results/study/)",
        "[external](https://example.com/nothing#here) [mail](mailto:someone@example.com)",
        "`[in code](missing.md)`",
        "```", "[in a code block](missing.md)", "```",
        "[missing file](docs/missing.md) ![missing image](docs/missing.png)",
        "[missing anchor](docs/page.md#no-such-section) [missing here](#nowhere)",
        '<img src="docs/missing.svg"> [ref]: docs/missing-ref.md',
        "[ref]: docs/also-missing.md",
    ]))
    found = problems(str(tmp_path), documentation_files(str(tmp_path)))
    assert found == [
        "README.md:8: docs/missing.md: no such file or folder docs/missing.md",
        "README.md:8: docs/missing.png: no such file or folder docs/missing.png",
        "README.md:9: docs/page.md#no-such-section: docs/page.md has no anchor #no-such-section",
        "README.md:9: #nowhere: README.md has no anchor #nowhere",
        "README.md:10: docs/missing.svg: no such file or folder docs/missing.svg",
        "README.md:11: docs/also-missing.md: no such file or folder docs/also-missing.md",
    ]


def changed_lines(a: str, b: str) -> int:
    """`diff -u A B | grep -E '^[+-]' | grep -vE '^(\\+\\+\\+|---) ' | wc -l`, the count the docs pages give."""
    lines = subprocess.run(["diff", "-u", a, b], cwd=ROOT, capture_output=True, text=True).stdout.splitlines()
    return sum(1 for line in lines if line[:1] in "+-" and not line.startswith(("+++ ", "--- ")))


def test_the_diff_sizes_the_docs_give_are_the_files():
    """Each docs page's "N changed lines" for its ablation (the `diff A B` block above it, or a `diff A B` in the same
    sentence) is what the files give today."""
    claims = []
    for page in sorted(glob.glob(os.path.join(ROOT, "docs", "*.md"))):
        text = open(page).read()
        for match in re.finditer(r"```bash\ndiff (\S+\.py) (\S+\.py)\n```\n\n(?:[^\n]*?)(\d+) changed lines", text):
            claims.append((page, match.group(1), match.group(2), int(match.group(3))))
        for match in re.finditer(r"`diff (\S+\.py) (\S+\.py)`[^.]*?\((\d+) changed lines", text):
            claims.append((page, match.group(1), match.group(2), int(match.group(3))))
    assert len(claims) >= 12, claims
    wrong = [(os.path.basename(page), a, b, n, changed_lines(a, b)) for page, a, b, n in claims if changed_lines(a, b) != n]
    assert not wrong, wrong
