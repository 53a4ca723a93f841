"""The cheetah study's power calculation, from the pilot's event files, by the rules of PILOT.md (fixed before it ran).

    python results/cheetah-study/power.py            # prints the numbers that PROTOCOL.md quotes
    python results/cheetah-study/power.py --achieved # once all 8 + 8 study runs are in: the power they achieved

Primary metric: the mean of a run's last 3 evaluations. SD for planning: the larger of the PEBBLE seeds' SD and 25% of
their mean. Effect: half the paper's relative gain (+70%), i.e. +35% of PEBBLE's pilot mean. Test: one-tailed Welch at
alpha 0.05, power from the noncentral t (equal n and SD, df = 2n - 2).
"""
import argparse
import glob
import os
import sys

import numpy as np

STUDY = os.path.dirname(os.path.abspath(__file__))
PILOT = os.path.join(STUDY, "..", "cheetah-pilot")
sys.path.insert(0, os.path.join(STUDY, "..", ".."))
import analyze  # noqa: E402 (the repository's: its run reading and power calculation)
LAST, ALPHA, TARGET, CAP, FLOOR = 3, 0.05, 0.80, 12, 8  # CAP: the most seeds per arm this project's CPU affords


def curve(run_dir):
    """A run's evaluation steps and returns, read as `analyze.py` reads them (a resumed run's files as one run)."""
    [run] = analyze.read_folder(sorted(glob.glob(os.path.join(run_dir, "events.out.tfevents.*"))))
    return run.scalars[analyze.EVAL_TAG]


def power(d, n):
    return analyze.power(d, 1.0, n, ALPHA)


def achieved(planned_effect, planned_sd):
    """The study's achieved power, with the SD it observed: read only once every PbRL run of the protocol is in."""
    arms = {}
    for method in ("pebble", "r2n_pebble"):
        folders = sorted(glob.glob(os.path.join(STUDY, f"{method}__*__seed*")))
        finished = [d for d in folders if os.path.exists(os.path.join(d, "done"))]
        if len(finished) < FLOOR:
            raise SystemExit(f"power.py --achieved: {len(finished)} of {FLOOR} {method} runs are in; the protocol reads "
                             "the study only when all are")
        arms[method] = np.array([curve(d)[1][-LAST:].mean() for d in finished])
    sds = {method: values.std(ddof=1) for method, values in arms.items()}
    pooled = np.sqrt(np.mean([sd**2 for sd in sds.values()]))
    n = min(len(values) for values in arms.values())
    print("observed SD of the primary metric: " + ", ".join(f"{m} {sd:.1f}" for m, sd in sds.items()) +
          f"; pooled {pooled:.1f} (planned: {planned_sd})")
    print(f"power for the planned effect +{planned_effect:.1f} at {n} per arm: {power(planned_effect / pooled, n):.2f}; "
          f"smallest effect with 80% power: {analyze.smallest_detectable(pooled, n):.0f} points")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--achieved", action="store_true", help="the power achieved, once every run of the study is in")
    if parser.parse_args().achieved:
        achieved(planned_effect=79.4, planned_sd=60.6)  # PROTOCOL.md's, from the pilot (printed without the flag)
        raise SystemExit
    runs = {os.path.basename(d): curve(d) for d in sorted(glob.glob(os.path.join(PILOT, "*__seed*")))}
    for name, (steps, values) in runs.items():
        at = {s: round(float(values[steps <= s][-LAST:].mean()), 1) for s in (150_000, 200_000, int(steps[-1]))}
        print(f"{name}: last step {steps[-1]}, mean of the last {LAST} evaluations ending at {at}")
    sac = [v[-LAST:].mean() for n, (s, v) in runs.items() if n.startswith("sac__")]
    pebble = np.array([v[-LAST:].mean() for n, (s, v) in runs.items() if n.startswith("pebble__")])
    print(f"fallback rule: SAC {np.round(sac, 1)} (< 200?), PEBBLE {np.round(pebble, 1)} (both < 50?)")
    sd = max(pebble.std(ddof=1), 0.25 * pebble.mean())
    effect = 0.35 * pebble.mean()
    d = effect / sd
    needed = next(n for n in range(2, 1000) if power(d, n) >= TARGET)
    chosen = min(max(needed, FLOOR), CAP)
    print(f"PEBBLE pilot mean {pebble.mean():.1f}, seed SD {pebble.std(ddof=1):.1f}, planning SD {sd:.1f}")
    print(f"effect +35% = {effect:.1f}, d = {d:.2f}; 80% power needs {needed} per arm; chosen {chosen} per arm, "
          f"power {power(d, chosen):.2f}")
    smallest = analyze.smallest_detectable(sd, chosen)
    print(f"smallest effect with 80% power at {chosen} per arm: {smallest:.0f} points "
          f"({100 * smallest / pebble.mean():.0f}% of the pilot mean)")
