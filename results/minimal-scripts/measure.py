"""Issue 68's measures of each script, the way the issue took them: lines; code lines (no blank line, comment or
docstring); the `# RUN:` block; the line of the first `nn.Module`; top-level functions and classes; `Args` fields and
lines; and the lines of each section (`# ALGO LOGIC`, `# FLAGS`, `# RUN`, the main block). Usage, from the repository
root: `python results/minimal-scripts/measure.py [script ...]` (default: all 12), a Markdown table on stdout."""
import ast
import io
import sys
import tokenize

SCRIPTS = ["sac.py", "anf_sac.py", "pebble.py", "r2n_pebble.py", "set_pebble.py", "static_pebble.py", "l1_pebble.py",
           "dropconnect_pebble.py", "surf.py", "r2n_surf.py", "rune.py", "r2n_rune.py"]


def code_lines(source: str, tree: ast.AST) -> int:
    """Lines holding a token other than a comment, with every docstring's lines removed."""
    docstrings = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.FunctionDef, ast.ClassDef, ast.AsyncFunctionDef)) and node.body:
            first = node.body[0]
            if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant) and isinstance(first.value.value, str):
                docstrings.update(range(first.lineno, first.end_lineno + 1))
        if isinstance(node, ast.ClassDef):  # dataclass fields' docstrings (tyro's help)
            for stmt in node.body:
                if isinstance(stmt, ast.Expr) and isinstance(stmt.value, ast.Constant):
                    docstrings.update(range(stmt.lineno, stmt.end_lineno + 1))
    lines = set()
    skip = (tokenize.COMMENT, tokenize.NL, tokenize.NEWLINE, tokenize.INDENT, tokenize.DEDENT, tokenize.ENDMARKER)
    for token in tokenize.generate_tokens(io.StringIO(source).readline):
        if token.type not in skip:
            lines.update(range(token.start[0], token.end[0] + 1))
    return len(lines - docstrings)


def measure(path: str) -> dict:
    source = open(path).read()
    text, tree = source.split("\n"), ast.parse(source)
    n = len(text) - (text[-1] == "")
    main = next(i for i, line in enumerate(text) if line.startswith("if __name__")) + 1
    run = next((i for i, line in enumerate(text) if line.startswith("# RUN:")), None)
    flags = next((i for i, line in enumerate(text) if line.startswith("# FLAGS")), None)
    algo = next(i for i, line in enumerate(text) if line.startswith("# ALGO LOGIC"))
    settings = next(i for i, line in enumerate(text) if line.strip().startswith("# Run settings"))
    modules = [node.lineno for node in tree.body if isinstance(node, ast.ClassDef)
               and any(ast.unparse(base) == "nn.Module" for base in node.bases)]
    args = next(node for node in tree.body if isinstance(node, ast.ClassDef) and node.name == "Args")
    return {
        "lines": n, "code lines": code_lines(source, tree),
        "header and imports": next(i for i, line in enumerate(text) if line.startswith("@dataclass")),
        "`Args`: the method's flags": settings - next(i for i, line in enumerate(text) if line.startswith("class Args")),
        "`# ALGO LOGIC` sections": (flags or run or main - 1) - algo,
        "`# FLAGS` block": None if flags is None else (run or main - 1) - flags,
        "`# RUN:` block": None if run is None else main - 1 - run,
        "main block": n - main + 1,
        "first `nn.Module`": min(modules),
        "top-level functions / classes": "{} / {}".format(
            sum(isinstance(node, ast.FunctionDef) for node in tree.body),
            sum(isinstance(node, ast.ClassDef) for node in tree.body)),
        "`Args` fields, lines": "{}, {}".format(
            sum(isinstance(node, ast.AnnAssign) for node in args.body), args.end_lineno - args.lineno + 2),
    }


if __name__ == "__main__":
    scripts = sys.argv[1:] or SCRIPTS
    measures = {script: measure(script) for script in scripts}
    rows = list(next(iter(measures.values())))
    print("| | " + " | ".join(f"`{s}`" for s in scripts) + " |")
    print("|---|" + "---|" * len(scripts))
    for row in rows:
        print(f"| {row} | " + " | ".join("–" if m[row] is None else str(m[row]) for m in measures.values()) + " |")
