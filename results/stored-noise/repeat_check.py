"""Does the `pebble_repeat` probe repeat the cheetah study's PEBBLE runs bit for bit?

    python results/stored-noise/repeat_check.py              # the committed probes (results/stored-noise/probes)
    python results/stored-noise/repeat_check.py FOLDER ...   # other folders, e.g. a study worktree's logs/scratch

Each `pebble_repeat` run found is set beside the cheetah study's committed `pebble` run of the same seed. Every scalar
the two share (same tag, same step) is compared for equality. The SPS chart is left out: it is wall time. A run under
way is compared to its last point, and the line says so. This is a report: it exits 0 whatever it finds.
"""
import os
import sys

import numpy as np

STUDY = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(STUDY, "..", ".."))
import analyze  # noqa: E402 (the repository's: its run reading)

CHEETAH = os.path.join(STUDY, "..", "cheetah-study")
TIMING_TAGS = frozenset({"charts/SPS"})


def runs_of(folders, exp_name: str) -> dict:
    """The runs of `exp_name` under `folders`, by seed, finished or not (a resumed run's event files read as one)."""
    runs = analyze.load_runs(folders, include_unfinished=True)
    return {run.hparams["seed"]: run for run in runs if run.status == "used" and run.hparams["exp_name"] == exp_name}


def compare(repeat, original) -> str:
    """One line: how many shared scalars are equal, and the first that is not (by step, then tag)."""
    shared, unequal = 0, []
    for tag in sorted(set(repeat.scalars) & set(original.scalars) - TIMING_TAGS):
        steps, values = repeat.scalars[tag]
        original_steps, original_values = original.scalars[tag]
        _, here, there = np.intersect1d(steps, original_steps, return_indices=True)
        shared += len(here)
        a, b = values[here], original_values[there]
        differ = (a != b) & ~(np.isnan(a) & np.isnan(b))  # the same NaN in both is a repeat too
        unequal += [(int(steps[i]), tag) for i in here[differ]]
    last, total = int(repeat.eval_steps[-1]), repeat.hparams.get("total_timesteps")
    extent = f"to the evaluation at step {last}"
    if isinstance(total, int) and last < total:
        extent += f" of {total} (under way)"
    if not unequal:
        return f"{shared} of {shared} shared scalars equal, {extent}"
    step, tag = min(unequal)
    equal = shared - len(unequal)
    return f"{equal} of {shared} shared scalars equal, {extent}; the first that differs: {tag} at step {step}"


def main(folders, cheetah: str = CHEETAH) -> int:
    repeats = runs_of(folders, "pebble_repeat")
    originals = runs_of([cheetah], "pebble")
    if not repeats:
        print(f"no pebble_repeat run under {', '.join(os.path.relpath(folder) for folder in folders)}")
    for seed in sorted(repeats):
        line = f"pebble_repeat seed {seed} against the cheetah study's pebble seed {seed}: "
        if seed in originals:
            print(line + compare(repeats[seed], originals[seed]))
        else:
            print(line + "no such pebble run")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:] or [os.path.join(STUDY, "probes")]))
