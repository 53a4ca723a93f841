"""Subnormal floats in a run's state, what they cost a CPU matmul, and whether zeroing them changes a run.

A target critic is a Polyak average of its online critic. Where the sparse methods prune a connection, the online
weight is zero and the target's decays by 1 - tau per update, into the subnormal floats, where it stays: 0.995 times a
subnormal of fewer than 100 steps rounds back to it. A CPU matmul over subnormal operands is slow, so the scripts'
`target_update` sets such target weights to zero. Three commands, each on one thread:

    python results/cpu-step/subnormals.py count STATE        # the subnormal entries of a state.pt, per tensor
    python results/cpu-step/subnormals.py time STATE         # the target critics' input layer, as saved and zeroed
    python results/cpu-step/subnormals.py compare KEPT ZEROED

`compare` reads two run folders resumed at the same time from copies of one state.pt with the same command: KEPT by
code that keeps the subnormals, ZEROED by code that zeroes them (or that flushes every subnormal, the CPU's
flush-to-zero mode). It compares every TensorBoard point both reached, bit for bit, and names each tag's first
difference; gives each run's steps/s over the wall-clock window both ran; and compares their checkpoints where both
wrote one at the same step (bit for bit, but that a subnormal in KEPT may be a zero in ZEROED).
"""
import argparse
import os
import sys
import time

import torch
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

torch.set_num_threads(1)


def tensors_of(obj, path=""):
    """Every tensor in a nested state (dicts, lists, tuples), by its path."""
    if isinstance(obj, torch.Tensor):
        return {path: obj}
    items = obj.items() if isinstance(obj, dict) else enumerate(obj) if isinstance(obj, (list, tuple)) else ()
    return {p: t for key, value in items for p, t in tensors_of(value, f"{path}/{key}").items()}


def subnormals(t):
    """Where a tensor holds a subnormal float (none in a tensor of integers)."""
    if not t.is_floating_point():
        return torch.zeros_like(t, dtype=torch.bool)
    return (t != 0) & (t.abs() < torch.finfo(t.dtype).tiny)


def count(state_path):
    state = torch.load(state_path, map_location="cpu", mmap=True, weights_only=False)
    tensors = tensors_of(state)
    print(f"{state_path}: step {state['global_step']}, {len(tensors)} tensors")
    for path, t in tensors.items():
        n = int(subnormals(t).sum())
        if n:
            print(f"{path} {tuple(t.shape)}: {n} subnormal ({n / t.numel():.3f}), {float((t == 0).float().mean()):.3f} zero")


def best_seconds(weight, bias, x, repeats=50, blocks=5):
    """The fastest of `blocks` timings of `repeats` forward passes, per pass."""
    best = float("inf")
    for _ in range(blocks):
        start = time.perf_counter()
        for _ in range(repeats):
            torch.nn.functional.linear(x, weight, bias)
        best = min(best, (time.perf_counter() - start) / repeats)
    return best


def time_layer(state_path):
    state = torch.load(state_path, map_location="cpu", mmap=True, weights_only=False)
    generator = torch.Generator().manual_seed(0)
    for name in ("qf1_target", "qf2_target"):
        critic = state["objects"]["agent"][name]
        weight, bias = critic["net.0.weight"], critic["net.0.bias"]
        x = torch.randn(128, weight.shape[1], generator=generator)  # a batch of 128, as the studies train
        flushed = torch.where(subnormals(weight), torch.zeros_like(weight), weight)
        same = torch.equal(torch.nn.functional.linear(x, weight, bias), torch.nn.functional.linear(x, flushed, bias))
        kept_s, flushed_s = best_seconds(weight, bias, x), best_seconds(flushed, bias, x)
        torch.set_flush_denormal(True)
        flag_s = best_seconds(weight, bias, x)
        torch.set_flush_denormal(False)
        print(f"{name} input layer {tuple(weight.shape)}, {int(subnormals(weight).sum())} subnormal weights: "
              f"{kept_s * 1e6:.0f} us as saved, {flushed_s * 1e6:.0f} us with them zeroed ({kept_s / flushed_s:.0f}x), "
              f"{flag_s * 1e6:.0f} us as saved under set_flush_denormal(True); the same output: {same}")


def points(run_dir):
    events = EventAccumulator(run_dir, size_guidance={"scalars": 0})
    events.Reload()
    return {tag: [(e.step, e.value, e.wall_time) for e in events.Scalars(tag)] for tag in events.Tags()["scalars"]}


def compare(kept_dir, zeroed_dir):
    kept, flushed = points(kept_dir), points(zeroed_dir)
    last = min(max(p[0] for pts in run.values() for p in pts) for run in (kept, flushed))
    first_step = min(p[0] for pts in kept.values() for p in pts)
    compared = differ = 0
    for tag in sorted(kept.keys() | flushed.keys()):
        if tag == "charts/SPS":
            continue
        a = [(s, v) for s, v, _ in kept.get(tag, []) if s <= last]
        b = [(s, v) for s, v, _ in flushed.get(tag, []) if s <= last]
        compared += len(a)
        if a != b:
            differ += 1
            first = next(((x, y) for x, y in zip(a, b) if x != y), (f"{len(a)} points", f"{len(b)} points"))
            print(f"differs: {tag}: first {first[0]} vs {first[1]}")
    print(f"TensorBoard: {compared} points of {len(kept) - 1} tags from step {first_step} to {last}, {differ} tags differ")
    # steps/s over the wall-clock window both ran: from both runs' first loss point to the earlier end
    losses = {name: run["losses/qf_loss"] for name, run in (("kept", kept), ("zeroed", flushed))}
    start = max(pts[0][2] for pts in losses.values())
    end = min(pts[-1][2] for pts in losses.values())
    rates = {}
    for name, pts in losses.items():
        inside = [(s, w) for s, _, w in pts if start <= w <= end]
        rates[name] = (inside[-1][0] - inside[0][0]) / (inside[-1][1] - inside[0][1])
        print(f"{name}: {rates[name]:.1f} steps/s over {inside[0][0]}-{inside[-1][0]} ({end - start:.0f} s window)")
    print(f"zeroed / kept: {rates['zeroed'] / rates['kept']:.2f}")
    a, b = (torch.load(os.path.join(d, name), weights_only=False) for d in (kept_dir, zeroed_dir)
            for name in os.listdir(d) if name.endswith(".cleanrl_model"))
    if a["global_step"] != b["global_step"]:
        print(f"checkpoints at steps {a['global_step']} and {b['global_step']}: not compared")
        return
    ta, tb = tensors_of(a), tensors_of(b)
    equal = sum(torch.equal(torch.where(subnormals(t), torch.zeros_like(t), t), tb[p]) for p, t in ta.items())
    print(f"checkpoints at step {a['global_step']}: {equal} of {len(ta)} tensors the same "
          f"({sum(int(subnormals(t).sum()) for t in ta.values())} subnormals in the kept run's)")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("command", choices=("count", "time", "compare"))
    parser.add_argument("paths", nargs="+")
    args = parser.parse_args()
    {"count": count, "time": time_layer, "compare": compare}[args.command](*args.paths)
    sys.stdout.flush()
