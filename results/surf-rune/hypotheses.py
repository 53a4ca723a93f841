"""Issue 91's tests, as PROTOCOL.md fixes them: H1-H2 with Holm's correction, E1's reading, E2-E4.

    python results/surf-rune/hypotheses.py            # once every run is in: analysis/hypotheses.md

The primary metric of a run is the mean of its last 3 evaluations (`power.primary`). The study's five arms are its
`runs/`; the stored-noise study's PEBBLE (8 seeds) and R2N-PEBBLE (8, with seeds 9-10 from which-sparsity) are only
shown beside them. It refuses, with one line naming what is missing, until every run of the protocol is in.
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

PEBBLE, R2N_PEBBLE = "pebble_stored_noise", "r2n_pebble_stored_noise"
SURF, R2N_SURF, AGENT, RUNE, R2N_RUNE = power.SURF, power.R2N_SURF, power.AGENT, power.RUNE, power.R2N_RUNE
SEEDS = dict(power.SEEDS)
# arm -> what is sparse, and the paper's final return ± SE on cheetah-run 0.9/1000 (14 seeds; RQ 2's table, which
# has no actor/critic-only SURF)
PAPER = {
    PEBBLE: ("nothing", 237.62, 14.43), R2N_PEBBLE: ("reward, actor, critics (RigL)", 404.59, 17.12),
    SURF: ("nothing", 260.47, 10.74), R2N_SURF: ("reward, actor, critics (RigL)", 405.68, 18.38),
    AGENT: ("actor, critics (RigL)", None, None),
    RUNE: ("nothing", 202.37, 15.26), R2N_RUNE: ("reward, actor, critics (RigL)", 410.94, 19.18),
}
CONFIRMATORY = power.CONFIRMATORY  # H1 R2N-SURF > SURF, H2 R2N-RUNE > RUNE
# E1's threshold: the planned R2N-SURF minus the planned actor/critic-only arm (PROTOCOL.md: +46.2)
E1_EFFECT = 46.2
# which-sparsity's E1 on PEBBLE, quoted beside ours (its analysis/hypotheses.md): delta and one-sided upper bound
WHICH_SPARSITY_E1 = (-1.0, 38.8)
REWARD_MEMBERS = ("reward0", "reward1", "reward2")
RESAMPLES = 10_000


def runs_of(folder: str, arm: str) -> list:
    """The finished runs of `arm` in `folder` (analyze.py's Run objects), in seed order."""
    names = sorted((d for d in os.listdir(folder) if d.startswith(f"{arm}__") and
                    os.path.exists(os.path.join(folder, d, "done"))), key=analyze.natural_order)
    out = []
    for name in names:
        path = os.path.join(folder, name)
        [run] = analyze.read_folder(sorted(os.path.join(path, f) for f in os.listdir(path) if f.startswith("events.")))
        out.append(run)
    return out


def last(run, tag: str) -> float:
    return float(run.scalars[tag][1][-1]) if tag in run.scalars else float("nan")


def topology_updates(runs: list) -> str:
    """Mean ± SE over runs of the reward members' topology updates in a run (each run's mean over its members)."""
    values = [np.mean([last(run, f"sparse/{net}/topology_updates") for net in REWARD_MEMBERS]) for run in runs]
    values = np.asarray(values)[~np.isnan(values)]
    if len(values) == 0:
        return "none (dense reward)"
    mean, se = analyze.mean_se(values)
    return f"{mean:.1f}" + (f" ± {se:.1f}" if not np.isnan(se) else "") + f" ({len(values)} runs)"


def arms(reference: str, which_sparsity: str, runs: str) -> dict:
    """arm -> the primary metrics of its finished runs, by seed order; R2N-PEBBLE joins its two folders."""
    values = {arm: power.arm_values(runs, arm) for arm in SEEDS}
    values[PEBBLE] = power.arm_values(reference, PEBBLE)
    values[R2N_PEBBLE] = np.concatenate([power.arm_values(reference, R2N_PEBBLE),
                                         power.arm_values(which_sparsity, R2N_PEBBLE)])
    return values


def missing(values: dict) -> list:
    return [f"{arm} ({len(values[arm])} of {n})" for arm, n in SEEDS.items() if len(values[arm]) < n]


def cpus(folder: str, arm: str) -> str:
    """The CPUs and thread counts an arm's runs ran on, from their `done` files, with counts."""
    found = {}
    for run in sorted(os.listdir(folder)):
        done = os.path.join(folder, run, "done")
        if run.startswith(f"{arm}__") and os.path.exists(done):
            lines = open(done).read().splitlines()
            cpu = next((line[4:].strip() for line in lines if line.startswith("cpu ")), "not recorded")
            command = next((line for line in lines if "--threads" in line), "")
            words = command.split()
            threads = words[words.index("--threads") + 1] if "--threads" in words[:-1] else "?"
            key = f"{cpu}, {threads} thread{'s' if threads != '1' else ''}"
            found[key] = found.get(key, 0) + 1
    return "; ".join(f"{key} ×{n}" for key, n in found.items()) or "-"


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


def e1_reading(delta: float, upper: float, p: float) -> str:
    """E1's reading, fixed before the runs (PROTOCOL.md, "The second question")."""
    if p < 0.05:
        return "R2N's sparse reward adds to the return where its topology moves"
    if delta <= 0 and upper < E1_EFFECT:
        return "it adds nothing at this scale"
    return f"this study cannot tell: R2N's sparse reward adds at most {upper:.1f}"


def report(values: dict, runs_folder: str, topology: dict) -> list:
    m = {arm: float(np.mean(v)) for arm, v in values.items()}
    lines = ["# R2N on SURF and RUNE, and R2N's sparse reward where its topology moves: the tests of PROTOCOL.md", "",
             "Primary metric: the mean of a run's last 3 evaluations (cheetah-run, noise 0.9, budget 1000), ± its "
             "standard error, with Student's 95% CI. The paper's: final return ± SE over 14 seeds (RQ 2's table). "
             "PEBBLE and R2N-PEBBLE are the stored-noise study's (another commit, one thread), shown beside and not "
             "tested.", "",
             "| arm | what is sparse | seeds | ours | 95% CI | SD | paper | CPUs, threads |",
             "|---|---|---|---|---|---|---|---|"]
    for arm in (PEBBLE, R2N_PEBBLE, SURF, R2N_SURF, AGENT, RUNE, R2N_RUNE):
        v, (sparse, paper, paper_se) = values[arm], PAPER[arm]
        se = float(np.std(v, ddof=1) / math.sqrt(len(v)))
        half = stats.t.ppf(0.975, len(v) - 1) * se
        where = (cpus(runs_folder, arm) if arm in SEEDS else "stored-noise study" if arm == PEBBLE
                 else "stored-noise study (seeds 1-8), which-sparsity (9-10)")
        lines.append(f"| `{arm}` | {sparse} | {len(v)} | {m[arm]:.1f} ± {se:.1f} | [{m[arm] - half:.1f}, "
                     f"{m[arm] + half:.1f}] | {np.std(v, ddof=1):.1f} | "
                     f"{f'{paper:.2f} ± {paper_se:.2f}' if paper else '-'} | {where} |")
    p = {name: analyze.welch_p(values[high], values[low], "greater") for name, (high, low) in CONFIRMATORY.items()}
    adjusted = holm(p)
    lines += ["", "## Confirmatory: H1-H2, each R2N arm above its method, Holm at 0.05", "",
              "| | comparison | difference | paper's | Welch p (one-tailed) | Holm p | permutation p | "
              "bootstrap 95% CI | rejected |", "|---|---|---|---|---|---|---|---|---|"]
    for name, (high, low) in CONFIRMATORY.items():
        perm, _ = analyze.permutation_p(values[high], values[low], "greater")
        low_ci, high_ci = analyze.bootstrap_ci(values[high], values[low])
        lines.append(f"| {name} | `{high}` > `{low}` | {m[high] - m[low]:+.1f} | "
                     f"{PAPER[high][1] - PAPER[low][1]:+.1f} | {p[name]:.4f} | {adjusted[name]:.4f} | {perm:.4f} | "
                     f"[{low_ci:+.1f}, {high_ci:+.1f}] | {'yes' if adjusted[name] < 0.05 else 'no'} |")
    delta, se, df = welch(values[R2N_SURF], values[AGENT])
    upper, lower = delta + stats.t.ppf(0.95, df) * se, delta - stats.t.ppf(0.95, df) * se
    p_e1 = analyze.welch_p(values[R2N_SURF], values[AGENT], "greater")
    share = bootstrap({a: values[a] for a in (SURF, AGENT, R2N_SURF)},
                      lambda x: (x[AGENT] - x[SURF]) / (x[R2N_SURF] - x[SURF]))
    lines += ["", "## E1, the second question (pre-registered, exploratory)", "",
              f"Δ = R2N-SURF - its actor/critic-only arm = {delta:+.1f}, one-sided 95% bounds: lower {lower:+.1f}, "
              f"upper {upper:+.1f} (Welch, df {df:.1f}); one-tailed Welch p {p_e1:.4f}. The effect planned: "
              f"+{E1_EFFECT}.", "",
              f"**Reading, as fixed before the runs: {e1_reading(delta, upper, p_e1)}.**", "",
              f"The actor/critic-only arm's gain over SURF as a share of R2N-SURF's: "
              f"{(m[AGENT] - m[SURF]) / (m[R2N_SURF] - m[SURF]):.2f}, bootstrap 95% CI [{share[0]:.2f}, "
              f"{share[1]:.2f}].", "",
              "Beside it, descriptive (other commits, other seeds' machines; not tested against each other):", "",
              "| study | R2N minus its actor/critic-only arm | one-sided 95% upper bound | reward members' topology "
              "updates a run |", "|---|---|---|---|",
              f"| which-sparsity (PEBBLE's reward rounds) | {WHICH_SPARSITY_E1[0]:+.1f} | +{WHICH_SPARSITY_E1[1]} | "
              f"{topology[R2N_PEBBLE]} |",
              f"| this study (SURF's reward rounds) | {delta:+.1f} | {upper:+.1f} | {topology[R2N_SURF]} |"]
    low_ci, high_ci = analyze.bootstrap_ci(values[AGENT], values[SURF])
    lines += ["", "## Exploratory, no correction", "", "| | comparison | ours | paper's | p | 95% CI |",
              "|---|---|---|---|---|---|",
              f"| E2 | `{AGENT}` > `{SURF}` | {m[AGENT] - m[SURF]:+.1f} | - | "
              f"{analyze.welch_p(values[AGENT], values[SURF], 'greater'):.4f} (one-tailed) | "
              f"[{low_ci:+.1f}, {high_ci:+.1f}] (bootstrap) |"]
    for arm, base in ((SURF, PEBBLE), (RUNE, PEBBLE), (R2N_SURF, R2N_PEBBLE), (R2N_RUNE, R2N_PEBBLE)):
        low_ci, high_ci = bootstrap({arm: values[arm], base: values[base]}, lambda x: x[arm] / x[base])
        lines.append(f"| E3 | `{arm}` / `{base}` | ×{m[arm] / m[base]:.3f} | ×{PAPER[arm][1] / PAPER[base][1]:.3f} "
                     f"| - | [×{low_ci:.3f}, ×{high_ci:.3f}] (bootstrap) |")
    for arm, base in ((R2N_SURF, SURF), (R2N_RUNE, RUNE), (R2N_PEBBLE, PEBBLE)):
        a, b = values[arm], values[base]
        if arm == R2N_PEBBLE:  # the stored-noise study's own gain, its 8 seeds a side (+77.6)
            a = a[:len(b)]
        low_ci, high_ci = analyze.bootstrap_ci(a, b)
        lines.append(f"| E4 | R2N's gain: `{arm}` - `{base}` | {np.mean(a) - np.mean(b):+.1f} | "
                     f"{PAPER[arm][1] - PAPER[base][1]:+.1f} | - | [{low_ci:+.1f}, {high_ci:+.1f}] (bootstrap) |")
    return lines


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--reference", default=power.REFERENCE, help="the stored-noise study's runs")
    parser.add_argument("--which-sparsity", default=power.WHICH_SPARSITY, help="R2N-PEBBLE's seeds 9-10")
    parser.add_argument("--runs", default=os.path.join(STUDY, "runs"), help="this study's runs")
    parser.add_argument("--out", default=os.path.join(STUDY, "analysis", "hypotheses.md"))
    args = parser.parse_args()
    values = arms(args.reference, args.which_sparsity, args.runs)
    if missing(values):
        raise SystemExit(f"hypotheses: not every run is in, so no test is read: {', '.join(missing(values))}")
    topology = {R2N_PEBBLE: topology_updates(runs_of(args.reference, R2N_PEBBLE)
                                             + runs_of(args.which_sparsity, R2N_PEBBLE)),
                R2N_SURF: topology_updates(runs_of(args.runs, R2N_SURF))}
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    with open(args.out, "w") as f:
        f.write("\n".join(report(values, args.runs, topology)) + "\n")
    print(f"hypotheses: {args.out}")


if __name__ == "__main__":
    main()
