"""What a session of the surf-rune study runs (PROTOCOL.md, the additions of 2026-12-06): `continue.sh` asks it.

    python results/surf-rune/schedule.py [RUNS]   # prints the launcher's arguments, or nothing when no run can go

A machine here keeps nothing between sessions (180 minutes each), so a run must finish in the session that starts
it. RUNE's runs take about an hour, two at a time at one thread. A SURF-family run takes about 3 hours even alone at
two threads: more than a session, so that family is blocked (`BLOCKED`) until a run can carry its state across
sessions. A session runs one family that is not blocked: SURF's if the share of its runs that are in is at most
RUNE's, else RUNE's. In each family, the runs go in the preset's order (the protocol's), minus those in.
"""
import os
import sys

STUDY = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, STUDY)
import power  # noqa: E402 (this study's: the arms)

sys.path.insert(0, power.ROOT)
import benchmark  # noqa: E402 (the repository's: the preset)

FAMILIES = {"surf": (power.SURF, power.R2N_SURF, power.AGENT), "rune": (power.RUNE, power.R2N_RUNE)}
# (threads a run, runs at a time, runs a session starts at most)
SETTINGS = {"surf": (2, 1, 1), "rune": (1, 2, 4)}  # RUNE: two pairs, about 2 hours
# family -> why none of its runs can start (PROTOCOL.md, the second addition of 2026-12-06)
BLOCKED = {"surf": "a SURF-family run takes about 3 hours alone at two threads, more than a 180-minute session, and "
                   "its state (0.7-1.2 GB) cannot be carried to the next one"}


def left(runs: str) -> dict:
    """family -> the preset's runs of that family not yet in `runs`, in the preset's order; and how many it has."""
    runs_planned, out = benchmark.expand(benchmark.Args(preset="surf-rune")), {}
    for family, arms in FAMILIES.items():
        planned = [run for run in runs_planned if run.method in arms]
        out[family] = ([run for run in planned if not os.path.exists(os.path.join(runs, run.run_id, "done"))],
                       len(planned))
    return out


def next_session(runs: str) -> list:
    """The launcher's arguments for this session's runs (empty once every run is in)."""
    todo = left(runs)
    share = {family: 1 - len(rest) / total for family, (rest, total) in todo.items()}
    families = [family for family in ("surf", "rune") if todo[family][0] and family not in BLOCKED]
    if not families:
        return []
    family = min(families, key=lambda f: share[f])  # the family furthest behind; SURF's on a tie
    threads, workers, most = SETTINGS[family]
    chosen = todo[family][0][:most]
    methods = list(dict.fromkeys(run.method for run in chosen))
    seeds = list(dict.fromkeys(run.seed for run in chosen))
    return (["--preset", "surf-rune", "--methods", *methods, "--seeds", *map(str, seeds), "--threads", str(threads),
             "--workers", str(workers)])


if __name__ == "__main__":
    runs = sys.argv[1] if len(sys.argv) > 1 else os.path.join(STUDY, "runs")
    for family, (rest, _) in left(runs).items():
        if rest and family in BLOCKED:
            print(f"schedule: the {family.upper()} family's {len(rest)} runs wait: {BLOCKED[family]}", file=sys.stderr)
    print(" ".join(next_session(runs)))
