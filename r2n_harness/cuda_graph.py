"""`--cuda-graph`: the training steps replayed as CUDA graphs (docs/running.md: "The GPU flags").

`CudaGraph` replays each of `sac_update`'s three gradient steps; `WholeUpdate` replays the whole update, the optimiser
steps inside, once every Adam's host scalars have settled. Both replay the kernels eager runs, with the same scalars."""
import functools

import numpy as np
import torch
import torch.nn as nn


class CudaGraph:
    """`--cuda-graph`: `step(agent, *inputs)` replayed as a CUDA graph, one launch instead of
    hundreds of small kernels from Python. Tensor inputs (a `Batch`'s too) are copied into the
    graph's own before each replay; other inputs are fixed. The first calls run eagerly on a
    side stream, as CUDA asks (autograd's and cuBLAS's buffers exist by the capture), the next
    is captured, later ones replay it and return the same output tensors, overwritten. A graph
    reads the tensors it was captured with: when the agent's networks or optimisers are
    replaced (PEBBLE's critic reset), a fixed input changes, its `signature` changes or a
    `.grad` it writes is replaced, it is captured again. A change of device stops the run."""
    warmup_calls = 2

    def __init__(self, step):
        self.step, self.graph, self.agent_objects, self.fixed, self.calls = step, None, [], None, 0
        self.params, self.seen, self.grads = [], None, []

    @staticmethod
    def tensors(inputs) -> list:
        return [
            t
            for x in inputs
            for t in (x if isinstance(x, tuple) else [x])
            if isinstance(t, torch.Tensor)
        ]

    @staticmethod
    def parameters(agent) -> list:
        """The agent's networks' parameters and its own tensors (the temperature)."""
        return [
            p
            for x in vars(agent).values()
            for p in (
                x.parameters() if isinstance(x, nn.Module)
                else [x] if isinstance(x, torch.Tensor)
                else []
            )
        ]

    @staticmethod
    def tf32() -> tuple:
        """cuBLAS's and cuDNN's TF32 settings. Torch >= 2.9 keeps them per
        backend, and there the older flags raise once the newer ones are set."""
        if hasattr(torch.backends, "fp32_precision"):
            return (
                torch.backends.cuda.matmul.fp32_precision,
                torch.backends.cudnn.conv.fp32_precision,
                torch.backends.cudnn.rnn.fp32_precision,
            )
        return (
            torch.backends.cuda.matmul.allow_tf32,
            torch.backends.cudnn.allow_tf32,
            torch.get_float32_matmul_precision(),
        )

    @staticmethod
    def signature(inputs, parameters: list) -> tuple:
        """What a graph depends on besides tensor values: the inputs' shapes and dtypes,
        the devices, each parameter's `requires_grad` and storage, the TF32 settings.
        It reads host attributes only, so a call adds no sync."""
        tensors = CudaGraph.tensors(inputs)
        return (
            tuple((t.shape, t.dtype) for t in tensors),
            frozenset(t.device for t in tensors + parameters),
            tuple((p.requires_grad, p.data_ptr()) for p in parameters),
            CudaGraph.tf32(),
        )

    def stale(self, agent, inputs) -> bool:
        """Whether the graph must be captured again; raises where a new capture would be wrong."""
        objects = list(vars(agent).values())
        fixed = [x for x in inputs if not isinstance(x, (torch.Tensor, tuple))]
        replaced = not self.agent_objects or any(
            a is not b for a, b in zip(objects, self.agent_objects)
        )
        # listing them is slow: once per agent
        params = self.parameters(agent) if replaced else self.params
        signature = self.signature(inputs, params)
        # A graph replays on its capture's device and stream. A capture elsewhere would mix devices.
        if self.seen is not None and signature[1] != self.seen[1]:
            old, new = (
                ", ".join(sorted(map(str, devices))) for devices in (self.seen[1], signature[1])
            )
            raise RuntimeError(
                f"--cuda-graph: {self.step.__name__} was captured on {old} "
                f"and is now called on {new}; a CUDA graph replays on one device"
            )
        # New shapes, dtypes, storage, requires_grad or TF32 settings: a new capture
        # records what eager now runs. A replaced `.grad` (zero_grad's None): a
        # replay would write the old one, which the optimiser no longer reads.
        stale = (
            replaced or fixed != self.fixed or signature != self.seen
            or any(p.grad is not g for p, g in self.grads)
        )
        if stale:  # held here, the replaced objects keep their ids: no false match
            self.agent_objects = objects
            self.fixed = fixed
            self.params = params
            self.seen = signature
            self.grads = []
        return stale

    def __call__(self, agent, *inputs):
        if WholeUpdate.capturing:  # recorded into the whole update's graph
            return self.step(agent, *inputs)
        if self.stale(agent, inputs):
            self.graph, self.calls = None, 0
        self.calls += 1
        if self.calls <= self.warmup_calls:
            side = torch.cuda.Stream()
            side.wait_stream(torch.cuda.current_stream())
            with torch.cuda.stream(side):
                outputs = self.step(agent, *inputs)
            torch.cuda.current_stream().wait_stream(side)
            return outputs
        if self.graph is None:
            self.inputs = [type(x)(*map(torch.clone, x)) if isinstance(x, tuple) else x.clone()
                           if isinstance(x, torch.Tensor) else x for x in inputs]
            before = [(p, p.grad, None if p.grad is None else p.grad._version) for p in self.params]
            graph = torch.cuda.CUDAGraph()
            with torch.cuda.graph(graph):
                self.outputs = self.step(agent, *self.inputs)
            # Only the `.grad` tensors the capture created
            # or added to: another step's may change freely.
            self.grads = [
                (p, p.grad)
                for p, g, v in before
                if p.grad is not g or (g is not None and g._version != v)
            ]
            self.graph = graph  # only once captured: a failed capture is never replayed
        elif self.tensors(inputs):
            torch._foreach_copy_(self.tensors(self.inputs), self.tensors(inputs))
        self.graph.replay()
        return self.outputs


@functools.lru_cache
def settle_step(lr: float, beta1: float, beta2: float) -> int:
    """The first step count t from which foreach Adam's host scalars, -lr / (1 - beta1^t) and sqrt(1 - beta2^t),
    no longer change in float32 (16 628 at the scripts' betas). They move monotonically towards their limits, -lr and
    1, so once equal to them they stay equal."""
    limits = np.float32(-lr), np.float32(1.0)
    t = 1
    while (np.float32((lr / (1 - beta1**t)) * -1), np.float32((1 - beta2**t) ** 0.5)) != limits:
        t += 1
    return t


class WholeUpdate:
    """`--cuda-graph`: `update(agent, data, loop, args)` (a script's `sac_update`) replayed as one CUDA graph per
    branch pattern (where the update stands in `actor_update_freq` and `target_update_freq`), the optimiser steps
    inside it.

    torch's foreach Adam (not capturable) passes its bias corrections to its kernels as host scalars of each step
    count t, which a graph captured at t would replay. From `settle_step` on they no longer change: a replay runs
    exactly the kernels and scalars of eager. Until every Adam of the agent has settled (after PEBBLE's critic reset,
    its new Adam again), and for an update that may hold a topology step (the sparse optimisers pick their weights on
    the host), the update runs as before, its steps captured apart (`CudaGraph`).
    The counts an update keeps on the host (the loop's and the sparse optimisers' integers, Adam's step counts) move
    during the capture and not during a replay: the capture's moves are undone, and each replay applies them."""
    warmup_calls = 2  # ordinary updates first, after a new agent or input
    capturing = False  # read by `CudaGraph`: inside this capture, a step records its own kernels

    def __init__(self, update):
        self.update, self.objects, self.seen, self.settled, self.calls, self.graphs = update, [], None, False, 0, {}

    @staticmethod
    def adams(agent) -> list:
        """The agent's torch optimisers (inside a sparse optimiser's wrapper, where there is one)."""
        return [o for x in vars(agent).values() for o in [getattr(x, "optimizer", x)]
                if isinstance(o, torch.optim.Optimizer)]

    @staticmethod
    def adams_settled(adams: list) -> bool:
        """Whether every trained parameter's step count has reached its Adam's settle step."""
        return all(
            (state := adam.state.get(p)) is not None and float(state["step"]) >= settle_step(g["lr"], *g["betas"])
            for adam in adams for g in adam.param_groups for p in g["params"] if p.requires_grad
        )

    @staticmethod
    def topology_due(agent) -> bool:
        """Whether a sparse optimiser's next step may change its topology (an update that may not, replays)."""
        return any(getattr(x, "sparsity", 0) and (x.steps + 1) % x.period == 0
                   for x in vars(agent).values() if hasattr(x, "period"))

    @staticmethod
    def counters(agent, loop) -> list:
        """(object, name) of every integer that an update may move on the host: the loop's and the optimisers'."""
        owners = [loop] + [x for x in vars(agent).values() if hasattr(x, "optimizer")]
        return [(o, name) for o in owners for name, value in vars(o).items() if type(value) is int]

    def __call__(self, agent, data, loop, args):
        adams = self.adams(agent)
        objects = [agent, loop, args, *vars(agent).values(), *(adam.state for adam in adams)]
        if len(objects) != len(self.objects) or any(a is not b for a, b in zip(objects, self.objects)):
            # a new agent, network, optimiser or optimiser state (PEBBLE's critic reset, a resume): its own graphs
            self.objects, self.params, self.settled, self.seen = objects, CudaGraph.parameters(agent), False, None
        signature = CudaGraph.signature((data,), self.params)
        if signature != self.seen:  # as `CudaGraph`: what eager now runs is captured again
            self.seen, self.graphs, self.calls = signature, {}, 0
        self.settled = self.settled or self.adams_settled(adams)  # step counts only grow
        if not self.settled or self.topology_due(agent) or self.calls < self.warmup_calls:
            self.calls += self.settled
            return self.update(agent, data, loop, args)
        n = loop.sac_updates + 1  # this update's branches: at most four graphs
        key = n % args.actor_update_freq == 0, n % args.target_update_freq == 0
        if key not in self.graphs:
            self.graphs[key] = self.capture(agent, data, loop, args, adams)
        graph, inputs, moved, steps, losses = self.graphs[key]
        torch._foreach_copy_(list(inputs), list(data))
        graph.replay()
        for owner, name, delta in moved:
            setattr(owner, name, getattr(owner, name) + delta)
        if steps:  # as Adam counts its steps: float32 tensors on the host
            torch._foreach_add_(steps, 1.0)
        loop.losses.update(losses)

    def capture(self, agent, data, loop, args, adams) -> tuple:
        """One update's graph, and what its replays move on the host: the integers, Adam's step counts, the losses."""
        inputs = type(data)(*map(torch.clone, data))
        counters = self.counters(agent, loop)
        before = [getattr(o, name) for o, name in counters]
        steps = [state["step"] for adam in adams for state in adam.state.values()]
        counts = [float(t) for t in steps]
        losses = dict(loop.losses)
        graph = torch.cuda.CUDAGraph()
        for adam in adams:  # not capturable: exact here only because its scalars have settled
            adam._accelerator_graph_capture_health_check = adam._cuda_graph_capture_health_check = lambda: None
        WholeUpdate.capturing = True
        try:
            with torch.cuda.graph(graph):
                self.update(agent, inputs, loop, args)
        finally:
            WholeUpdate.capturing = False
            for adam in adams:
                del adam._accelerator_graph_capture_health_check, adam._cuda_graph_capture_health_check
        # the capture ran no kernel: its moves on the host are undone here, and each replay makes them
        moved = [(o, name, getattr(o, name) - b) for (o, name), b in zip(counters, before) if getattr(o, name) != b]
        for (o, name), b in zip(counters, before):
            setattr(o, name, b)
        stepped = [(t, c) for t, c in zip(steps, counts) if float(t) != c]
        assert all(float(t) == c + 1 for t, c in stepped), "an update stepped an Adam twice"
        for t, c in stepped:
            t.fill_(c)
        written = {k: v for k, v in loop.losses.items() if losses.get(k) is not v}
        return graph, inputs, moved, [t for t, _ in stepped], written
