"""The host cost of one `WholeUpdate` call on its replay path, and of its parts, with the CUDA graph faked on the CPU
(its replay does nothing, so what is timed is the bookkeeping around it). Tiny agents: the parameter count, not the
width, sets these costs.

    OMP_NUM_THREADS=1 python results/gpu-speed/whole_overhead.py
"""
import contextlib
import importlib
import os
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path[:0] = [ROOT, os.path.join(ROOT, "tests")]
import torch  # noqa: E402
torch.set_num_threads(1)


class Graph:
    def replay(self):
        pass


class Stream:
    def wait_stream(self, other):
        pass


torch.cuda.CUDAGraph, torch.cuda.graph = Graph, lambda graph: contextlib.nullcontext()
torch.cuda.Stream = torch.cuda.current_stream = Stream
torch.cuda.stream = lambda stream: contextlib.nullcontext()
from test_cuda_graph import random_batch, settled_twins  # noqa: E402
from r2n_harness.cuda_graph import CudaGraph, WholeUpdate  # noqa: E402


def micros(f, n: int = 20_000) -> float:
    """Mean microseconds per call of `f`."""
    start = time.perf_counter()
    for _ in range(n):
        f()
    return (time.perf_counter() - start) / n * 1e6


for name in ("pebble", "r2n_pebble"):
    module = importlib.import_module(name)
    (_, (agent, loop)), args = settled_twins(module, torch.device("cpu"), topology_period=10**9)  # no topology step
    whole, data = WholeUpdate(module.sac_update), random_batch(module, 1, "cpu", n=4)
    for _ in range(10):  # past the warm-up calls and the captures
        whole(agent, data, loop, args)
    _, inputs, _, steps, _ = next(iter(whole.graphs.values()))
    print(f"{name}: {micros(lambda: whole(agent, data, loop, args)):.1f} µs per call, of which")
    print(f"  the batch's copy: {micros(lambda: torch._foreach_copy_(list(inputs), list(data))):.1f} µs")
    objects = lambda: [agent, loop, args, *vars(agent).values(), *(a.state for a in WholeUpdate.adams(agent))]  # noqa: E731
    print(f"  the objects' identities: {micros(objects):.1f} µs")
    print(f"  the signature: {micros(lambda: CudaGraph.signature((data,), whole.params)):.1f} µs")
    print(f"  topology_due: {micros(lambda: WholeUpdate.topology_due(agent)):.1f} µs")
    print(f"  Adam's step counts, {len(steps)} host tensors: {micros(lambda: torch._foreach_add_(steps, 1.0)):.1f} µs")
