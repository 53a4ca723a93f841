"""`--resumable`: exact resume (docs/running.md, "Resuming a run"). A run writes its whole training
state to `runs/{run_name}/state.pt`: the objects its loop changes (the script's `saved` dict), the
global generators, the envs' generators and the observation to act on. The same command with
`--run-name` continues it, bit for bit as if it had never stopped.

What it keeps of an object (`state_of`): a tensor itself, `state_dict()` where there is one, a
dataclass field by field, a buffer's stored rows (not its preallocation), a sparse optimizer's
inner state with its masks and counters. The running episode is not saved: its actions are
(`Loop.episode_actions`), and a resume replays them from the generators saved at its start
(`Loop.episode_start`), as MuJoCo is deterministic."""
import dataclasses
import os
import random
import time
from collections import deque
from dataclasses import fields
from typing import Optional

import numpy as np
import torch

import ene


# the flags a resume may change, and no others: none of them touches training
RESUMABLE_FLAGS = (
    "threads", "cuda", "track", "wandb_project_name", "wandb_entity", "capture_video", "save_model",
    "log_freq", "state_minutes", "checkpoint_freq", "keep_state", "parallel_eval", "diagnostics",
)


def open_state(args) -> Optional[dict]:
    """The saved state when `--run-name` names a folder holding a `state.pt`, else None. A
    ValueError with one line if it cannot be read, or if the run it saved differs in a flag that a
    resume may not change."""
    path = f"runs/{args.run_name}/state.pt"
    if args.run_name is None or not os.path.exists(path):
        return None
    try:
        # our own file: not only tensors
        state = torch.load(path, map_location="cpu", mmap=True, weights_only=False)
    except Exception as e:  # not a state file, or a truncated one
        raise ValueError(
            f"--run-name {args.run_name}: cannot read {path} ({type(e).__name__}: {e})"
        ) from None
    if "loop" in state:  # an older state format: the loop's variables as tuples, not as `Loop`
        raise ValueError(
            f"--run-name {args.run_name}: {path} was written by an older version of this script; "
            "resume it with that version (git checkout 88b95d9)"
        )
    # a flag added since: its default; a state written before these flags had both on
    defaults = {field.name: field.default for field in fields(args)}
    defaults |= {name: True for name in ("resumable", "query_log") if name in defaults}
    defaults |= {"hidden_layers": 2}  # before --hidden-layers, every network had two
    saved = {**defaults, **state["args"]}
    changed = [
        f"--{name.replace('_', '-')} {saved[name]} (now {value})"
        for name, value in vars(args).items()
        if name not in RESUMABLE_FLAGS and saved[name] != value
    ]
    if changed:
        resumable = ", --".join(flag.replace("_", "-") for flag in RESUMABLE_FLAGS)
        raise ValueError(
            f"--run-name {args.run_name}: the saved run differs in {', '.join(changed)}; "
            f"a resume may change only --{resumable}"
        )
    return state


def save_atomically(state: dict, path: str):
    """Write a temporary file, flush it to disk, then rename
    it: a kill during the write leaves the last state."""
    with open(f"{path}.tmp", "wb") as f:
        torch.save(state, f)
        f.flush()
        os.fsync(f.fileno())
    os.replace(f"{path}.tmp", path)


# a dataclass's fields of these types are saved as they are
PLAIN = (int, float, list, dict, deque, type(None))


def state_of(obj):
    """What `state.pt` keeps of an object.

    That is a tensor itself, a sparse optimizer's inner state with its masks and counters,
    `obj.state_dict()`, a dataclass field by field, a buffer's stored rows (`stored_rows`),
    or for another plain object (episode store, statistics) its tensors and numbers."""
    if isinstance(obj, torch.Tensor):
        return obj.detach()
    if hasattr(obj, "masks"):  # the weights are saved with their networks
        counters = {name: value for name, value in vars(obj).items() if isinstance(value, int)}
        return {"optimizer": obj.optimizer.state_dict(), "masks": obj.masks, "counters": counters}
    if hasattr(obj, "state_dict"):
        return obj.state_dict()
    if dataclasses.is_dataclass(obj):
        return {name: value if isinstance(value, PLAIN) else state_of(value)
                for name, value in vars(obj).items()}
    if hasattr(obj, "size"):
        return stored_rows(obj)
    return {
        name: value
        for name, value in vars(obj).items()
        if isinstance(value, (torch.Tensor, np.ndarray, int, float))
    }


def stored_rows(buffer) -> dict:
    """A buffer's numbers and the first `size` rows of its
    tensors: a slice alone would save the whole preallocation.

    A replay buffer's `next_obs` is kept only where it is not the next row's `obs`,
    that is at episode ends and in the newest row. The comparison is bitwise."""
    n = buffer.size
    state = {name: value for name, value in vars(buffer).items() if isinstance(value, (int, float))}
    state["rows"] = {
        name: x[:n] if n == len(x) else x[:n].clone()
        for name, x in vars(buffer).items()
        if isinstance(x, torch.Tensor) and name != "next_obs"
    }
    if hasattr(buffer, "next_obs"):
        own = torch.ones(n, dtype=torch.bool, device=buffer.obs.device)
        next_bits = buffer.next_obs[: n - 1].view(torch.int32)
        own[:-1] = (next_bits != buffer.obs[1:n].view(torch.int32)).any(1)
        state["own_next_obs"] = own
        state["next_obs"] = buffer.next_obs[:n][own]
    return state


def load_stored_rows_(buffer, state: dict):
    """Restore what `stored_rows` saved, in place."""
    for name, rows in state["rows"].items():
        full = getattr(buffer, name)
        # a buffer that allocates its rows at the first add (SURF's segments)
        if full.shape[1:] != rows.shape[1:]:
            full = full.new_zeros((len(full), *rows.shape[1:]))
            setattr(buffer, name, full)
        full[: len(rows)] = rows
    if "next_obs" in state:
        n, own = state["size"], state["own_next_obs"].to(buffer.obs.device)
        buffer.next_obs[: n - 1] = buffer.obs[1:n]
        buffer.next_obs[:n][own] = state["next_obs"].to(buffer.obs.device)
    for name, value in state.items():
        if isinstance(value, (int, float)):
            setattr(buffer, name, value)


@torch.no_grad()
def load_state_(obj, state):
    """Restore what `state_of` saved, in place (tensors are copied onto the object's device)."""
    if isinstance(obj, torch.Tensor):
        obj.copy_(state)
    elif hasattr(obj, "masks"):
        obj.optimizer.load_state_dict(state["optimizer"])
        for name, mask in obj.masks.items():
            mask.copy_(state["masks"][name])
        vars(obj).update(state["counters"])
    elif hasattr(obj, "load_state_dict"):
        obj.load_state_dict(state)
    # what `state_of` saved as it was is set, the rest restored in place
    elif dataclasses.is_dataclass(obj):
        for name, value in state.items():
            if isinstance(getattr(obj, name), PLAIN):
                setattr(obj, name, value)
            else:
                load_state_(getattr(obj, name), value)
    elif hasattr(obj, "size"):
        load_stored_rows_(obj, state)
    else:
        for name, value in state.items():
            if isinstance(value, torch.Tensor):
                getattr(obj, name).copy_(value)
            else:
                setattr(obj, name, value)


def rng_states(device: torch.device) -> dict:
    """The global generators: python's, numpy's, torch's
    (and the GPU's on one); the envs keep their own."""
    cuda = torch.cuda.get_rng_state(device) if device.type == "cuda" else None
    return {
        "python": random.getstate(),
        "numpy": np.random.get_state(),
        "torch": torch.get_rng_state(),
        "cuda": cuda,
    }


def set_rng_states(states: dict, device: torch.device):
    random.setstate(states["python"])
    np.random.set_state(states["numpy"])
    torch.set_rng_state(states["torch"])
    if states["cuda"] is not None and device.type == "cuda":
        torch.cuda.set_rng_state(states["cuda"], device)


def save_state(path: str, args, global_step: int, elapsed: float, obs: torch.Tensor, saved: dict,
               device: torch.device, envs: list, writer):
    """Write `state.pt`: everything the loop needs to continue exactly after step `global_step`:
    the `saved` objects, the generators, the envs' generators and the observation to act on."""
    started = time.time()
    # the points up to this step are on disk before a state that a resume purges back to
    writer.flush()
    save_atomically({
        "args": vars(args), "global_step": global_step + 1, "elapsed": elapsed, "obs": obs,
        "objects": {name: state_of(obj) for name, obj in saved.items()}, "rng": rng_states(device),
        "envs": [e.rng_state() for e in envs],
    }, path)
    print(f"state saved after step {global_step + 1}: {os.path.getsize(path) / 1e9:.2f} GB in "
          f"{time.time() - started:.1f} s", flush=True)


def state_due(global_step: int, args, last_state: float) -> bool:
    """Whether `state.pt` is written after this step: `state_minutes` after the
    last one (`last_state`, from `time.monotonic`), or every `checkpoint_freq`
    steps if set; at the last step only with `keep_state`."""
    if global_step + 1 == args.total_timesteps:
        return args.keep_state
    if args.checkpoint_freq is not None:
        return (global_step + 1) % args.checkpoint_freq == 0
    return time.monotonic() - last_state >= 60 * args.state_minutes


def restore_run(resume: dict, saved: dict, envs: list, args, device: torch.device,
                writer) -> tuple:
    """Continue from the saved state: restore the `saved` objects, replay the running episode on
    `envs[0]` to where the saved run was, then restore the generators.
    Returns (observation, first step, seconds trained)."""
    loop = saved["loop"]
    for name, obj in saved.items():
        load_state_(obj, resume["objects"][name])
    loop.losses = {name: value.to(device) for name, value in loop.losses.items()}
    obs = ene.replay_episode(envs[0], args.seed, loop.episode_start, loop.episode_actions)
    set_rng_states(resume["rng"], device)
    for e, state in zip(envs, resume["envs"]):
        e.set_rng_state(state)
    if not np.array_equal(obs, resume["obs"].cpu().numpy()):
        print(
            f"{args.exp_name}: warning: the replayed episode differs from the saved one "
            "(another MuJoCo?); the run continues, not bitwise as uninterrupted",
            flush=True,
        )
    start_step = resume["global_step"]
    # the purge hid the step's evaluation
    if start_step % args.eval_freq == 0 or start_step == args.total_timesteps:
        for tag, value in loop.last_eval.items():
            writer.add_scalar(tag, value, start_step)
    print(f"resuming runs/{args.run_name}/state.pt at step {start_step}", flush=True)
    return obs, start_step, resume["elapsed"]
