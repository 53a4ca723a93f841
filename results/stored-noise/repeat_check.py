"""Does the `pebble_repeat` probe repeat the cheetah study's PEBBLE runs bit for bit?

    python results/stored-noise/repeat_check.py              # the committed probes (results/stored-noise/probes)
    python results/stored-noise/repeat_check.py FOLDER ...   # other folders, e.g. a study worktree's logs/scratch

Each `pebble_repeat` run found is set beside the cheetah study's committed `pebble` run of the same seed. Every scalar
the two share (same tag, same step) is compared for equality. The SPS chart is left out: it is wall time. A run under
way is compared up to its last point, and the line says so. This is a report: it exits 0 whatever it finds.
"""
import itertools
import os
import sys

import numpy as np

STUDY = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(STUDY, "..", ".."))
import analyze  # noqa: E402 (the repository's: its run reading)

CHEETAH = os.path.join(STUDY, "..", "cheetah-study")
TIMING_TAGS = frozenset({"charts/SPS"})


def runs_of(folders, exp_name: str) -> dict:
    """The runs of `exp_name` under `folders`, by seed (a resumed run's event files read as one)."""
    found = {}
    for _, paths in itertools.groupby(analyze.find_event_files(folders), key=os.path.dirname):
        for run in analyze.read_folder(list(paths)):
            if run.status == "used" and run.hparams.get("exp_name") == exp_name:
                found[run.hparams["seed"]] = run
    return found


def compare(repeat, original) -> str:
    """One line: how many shared scalars are equal, and the first that is not (by step, then tag)."""
    shared, unequal = 0, []
    for tag in sorted(set(repeat.scalars) & set(original.scalars) - TIMING_TAGS):
        steps, values = repeat.scalars[tag]
        original_steps, original_values = original.scalars[tag]
        _, here, there = np.intersect1d(steps, original_steps, return_indices=True)
        shared += len(here)
        differ = values[here] != original_values[there]
        unequal += [(int(steps[i]), tag) for i in here[differ]]
    last = int(repeat.eval_steps[-1]) if len(repeat.eval_steps) else 0
    total = repeat.hparams.get("total_timesteps")
    extent = f"up to step {last}" + ("" if last >= total else f" of {total} (under way)")
    if not unequal:
        return f"{shared} of {shared} shared scalars equal, {extent}"
    step, tag = min(unequal)
    return f"{shared - len(unequal)} of {shared} shared scalars equal, {extent}; the first that differs: {tag} at step {step}"


def main(folders, cheetah: str = CHEETAH) -> int:
    repeats = runs_of(folders, "pebble_repeat")
    originals = runs_of([cheetah], "pebble")
    if not repeats:
        print(f"no pebble_repeat run under {', '.join(folders)}")
    for seed in sorted(repeats):
        print(f"pebble_repeat seed {seed} against the cheetah study's pebble seed {seed}: "
              + compare(repeats[seed], originals[seed]))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:] or [os.path.join(STUDY, "probes")]))
