"""The learning check's curves (README.md here): evaluation return and success rate against steps for each committed
run in runs/, with the random policy's. Writes curves.png and curves.md.

    python results/metaworld-check/curves.py
"""
import os

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

HERE = os.path.dirname(os.path.abspath(__file__))
RANDOM_RETURN = 582.8  # run.sh's measure: uniform actions in the 10 evaluation envs, success rate 0.0
RUNS = {"sac-drawer-open-v3": "sac.py, noise 0.9 (the check)", "sac-drawer-open-v3-noise0": "sac.py, noise 0",
        "pebble-drawer-open-v3": "pebble.py, noise 0.9", "r2n_pebble-drawer-open-v3": "r2n_pebble.py, noise 0.9"}

fig, (ax_return, ax_success) = plt.subplots(1, 2, figsize=(10, 3.8))
rows = ["| run | step | eval return | success rate |", "|---|---|---|---|"]
for run, label in RUNS.items():
    folder = os.path.join(HERE, "runs", run)
    if not os.path.isdir(folder):
        continue
    events = EventAccumulator(folder, size_guidance={"scalars": 0})
    events.Reload()
    if "eval/episodic_return" not in events.Tags()["scalars"]:  # not evaluated yet
        continue
    returns = events.Scalars("eval/episodic_return")
    success = {e.step: e.value for e in events.Scalars("eval/success_rate")}
    ax_return.plot([e.step for e in returns], [e.value for e in returns], marker="o", label=label)
    ax_success.plot(list(success), list(success.values()), marker="o", label=label)
    rows += [f"| {label} | {e.step} | {e.value:.1f} | {success.get(e.step, float('nan')):.1f} |" for e in returns]
ax_return.axhline(RANDOM_RETURN, color="grey", linestyle="--", label="random policy")
ax_return.set(xlabel="environment steps", ylabel="evaluation return (10 episodes)", title="drawer-open-v3")
ax_success.axhline(0.5, color="grey", linestyle=":", label="the check's threshold")
ax_success.set(xlabel="environment steps", ylabel="success rate", ylim=(-0.05, 1.05), title="drawer-open-v3")
ax_return.legend(fontsize=7)
ax_success.legend(fontsize=7)
fig.tight_layout()
fig.savefig(os.path.join(HERE, "curves.png"), dpi=120)
with open(os.path.join(HERE, "curves.md"), "w") as f:
    f.write("\n".join(rows) + "\n")
print(f"curves: {HERE}/curves.png, curves.md")
