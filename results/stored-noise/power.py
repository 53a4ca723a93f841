"""The stored-noise study's power, before the runs (from the cheetah study's committed runs) and after them.

    python results/stored-noise/power.py            # prints the numbers that PROTOCOL.md quotes
    python results/stored-noise/power.py --achieved # once all runs of the four arms are in: the power achieved

Primary metric: the mean of a run's last 3 evaluations. H1: one-tailed Welch at alpha 0.05, its power from the
noncentral t with df = 2n - 2 (`analyze.power`). H2: the difference of differences D, its power from the noncentral t
with df = 4n - 4 (`interaction.interaction_power`). Both assume one SD common to the arms.
"""
import argparse
import os
import sys

import numpy as np

STUDY = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, STUDY)
import interaction  # noqa: E402 (its arms, its run reading and the power of D)
from interaction import analyze  # noqa: E402

ALPHA, N = 0.05, 8
EFFECT = 79.4  # the cheetah study's planned effect: half the paper's relative gain (+70%) on its pilot's PEBBLE mean
SCALES = (1.0, 1.5, 2.0)  # the stored arms' SD is unknown before the runs: the cheetah study's, and 1.5 and 2 times it


def pooled_sd(arms: list) -> float:
    return float(np.sqrt(np.mean([np.var(a, ddof=1) for a in arms])))


def smallest_interaction(sd: float, n: int, target: float = 0.80) -> int:
    return next(effect for effect in range(1, 100_000) if interaction.interaction_power(effect, sd, n) >= target)


def report(sd: float, label: str):
    h1 = analyze.power(EFFECT, sd, N, ALPHA)
    h2 = interaction.interaction_power(EFFECT, sd, N, ALPHA)
    print(f"{label}: SD {sd:.1f}. H1 power for +{EFFECT} at {N} per arm: {h1:.2f}; smallest effect with 80% power "
          f"{analyze.smallest_detectable(sd, N, 0.80, ALPHA)}. H2 power for D = +{EFFECT}: {h2:.2f}; smallest D with "
          f"80% power {smallest_interaction(sd, N)}")


def redrawn_arms() -> list:
    """The cheetah study's `r2n_pebble` and `pebble` primary metrics (8 runs each)."""
    arms = []
    for name in ("r2n_redrawn", "pebble_redrawn"):
        folder, method = interaction.ARMS[name]
        runs = sorted(d for d in os.listdir(folder) if d.startswith(f"{method}__"))
        arms.append(np.array([interaction.primary(os.path.join(folder, d)) for d in runs]))
    return arms


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--achieved", action="store_true", help="the power achieved, once every run of the four arms is in")
    if parser.parse_args().achieved:
        values = interaction.read_arms()
        for name, v in values.items():
            print(f"{name}: SD {v.std(ddof=1):.1f}")
        stored = [values["r2n_stored"], values["pebble_stored"]]
        report(pooled_sd(stored), "achieved, H1 (the stored arms' pooled SD)")
        report(pooled_sd(list(values.values())), "achieved, H2 (the four arms' pooled SD)")
        raise SystemExit
    arms = redrawn_arms()
    sd = pooled_sd(arms)
    print("cheetah study (redrawn noise): " + ", ".join(f"n {len(a)}, mean {a.mean():.1f}, SD {a.std(ddof=1):.1f}"
                                                      for a in arms) + f"; pooled SD {sd:.1f}")
    for scale in SCALES:
        report(scale * sd, f"planned at {scale:g} x the cheetah study's SD")
