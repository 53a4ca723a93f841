"""Where RigL would grow a run's reward members at its end, on stored noise and on fresh noise (a diagnostic for the
mechanisms' stop rule, no test; the study README's "bug search").

    python results/surf-rune/grow_probe.py RUN_FOLDER [RUN_FOLDER ...]

RUN_FOLDER is a run's scratch folder (its final model and `preferences/`, as for `members.py`). For each member,
from the final model on the run's labelled pairs (equal and skipped ones left out), twice: with the noise columns as
stored, and with them drawn anew (N(0, 1), seed 0):
- `accuracy`: its label accuracy (a tie half right);
- `grad_share`: the share of the Bradley-Terry loss's dense input-layer gradient |g| on relevant columns (real
  features and actions), the quantity RigL's grow step ranks;
- `grow_share`: of the 20% of positions RigL would grow (the largest |g| among the zero weights), the share on
  relevant columns;
- `drop_share`: of the 20% of active weights RigL would drop (the smallest |w|), the share on relevant columns;
- `active_share`: the share of non-zero input weights on relevant columns (1.0 when dense).
Chance for each share: relevant columns / all columns. If the stored noise, not the code, moves the topology onto
the noise, the members lean on it (accuracy falls when it is drawn anew) and the gradient ranks it first.
"""
import json
import os
import sys

import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from members import labelled_pairs, load  # noqa: E402 (this study's; it puts the repository on the path)
from surf import preference_loss  # noqa: E402 (the same in every PbRL script)


def shares(model, rows, labels, relevant, grow_fraction=0.2) -> dict:
    """accuracy, grad_share, active_share, and grow_share and drop_share (sparse) per member (lists), on rows (P, 2, H, D)."""
    weight = model.weights[0]
    model.zero_grad()
    returns = model(rows.reshape(-1, rows.shape[-1])).view(-1, *rows.shape[:3]).sum(-1)  # (E, P, 2)
    preference_loss(returns, labels).sum().backward()
    first, second = returns[..., 0].detach(), returns[..., 1].detach()
    accuracy = torch.where(first == second, 0.5, ((second > first).float() == labels).float()).mean(-1)
    g = weight.grad.abs()  # (E, hidden, D)
    grad_share = g[:, :, relevant].sum((1, 2)) / g.sum((1, 2))
    active = weight.detach() != 0
    zero = (~active).flatten(1)
    out = {"accuracy": accuracy, "grad_share": grad_share,
           "active_share": active[:, :, relevant].sum((1, 2)) / active.sum((1, 2))}
    if zero.any():
        k = int(grow_fraction * active[0].sum())
        top = torch.where(zero, g.flatten(1), -1.0).topk(k, dim=1).indices % g.shape[-1]  # their columns
        out["grow_share"] = relevant[top].float().mean(1)
        w = torch.where(active, weight.detach().abs(), torch.inf).flatten(1)
        smallest = (-w).topk(k, dim=1).indices % g.shape[-1]
        out["drop_share"] = relevant[smallest].float().mean(1)
    return {key: [round(float(v), 4) for v in value] for key, value in out.items()}


def probe(folder: str) -> dict:
    model, saved = load(folder)
    args = saved["args"]
    rows, labels = labelled_pairs(folder, args.get("surf_crop", 0))
    clear = (labels == 0) | (labels == 1)
    rows, labels = rows[clear], labels[clear]
    real, total = saved["obs_dim_real"], saved["obs_dim"]
    column = torch.arange(rows.shape[-1])
    relevant = (column < real) | (column >= total)
    fresh = rows.clone()
    fresh[..., real:total] = torch.randn(fresh[..., real:total].shape, generator=torch.Generator().manual_seed(0))
    return {"step": saved["global_step"], "chance": round(float(relevant.float().mean()), 4),
            "stored": shares(model, rows, labels, relevant), "fresh": shares(model, fresh, labels, relevant)}


if __name__ == "__main__":
    torch.set_num_threads(1)
    for folder in sys.argv[1:]:
        print(json.dumps({"run": os.path.basename(os.path.normpath(folder)), **probe(folder)}))
