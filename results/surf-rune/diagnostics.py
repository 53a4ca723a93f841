"""Issue 91's diagnostics per arm (PROTOCOL.md, "Diagnostics per arm" and the mechanisms' stop rule), from the event
files.

    python results/surf-rune/diagnostics.py           # analysis/diagnostics.md

For each arm, over its seeds (mean ± SE of each run's last value): the reward members' topology updates a run,
`features/{net}/relevant_weight_frac` of the actor, the critics and the reward members against its chance,
`sparse/{net}/relevant_active_frac` of every sparse layer, `pbrl/reward_true_corr`, `pbrl/heldout_accuracy`, SURF's
share of pseudo-labels kept (`pbrl/pseudo_label_rate`) and RUNE's bonus (`pbrl/beta`, `losses/rune_bonus`), and
the reward members at the run's end (`members.json`, written by `members.py`: constant members, share of rewards at
tanh's bound, label accuracy). Then the mechanisms' stop rule: a sparse layer at chance in every seed, or an arm
whose learning curve stays below 50, is named. Unlike `hypotheses.py` it reads whatever runs are in.
"""
import argparse
import json
import os
import sys

import numpy as np

STUDY = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, STUDY)
import hypotheses as h  # noqa: E402 (this study's: the arms, the runs' reading)
import power  # noqa: E402

import analyze  # noqa: E402 (the repository's; `power` put it on the path)

NETS = ["actor", "qf1", "qf2", "reward0", "reward1", "reward2"]
AGENT_NETS = NETS[:3]
# the layers each arm trains sparse, whose connectivity the stop rule reads
SPARSE = {h.R2N_PEBBLE: NETS, h.R2N_SURF: NETS, h.R2N_RUNE: NETS, h.AGENT: AGENT_NETS}
FLAT = 50.0  # a learning curve that never reaches this: the stop rule's "flat"
AT_CHANCE = 0.01  # a sparse layer whose relevant share is within this of chance has not moved
# the methods' own quantities: (tag, what it is), each run's last value and its mean over the run
METHOD_TAGS = [("pbrl/pseudo_label_rate", "SURF: share of pseudo-labels kept"), ("pbrl/beta", "RUNE: beta"),
               ("losses/rune_bonus", "RUNE: bonus, beta x mean sigma")]


def cell(values) -> str:
    values = np.asarray(values, dtype=np.float64)
    if np.isnan(values).all():
        return "-"
    mean, se = analyze.mean_se(values[~np.isnan(values)])
    return f"{mean:.3f} ± {se:.3f}" if not np.isnan(se) else f"{mean:.3f}"


def run_mean(run, tag: str) -> float:
    return float(np.mean(run.scalars[tag][1])) if tag in run.scalars else float("nan")


def members_of(run):
    """The run's `members.json` (a list, one entry per reward member), or None where it has none."""
    path = os.path.join(os.path.dirname(run.path), "members.json")
    if not os.path.exists(path):
        return None
    with open(path) as f:
        return json.load(f)


def report(arms: dict) -> list:
    lines = ["# R2N on SURF and RUNE: diagnostics per arm", "",
             "Each cell: mean ± SE over the arm's seeds of each run's last value. PEBBLE and R2N-PEBBLE are the "
             "stored-noise study's (with R2N-PEBBLE's seeds 9-10 from which-sparsity), shown beside.", "",
             "## The reward members' topology updates a run (`sparse/reward*/topology_updates`)", "",
             "| arm | seeds | updates a run (mean over the 3 members) |", "|---|---|---|"]
    for arm, runs in arms.items():
        lines.append(f"| `{arm}` | {len(runs)} | {h.topology_updates(runs)} |")
    lines += ["", "## Share of the input layer's weight on the real features (`features/{net}/relevant_weight_frac`)",
              "", "Chance: the relevant columns' share, the actor's (real features) / the others' (and actions).", "",
              "| arm | chance | " + " | ".join(NETS) + " |", "|---|---|" + "---|" * len(NETS)]
    for arm, runs in arms.items():
        chance = " / ".join(cell([h.last(r, f"features/{net}/chance") for r in runs]) for net in ("actor", "qf1"))
        lines.append(f"| `{arm}` | {chance} | " + " | ".join(
            cell([h.last(r, f"features/{net}/relevant_weight_frac") for r in runs]) for net in NETS) + " |")
    lines += ["", "## Sparse layers' share of active weights on the real features (`sparse/{net}/relevant_active_frac`)",
              "", "| arm | " + " | ".join(NETS) + " |", "|---|" + "---|" * len(NETS)]
    for arm, runs in arms.items():
        lines.append(f"| `{arm}` | " + " | ".join(
            cell([h.last(r, f"sparse/{net}/relevant_active_frac") for r in runs]) if net in SPARSE.get(arm, [])
            else "dense" for net in NETS) + " |")
    lines += ["", "## The reward against the true one", "", "| arm | `pbrl/reward_true_corr` | `pbrl/heldout_accuracy` |",
              "|---|---|---|"]
    for arm, runs in arms.items():
        lines.append(f"| `{arm}` | {cell([h.last(r, 'pbrl/reward_true_corr') for r in runs])} | "
                     f"{cell([h.last(r, 'pbrl/heldout_accuracy') for r in runs])} |")
    lines += ["", "## SURF's pseudo-labels and RUNE's bonus: last value, and mean over the run", "",
              "| arm | " + " | ".join(f"{what} (`{tag}`)" for tag, what in METHOD_TAGS) + " |",
              "|---|" + "---|" * len(METHOD_TAGS)]
    for arm, runs in arms.items():
        cells = []
        for tag, _ in METHOD_TAGS:
            final, mean = cell([h.last(r, tag) for r in runs]), cell([run_mean(r, tag) for r in runs])
            cells.append("-" if final == "-" else f"{final}; mean {mean}")
        lines.append(f"| `{arm}` | " + " | ".join(cells) + " |")
    lines += ["", "## The reward members at the run's end (`members.json`, from `members.py`; added 2026-12-07)", "",
              "From each run's final model on its labelled pairs. A constant member outputs one value on every input "
              "(tanh's gradient is 0 there): it never trains again. At the bound: |reward| > 0.999. The reference "
              "arms have no `members.json`.", "",
              "| arm | runs with it | constant members (runs with one) | share of rewards at the bound | "
              "members' label accuracy |", "|---|---|---|---|---|"]
    for arm, runs in arms.items():
        found = [m for m in map(members_of, runs) if m is not None]
        if not found:
            lines.append(f"| `{arm}` | 0 of {len(runs)} | - | - | - |")
            continue
        constant = [sum(member["constant"] for member in run) for run in found]
        lines.append(f"| `{arm}` | {len(found)} of {len(runs)} | {sum(constant)} ({sum(c > 0 for c in constant)}) | "
                     f"{cell([np.mean([m['share_at_bound'] for m in run]) for run in found])} | "
                     f"{cell([np.mean([m['label_accuracy'] for m in run]) for run in found])} |")
    lines += ["", "## Stop rule (mechanisms)", ""] + (stop_rule(arms) or [
        "Nothing to look into: no sparse layer stays at chance in every seed, and every arm's curve reaches 50."])
    return lines


def stop_rule(arms: dict) -> list:
    """A line per sparse layer at chance in every seed of its arm, and per arm whose curve never reaches `FLAT`."""
    found = []
    for arm, runs in arms.items():
        for net in SPARSE.get(arm, []):
            shares = [h.last(r, f"sparse/{net}/relevant_active_frac") - h.last(r, f"features/{net}/chance")
                      for r in runs]
            if runs and not np.isnan(shares).any() and all(share < AT_CHANCE for share in shares):
                found.append(f"- `{arm}`: `sparse/{net}/relevant_active_frac` is at chance in every seed: look for a bug")
        if runs and all(run.scalars[analyze.EVAL_TAG][1].max() < FLAT for run in runs):
            found.append(f"- `{arm}`: the learning curve stays below {FLAT:g} in every seed: look for a bug")
    return found


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--reference", default=power.REFERENCE, help="the stored-noise study's runs")
    parser.add_argument("--which-sparsity", default=power.WHICH_SPARSITY, help="R2N-PEBBLE's seeds 9-10")
    parser.add_argument("--runs", default=os.path.join(STUDY, "runs"), help="this study's runs")
    parser.add_argument("--out", default=os.path.join(STUDY, "analysis", "diagnostics.md"))
    args = parser.parse_args()
    arms = {h.PEBBLE: h.runs_of(args.reference, h.PEBBLE),
            h.R2N_PEBBLE: h.runs_of(args.reference, h.R2N_PEBBLE) + h.runs_of(args.which_sparsity, h.R2N_PEBBLE)}
    arms |= {arm: h.runs_of(args.runs, arm) for arm in h.SEEDS}
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    with open(args.out, "w") as f:
        f.write("\n".join(report(arms)) + "\n")
    print(f"diagnostics: {args.out}")


if __name__ == "__main__":
    main()
