"""The early-stop confirmation's power calculation (PROTOCOL.md), from the cpu-study's committed event files.

    python results/early-stop/power.py             # prints the numbers that PROTOCOL.md quotes
    python results/early-stop/power.py --achieved  # once all 16 runs are in: the power the two tests achieved

Primary metric: the mean of a run's last 3 evaluations. Planning SD: the pooled SD of the cpu-study's main arms
(`pebble`, `r2n_pebble`, 8 seeds each). Effect: the unregistered lead of `r2n_pebble_no_early_stop` over
`pebble_no_early_stop` (3 seeds each), and half of it. Test: one-tailed Welch at alpha 0.05, 8 seeds per arm, power
from the noncentral t (`analyze.power`).
"""
import argparse
import os
import sys

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", ".."))
import analyze  # noqa: E402 (the repository's: its run reading and power calculation)

LAST, N, SETTING = 3, 8, ("cartpole-swingup", 0.9, 400)


def primary(folders: list) -> dict:
    """Each method's primary metric per seed, from the finished runs under `folders`."""
    groups = analyze.make_groups(analyze.load_runs(folders))
    return {g.key[3]: g.values("primary", LAST) for g in groups if g.key[:3] == SETTING}


def pooled_sd(*arms) -> float:
    return float(np.sqrt(np.mean([np.var(arm, ddof=1) for arm in arms])))


def achieved(lead: float, cpu_study: np.ndarray):
    """The power the tests achieved at the SDs they observed (H2 against `cpu_study`, the cpu-study's `r2n_pebble`):
    read only once all 16 runs of the protocol are in."""
    runs = primary([HERE])
    arms = ("pebble_no_early_stop", "r2n_pebble_no_early_stop")
    counts = {arm: len(runs.get(arm, ())) for arm in arms}
    if min(counts.values()) < N:
        raise SystemExit(f"power.py --achieved: {counts} runs of {N} per arm are in; the protocol reads the study only "
                         "when all are")
    for name, (a, b) in {"H1": (runs[arms[1]], runs[arms[0]]), "H2": (runs[arms[1]], cpu_study)}.items():
        sd = pooled_sd(a, b)
        print(f"{name}: observed pooled SD {sd:.1f}; power for the lead +{lead:.0f}: "
              f"{analyze.power(lead, sd, N):.2f}, for half of it: {analyze.power(lead / 2, sd, N):.2f}; smallest "
              f"effect with 80% power: {analyze.smallest_detectable(sd, N)} points")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--achieved", action="store_true", help="the power achieved, once every run of the study is in")
    options = parser.parse_args()
    cpu = primary([os.path.join(HERE, "..", "cpu-study")])
    for method in ("pebble", "r2n_pebble", "pebble_no_early_stop", "r2n_pebble_no_early_stop"):
        values = cpu[method]
        print(f"cpu-study {method}: {len(values)} seeds, mean {values.mean():.1f}, SD {values.std(ddof=1):.1f}")
    sd = pooled_sd(cpu["pebble"], cpu["r2n_pebble"])
    lead = float(cpu["r2n_pebble_no_early_stop"].mean() - cpu["pebble_no_early_stop"].mean())
    if options.achieved:
        achieved(lead, cpu["r2n_pebble"])
        raise SystemExit
    print(f"planning SD (pooled, main arms) {sd:.1f}; lead {lead:+.1f}, d = {lead / sd:.2f}, "
          f"power {analyze.power(lead, sd, N):.2f} at {N} per arm")
    needed = next(n for n in range(2, 1000) if analyze.power(lead / 2, sd, n) >= 0.80)
    print(f"half the lead {lead / 2:+.1f}: power {analyze.power(lead / 2, sd, N):.2f}; 80% power needs {needed} per arm")
    small_sd = pooled_sd(cpu["pebble_no_early_stop"], cpu["r2n_pebble_no_early_stop"])
    print(f"smallest effect with 80% power at {N} per arm: {analyze.smallest_detectable(sd, N)} points; at the "
          f"no-early-stop arms' pooled SD {small_sd:.1f}: {analyze.smallest_detectable(small_sd, N)} points, and the "
          f"lead has power {analyze.power(lead, small_sd, N):.2f}")
