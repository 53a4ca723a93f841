"""Where RigL would grow a run's reward members at its end, on stored noise and on fresh noise (a diagnostic for the
mechanisms' stop rule, no test; the study README's "bug search").

    python results/surf-rune/grow_probe.py RUN_FOLDER [RUN_FOLDER ...]

RUN_FOLDER is a run's scratch folder (its final model and `preferences/`, as for `members.py`). For each member,
from the final model on the run's labelled pairs (equal and skipped ones left out), twice: with the noise columns as
stored, and with them drawn anew (N(0, 1), seed 0):
- `accuracy`: its label accuracy (a tie half right);
- `grad_share`: the share of the Bradley-Terry loss's dense input-layer gradient |g| on relevant columns (real
  features and actions), the quantity RigL's grow step ranks (NaN for a constant member: it has no gradient);
- `drop_share`: of the active weights RigL would drop (the run's `reward_drop_fraction` of them, the smallest |w|),
  the share on relevant columns;
- `grow_share`: of as many positions RigL would grow (the largest |g| among those not kept, so a just-dropped one may
  regrow), the share on relevant columns; `regrown`: the share of them that were just dropped;
- `active_share`: the share of non-zero input weights on relevant columns (1.0 when dense).
Chance for each share: relevant columns / all columns. If the stored noise, not the code, moves the topology onto
the noise, the members lean on it (accuracy falls when it is drawn anew) and the gradient ranks it first.
"""
import json
import math
import os
import sys

import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from members import label_accuracy, labelled_pairs, load  # noqa: E402 (this study's; it puts the repository on the path)
from surf import preference_loss  # noqa: E402 (the same in every PbRL script)


def shares(model, rows, labels, relevant, drop_fraction) -> dict:
    """accuracy, grad_share, active_share, and drop_share, grow_share and regrown (sparse) per member (lists), on rows
    (P, 2, H, D)."""
    weight = model.weights[0]
    model.zero_grad()
    returns = model(rows.reshape(-1, rows.shape[-1])).view(-1, *rows.shape[:3]).sum(-1)  # (E, P, 2)
    preference_loss(returns, labels).sum().backward()
    g = weight.grad.abs()  # (E, hidden, D)
    active = weight.detach() != 0
    out = {"accuracy": label_accuracy(returns.detach(), labels),
           "grad_share": g[:, :, relevant].sum((1, 2)) / g.sum((1, 2)),
           "active_share": active[:, :, relevant].sum((1, 2)) / active.sum((1, 2))}
    if not active.all():
        columns = relevant.repeat(weight.shape[1])  # each flattened position's column
        k = math.floor(drop_fraction * int(active[0].sum()))
        drop = torch.where(active, -weight.detach().abs(), -torch.inf).flatten(1).topk(k, dim=1).indices
        kept = active.flatten(1).scatter(1, drop, False)
        grow = torch.where(kept, -1.0, g.flatten(1)).topk(k, dim=1).indices
        out["drop_share"], out["grow_share"] = columns[drop].float().mean(1), columns[grow].float().mean(1)
        out["regrown"] = active.flatten(1).gather(1, grow).float().mean(1)
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
            **{name: shares(model, x, labels, relevant, args.get("reward_drop_fraction", 0.2))
               for name, x in (("stored", rows), ("fresh", fresh))}}


if __name__ == "__main__":
    torch.set_num_threads(1)
    for folder in sys.argv[1:]:
        print(json.dumps({"run": os.path.basename(os.path.normpath(folder)), **probe(folder)}))
