"""The layout of issue 18: every script reads algorithm first, and its run plumbing is one block, the same everywhere.

The `# RUN PLUMBING` block (from that comment line to `if __name__ == "__main__":`) is byte-identical in the ten PbRL
scripts; sac.py and anf_sac.py keep a subset of its top-level definitions, each byte-identical and in the same order.
A fix to the plumbing is made in pebble.py and copied; this test fails until every copy is the same.
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


def plumbing(script):
    """The script's `# RUN PLUMBING` block, as text."""
    text = lines(script)
    starts = [i for i, line in enumerate(text) if line.startswith("# RUN PLUMBING")]
    main = [i for i, line in enumerate(text) if line.startswith("if __name__")]
    assert len(starts) == 1 and len(main) == 1 and starts[0] < main[0], f"{script}: one RUN PLUMBING block before main"
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
    assert plumbing(script) == plumbing("pebble.py"), f"{script}'s RUN PLUMBING block differs from pebble.py's"


@pytest.mark.parametrize("script", ORACLES)
def test_oracle_plumbing_is_a_subset_of_pebbles(script):
    reference = definitions(plumbing("pebble.py"))
    order = [name for name, _ in reference]
    own = definitions(plumbing(script))
    changed = [name for name, source in own if (name, source) not in reference]
    assert not changed, f"{script}: plumbing definitions that are not pebble.py's, byte for byte: {changed}"
    positions = [order.index(name) for name, _ in own]
    assert positions == sorted(positions), f"{script}: plumbing definitions in another order than pebble.py's"
    assert len(own) < len(reference)


@pytest.mark.parametrize("script", PBRL + ORACLES)
def test_no_global_and_algorithm_first(script):
    text = lines(script)
    assert not [line for line in text if re.match(r"\s*global\s", line)], f"{script} uses `global`"
    order = [next(i for i, line in enumerate(text) if line.startswith(start))
             for start in ("class Args", "# ALGO LOGIC", "# RUN PLUMBING", "if __name__")]
    assert order == sorted(order), f"{script}: expected Args, ALGO LOGIC, RUN PLUMBING, then the main block"


def test_pebble_reads_algorithm_first():
    text = lines("pebble.py")
    first_network = next(i + 1 for i, line in enumerate(text) if re.match(r"class \w+\(nn\.Module\)", line))
    assert first_network < 300
