"""Issue 19 on a GPU: `--cuda-graph` replays the SAC steps' gradients (and the targets' update) as CUDA graphs.
Skipped where torch sees no GPU, as on CI (docs/running.md: "Testing on a GPU"). On a GPU:
- all 12 scripts, through every phase (pre-training, the critic reset and its re-capture, feedback rounds, topology
  updates), give the same TensorBoard points and final weights with and without `--cuda-graph`;
- after a critic reset the graphs train the new critic (their captured tensors are the new networks' storage);
- once captured, an SAC update (sampling, replays, eager optimiser steps) never syncs with the host."""
import copy
import importlib
import sys

import pytest
import torch

from test_layout import ORACLES, PBRL
from test_numerics import ARGS
from test_scripts import ROOT, run_script, scalars

sys.path.insert(0, ROOT)
pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA graphs need a CUDA GPU")
STEPS = ("critic_gradients", "actor_gradients", "target_update")


@pytest.mark.parametrize("script", PBRL + ORACLES)
def test_captured_run_equals_eager(script, tmp_path):
    runs = {}
    for mode, flags in (("eager", []), ("graph", ["--cuda-graph"])):
        run_script(script, ARGS[script] + ["--cuda", "--seed", "3", "--run-name", mode, "--save-model", *flags], tmp_path)
        runs[mode] = scalars(str(tmp_path / "runs" / mode))
    assert runs["eager"].keys() == runs["graph"].keys()
    for tag, values in runs["eager"].items():
        if tag != "charts/SPS":
            assert runs["graph"][tag] == values, f"{script}: {tag}"
    eager, graph = (torch.load(tmp_path / "runs" / mode / f"{script[:-3]}.cleanrl_model", weights_only=False)
                    for mode in ("eager", "graph"))
    for net in ("actor", "qf1", "qf2"):
        for key, value in eager[net].items():
            assert torch.equal(graph[net][key], value), f"{script}: {net}.{key}"


def tiny_agent(module, device):
    args = module.Args(hidden_dim=32, batch_size=16)
    torch.manual_seed(0)
    return module.make_agent(6, 2, args, device), args


def random_batch(module, step: int, device):
    g = torch.Generator(device=device).manual_seed(step)
    n = 16
    return module.Batch(obs=torch.randn(n, 6, generator=g, device=device), actions=torch.rand(n, 2, generator=g, device=device),
                        rewards=torch.randn(n, generator=g, device=device), next_obs=torch.randn(n, 6, generator=g, device=device),
                        dones=torch.zeros(n, device=device), indices=torch.arange(n, device=device))


@pytest.fixture
def run_stream():
    """The stream of its own that `--cuda-graph` gives a run."""
    with torch.cuda.stream(torch.cuda.Stream()):
        yield


def test_critic_reset_is_captured_again_and_trains_the_new_critic(monkeypatch, run_stream):
    """Eager and captured twins through 5 updates, PEBBLE's critic reset, and 5 more: equal parameters, and the
    captured critic graph's `.grad` tensors are the new critic's (a stale graph would train the old networks)."""
    module = importlib.import_module("pebble")
    device = torch.device("cuda")
    originals, agents = {name: getattr(module, name) for name in STEPS}, {}
    for mode in ("eager", "graph"):
        for name in STEPS:
            monkeypatch.setattr(module, name, module.CudaGraph(originals[name]) if mode == "graph" else originals[name])
        agent, args = tiny_agent(module, device)
        loop = module.Loop()
        torch.manual_seed(1)
        for step in range(10):
            if step == 5:
                torch.manual_seed(2)
                agent.qf1, agent.qf2, agent.q_optimizer, agent.qf1_target, agent.qf2_target = module.make_critic(
                    6, 2, args, device)
                fresh = [p.clone() for p in agent.qf1.parameters()]
            module.sac_update(agent, random_batch(module, step, device), loop, args)
        assert not any(torch.equal(p, q) for p, q in zip(fresh, agent.qf1.parameters())), f"{mode}: the new critic is trained"
        agents[mode] = {net: [p.clone() for p in getattr(agent, net).parameters()]
                        for net in ("actor", "qf1", "qf2", "qf1_target", "qf2_target")}
        if mode == "graph":
            assert any(x is agent.qf1 for x in module.critic_gradients.agent_objects)  # captured with the new critic
            grads = [p.grad for p in agent.qf1.parameters()]
            values = [g.clone() for g in grads]
            module.sac_update(agent, random_batch(module, 10, device), loop, args)
            # the replay wrote the new batch's gradients into the storage the new critic's `.grad` holds
            assert all(p.grad is g for p, g in zip(agent.qf1.parameters(), grads))
            assert not any(torch.equal(g, v) for g, v in zip(grads, values))
    for net, parameters in agents["eager"].items():
        assert all(torch.equal(p, q) for p, q in zip(parameters, agents["graph"][net])), net


def test_a_captured_update_never_syncs_with_the_host(monkeypatch, run_stream):
    module = importlib.import_module("r2n_pebble")  # the sparse optimiser's masked steps included
    device = torch.device("cuda")
    for name in STEPS:
        monkeypatch.setattr(module, name, module.CudaGraph(getattr(module, name)))
    agent, args = tiny_agent(module, device)
    rb = module.ReplayBuffer(1000, 6, 2, device)
    for _ in range(100):
        rb.add(torch.randn(6, device=device), torch.rand(2, device=device), torch.randn(6, device=device), False, 0.0,
               torch.randn((), device=device))
    loop = module.Loop()
    for _ in range(4):  # warm-up and capture: capturing synchronises, once
        module.sac_update(agent, rb.sample(args.batch_size), loop, args)
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")
    try:
        for _ in range(20):  # no topology update: RigL reads its counts on the host, every 1000 optimiser steps
            module.sac_update(agent, rb.sample(args.batch_size), loop, args)
    finally:
        torch.cuda.set_sync_debug_mode("default")
    assert all(torch.isfinite(value).all() for value in loop.losses.values())
