"""Each reward member at a run's end, from its final model and its labelled pairs (PROTOCOL.md, addition of
2026-12-07, second): a diagnostic, no test.

    python results/surf-rune/members.py RUN_FOLDER OUT_JSON

RUN_FOLDER holds the run's `{exp_name}.cleanrl_model` and `preferences/` (the launcher's scratch folder of the run).
Per member (with the model's step): its accuracy on the run's labelled pairs (equal and skipped ones left out, a tie
half right), the share of its per-step rewards at tanh's bound (|r| > 0.999), the median |pre-activation| of its
output, and whether it is constant (its rewards' SD below 1e-6). A constant member sits where tanh's gradient is 0 on
every input: it never trains again, and the ensemble mean the agent learns from carries only the others' signal.
"""
import glob
import json
import os
import sys

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.realpath(__file__)))))
from surf import RewardEnsemble  # noqa: E402 (the same class in every PbRL script)

AT_BOUND = 0.999  # tanh(3.8): a reward this close to +-1 barely moves under its gradient
CONSTANT = 1e-6  # a member whose rewards' SD is below this outputs one value


def labelled_pairs(folder: str, crop: int):
    """The run's labelled pairs: rows (P, 2, H, obs + action) over the labelled steps, and labels (P,)."""
    parts = [np.load(f) for f in sorted(glob.glob(os.path.join(folder, "preferences", "*.npz")))]
    rows = np.concatenate([np.concatenate([p["obs"], p["actions"]], -1) for p in parts])
    labels = np.concatenate([p["labels"] for p in parts])
    if crop:  # SURF stores crop steps either side of the H steps the teacher labelled
        rows = rows[:, :, crop:rows.shape[2] - crop]
    return torch.as_tensor(rows, dtype=torch.float32), torch.as_tensor(labels, dtype=torch.float32)


def label_accuracy(returns: torch.Tensor, labels: torch.Tensor) -> torch.Tensor:
    """Per member, the share of pairs (returns (E, P, 2), labels (P,) of 0 or 1) whose preferred segment it returns
    higher. A tie (a constant member ties every pair) is half right, as a coin would be."""
    first, second = returns[..., 0], returns[..., 1]
    return torch.where(first == second, 0.5, ((second > first).float() == labels).float()).mean(-1)


def load(folder: str):
    """The run's reward ensemble from its final model, and the saved checkpoint."""
    found = glob.glob(os.path.join(folder, "*.cleanrl_model"))
    if len(found) != 1:
        raise SystemExit(f"members.py: {folder} holds {len(found)} final models (*.cleanrl_model), not one")
    [path] = found
    saved = torch.load(path, map_location="cpu", weights_only=False)
    args, states = saved["args"], saved["reward_models"]
    model = RewardEnsemble(saved["obs_dim"] + saved["act_dim"], args["reward_hidden_dim"], args["reward_layers"],
                           len(states))
    model.load_state_dict({name: torch.stack([s[name] for s in states]) for name in states[0]})
    return model, saved


def members(folder: str) -> list:
    model, saved = load(folder)
    states = saved["reward_models"]
    rows, labels = labelled_pairs(folder, saved["args"].get("surf_crop", 0))
    with torch.no_grad():  # the model's forward, keeping the output layer's pre-activation
        x = rows.reshape(-1, rows.shape[-1]).expand(len(states), -1, -1)
        for weight, bias in zip(model.weights, model.biases):
            pre = torch.baddbmm(bias, x, weight.transpose(1, 2))
            x = torch.nn.functional.leaky_relu(pre)
        pre = pre.squeeze(-1)  # (E, rows)
        rewards = torch.tanh(pre)
        assert torch.equal(rewards, model(rows.reshape(-1, rows.shape[-1]))), "not the model's forward"
    returns = rewards.view(len(states), *rows.shape[:3]).sum(-1)  # (E, P, 2)
    clear = (labels == 0) | (labels == 1)  # not equal (0.5), nor skipped (NaN)
    correct = label_accuracy(returns[:, clear], labels[clear])
    return [{"member": e, "step": saved["global_step"], "label_accuracy": round(float(correct[e]), 4),
             "share_at_bound": round(float((rewards[e].abs() > AT_BOUND).float().mean()), 4),
             "median_abs_preactivation": round(float(pre[e].abs().median()), 2),
             "constant": bool(rewards[e].std() < CONSTANT)} for e in range(len(states))]


if __name__ == "__main__":
    folder, out = sys.argv[1], sys.argv[2]
    torch.set_num_threads(1)
    result = members(folder)
    with open(out, "w") as f:
        json.dump(result, f, indent=1)
    print(f"{out}: {sum(m['constant'] for m in result)} of {len(result)} members constant")
