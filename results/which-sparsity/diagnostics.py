"""Issue 69's diagnostics per arm (PROTOCOL.md, "Diagnostics per arm" and the stop rule), from the event files.

    python results/which-sparsity/diagnostics.py           # analysis/diagnostics.md

For each arm, over its seeds (mean ± SE of each run's last value): `features/{net}/relevant_weight_frac` of the actor,
the critics and the reward members against its chance, `sparse/{net}/relevant_active_frac` of every sparse layer,
`pbrl/reward_true_corr` and `pbrl/heldout_accuracy`. Then the stop rule: a sparse layer at chance in every seed, or
an arm whose learning curve stays below 50, is named, to look for a bug before any test is read. Unlike
`hypotheses.py` it reads whatever runs are in: the stop rule is checked as they land.
"""
import argparse
import os
import sys

import numpy as np

STUDY = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, STUDY)
import hypotheses  # noqa: E402
import power  # noqa: E402

import analyze  # noqa: E402 (the repository's; `power` put it on the path)

NETS = ["actor", "qf1", "qf2", "reward0", "reward1", "reward2"]
AGENT_NETS, REWARD_NETS = NETS[:3], NETS[3:]
# the layers each arm trains sparse, whose connectivity the stop rule reads (the others are dense, their masks drawn
# and unused); Static's masks never change, so its connectivity stays at chance by design and is not read
SPARSE = {hypotheses.R2N: NETS, hypotheses.AGENT: AGENT_NETS, hypotheses.REWARD: REWARD_NETS,
          "set_pebble_stored_noise": NETS}
FLAT = 50.0  # a learning curve that never reaches this: the stop rule's "flat"
AT_CHANCE = 0.01  # a sparse layer whose relevant share is within this of chance has not moved


def runs_of(folder: str, arm: str) -> list:
    names = sorted(d for d in os.listdir(folder) if d.startswith(f"{arm}__") and
                   os.path.exists(os.path.join(folder, d, "done")))
    out = []
    for name in names:
        path = os.path.join(folder, name)
        [run] = analyze.read_folder(sorted(os.path.join(path, f) for f in os.listdir(path) if f.startswith("events.")))
        out.append(run)
    return out


def last(run, tag: str) -> float:
    return float(run.scalars[tag][1][-1]) if tag in run.scalars else float("nan")


def cell(values) -> str:
    values = np.asarray(values, dtype=np.float64)
    if np.isnan(values).all():
        return "-"
    mean, se = analyze.mean_se(values[~np.isnan(values)])
    return f"{mean:.3f} ± {se:.3f}" if not np.isnan(se) else f"{mean:.3f}"


def report(arms: dict) -> list:
    lines = ["# Which sparsity carries R2N's gain? Diagnostics per arm", "",
             "Each cell: mean ± SE over the arm's seeds of each run's last value.", "",
             "## Share of the input layer's weight on the real features (`features/{net}/relevant_weight_frac`)", "",
             "Chance: the relevant columns' share, the actor's (real features) / the others' (and actions).", "",
             "| arm | seeds | chance | " + " | ".join(NETS) + " |", "|---|---|---|" + "---|" * len(NETS)]
    for arm, runs in arms.items():
        chance = " / ".join(cell([last(r, f"features/{net}/chance") for r in runs]) for net in ("actor", "qf1"))
        lines.append(f"| `{arm}` | {len(runs)} | {chance} | " + " | ".join(
            cell([last(r, f"features/{net}/relevant_weight_frac") for r in runs]) for net in NETS) + " |")
    lines += ["", "## Sparse layers' share of active weights on the real features (`sparse/{net}/relevant_active_frac`)",
              "", "| arm | " + " | ".join(NETS) + " |", "|---|" + "---|" * len(NETS)]
    for arm, runs in arms.items():
        lines.append(f"| `{arm}` | " + " | ".join(
            cell([last(r, f"sparse/{net}/relevant_active_frac") for r in runs]) for net in NETS) + " |")
    lines += ["", "## The reward against the true one", "", "| arm | `pbrl/reward_true_corr` | `pbrl/heldout_accuracy` |",
              "|---|---|---|"]
    for arm, runs in arms.items():
        lines.append(f"| `{arm}` | {cell([last(r, 'pbrl/reward_true_corr') for r in runs])} | "
                     f"{cell([last(r, 'pbrl/heldout_accuracy') for r in runs])} |")
    lines += ["", "## Stop rule", ""] + (stop_rule(arms) or ["Nothing to look into: no sparse layer stays at chance in "
                                                          "every seed, and every arm's curve reaches 50."])
    return lines


def stop_rule(arms: dict) -> list:
    """A line per sparse layer at chance in every seed of its arm, and per arm whose curve never reaches `FLAT`."""
    found = []
    for arm, runs in arms.items():
        for net in SPARSE.get(arm, []):
            shares = [last(r, f"sparse/{net}/relevant_active_frac") - last(r, f"features/{net}/chance") for r in runs]
            if runs and not np.isnan(shares).any() and all(share < AT_CHANCE for share in shares):
                found.append(f"- `{arm}`: `sparse/{net}/relevant_active_frac` is at chance in every seed: look for a bug")
        if runs and all(run.scalars[analyze.EVAL_TAG][1].max() < FLAT for run in runs):
            found.append(f"- `{arm}`: the learning curve stays below {FLAT:g} in every seed: look for a bug")
    return found


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--reference", default=power.REFERENCE, help="the stored-noise study's runs")
    parser.add_argument("--runs", default=os.path.join(STUDY, "runs"), help="this study's runs")
    parser.add_argument("--out", default=os.path.join(STUDY, "analysis", "diagnostics.md"))
    args = parser.parse_args()
    arms = {arm: runs_of(args.reference, arm) for arm in (hypotheses.PEBBLE, hypotheses.R2N)}
    arms[hypotheses.R2N] += runs_of(args.runs, hypotheses.R2N)
    arms |= {arm: runs_of(args.runs, arm) for arm in power.ARMS}
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    with open(args.out, "w") as f:
        f.write("\n".join(report(arms)) + "\n")
    print(f"diagnostics: {args.out}")


if __name__ == "__main__":
    main()
