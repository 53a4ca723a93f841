"""Issue 44, item 2, prepared for a GPU: one CUDA graph per SAC update, the optimiser steps inside it, exact.

torch's foreach Adam (the scripts' Adams, not capturable) computes its bias corrections on the host from each
parameter's step count t and passes them to its kernels as scalars: -lr / (1 - beta1^t) and sqrt(1 - beta2^t). A graph
captured at step t would replay t's scalars. They stop changing in float32 once they round to their limits, -lr and 1:
from `settle_step` on (16 6xx steps at the scripts' betas). From there a captured update replays exactly the kernels
that eager runs, with the same scalars. Before it, the updates stay eager. The counts that the update keeps on the host
(Adam's `step` tensors on the CPU, `loop.sac_updates`, the sparse optimiser's `steps`) move during the capture and not
during a replay: the capture's own moves are undone, and each replay applies them.

    python results/gpu-speed/adam_capture.py --device cuda [--script pebble] [--hidden-dim 1024 --batch-size 1024]

Four arms, each on an agent built from the same seed, sampling the same random replay buffer with the same RNG stream:
`eager` (the scripts' `sac_update` on `rb.sample`), `parts` (today's `--cuda-graph`: the three gradient steps
captured, the optimiser steps eager; CUDA only), `whole` (one graph per update and per branch pattern, after
`--warmup` eager updates, the sampled batch copied in) and `gather` (the same with the batch's gathers inside the
graph: only the indices are drawn eagerly, as `sample` draws them, so the random stream is unchanged). Every
optimiser's step count starts at the settle step (as in a run past its first 16 6xx updates). Prints and writes
(`--out`) the bit-for-bit comparison of every parameter, Adam moment and step count against `eager`, and the median
milliseconds per update of each arm over interleaved blocks. On the CPU, `whole` and `gather` run their updates
eagerly through the same host bookkeeping: a check of the harness and of the gathers, not of a graph.
"""
import argparse
import importlib
import json
import os
import statistics
import sys
import time

import torch

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, ROOT)
from r2n_harness.cuda_graph import CudaGraph, WholeUpdate, settle_step  # noqa: E402
OBS_DIM, ACT_DIM = 171, 6  # cheetah-run at --noise 0.9
adams = WholeUpdate.adams  # the agent's torch Adams, inside the sparse optimisers' wrappers


def agent_settle_step(agent) -> int:
    return max(settle_step(g["lr"], *g["betas"]) for adam in adams(agent) for g in adam.param_groups)


def set_steps(agent, t: int):
    for adam in adams(agent):
        for state in adam.state.values():
            state["step"].fill_(t)


class HostCounts:
    """The counts an update keeps on the host: read, restored, and moved by a delta."""

    def __init__(self, agent, loop):
        self.loop = loop
        self.steps = [s["step"] for adam in adams(agent) for s in adam.state.values()]
        self.sparse = [o for o in (agent.actor_optimizer, agent.q_optimizer) if hasattr(o, "steps")]

    def read(self) -> list:
        return ([self.loop.sac_updates] + [o.steps for o in self.sparse]
                + [float(t) for t in self.steps])

    def write(self, values: list):
        self.loop.sac_updates = values[0]
        for o, v in zip(self.sparse, values[1:]):
            o.steps = v
        for t, v in zip(self.steps, values[1 + len(self.sparse):]):
            t.fill_(v)


def gathered(module, rb, idx: torch.Tensor):
    """`ReplayBuffer.sample`'s batch at the indices `idx` (its gathers, after its index draw): what a graph holds when
    the sampled indices stay eager (tests/test_gpu_measure.py checks it against `sample`)."""
    return module.Batch(module.read_noisy(rb.obs[idx], rb.noise), rb.actions[idx], rb.rewards[idx],
                        module.read_noisy(rb.next_obs[idx], rb.noise), rb.dones[idx], idx)


def tensors(x) -> list:
    return list(x) if isinstance(x, tuple) else [x]


class WholeUpdate:
    """`update(x)` (one SAC update from its input: a batch, or the sampled indices when the gathers are inside) as one
    graph per branch pattern (actor due, target due), after `warmup` eager updates."""

    def __init__(self, update, agent, loop, args, device, warmup: int):
        self.update, self.agent, self.loop, self.args, self.device = update, agent, loop, args, device
        self.warmup, self.calls, self.graphs, self.counts = warmup, 0, {}, HostCounts(agent, loop)
        for adam in adams(agent):  # the scalars are the same at every replay: see settle_step
            adam._accelerator_graph_capture_health_check = lambda: None
            adam._cuda_graph_capture_health_check = lambda: None

    def key(self) -> tuple:
        n = self.loop.sac_updates + 1
        return n % self.args.actor_update_freq == 0, n % self.args.target_update_freq == 0

    def topology_due(self) -> bool:
        """RigL's steps stay eager: an update that holds one runs eagerly."""
        return any(o.sparsity and (o.steps + 1) % o.period == 0 for o in self.counts.sparse)

    def __call__(self, x):
        self.calls += 1
        if self.device.type != "cuda" or self.topology_due():
            return self.update(x)
        if self.calls <= self.warmup:  # on a side stream, as a capture asks
            side = torch.cuda.Stream()
            side.wait_stream(torch.cuda.current_stream())
            with torch.cuda.stream(side):
                self.update(x)
            torch.cuda.current_stream().wait_stream(side)
            return
        key = self.key()
        if key not in self.graphs:
            static = type(x)(*map(torch.clone, x)) if isinstance(x, tuple) else x.clone()
            before = self.counts.read()
            graph = torch.cuda.CUDAGraph()
            with torch.cuda.graph(graph):
                self.update(static)
            after = self.counts.read()
            self.counts.write(before)  # the capture ran no kernel: its host moves are undone
            # the losses this graph writes: `loop.losses` points at another graph's after that one's capture
            self.graphs[key] = graph, static, [a - b for a, b in zip(after, before)], dict(self.loop.losses)
        graph, static, delta, losses = self.graphs[key]
        torch._foreach_copy_(tensors(static), tensors(x))
        graph.replay()
        self.counts.write([v + d for v, d in zip(self.counts.read(), delta)])
        self.loop.losses.update(losses)


def snapshot(agent, loop) -> dict:
    """Every parameter, Adam moment and step count of the agent, the sparse masks and the host counts, by name, on the
    host; and the latest losses."""
    out = {f"loss.{k}": v.detach().cpu().clone() for k, v in loop.losses.items()}
    out["sac_updates"] = torch.tensor(loop.sac_updates)
    for name in ("actor_optimizer", "q_optimizer"):
        sparse = getattr(agent, name)
        if hasattr(sparse, "masks"):
            out |= {f"{name}.mask.{k}": m.cpu().clone() for k, m in sparse.masks.items()}
            out[f"{name}.steps"] = torch.tensor([sparse.steps, sparse.topology_updates])
    for name, value in vars(agent).items():
        if isinstance(value, torch.nn.Module):
            out |= {f"{name}.{k}": v.detach().cpu().clone() for k, v in value.state_dict().items()}
        elif isinstance(value, torch.Tensor):
            out[name] = value.detach().cpu().clone()
    for i, adam in enumerate(adams(agent)):
        for j, state in enumerate(adam.state.values()):
            out |= {f"adam{i}.{j}.{k}": v.detach().cpu().clone() for k, v in state.items()}
    return out


def same_bits(a: dict, b: dict) -> list:
    """The names whose tensors differ in any bit."""
    return [k for k in a if a[k].shape != b[k].shape
            or not torch.equal(a[k].view(torch.int32) if a[k].dtype == torch.float32 else a[k],
                               b[k].view(torch.int32) if b[k].dtype == torch.float32 else b[k])]


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--scripts", nargs="+", default=["pebble", "r2n_pebble"])
    parser.add_argument("--hidden-dim", type=int, default=1024)
    parser.add_argument("--batch-size", type=int, default=1024)
    parser.add_argument("--updates", type=int, default=300)
    parser.add_argument("--buffer-size", type=int, default=20_000, help="a replay buffer of random rows to sample")
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--blocks", type=int, default=5, help="timing: interleaved blocks of `--updates` each")
    parser.add_argument("--out", default=None)
    cli = parser.parse_args()
    device = torch.device(cli.device)
    torch.set_num_threads(1)
    if device.type == "cuda":  # a stream of its own, as the scripts' --cuda-graph
        torch.cuda.set_stream(torch.cuda.Stream())
    result = dict(device=torch.cuda.get_device_name() if device.type == "cuda" else "cpu", torch=torch.__version__,
                  hidden_dim=cli.hidden_dim, batch_size=cli.batch_size, updates=cli.updates, scripts={})
    for name in cli.scripts:
        module = importlib.import_module(name)
        args = module.ene.suite_settings(module.Args(hidden_dim=cli.hidden_dim, batch_size=cli.batch_size))
        rb = module.ReplayBuffer(cli.buffer_size, OBS_DIM, ACT_DIM, device)
        generator = torch.Generator().manual_seed(1)
        for stored in (rb.obs, rb.next_obs, rb.rewards):
            stored.copy_(torch.randn(stored.shape, generator=generator))
        rb.actions.copy_(torch.rand(rb.actions.shape, generator=generator) * 2 - 1)
        rb.pos, rb.size = 0, cli.buffer_size
        arms = ["eager", "whole", "gather"] + (["parts"] if device.type == "cuda" else [])
        agents, loops, steps = {}, {}, {}
        for arm in arms:
            torch.manual_seed(0)
            agents[arm], loops[arm] = module.make_agent(OBS_DIM, ACT_DIM, args, device), module.Loop()
            module.sac_update(agents[arm], rb.sample(cli.batch_size), loops[arm], args)  # Adam's state from here
            settled = agent_settle_step(agents[arm])
            set_steps(agents[arm], settled)
            for sparse in HostCounts(agents[arm], loops[arm]).sparse:  # a RigL step inside the comparison
                sparse.steps = sparse.period - cli.updates // 2
        saved = {n: getattr(module, n) for n in ("critic_gradients", "actor_gradients", "target_update")}
        graphs = {n: CudaGraph(f) for n, f in saved.items()} if "parts" in arms else {}

        def eager(arm):
            return lambda: module.sac_update(agents[arm], rb.sample(cli.batch_size), loops[arm], args)

        def parts():
            for n, g in graphs.items():
                setattr(module, n, g)
            try:
                module.sac_update(agents["parts"], rb.sample(cli.batch_size), loops["parts"], args)
            finally:
                for n, f in saved.items():
                    setattr(module, n, f)

        whole = WholeUpdate(lambda data: module.sac_update(agents["whole"], data, loops["whole"], args),
                            agents["whole"], loops["whole"], args, device, cli.warmup)
        gather = WholeUpdate(lambda idx: module.sac_update(agents["gather"], gathered(module, rb, idx),
                                                           loops["gather"], args),
                             agents["gather"], loops["gather"], args, device, cli.warmup)
        steps = dict(eager=eager("eager"), parts=parts, whole=lambda: whole(rb.sample(cli.batch_size)),
                     # the indices drawn eagerly, as `sample` draws them: the random stream is unchanged
                     gather=lambda: gather(torch.randint(0, rb.size, (cli.batch_size,), device=device)))
        # the comparison: the same seed's RNG stream for every arm
        states = {}
        for arm in arms:
            torch.manual_seed(2)
            for _ in range(cli.updates):
                steps[arm]()
            if device.type == "cuda":
                torch.cuda.synchronize()
            states[arm] = snapshot(agents[arm], loops[arm])
        compare = {arm: same_bits(states["eager"], states[arm]) for arm in arms if arm != "eager"}
        # the timing: interleaved blocks, each arm continuing from where it stood
        times = {arm: [] for arm in arms}
        for _ in range(cli.blocks):
            for arm in arms:
                if device.type == "cuda":
                    torch.cuda.synchronize()
                start = time.perf_counter()
                for _ in range(cli.updates):
                    steps[arm]()
                if device.type == "cuda":
                    torch.cuda.synchronize()
                times[arm].append(1e3 * (time.perf_counter() - start) / cli.updates)
        row = dict(settle_step=settled, tensors=len(states["eager"]),
                   differ={arm: len(names) for arm, names in compare.items()},
                   first_differ={arm: names[:5] for arm, names in compare.items()},
                   ms_per_update={arm: statistics.median(t) for arm, t in times.items()},
                   graphs={"whole": len(whole.graphs), "gather": len(gather.graphs)})
        result["scripts"][name] = row
        print(name, json.dumps(row), flush=True)
        if cli.out:  # after each script: a part cut off at its budget keeps the scripts it finished
            with open(cli.out, "w") as f:
                json.dump(result, f, indent=1)


if __name__ == "__main__":
    main()
