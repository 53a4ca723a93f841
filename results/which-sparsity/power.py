"""Issue 69's power, before its runs (from the stored-noise study's reference arms) and, with --achieved, after them.

    python results/which-sparsity/power.py             # prints the numbers PROTOCOL.md quotes
    python results/which-sparsity/power.py --achieved  # once every run is in: the power at the SDs observed

Each hypothesis takes the paper's direction and its relative effect (the paper's arm over its R2N-PEBBLE, cheetah-run
0.9/1000, final return, appendix tables) applied to our R2N-PEBBLE's primary metric (the mean of a run's last 3
evaluations). Power: one-tailed, the noncentral t with df = n1 + n2 - 2 and unequal seeds (the planning
approximation of Welch's test), at one SD common to the two arms. The confirmatory family is corrected with Holm's
method; its power is bounded below by testing each hypothesis at alpha / 3 (Holm rejects at least what Bonferroni
does).
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
REFERENCE = os.path.join(ROOT, "results", "stored-noise", "runs")  # committed at e6130f6, 8 seeds per arm
R2N_SEEDS = 10  # R2N-PEBBLE's seeds 1-8 from REFERENCE and 9-10 run here: H1's power needs them
PAPER_R2N = 384.80  # the paper's R2N-PEBBLE on cheetah-run 0.9/1000, final return over 14 seeds
# arm -> (the paper's final return, the direction it claims against R2N-PEBBLE, family, seeds planned)
ARMS = {
    "r2n_pebble_reward_only_stored_noise": (265.27, "less", "confirmatory", 10),
    "dropconnect_pebble_stored_noise": (219.24, "less", "confirmatory", 8),
    "l1_pebble_stored_noise": (239.53, "less", "confirmatory", 8),
    "r2n_pebble_agent_only_stored_noise": (327.33, "less", "exploratory (pre-registered question)", 10),
    "set_pebble_stored_noise": (404.03, "none", "exploratory", 8),
    "static_pebble_stored_noise": (377.23, "none", "exploratory", 8),
}
CONFIRMATORY = [arm for arm, spec in ARMS.items() if spec[2] == "confirmatory"]


def primary(run_dir: str) -> float:
    """The mean of a run's last 3 evaluations (a resumed run's event files read as one)."""
    [run] = analyze.read_folder(sorted(os.path.join(run_dir, f) for f in os.listdir(run_dir) if f.startswith("events.")))
    return float(run.scalars[analyze.EVAL_TAG][1][-3:].mean())


def arm_values(folder: str, method: str) -> np.ndarray:
    runs = sorted(d for d in os.listdir(folder) if d.startswith(f"{method}__") and os.path.exists(os.path.join(folder, d, "done")))
    return np.array([primary(os.path.join(folder, d)) for d in runs])


def power(effect: float, sd: float, n1: int, n2: int, alpha: float = ALPHA) -> float:
    """Power of the one-tailed test of a difference `effect` with n1 and n2 seeds at a common SD."""
    df = n1 + n2 - 2
    return float(1 - stats.nct.cdf(stats.t.ppf(1 - alpha, df), df, effect / (sd * math.sqrt(1 / n1 + 1 / n2))))


def seeds_for(effect: float, sd: float, n_ref: int, alpha: float, target: float = 0.80) -> int:
    """The fewest seeds of the new arm that reach `target` power against a reference arm of n_ref seeds (0: none do)."""
    return next((n for n in range(2, 201) if power(effect, sd, n, n_ref, alpha) >= target), 0)


def report(r2n_mean: float, sds: dict, n_ref: int, seeds: dict, arms: tuple = tuple(ARMS)):
    k = len(CONFIRMATORY)
    for arm in arms:
        paper, direction, family, _ = ARMS[arm]
        ratio = paper / PAPER_R2N
        effect = (1 - ratio) * r2n_mean
        line = f"{arm}: paper ratio {ratio:.3f}, expected {ratio * r2n_mean:.1f}, effect {effect:+.1f}; {family}"
        if direction == "none":
            print(line + "; the paper claims no difference: described, no test")
            continue
        n = seeds[arm]
        alpha = ALPHA / k if family == "confirmatory" else ALPHA
        parts = [f"SD {sd:.1f} ({name}): power {power(abs(effect), sd, n, n_ref, alpha):.2f} at {n} vs {n_ref} seeds, "
                 f"80% needs {seeds_for(abs(effect), sd, n_ref, alpha) or '> 200'}" for name, sd in sds.items()]
        print(line + f" (alpha {alpha:.4f}); " + "; ".join(parts))


def holm_power(r2n_mean: float, sd: float, n_ref: int, seeds: dict, reps: int = 20_000, seed: int = 0,
               arm_sds: dict | None = None) -> dict:
    """Each confirmatory hypothesis's power under Holm's correction, by simulation: normal primary metrics at the
    planned means, one-tailed Welch tests against one shared R2N-PEBBLE sample, Holm at ALPHA. R2N-PEBBLE's SD is
    `sd`; a new arm's is its entry in `arm_sds`, else `sd`."""
    rng = np.random.default_rng(seed)
    reference = rng.normal(r2n_mean, sd, (reps, n_ref))
    p = []
    for arm in CONFIRMATORY:
        new = rng.normal(ARMS[arm][0] / PAPER_R2N * r2n_mean, (arm_sds or {}).get(arm, sd), (reps, seeds[arm]))
        va, vb = new.var(axis=1, ddof=1) / new.shape[1], reference.var(axis=1, ddof=1) / n_ref
        t = (new.mean(axis=1) - reference.mean(axis=1)) / np.sqrt(va + vb)
        df = (va + vb) ** 2 / (va ** 2 / (new.shape[1] - 1) + vb ** 2 / (n_ref - 1))
        p.append(stats.t.cdf(t, df))  # H1: the new arm is below R2N-PEBBLE
    p = np.array(p).T  # (reps, hypotheses)
    order = np.argsort(p, axis=1)
    thresholds = ALPHA / (p.shape[1] - np.arange(p.shape[1]))
    passed = np.cumprod(np.take_along_axis(p, order, axis=1) <= thresholds, axis=1).astype(bool)  # Holm stops at a miss
    rejected = np.zeros_like(passed)
    np.put_along_axis(rejected, order, passed, axis=1)
    return {arm: float(rejected[:, i].mean()) for i, arm in enumerate(CONFIRMATORY)}


def pooled_sd(arms) -> float:
    return float(np.sqrt(np.mean([np.var(a, ddof=1) for a in arms])))


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--achieved", action="store_true", help="the power at the SDs observed, once every run is in")
    achieved = parser.parse_args().achieved
    r2n = arm_values(REFERENCE, "r2n_pebble_stored_noise")
    pebble = arm_values(REFERENCE, "pebble_stored_noise")
    print(f"reference arms (results/stored-noise/runs): r2n_pebble_stored_noise n {len(r2n)}, mean {r2n.mean():.1f}, "
          f"SD {r2n.std(ddof=1):.1f}; pebble_stored_noise n {len(pebble)}, mean {pebble.mean():.1f}, "
          f"SD {pebble.std(ddof=1):.1f}; pooled SD {pooled_sd([r2n, pebble]):.1f}")
    if not achieved:
        sds = {"pooled reference": pooled_sd([r2n, pebble]), "R2N-PEBBLE's": float(r2n.std(ddof=1))}
        planned = {arm: spec[3] for arm, spec in ARMS.items()}
        for n_ref in (len(r2n), R2N_SEEDS):
            print(f"with R2N-PEBBLE at {n_ref} seeds:")
            report(float(r2n.mean()), sds, n_ref, planned)
        for name, sd in sds.items():
            holm = holm_power(float(r2n.mean()), sd, R2N_SEEDS, planned)
            print(f"Holm, simulated, SD {sd:.1f} ({name}), R2N-PEBBLE at {R2N_SEEDS}: "
                  + ", ".join(f"{arm} {value:.2f}" for arm, value in holm.items()))
        # the question the study exists for: R2N - agent-only, read on its CI (PROTOCOL.md); its chance to say
        # "the reward's sparsity adds less than the paper's effect" when it adds nothing
        effect = (1 - ARMS["r2n_pebble_agent_only_stored_noise"][0] / PAPER_R2N) * r2n.mean()
        for name, sd in sds.items():
            se = sd * math.sqrt(1 / 10 + 1 / R2N_SEEDS)
            t = stats.t.ppf(0.95, 10 + R2N_SEEDS - 2)
            print(f"agent-only, SD {sd:.1f} ({name}): SE of R2N - agent-only {se:.1f}; the 95% upper bound falls below "
                  f"{effect:.1f} with probability {stats.norm.cdf((effect - t * se) / se):.2f} if the true difference is 0")
        raise SystemExit
    r2n = np.concatenate([r2n, arm_values(os.path.join(STUDY, "runs"), "r2n_pebble_stored_noise")])
    print(f"R2N-PEBBLE, the {len(r2n)} seeds of the tests: mean {r2n.mean():.1f}, SD {r2n.std(ddof=1):.1f}")
    values = {arm: arm_values(os.path.join(STUDY, "runs"), arm) for arm in ARMS}
    seeds = {arm: len(v) for arm, v in values.items()}
    for arm, v in values.items():
        if len(v) < 2:
            raise SystemExit(f"{arm}: {len(v)} runs in; the power achieved needs every run")
        print(f"{arm}: n {len(v)}, mean {v.mean():.1f}, SD {v.std(ddof=1):.1f}")
    print("each arm at the SD its own test saw (its own pooled with R2N-PEBBLE's), for the effect PROTOCOL.md planned:")
    for arm, v in values.items():
        report(float(r2n.mean()), {"pooled with R2N-PEBBLE": pooled_sd([v, r2n])}, len(r2n), seeds, (arm,))
    own = {arm: float(v.std(ddof=1)) for arm, v in values.items()}
    holm = holm_power(float(r2n.mean()), float(r2n.std(ddof=1)), len(r2n), seeds, arm_sds=own)
    print(f"Holm, simulated at the SDs observed (R2N-PEBBLE {r2n.std(ddof=1):.1f}, each arm its own): "
          + ", ".join(f"{arm} {value:.2f}" for arm, value in holm.items()))
    agent = values["r2n_pebble_agent_only_stored_noise"]
    effect = (1 - ARMS["r2n_pebble_agent_only_stored_noise"][0] / PAPER_R2N) * r2n.mean()
    va, vb = r2n.var(ddof=1) / len(r2n), agent.var(ddof=1) / len(agent)
    se, df = math.sqrt(va + vb), (va + vb) ** 2 / (va ** 2 / (len(r2n) - 1) + vb ** 2 / (len(agent) - 1))
    print(f"agent-only at the SDs observed: SE of R2N - agent-only {se:.1f}; the 95% upper bound falls below "
          f"{effect:.1f} with probability {stats.norm.cdf((effect - stats.t.ppf(0.95, df) * se) / se):.2f} "
          "if the true difference is 0")
