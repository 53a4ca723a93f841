"""Issue 91's power, before its runs, from the stored-noise study's reference arms (and, with --achieved, after).

    python results/surf-rune/power.py             # prints the numbers PROTOCOL.md quotes
    python results/surf-rune/power.py --achieved  # once every run is in: the power at the SDs observed

No run of SURF or RUNE existed when this was written, so each arm's planned mean comes from the stored-noise study's
PEBBLE (its primary metric, 8 seeds) and the paper's ratios (cheetah-run 0.9/1000, final return over 14 seeds, the
appendix's RQ 2 and RQ 4 tables): SURF = PEBBLE x SURF/PEBBLE, R2N-SURF = SURF x R2N-SURF/SURF, and so for RUNE; the
actor/critic-only arm = R2N-SURF x the paper's actor/critic-only R2N-PEBBLE over its R2N-PEBBLE (the paper has no such
arm for SURF). Power: one-tailed, the noncentral t with df = n1 + n2 - 2 (the planning approximation of Welch's test)
at a stated SD per arm; Holm's power over H1-H2 simulated (normal primary metrics, one-tailed Welch tests).
"""
import argparse
import math
import os
import sys

import numpy as np
from scipy import stats

STUDY = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.join(STUDY, "..", "..")
sys.path.insert(0, ROOT)
import analyze  # noqa: E402 (the repository's: its run reading)

ALPHA = 0.05
REFERENCE = os.path.join(ROOT, "results", "stored-noise", "runs")  # PEBBLE and R2N-PEBBLE, 8 seeds each
WHICH_SPARSITY = os.path.join(ROOT, "results", "which-sparsity", "runs")  # R2N-PEBBLE's seeds 9-10
# the paper's final returns, cheetah-run 0.9/1000 (RQ 2 and RQ 4 tables)
PAPER = {"pebble": 237.62, "surf": 260.47, "r2n_surf": 405.68, "rune": 202.37, "r2n_rune": 410.94,
         "r2n_pebble": 384.80, "r2n_pebble_agent_only": 327.33}
SURF, R2N_SURF, AGENT = "surf_stored_noise", "r2n_surf_stored_noise", "r2n_surf_agent_only_stored_noise"
RUNE, R2N_RUNE = "rune_stored_noise", "r2n_rune_stored_noise"
SEEDS = {SURF: 8, R2N_SURF: 10, AGENT: 10, RUNE: 10, R2N_RUNE: 10}  # PROTOCOL.md: why each
# hypothesis -> (the arm the paper says is higher, the arm it is tested against)
CONFIRMATORY = {"H1": (R2N_SURF, SURF), "H2": (R2N_RUNE, RUNE)}
E1 = (R2N_SURF, AGENT)  # the pre-registered question: does R2N's sparse reward add, where its topology moves?


def planned_means(pebble: float) -> dict:
    """Each arm's planned primary metric from our PEBBLE's and the paper's ratios."""
    surf = pebble * PAPER["surf"] / PAPER["pebble"]
    rune = pebble * PAPER["rune"] / PAPER["pebble"]
    r2n_surf = surf * PAPER["r2n_surf"] / PAPER["surf"]
    return {SURF: surf, R2N_SURF: r2n_surf, RUNE: rune, R2N_RUNE: rune * PAPER["r2n_rune"] / PAPER["rune"],
            AGENT: r2n_surf * PAPER["r2n_pebble_agent_only"] / PAPER["r2n_pebble"]}


def primary(run_dir: str) -> float:
    """The mean of a run's last 3 evaluations (a resumed run's event files read as one)."""
    [run] = analyze.read_folder(sorted(os.path.join(run_dir, f) for f in os.listdir(run_dir) if f.startswith("events.")))
    return float(run.scalars[analyze.EVAL_TAG][1][-3:].mean())


def arm_values(folder: str, method: str) -> np.ndarray:
    runs = sorted((d for d in os.listdir(folder) if d.startswith(f"{method}__")
                   and os.path.exists(os.path.join(folder, d, "done"))), key=analyze.natural_order)
    return np.array([primary(os.path.join(folder, d)) for d in runs])


def power(effect: float, sd1: float, sd2: float, n1: int, n2: int, alpha: float = ALPHA) -> float:
    """Power of the one-tailed test of a difference `effect` with n1 and n2 seeds, the arms at SDs sd1 and sd2."""
    df = n1 + n2 - 2
    se = math.sqrt(sd1 ** 2 / n1 + sd2 ** 2 / n2)
    return float(1 - stats.nct.cdf(stats.t.ppf(1 - alpha, df), df, effect / se))


def welch_p(high: np.ndarray, low: np.ndarray) -> np.ndarray:
    """One-tailed Welch p (H1: `high` above `low`) per row of two (reps, n) samples."""
    va, vb = high.var(axis=1, ddof=1) / high.shape[1], low.var(axis=1, ddof=1) / low.shape[1]
    t = (high.mean(axis=1) - low.mean(axis=1)) / np.sqrt(va + vb)
    df = (va + vb) ** 2 / (va ** 2 / (high.shape[1] - 1) + vb ** 2 / (low.shape[1] - 1))
    return stats.t.sf(t, df)


def holm_power(means: dict, sds: dict, seeds: dict, reps: int = 20_000, seed: int = 0) -> dict:
    """Each confirmatory hypothesis's power under Holm's correction at ALPHA, by simulation."""
    rng = np.random.default_rng(seed)
    draws = {arm: rng.normal(means[arm], sds[arm], (reps, seeds[arm])) for arm in seeds}
    p = np.array([welch_p(draws[high], draws[low]) for high, low in CONFIRMATORY.values()]).T  # (reps, hypotheses)
    order = np.argsort(p, axis=1)
    thresholds = ALPHA / (p.shape[1] - np.arange(p.shape[1]))
    passed = np.cumprod(np.take_along_axis(p, order, axis=1) <= thresholds, axis=1).astype(bool)  # Holm stops at a miss
    rejected = np.zeros_like(passed)
    np.put_along_axis(rejected, order, passed, axis=1)
    return {h: float(rejected[:, i].mean()) for i, h in enumerate(CONFIRMATORY)}


def adds_nothing_chance(sd1: float, sd2: float, n1: int, n2: int, threshold: float) -> float:
    """E1's chance of the reading "adds nothing" (the one-sided 95% upper bound of the difference below `threshold`)
    if the true difference is 0 (normal approximation of the estimate, Student's bound)."""
    se = math.sqrt(sd1 ** 2 / n1 + sd2 ** 2 / n2)
    return float(stats.norm.cdf((threshold - stats.t.ppf(0.95, n1 + n2 - 2) * se) / se))


def report(means: dict, sds: dict, seeds: dict, label: str):
    print(f"{label}:")
    k = len(CONFIRMATORY)
    for name, (high, low) in CONFIRMATORY.items():
        effect = means[high] - means[low]
        bound = power(effect, sds[high], sds[low], seeds[high], seeds[low], ALPHA / k)
        need = next((n for n in range(2, 201) if power(effect, sds[high], sds[low], n, n, ALPHA / k) >= 0.8), "> 200")
        print(f"  {name} {high} > {low}: effect {effect:+.1f}, SDs {sds[high]:.1f} / {sds[low]:.1f}, "
              f"{seeds[high]} vs {seeds[low]} seeds: power >= {bound:.2f} (alpha {ALPHA / k:.3f}); "
              f"80% needs {need} seeds per arm")
    holm = holm_power(means, sds, seeds)
    print("  Holm, simulated: " + ", ".join(f"{h} {v:.2f}" for h, v in holm.items()))
    high, low = E1
    effect = means[high] - means[low]
    need = next((n for n in range(2, 201) if power(effect, sds[high], sds[low], n, n) >= 0.8), "> 200")
    print(f"  E1 {high} > {low}: effect {effect:+.1f}, {seeds[high]} vs {seeds[low]} seeds: power "
          f"{power(effect, sds[high], sds[low], seeds[high], seeds[low]):.2f} (alpha {ALPHA}), 80% needs {need} per "
          f"arm; if the sparse reward adds nothing, \"adds nothing\" is read with probability "
          f"{adds_nothing_chance(sds[high], sds[low], seeds[high], seeds[low], effect):.2f}")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--achieved", action="store_true", help="the power at the SDs observed, once every run is in")
    achieved = parser.parse_args().achieved
    pebble = arm_values(REFERENCE, "pebble_stored_noise")
    r2n = np.concatenate([arm_values(REFERENCE, "r2n_pebble_stored_noise"),
                          arm_values(WHICH_SPARSITY, "r2n_pebble_stored_noise")])
    sd_pebble, sd_r2n = float(pebble.std(ddof=1)), float(r2n.std(ddof=1))
    print(f"reference arms: pebble_stored_noise n {len(pebble)}, mean {pebble.mean():.1f}, SD {sd_pebble:.1f}; "
          f"r2n_pebble_stored_noise n {len(r2n)}, mean {r2n.mean():.1f}, SD {sd_r2n:.1f}")
    means = planned_means(float(pebble.mean()))
    print("planned means (PEBBLE x the paper's ratios): " + ", ".join(f"{a} {m:.1f}" for a, m in means.items()))
    if not achieved:
        dense = {SURF: sd_pebble, RUNE: sd_pebble}
        report(means, {arm: dense.get(arm, sd_r2n) for arm in SEEDS}, SEEDS,
               f"each baseline arm at PEBBLE's SD {sd_pebble:.1f}, each R2N arm at R2N-PEBBLE's {sd_r2n:.1f}")
        report(means, {arm: sd_r2n for arm in SEEDS}, SEEDS, f"every arm at R2N-PEBBLE's SD {sd_r2n:.1f}")
        # sensitivity: R2N's gain as our R2N-PEBBLE's over our PEBBLE, not the paper's
        ours = r2n.mean() / pebble.mean()
        smaller = dict(means, **{R2N_SURF: means[SURF] * ours, R2N_RUNE: means[RUNE] * ours})
        smaller[AGENT] = smaller[R2N_SURF] * PAPER["r2n_pebble_agent_only"] / PAPER["r2n_pebble"]
        report(smaller, {arm: sd_r2n for arm in SEEDS}, SEEDS,
               f"sensitivity, not planned: R2N's gain as ours on PEBBLE (x{ours:.3f}), every arm at SD {sd_r2n:.1f}")
        raise SystemExit
    values = {arm: arm_values(os.path.join(STUDY, "runs"), arm) for arm in SEEDS}
    for arm, v in values.items():
        if len(v) != SEEDS[arm]:
            raise SystemExit(f"{arm}: {len(v)} of {SEEDS[arm]} runs in; the power achieved needs every run")
        print(f"{arm}: n {len(v)}, mean {v.mean():.1f}, SD {v.std(ddof=1):.1f}")
    report(means, {arm: float(v.std(ddof=1)) for arm, v in values.items()}, SEEDS,
           "at the SDs observed, for the effects planned")
