"""What a session of the surf-rune study runs (PROTOCOL.md, its additions): `continue.sh` asks it.

    python results/surf-rune/schedule.py [RUNS [SCRATCH]]   # the launcher's arguments, or nothing when no run can go

RUNS is the committed runs' folder, SCRATCH the worktree's `logs/scratch`, where a run cut off by a session's end
keeps its `state.pt` while the machine keeps it. A session (180 minutes) first goes on with the family whose run is
in progress there: its state lives on this machine only, and a new machine starts it over whole. Else it runs the
family whose share of runs in is the smaller (SURF's on a tie). Every run takes one torch thread, two at a time, at
most two pairs a plan; the watcher starts the next plan when one is in. In each family, the runs go in the preset's
order (the protocol's), minus those in: the launcher goes seed by seed, and the methods are named in the preset's
order, so that a seed's first arm, which a session's end may have cut off, goes before its second.
"""
import glob
import os
import sys

STUDY = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, STUDY)
import power  # noqa: E402 (this study's: the arms)

sys.path.insert(0, power.ROOT)
import benchmark  # noqa: E402 (the repository's: the preset)

FAMILIES = {"surf": (power.SURF, power.R2N_SURF, power.AGENT), "rune": (power.RUNE, power.R2N_RUNE)}
THREADS, WORKERS, MOST = 1, 2, 4  # one thread a run (the protocol's Design), two at a time, two pairs a plan
# family -> why none of its runs can start; none since the addition of 2026-12-07
BLOCKED = {}


def left(runs: str) -> dict:
    """family -> the preset's runs of that family not yet in `runs`, in the preset's order; and all it plans."""
    runs_planned, out = benchmark.expand(benchmark.Args(preset="surf-rune")), {}
    for family, arms in FAMILIES.items():
        planned = [run for run in runs_planned if run.method in arms]
        out[family] = ([run for run in planned if not os.path.exists(os.path.join(runs, run.run_id, "done"))],
                       planned)
    return out


def in_progress(scratch: str) -> set:
    """The run ids with a `state.pt` in the launcher's scratch folder."""
    return {path.split(os.sep)[-2] for path in glob.glob(os.path.join(scratch, "*", "runs", "*", "state.pt"))}


def first_grid(rest: list, done: set) -> list:
    """The longest head of `rest`, at most MOST runs, that the launcher's methods x seeds grid covers exactly: the
    grid's runs are that head or runs already in, so that no run outside the head (nor outside the preset) starts."""
    for size in range(min(MOST, len(rest)), 0, -1):
        head = {(run.method, run.seed) for run in rest[:size]}
        grid = {(method, seed) for method, _ in head for _, seed in head}
        if grid - done == head:
            return rest[:size]
    return []


def next_session(runs: str, scratch: str = "") -> list:
    """The launcher's arguments for this session's runs (empty once every run is in)."""
    todo, started = left(runs), in_progress(scratch) if scratch else set()
    share = {family: 1 - len(rest) / len(planned) for family, (rest, planned) in todo.items()}
    families = [family for family in ("surf", "rune") if todo[family][0] and family not in BLOCKED]
    if not families:
        return []
    # a family with a run in progress first, then the one furthest behind; SURF's on a tie
    family = min(families, key=lambda f: (not started & {run.run_id for run in todo[f][0]}, share[f]))
    rest, planned = todo[family]
    chosen = first_grid(rest, {(run.method, run.seed) for run in planned if run not in rest})
    arms = {run.method for run in chosen}
    methods = [method for method in dict.fromkeys(run.method for run in planned) if method in arms]
    seeds = list(dict.fromkeys(run.seed for run in chosen))
    return (["--preset", "surf-rune", "--methods", *methods, "--seeds", *map(str, seeds), "--threads", str(THREADS),
             "--workers", str(WORKERS)])


if __name__ == "__main__":
    runs = sys.argv[1] if len(sys.argv) > 1 else os.path.join(STUDY, "runs")
    scratch = sys.argv[2] if len(sys.argv) > 2 else ""
    for family, (rest, _) in left(runs).items():
        if rest and family in BLOCKED:
            print(f"schedule: the {family.upper()} family's {len(rest)} runs wait: {BLOCKED[family]}", file=sys.stderr)
    print(" ".join(next_session(runs, scratch)))
