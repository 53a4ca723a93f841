"""Issue 69's tests, as PROTOCOL.md fixes them: H1-H3 with Holm's correction, E1's reading, E2-E5.

    python results/which-sparsity/hypotheses.py            # once every run is in: analysis/hypotheses.md

The primary metric of a run is the mean of its last 3 evaluations (`power.primary`). The reference arms are the
stored-noise study's (8 seeds each); R2N-PEBBLE's seeds 9-10 and the new arms are this study's `runs/`. It refuses,
with one line naming what is missing, until every run of the protocol is in.
"""
import argparse
import math
import os
import sys

import numpy as np
from scipy import stats

STUDY = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, STUDY)
import power  # noqa: E402 (this study's: the arms, the primary metric)

sys.path.insert(0, power.ROOT)
import analyze  # noqa: E402 (the repository's: Welch, permutation and bootstrap)

PEBBLE, R2N = "pebble_stored_noise", "r2n_pebble_stored_noise"
AGENT, REWARD = "r2n_pebble_agent_only_stored_noise", "r2n_pebble_reward_only_stored_noise"
SEEDS = {PEBBLE: 8, R2N: 10} | {arm: spec[3] for arm, spec in power.ARMS.items()}
HYPOTHESES = {"H1": REWARD, "H2": "dropconnect_pebble_stored_noise", "H3": "l1_pebble_stored_noise"}
# arm -> what is sparse, and the paper's final return ± SE on cheetah-run 0.9/1000 (14 seeds, appendix tables)
PAPER = {
    PEBBLE: ("nothing", 237.62, 14.43), R2N: ("reward, actor, critics (RigL)", power.PAPER_R2N, 12.53),
    AGENT: ("actor, critics (RigL)", 327.33, 17.82), REWARD: ("reward (RigL)", 265.27, 22.51),
    "set_pebble_stored_noise": ("everywhere, random regrowth", 404.03, 13.36),
    "static_pebble_stored_noise": ("everywhere, masks fixed", 377.23, 13.53),
    "dropconnect_pebble_stored_noise": ("reward (DropConnect), dense agent", 219.24, 19.39),
    "l1_pebble_stored_noise": ("reward (L1), dense agent", 239.53, 14.52),
}
E1_EFFECT = 38.6  # the paper's relative effect of the actor/critic-only arm, on our R2N-PEBBLE (PROTOCOL.md)
RESAMPLES = 10_000


def arms(reference: str, runs: str) -> dict:
    """arm -> the primary metrics of its finished runs, by seed order; R2N-PEBBLE joins the two folders."""
    values = {arm: power.arm_values(runs, arm) for arm in power.ARMS}
    values[PEBBLE] = power.arm_values(reference, PEBBLE)
    values[R2N] = np.concatenate([power.arm_values(reference, R2N), power.arm_values(runs, R2N)])
    return values


def cpus(folders: tuple, arm: str) -> str:
    """The CPUs an arm's runs ran on, from their `done` files, with counts (older files did not record it)."""
    found = {}
    for folder in folders:
        for run in sorted(os.listdir(folder)):
            done = os.path.join(folder, run, "done")
            if run.startswith(f"{arm}__") and os.path.exists(done):
                cpu = next((line[4:].strip() for line in open(done) if line.startswith("cpu ")), "not recorded")
                found[cpu] = found.get(cpu, 0) + 1
    return "; ".join(f"{cpu} ×{n}" for cpu, n in found.items())


def missing(values: dict) -> list:
    return [f"{arm} ({len(values[arm])} of {n})" for arm, n in SEEDS.items() if len(values[arm]) < n]


def welch(a, b) -> tuple:
    """mean(a) - mean(b), its standard error and Welch's degrees of freedom."""
    va, vb = np.var(a, ddof=1) / len(a), np.var(b, ddof=1) / len(b)
    df = (va + vb) ** 2 / (va ** 2 / (len(a) - 1) + vb ** 2 / (len(b) - 1))
    return float(np.mean(a) - np.mean(b)), math.sqrt(va + vb), df


def holm(p: dict) -> dict:
    """Holm's adjusted p of each hypothesis: the k-th smallest times (m - k + 1), kept monotone."""
    adjusted, running = {}, 0.0
    for k, name in enumerate(sorted(p, key=p.get)):
        running = max(running, min(1.0, (len(p) - k) * p[name]))
        adjusted[name] = running
    return adjusted


def bootstrap(values: dict, statistic, seed: int = 0) -> tuple:
    """Percentile 95% CI of `statistic(means)`, each arm resampled on its own."""
    rng = np.random.default_rng(seed)
    means = {arm: np.asarray(v)[rng.integers(0, len(v), (RESAMPLES, len(v)))].mean(axis=1)
             for arm, v in values.items()}
    low, high = np.percentile(statistic(means), [2.5, 97.5])
    return float(low), float(high)


def report(values: dict, folders: tuple) -> list:
    m = {arm: float(np.mean(v)) for arm, v in values.items()}
    lines = ["# Which sparsity carries R2N's gain? The tests of PROTOCOL.md", "",
             "Primary metric: the mean of a run's last 3 evaluations (cheetah-run, noise 0.9, budget 1000), ± its "
             "standard error, with Student's 95% CI. The paper's: final return ± SE over 14 seeds; relative: the arm's "
             "mean over R2N-PEBBLE's.", "",
             "| arm | what is sparse | seeds | ours | 95% CI | SD | relative | paper | paper relative | CPUs |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for arm in sorted(values, key=lambda a: -PAPER[a][1]):
        v, (sparse, paper, paper_se) = values[arm], PAPER[arm]
        se = float(np.std(v, ddof=1) / math.sqrt(len(v)))
        half = stats.t.ppf(0.975, len(v) - 1) * se
        lines.append(f"| `{arm}` | {sparse} | {len(v)} | {m[arm]:.1f} ± {se:.1f} | [{m[arm] - half:.1f}, "
                     f"{m[arm] + half:.1f}] | {np.std(v, ddof=1):.1f} | {m[arm] / m[R2N]:.2f} | {paper:.2f} ± "
                     f"{paper_se:.2f} | {paper / power.PAPER_R2N:.2f} | {cpus(folders, arm)} |")
    p = {name: analyze.welch_p(values[arm], values[R2N], "less") for name, arm in HYPOTHESES.items()}
    adjusted = holm(p)
    lines += ["", "## Confirmatory: H1-H3, each arm below R2N-PEBBLE, Holm at 0.05", "",
              "| | arm | difference | Welch p (one-tailed) | Holm p | permutation p | bootstrap 95% CI | rejected |",
              "|---|---|---|---|---|---|---|---|"]
    for name, arm in HYPOTHESES.items():
        perm, _ = analyze.permutation_p(values[arm], values[R2N], "less")
        low, high = analyze.bootstrap_ci(values[arm], values[R2N])
        lines.append(f"| {name} | `{arm}` | {m[arm] - m[R2N]:+.1f} | {p[name]:.4f} | {adjusted[name]:.4f} | "
                     f"{perm:.4f} | [{low:+.1f}, {high:+.1f}] | {'yes' if adjusted[name] < 0.05 else 'no'} |")
    delta, se, df = welch(values[R2N], values[AGENT])
    upper, lower = delta + stats.t.ppf(0.95, df) * se, delta - stats.t.ppf(0.95, df) * se
    p_e1 = analyze.welch_p(values[AGENT], values[R2N], "less")
    reading = ("the reward's sparsity adds nothing at this scale" if delta <= 0 and upper < E1_EFFECT
               else "the reward's sparsity adds to the gain" if p_e1 < 0.05
               else f"this study cannot tell: the reward's sparsity adds at most {upper:.1f}")
    share = bootstrap({a: values[a] for a in (PEBBLE, AGENT, R2N)},
                      lambda x: (x[AGENT] - x[PEBBLE]) / (x[R2N] - x[PEBBLE]))
    lines += ["", "## E1, the study's question (pre-registered, exploratory)", "",
              f"Δ = R2N-PEBBLE - actor/critic-only = {delta:+.1f}, one-sided 95% bounds: lower {lower:+.1f}, upper "
              f"{upper:+.1f} (Welch, df {df:.1f}); one-tailed Welch p {p_e1:.4f}.", "",
              f"**Reading, as fixed before the runs: {reading}.**", "",
              f"The actor/critic-only arm's gain over PEBBLE as a share of R2N-PEBBLE's: "
              f"{(m[AGENT] - m[PEBBLE]) / (m[R2N] - m[PEBBLE]):.2f}, bootstrap 95% CI [{share[0]:.2f}, {share[1]:.2f}]."]
    lines += ["", "## Exploratory, no correction", "", "| | comparison | difference | p | 95% CI |", "|---|---|---|---|---|"]
    for name, arm in (("E2", AGENT), ("E3", REWARD)):
        low, high = analyze.bootstrap_ci(values[arm], values[PEBBLE])
        lines.append(f"| {name} | `{arm}` > PEBBLE | {m[arm] - m[PEBBLE]:+.1f} | "
                     f"{analyze.welch_p(values[arm], values[PEBBLE], 'greater'):.4f} (one-tailed) | "
                     f"[{low:+.1f}, {high:+.1f}] (bootstrap) |")
    factorial = {a: values[a] for a in (PEBBLE, REWARD, AGENT, R2N)}
    effects = {
        "E4 agent's sparsity (main effect)": lambda x: ((x[R2N] - x[REWARD]) + (x[AGENT] - x[PEBBLE])) / 2,
        "E4 reward's sparsity (main effect)": lambda x: ((x[R2N] - x[AGENT]) + (x[REWARD] - x[PEBBLE])) / 2,
        "E4 interaction": lambda x: (x[R2N] - x[AGENT]) - (x[REWARD] - x[PEBBLE]),
    }
    for name, effect in effects.items():
        low, high = bootstrap(factorial, effect)
        lines.append(f"| {name.split()[0]} | {name[3:]} | {effect(m):+.1f} | - | [{low:+.1f}, {high:+.1f}] (bootstrap) |")
    for arm in ("set_pebble_stored_noise", "static_pebble_stored_noise"):
        delta, se, df = welch(values[arm], values[R2N])
        p_two = float(stats.ttest_ind(values[arm], values[R2N], equal_var=False).pvalue)
        half = stats.t.ppf(0.975, df) * se
        lines.append(f"| E5 | `{arm}` vs R2N-PEBBLE | {delta:+.1f} | {p_two:.4f} (two-sided) | "
                     f"[{delta - half:+.1f}, {delta + half:+.1f}] (Welch) |")
    return lines


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--reference", default=power.REFERENCE, help="the stored-noise study's runs")
    parser.add_argument("--runs", default=os.path.join(STUDY, "runs"), help="this study's runs")
    parser.add_argument("--out", default=os.path.join(STUDY, "analysis", "hypotheses.md"))
    args = parser.parse_args()
    values = arms(args.reference, args.runs)
    if missing(values):
        raise SystemExit(f"hypotheses: not every run is in, so no test is read: {', '.join(missing(values))}")
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    with open(args.out, "w") as f:
        f.write("\n".join(report(values, (args.reference, args.runs))) + "\n")
    print(f"hypotheses: {args.out}")


if __name__ == "__main__":
    main()
