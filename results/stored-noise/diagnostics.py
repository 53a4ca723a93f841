"""The PbRL arms of both environments side by side: return, reward quality and where the input layers put their weight.

    python results/stored-noise/diagnostics.py   # a Markdown table (analyze.sh keeps it in analysis-probes/)

Per arm, mean ± SE over seeds of each run's last logged value:
- the primary metric (the mean of the last 3 evaluations);
- `pbrl/reward_true_corr` and `pbrl/heldout_accuracy`;
- `relevant_weight_frac` of the actor, of the critics and of the reward members (the critics', and the members',
  averaged within each run first);
- `relevant_active_frac` of the reward members: the share of their active connections on the relevant columns.
A dash: the arm's runs do not log it. The cheetah study's runs predate `relevant_weight_frac`, and a dense layer has
no active-connection share of its own (it is chance).
"""
import os
import sys

import numpy as np

STUDY = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(STUDY, "..", ".."))
import analyze  # noqa: E402 (the repository's: its run reading)

CHEETAH = os.path.join(STUDY, "..", "cheetah-study")
PROBES, RUNS = os.path.join(STUDY, "probes"), os.path.join(STUDY, "runs")
LAST = 3
ARMS = (  # method, environment, its folder, agent and reward model
    ("pebble", "redrawn", CHEETAH, "dense", "dense"),
    ("r2n_pebble", "redrawn", CHEETAH, "sparse", "sparse"),
    ("pebble_repeat", "redrawn", PROBES, "dense", "dense"),
    ("r2n_pebble_reward_only", "redrawn", PROBES, "dense", "sparse"),
    ("r2n_pebble_agent_as_reward", "redrawn", PROBES, "sparse, the reward's settings", "sparse"),
    ("pebble_stored_noise", "stored", RUNS, "dense", "dense"),
    ("r2n_pebble_stored_noise", "stored", RUNS, "sparse", "sparse"),
)
COLUMNS = (  # header, the tags averaged within a run, digits
    ("primary metric", ("primary",), 1),
    ("`reward_true_corr`", ("pbrl/reward_true_corr",), 3),
    ("held-out accuracy", ("pbrl/heldout_accuracy",), 3),
    ("actor weight", ("features/actor/relevant_weight_frac",), 3),
    ("critics' weight", tuple(f"features/qf{i}/relevant_weight_frac" for i in (1, 2)), 3),
    ("reward members' weight", tuple(f"features/reward{i}/relevant_weight_frac" for i in range(3)), 3),
    ("reward members' active connections", tuple(f"sparse/reward{i}/relevant_active_frac" for i in range(3)), 3),
)


def final(run, tag: str) -> float:
    """A run's last value of `tag`; its primary metric for "primary"."""
    if tag == "primary":
        return float(run.scalars[analyze.EVAL_TAG][1][-LAST:].mean())
    return float(run.scalars[tag][1][-1])


def cell(runs, tags, digits: int) -> str:
    """Mean ± SE over the runs of each run's average of `tags`; a dash when a run lacks one."""
    if not all(tag == "primary" or tag in run.scalars for run in runs for tag in tags):
        return "-"
    per_run = np.array([np.mean([final(run, tag) for tag in tags]) for run in runs])
    mean, se = analyze.mean_se(per_run)
    return f"{mean:.{digits}f} ± {se:.{digits}f}"


def chance(runs, net: str) -> str:
    """The chance level of `net`'s `relevant_weight_frac`, as the runs log it."""
    tag = f"features/{net}/chance"
    values = {final(run, tag) for run in runs if tag in run.scalars}
    return ", ".join(f"{value:.3f}" for value in sorted(values))


def main() -> int:
    loaded = {folder: analyze.load_runs([folder]) for folder in (CHEETAH, PROBES, RUNS) if os.path.isdir(folder)}
    header = ["arm", "noise", "agent", "reward model", "seeds"] + [name for name, _, _ in COLUMNS]
    print("| " + " | ".join(header) + " |")
    print("|" + "---|" * len(header))
    for method, environment, folder, agent, reward in ARMS:
        runs = [run for run in loaded.get(folder, []) if run.status == "used" and run.hparams["exp_name"] == method]
        if not runs:
            continue
        cells = [f"`{method}`", environment, agent, reward, str(len(runs))]
        print("| " + " | ".join(cells + [cell(runs, tags, digits) for _, tags, digits in COLUMNS]) + " |")
    print()
    every_run = [run for runs in loaded.values() for run in runs if run.status == "used"]
    actor, critics, members = (chance(every_run, net) or "-" for net in ("actor", "qf1", "reward0"))
    print(f"Chance of `relevant_weight_frac`: actor {actor}, critics {critics}, reward members {members}; it is also "
          "the chance of the active-connection share.")
    return 0


if __name__ == "__main__":
    sys.exit(main())
