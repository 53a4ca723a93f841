"""H2 of the stored-noise study: is R2N's gain larger with the noise stored than with it redrawn?

    python results/stored-noise/interaction.py   # once all 8 runs of each of the four arms are in

The statistic, fixed before the runs (PROTOCOL.md), is the difference of differences of the primary metric (the mean
of a run's last 3 evaluations):
    D = (mean R2N stored - mean PEBBLE stored) - (mean R2N redrawn - mean PEBBLE redrawn).
- p: exact one-tailed permutation p of D. Arm labels are relabelled within each environment, over all
  C(16, 8)^2 relabelings. It is counted exactly from the two environments' C(16, 8) differences.
- CI: percentile bootstrap 95% CI of D, each of the four arms resampled on its own (10 000 resamples, seed 0).
- Beside them: a Welch-type t for D, with Satterthwaite's degrees of freedom.
The redrawn arms are the cheetah study's committed runs (`pebble`, `r2n_pebble`); the stored arms are this study's.
"""
import glob
import itertools
import math
import os
import sys

import numpy as np

STUDY = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(STUDY, "..", ".."))
import analyze  # noqa: E402 (the repository's: its run reading)

LAST, SEEDS, RESAMPLES = 3, 8, 10_000
ARMS = {  # (folder, method) of the four arms: R2N and PEBBLE with the noise stored, then redrawn
    "r2n_stored": (os.path.join(STUDY, "runs"), "r2n_pebble_stored_noise"),
    "pebble_stored": (os.path.join(STUDY, "runs"), "pebble_stored_noise"),
    "r2n_redrawn": (os.path.join(STUDY, "..", "cheetah-study"), "r2n_pebble"),
    "pebble_redrawn": (os.path.join(STUDY, "..", "cheetah-study"), "pebble"),
}


def primary(run_dir: str) -> float:
    """The primary metric of one run: the mean of its last `LAST` evaluations (a resumed run's files read as one)."""
    [run] = analyze.read_folder(sorted(glob.glob(os.path.join(run_dir, "events.out.tfevents.*"))))
    return float(run.scalars[analyze.EVAL_TAG][1][-LAST:].mean())


def split_differences(a, b) -> np.ndarray:
    """mean(first) - mean(second) for every split of the pooled values into two groups of len(a) and len(b)."""
    pooled = np.concatenate([a, b]).astype(np.float64)
    total, n = pooled.sum(), len(a)
    sums = np.array([pooled[list(first)].sum() for first in itertools.combinations(range(len(pooled)), n)])
    return sums / n - (total - sums) / len(b)


def interaction_p(r2n_stored, pebble_stored, r2n_redrawn, pebble_redrawn) -> float:
    """Exact one-tailed permutation p of D, relabelling the arms within each environment."""
    observed = (np.mean(r2n_stored) - np.mean(pebble_stored)) - (np.mean(r2n_redrawn) - np.mean(pebble_redrawn))
    stored = split_differences(r2n_stored, pebble_stored)
    redrawn = np.sort(split_differences(r2n_redrawn, pebble_redrawn))
    # D' >= D exactly when redrawn' <= stored' - D; a relative tolerance keeps the observed split itself counted
    tolerance = 1e-9 * max(1.0, abs(observed))
    at_least = np.searchsorted(redrawn, stored - observed + tolerance, side="right")
    return float(at_least.sum() / (len(stored) * len(redrawn)))


def interaction_ci(arms: list, resamples: int = RESAMPLES, level: float = 0.95, seed: int = 0) -> tuple:
    """Percentile bootstrap CI of D; `arms` in the order r2n stored, pebble stored, r2n redrawn, pebble redrawn."""
    rng = np.random.default_rng(seed)
    means = [np.asarray(a, np.float64)[rng.integers(0, len(a), (resamples, len(a)))].mean(1) for a in arms]
    differences = (means[0] - means[1]) - (means[2] - means[3])
    low, high = np.percentile(differences, [50 * (1 - level), 50 * (1 + level)])
    return float(low), float(high)


def interaction_welch(arms: list) -> tuple:
    """(t, Satterthwaite df, one-tailed p) of D, without assuming equal variances."""
    from scipy import stats

    terms = [np.var(a, ddof=1) / len(a) for a in arms]
    d = (np.mean(arms[0]) - np.mean(arms[1])) - (np.mean(arms[2]) - np.mean(arms[3]))
    se = math.sqrt(sum(terms))
    df = sum(terms) ** 2 / sum(term**2 / (len(a) - 1) for term, a in zip(terms, arms))
    t = d / se
    return t, df, float(stats.t.sf(t, df))


def interaction_power(effect: float, sd: float, n: int, alpha: float = 0.05) -> float:
    """Power of the one-tailed test of D at `n` runs per arm and a common SD: the noncentral t, df = 4n - 4."""
    from scipy import stats

    df = 4 * n - 4
    return float(1 - stats.nct.cdf(stats.t.ppf(1 - alpha, df), df, effect / (sd * math.sqrt(4 / n))))


def read_arms() -> dict:
    """name -> primary metrics of the arm's finished runs; refused while any arm has fewer than `SEEDS`."""
    values = {}
    for name, (folder, method) in ARMS.items():
        runs = sorted(d for d in glob.glob(os.path.join(folder, f"{method}__*__seed*"))
                      if os.path.exists(os.path.join(d, "done")))
        if len(runs) < SEEDS:
            raise SystemExit(f"interaction.py: {len(runs)} of {SEEDS} {method} runs are in {os.path.relpath(folder)}; "
                             "the protocol reads H2 only when all are")
        values[name] = np.array([primary(d) for d in runs])
    return values


if __name__ == "__main__":
    values = read_arms()
    arms = list(values.values())
    for name, v in values.items():
        print(f"{name}: n {len(v)}, mean {v.mean():.1f}, SD {v.std(ddof=1):.1f}")
    gain_stored, gain_redrawn = arms[0].mean() - arms[1].mean(), arms[2].mean() - arms[3].mean()
    low, high = interaction_ci(arms)
    t, df, welch = interaction_welch(arms)
    print(f"R2N's gain: stored {gain_stored:+.1f}, redrawn {gain_redrawn:+.1f}")
    print(f"H2: D = {gain_stored - gain_redrawn:+.1f}, bootstrap 95% CI [{low:+.1f}, {high:+.1f}], "
          f"exact permutation p {interaction_p(*arms):.4f} (one-tailed), Welch t {t:.2f} on {df:.1f} df, p {welch:.4f}")
