"""`--cuda-graph`: a training step replayed as one CUDA graph (docs/running.md: "Speed on a GPU")."""
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
