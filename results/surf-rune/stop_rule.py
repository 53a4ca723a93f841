"""The protocol's first-seeds stop rule (PROTOCOL.md, "Rules"), checked by the watcher after each committed run.

    python results/surf-rune/stop_rule.py   # exit 0: nothing fires; 1: names the run(s) it fires on

A finished seed-1 run of SURF, R2N-SURF, RUNE or R2N-RUNE whose primary metric (the mean of its last 3 evaluations) is
below 50 fires it: the pre-training policy scores 0-31 at its evaluation, and every stored-noise PEBBLE seed ended at
116 or more.
"""
import os
import sys

STUDY = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, STUDY)
import power  # noqa: E402 (this study's: the arms, the primary metric)

FIRST_SEED_ARMS = (power.SURF, power.R2N_SURF, power.RUNE, power.R2N_RUNE)
FLOOR = 50.0


def fired(runs: str) -> list:
    """(run, primary metric) of each finished seed-1 run below FLOOR."""
    out = []
    for arm in FIRST_SEED_ARMS:
        run = os.path.join(runs, f"{arm}__cheetah-run__noise0.9__budget1000__seed1")
        if os.path.exists(os.path.join(run, "done")) and (value := power.primary(run)) < FLOOR:
            out.append((os.path.basename(run), value))
    return out


if __name__ == "__main__":
    found = fired(sys.argv[1] if len(sys.argv) > 1 else os.path.join(STUDY, "runs"))
    for run, value in found:
        print(f"stop rule: {run} ended at {value:.1f} (< {FLOOR:g}): find the bug before any other run")
    raise SystemExit(1 if found else 0)
