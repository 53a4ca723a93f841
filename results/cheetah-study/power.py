"""The cheetah study's power calculation, from the pilot's event files, by the rules of PILOT.md (fixed before it ran).

    python results/cheetah-study/power.py            # prints the numbers that PROTOCOL.md quotes

Primary metric: the mean of a run's last 3 evaluations. SD for planning: the larger of the PEBBLE seeds' SD and 25% of
their mean. Effect: half the paper's relative gain (+70%), i.e. +35% of PEBBLE's pilot mean. Test: one-tailed Welch at
alpha 0.05, power from the noncentral t (equal n and SD, df = 2n - 2).
"""
import glob
import os

import numpy as np
from scipy import stats
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

PILOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "cheetah-pilot")
LAST, ALPHA, TARGET, CAP, FLOOR = 3, 0.05, 0.80, 12, 8  # CAP: the most seeds per arm this project's CPU affords


def curve(run_dir):
    points = {}
    for path in sorted(glob.glob(os.path.join(run_dir, "events.out.tfevents.*"))):
        events = EventAccumulator(path, size_guidance={"scalars": 0})
        events.Reload()
        points.update({e.step: e.value for e in events.Scalars("eval/episodic_return")})
    steps = np.array(sorted(points))
    return steps, np.array([points[s] for s in steps])


def power(d, n):
    df, tcrit = 2 * n - 2, stats.t.ppf(1 - ALPHA, 2 * n - 2)
    return 1 - stats.nct.cdf(tcrit, df, d * np.sqrt(n / 2))


if __name__ == "__main__":
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
    detectable = next(e for e in np.arange(1.0, 10 * sd) if power(e / sd, chosen) >= TARGET)
    print(f"smallest effect with 80% power at {chosen} per arm: {detectable:.0f} points "
          f"({100 * detectable / pebble.mean():.0f}% of the pilot mean)")
