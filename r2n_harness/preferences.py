"""`--preferences`: an earlier run's query log (its `preferences/` folder or one `.npz` of it) as this run's first
labelled pairs, counted in its budget (docs/labelling.md)."""
import os

import numpy as np
import torch


def read_preferences(path: str) -> dict:
    """A run's query log as one set of arrays, from its `preferences/` folder (seeded first, then
    the rounds in order) or a single `.npz` file."""
    if os.path.isdir(path):
        rounds = sorted(int(name[:-4]) for name in os.listdir(path)
                        if name.endswith(".npz") and name[:-4].isdigit())
        seeded = [f"{path}/seeded.npz"] if os.path.exists(f"{path}/seeded.npz") else []
        files = seeded + [f"{path}/{r}.npz" for r in rounds]
    else:
        files = [path]
    parts = []
    for file in files:
        with np.load(file) as data:
            parts.append({name: data[name] for name in data.files})
    if not parts:
        raise ValueError(f"no preferences files in {path}")
    joined = {name: np.concatenate([part[name] for part in parts])
              for name in parts[0] if name != "env_id"}
    return dict(joined, env_id=parts[0]["env_id"])


def load_preferences(path: str, env_id: str, input_dim: int, segment_steps: int,
                     budget: int) -> dict:
    """The arrays of an earlier run's query log (`--preferences`): its `preferences/` folder or one
    `.npz` of it. A ValueError with one line if they do not fit this run."""
    if not os.path.exists(path):
        raise ValueError(f"--preferences: no such file or folder: {path}")
    try:
        arrays = read_preferences(path)
        arrays = {name: arrays[name]
                  for name in ("env_id", "obs", "actions", "true_rewards", "physics", "labels")}
    except Exception as e:  # not an npz, a missing array
        raise ValueError(
            f"--preferences: {path} is not a run's preferences ({type(e).__name__}: {e})"
        ) from None
    shape = arrays["obs"].shape[2], arrays["obs"].shape[3] + arrays["actions"].shape[3]
    if str(arrays["env_id"]) != env_id or shape != (segment_steps, input_dim):
        raise ValueError(f"--preferences: {path} holds {arrays['env_id']} segments of {shape[0]} "
                         f"steps x {shape[1]} features; this run needs {env_id}, {segment_steps} x "
                         f"{input_dim}")
    if len(arrays["labels"]) > budget:
        raise ValueError(f"--preferences: {path} holds {len(arrays['labels'])} queries, more than "
                         f"--max-feedback {budget}")
    return arrays


def add_preferences(preferences: dict, queries, prefs, loop, run_folder: str,
                    env_id: str, obs_dim: int, device: torch.device):
    """An earlier run's labels (`--preferences`): the first pairs of the query log and of the
    labelled pairs, counted in the budget."""
    inputs = np.concatenate([preferences["obs"], preferences["actions"]], -1)
    if queries is not None:  # `--query-log`
        queries.add(inputs, preferences["true_rewards"], preferences["physics"],
                    preferences["labels"], -1, -1)
        queries.save_round(f"{run_folder}/preferences", env_id, obs_dim, -1)
    kept = ~np.isnan(preferences["labels"])
    prefs.add(torch.as_tensor(inputs[kept], device=device),
              torch.as_tensor(preferences["labels"][kept], device=device))
    loop.total_feedback, loop.labeled_feedback = len(kept), prefs.size
