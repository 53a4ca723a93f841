"""Issue 19: `--cuda-graph` replays the SAC steps' gradients (and the targets' update) as CUDA graphs, and (issue 71)
the whole update with Adam inside once Adam's host scalars have settled.
On the CPU, with CUDA's streams and graphs faked: what `CudaGraph` captures again, and what stops the run; when
`WholeUpdate` captures, and that its replays move the host counts as eager does.
The rest is skipped where torch sees no GPU, as on CI (docs/running.md: "Testing on a GPU"). On a GPU:
- all 12 scripts, through every phase (pre-training, the critic reset and its re-capture, feedback rounds, topology
  updates), give the same TensorBoard points and final weights with and without `--cuda-graph`;
- after a critic reset the graphs train the new critic (their captured tensors are the new networks' storage);
- once captured, an SAC update (sampling, replays, eager optimiser steps) never syncs with the host;
- from the settle step, the whole update replayed equals eager in every tensor, bit for bit."""
import contextlib
import importlib
import sys

import numpy as np
import pytest
import torch

from test_layout import ORACLES, PBRL
from test_numerics import ARGS
from test_scripts import ROOT, run_script, scalars

sys.path.insert(0, ROOT)
import ene  # noqa: E402
from r2n_harness.cuda_graph import CudaGraph, WholeUpdate, settle_step  # noqa: E402
gpu = pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA graphs need a CUDA GPU")
STEPS = ("critic_gradients", "actor_gradients", "target_update")


@gpu
@pytest.mark.parametrize("whole", [[], ["--cuda-graph-whole"]], ids=["steps", "whole"])
@pytest.mark.parametrize("script", PBRL + ORACLES)
def test_captured_run_equals_eager(script, whole, tmp_path):
    """`--cuda-graph` (the three steps as graphs), and with `--cuda-graph-whole` the whole update replayed: every
    point and final weight as eager's, bit for bit."""
    runs = {}
    for mode, flags in (("eager", []), ("graph", ["--cuda-graph", *whole])):
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
    args = ene.suite_settings(module.Args(hidden_dim=32, batch_size=16))
    torch.manual_seed(0)
    return module.make_agent(6, 2, args, device), args


def random_batch(module, step: int, device, n: int = 16):
    g = torch.Generator(device=device).manual_seed(step)
    stds = {"stds": torch.rand(n, generator=g, device=device)} if "stds" in module.Batch._fields else {}  # RUNE's
    return module.Batch(obs=torch.randn(n, 6, generator=g, device=device), actions=torch.rand(n, 2, generator=g, device=device),
                        rewards=torch.randn(n, generator=g, device=device), next_obs=torch.randn(n, 6, generator=g, device=device),
                        dones=torch.zeros(n, device=device), indices=torch.arange(n, device=device), **stds)


@pytest.fixture
def run_stream():
    """The stream of its own that `--cuda-graph` gives a run."""
    with torch.cuda.stream(torch.cuda.Stream()):
        yield


@gpu
def test_critic_reset_is_captured_again_and_trains_the_new_critic(monkeypatch, run_stream):
    """Eager and captured twins through 5 updates, PEBBLE's critic reset, and 5 more: equal parameters, and the
    captured critic graph's `.grad` tensors are the new critic's (a stale graph would train the old networks)."""
    module = importlib.import_module("pebble")
    device = torch.device("cuda")
    originals, agents = {name: getattr(module, name) for name in STEPS}, {}
    for mode in ("eager", "graph"):
        for name in STEPS:
            monkeypatch.setattr(module, name, CudaGraph(originals[name]) if mode == "graph" else originals[name])
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


@gpu
def test_a_captured_update_never_syncs_with_the_host(monkeypatch, run_stream):
    module = importlib.import_module("r2n_pebble")  # the sparse optimiser's masked steps included
    device = torch.device("cuda")
    for name in STEPS:
        monkeypatch.setattr(module, name, CudaGraph(getattr(module, name)))
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


@gpu
def test_a_new_batch_size_is_captured_again_and_equals_eager(monkeypatch, run_stream):
    """Eager and captured twins through 5 updates of 16 rows and 5 of 8: equal parameters. Without a new capture, the
    8 rows would be copied into the graph's 16-row inputs."""
    module = importlib.import_module("pebble")
    device = torch.device("cuda")
    originals, parameters = {name: getattr(module, name) for name in STEPS}, {}
    for mode in ("eager", "graph"):
        for name, step in originals.items():
            monkeypatch.setattr(module, name, CudaGraph(step) if mode == "graph" else step)
        agent, args = tiny_agent(module, device)
        loop = module.Loop()
        torch.manual_seed(1)
        for step in range(10):
            module.sac_update(agent, random_batch(module, step, device, 16 if step < 5 else 8), loop, args)
        parameters[mode] = [p.clone() for p in CudaGraph.parameters(agent)]
        if mode == "graph":
            assert module.critic_gradients.inputs[0].obs.shape == (8, 6)
            assert module.actor_gradients.inputs[0].obs.shape == (8, 6)
    assert all(torch.equal(p, q) for p, q in zip(parameters["eager"], parameters["graph"]))


# On the CPU: CudaGraph's decisions, with CUDA's streams and graphs faked.


@pytest.fixture
def fake_cuda(monkeypatch):
    """Warm-up and capture calls run eagerly, and a replay does nothing. Returns the list of graphs made."""
    graphs = []

    class Graph:
        def __init__(self):
            graphs.append(self)

        def replay(self):
            pass

    class Stream:
        def wait_stream(self, other):
            pass

    monkeypatch.setattr(torch.cuda, "Stream", Stream)
    monkeypatch.setattr(torch.cuda, "current_stream", Stream)
    monkeypatch.setattr(torch.cuda, "stream", lambda stream: contextlib.nullcontext())
    monkeypatch.setattr(torch.cuda, "CUDAGraph", Graph)
    monkeypatch.setattr(torch.cuda, "graph", lambda graph: contextlib.nullcontext())
    return graphs


@pytest.fixture
def float32_flags():
    """Restores the TF32 settings that a test changes: torch >= 2.9's per backend, then the older flags."""
    backends = [torch.backends.cuda.matmul, torch.backends.cudnn, torch.backends.cudnn.conv, torch.backends.cudnn.rnn]
    saved = [backend.fp32_precision for backend in backends] if NEW_TF32 else []
    flags = torch.get_float32_matmul_precision(), torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32
    yield
    for backend, value in zip(backends, saved):
        backend.fp32_precision = value
    torch.set_float32_matmul_precision(flags[0])
    torch.backends.cudnn.allow_tf32 = flags[2]
    # the older flags read back as before: no mix of the two APIs is left to raise in a later test
    assert (torch.get_float32_matmul_precision(), torch.backends.cuda.matmul.allow_tf32,
            torch.backends.cudnn.allow_tf32) == flags


def captured(module, monkeypatch) -> dict:
    """The three steps wrapped in `CudaGraph`, as `--cuda-graph` wraps them."""
    steps = {name: CudaGraph(getattr(module, name)) for name in STEPS}
    for name, step in steps.items():
        monkeypatch.setattr(module, name, step)
    return steps


def first_parameter(agent):
    return next(agent.qf1.parameters())


def fresh_storage(agent):
    first_parameter(agent).data = first_parameter(agent).data.clone()


def fresh_grad(agent):
    first_parameter(agent).grad = torch.zeros_like(first_parameter(agent))


INPUT_CHANGES = {
    "an input's shape": lambda data: data._replace(rewards=data.rewards[:8]),
    "an input's dtype": lambda data: data._replace(dones=data.dones.double()),
    "an input's device": lambda data: data._replace(indices=data.indices.to("meta")),
}
NEW_TF32 = hasattr(torch.backends, "fp32_precision")  # torch >= 2.9's TF32 settings per backend
STATE_CHANGES = {
    "a parameter's requires_grad": lambda agent: first_parameter(agent).requires_grad_(False),
    "a parameter's storage": fresh_storage,
    "TF32 matmuls": lambda agent: setattr(torch.backends.cuda.matmul, "allow_tf32", True),
    "cuDNN's TF32": lambda agent: setattr(torch.backends.cudnn, "allow_tf32", False),
    "the matmul precision": lambda agent: torch.set_float32_matmul_precision("high"),
}
if NEW_TF32:
    STATE_CHANGES.update({
        "cuBLAS's fp32_precision": lambda agent: setattr(torch.backends.cuda.matmul, "fp32_precision", "tf32"),
        "cuDNN convolutions' fp32_precision": lambda agent: setattr(torch.backends.cudnn.conv, "fp32_precision",
                                                                    "ieee"),
        "cuDNN RNNs' fp32_precision": lambda agent: setattr(torch.backends.cudnn.rnn, "fp32_precision", "ieee"),
    })


@pytest.mark.parametrize("change", [*INPUT_CHANGES, *STATE_CHANGES])
def test_the_signature_sees_each_change(change, float32_flags):
    module = importlib.import_module("pebble")
    agent, args = tiny_agent(module, torch.device("cpu"))
    parameters = CudaGraph.parameters
    signature = CudaGraph.signature((random_batch(module, 0, "cpu"), args.gamma), parameters(agent))
    module.critic_gradients(agent, random_batch(module, 1, "cpu"), args.gamma)  # new `.grad` tensors, new values
    assert CudaGraph.signature((random_batch(module, 2, "cpu"), args.gamma), parameters(agent)) == signature
    data = random_batch(module, 3, "cpu")
    if change in INPUT_CHANGES:
        data = INPUT_CHANGES[change](data)
    else:
        STATE_CHANGES[change](agent)
    assert CudaGraph.signature((data, args.gamma), parameters(agent)) != signature


@pytest.mark.parametrize("script", PBRL + ORACLES)
def test_each_step_is_captured_once(script, monkeypatch, fake_cuda):
    """Through 12 updates, a topology update included: each step's graph is captured once. Another step's new `.grad`
    tensors and the sparse optimisers' in-place masking do not make a graph stale."""
    module = importlib.import_module(script[:-3])
    steps = captured(module, monkeypatch)
    topology = {"agent_topology_period": 5} if "agent_topology_period" in module.Args.__dataclass_fields__ else {}
    args = ene.suite_settings(module.Args(hidden_dim=32, batch_size=16, **topology))
    torch.manual_seed(0)
    agent, loop = module.make_agent(6, 2, args, torch.device("cpu")), module.Loop()
    for step in range(12):
        module.sac_update(agent, random_batch(module, step, "cpu"), loop, args)
    assert len(fake_cuda) == 3 and all(wrapped.graph is not None for wrapped in steps.values())


def reset_critic(agent):
    module = importlib.import_module("pebble")
    critic = module.make_critic(6, 2, ene.suite_settings(module.Args(hidden_dim=32)), torch.device("cpu"))
    agent.qf1, agent.qf2, agent.q_optimizer, agent.qf1_target, agent.qf2_target = critic


GRADIENTS = {"critic_gradients", "actor_gradients"}  # the two steps that take the batch
RECAPTURES = {  # a change after 6 updates, and the steps captured again
    "a batch of 8 rows": GRADIENTS,  # target_update has no tensor input
    "a parameter's requires_grad": set(STEPS),
    "a parameter's storage": set(STEPS),
    "TF32 matmuls": set(STEPS),
    "the critics' .grad cleared": {"critic_gradients"},  # the actor's backward leaves the critics' `.grad` alone
    "a critic's .grad replaced": {"critic_gradients"},
    "the actor's .grad cleared": {"actor_gradients"},
    "PEBBLE's critic reset": set(STEPS),
    "a new critic optimiser": set(STEPS),  # any agent field replaced
}
STATE_CHANGES.update({"the critics' .grad cleared": lambda agent: agent.q_optimizer.zero_grad(),
                      "a critic's .grad replaced": fresh_grad,
                      "the actor's .grad cleared": lambda agent: agent.actor_optimizer.zero_grad(),
                      "PEBBLE's critic reset": reset_critic,
                      "a new critic optimiser": lambda agent: setattr(agent, "q_optimizer", torch.optim.Adam(
                          [*agent.qf1.parameters(), *agent.qf2.parameters()]))})


@pytest.mark.parametrize("change", RECAPTURES)
def test_a_change_is_captured_again(change, monkeypatch, fake_cuda, float32_flags):
    module = importlib.import_module("pebble")
    steps = captured(module, monkeypatch)
    agent, args = tiny_agent(module, torch.device("cpu"))
    loop, rows = module.Loop(), 16
    for step in range(12):  # from the change, 6 updates: 3 calls of each step, the third captures
        if step == 6:
            graphs = {name: wrapped.graph for name, wrapped in steps.items()}
            if change == "a batch of 8 rows":
                rows = 8
            else:
                STATE_CHANGES[change](agent)
        module.sac_update(agent, random_batch(module, step, "cpu", rows), loop, args)
    assert {name for name, wrapped in steps.items() if wrapped.graph is not graphs[name]} == RECAPTURES[change]
    assert len(fake_cuda) == 3 + len(RECAPTURES[change]) and all(wrapped.graph for wrapped in steps.values())
    critics = [*agent.qf1.parameters(), *agent.qf2.parameters()]  # the `.grad` a critic graph writes: the critics'
    assert [p for p, _ in steps["critic_gradients"].grads] == [p for p in critics if p.requires_grad]
    actor = [*agent.actor.parameters(), agent.log_alpha]  # the actor graph's: the actor's and the temperature's
    assert [p for p, _ in steps["actor_gradients"].grads] == [p for p in actor if p.requires_grad]


def test_a_new_device_stops_the_run(monkeypatch, fake_cuda):
    module = importlib.import_module("pebble")
    captured(module, monkeypatch)
    agent, args = tiny_agent(module, torch.device("cpu"))
    loop = module.Loop()
    for step in range(4):
        module.sac_update(agent, random_batch(module, step, "cpu"), loop, args)
    data = random_batch(module, 4, "cpu")._replace(indices=torch.arange(16, device="meta"))
    with pytest.raises(RuntimeError, match="critic_gradients was captured on cpu and is now called on cpu, meta"):
        module.sac_update(agent, data, loop, args)


# `WholeUpdate`: the whole SAC update as one graph, Adam inside, once its host scalars have settled.


def settled_twins(module, device, topology_period: int = 5):
    """Two agents from one seed, each after one update (Adam's state exists) with its step counts set to the settle
    step, as in a run past its first 16 628 updates; a topology step falls within the next `topology_period`."""
    topology = ({"agent_topology_period": topology_period}
                if "agent_topology_period" in module.Args.__dataclass_fields__ else {})
    args = ene.suite_settings(module.Args(hidden_dim=32, batch_size=16, **topology))
    twins = []
    for _ in range(2):
        torch.manual_seed(0)
        agent, loop = module.make_agent(6, 2, args, device), module.Loop()
        module.sac_update(agent, random_batch(module, 0, device), loop, args)
        for adam in WholeUpdate.adams(agent):
            for group in adam.param_groups:
                for p in group["params"]:
                    adam.state[p]["step"].fill_(settle_step(group["lr"], *group["betas"]))
        twins.append((agent, loop))
    return twins, args


def host_counts(agent, loop) -> list:
    """The integers an update moves on the host, and every Adam step count."""
    return ([getattr(o, name) for o, name in WholeUpdate.counters(agent, loop)]
            + [float(state["step"]) for adam in WholeUpdate.adams(agent) for state in adam.state.values()])


def test_adam_settles_where_its_float32_scalars_stop_changing():
    t = settle_step(1e-4, 0.9, 0.999)
    assert t == 16_628  # the scripts' learning rates and betas
    for step in (t - 1, t):  # foreach Adam's two host scalars at each step count
        scalars = np.float32(-1e-4 / (1 - 0.9**step)), np.float32((1 - 0.999**step) ** 0.5)
        assert (scalars == (np.float32(-1e-4), np.float32(1.0))) == (step == t)


@pytest.mark.parametrize("script", PBRL + ORACLES)
def test_whole_update_captures_once_settled_and_moves_the_host_counts_as_eager(script, monkeypatch, fake_cuda):
    """Eager and whole-update twins through 12 updates, a topology step included: one graph per branch pattern, the
    topology step eager, and after each update the same host counts (the loop's, the sparse optimisers', Adam's step
    counts) and the same loss tags. A replay (faked: it runs no kernel) moves the counts as the update would."""
    module = importlib.import_module(script[:-3])
    captured(module, monkeypatch)
    ((eager, eager_loop), (agent, loop)), args = settled_twins(module, torch.device("cpu"))
    whole = WholeUpdate(module.sac_update)
    topology_steps = []
    for step in range(12):
        data = random_batch(module, step + 1, "cpu")
        topology_steps.append(WholeUpdate.topology_due(agent))
        module.sac_update(eager, data, eager_loop, args)
        whole(agent, data, loop, args)
        assert host_counts(agent, loop) == host_counts(eager, eager_loop), f"{script}: update {step}"
        assert loop.losses.keys() == eager_loop.losses.keys()
        if whole.graphs and step >= 4 and not topology_steps[-1]:  # a replay: its graph's outputs
            written = {id(v) for graph in whole.graphs.values() for v in graph[4].values()}
            assert all(id(v) in written for v in loop.losses.values()), script
    patterns = {(n % args.actor_update_freq == 0, n % args.target_update_freq == 0) for n in range(2, 14)}
    assert set(whole.graphs) == patterns
    if any(hasattr(x, "period") and x.sparsity for x in vars(agent).values()):  # RigL's or SET's steps
        assert any(topology_steps) and not all(topology_steps)


def test_whole_update_waits_for_every_adam_to_settle(monkeypatch, fake_cuda):
    """Before the settle step nothing is captured; PEBBLE's critic reset gives a new Adam at step 0, and the whole
    update runs as before (its steps captured apart) until that one has settled too."""
    module = importlib.import_module("pebble")
    captured(module, monkeypatch)
    agent, args = tiny_agent(module, torch.device("cpu"))
    loop, whole = module.Loop(), WholeUpdate(module.sac_update)
    for step in range(6):
        whole(agent, random_batch(module, step, "cpu"), loop, args)
    assert whole.graphs == {}
    (_, (agent, loop)), args = settled_twins(module, torch.device("cpu"))
    for step in range(6):
        whole(agent, random_batch(module, step, "cpu"), loop, args)
    assert whole.graphs
    reset_critic(agent)
    for step in range(6):
        whole(agent, random_batch(module, step, "cpu"), loop, args)
    assert whole.graphs == {} and not whole.settled
    assert float(agent.q_optimizer.state[next(agent.qf1.parameters())]["step"]) == 6  # stepped eagerly


@gpu
@pytest.mark.parametrize("script", PBRL + ORACLES)
def test_whole_update_equals_eager(script, monkeypatch, run_stream):
    """All 12 scripts: 30 settled updates, eager against the whole update replayed (a topology step inside where the
    agent is sparse): every parameter, Adam moment and step count, mask and loss the same, bit for bit."""
    module = importlib.import_module(script[:-3])
    device = torch.device("cuda")
    ((eager, eager_loop), (agent, loop)), args = settled_twins(module, device, topology_period=15)
    whole = WholeUpdate(module.sac_update)
    for arm, update in (("eager", lambda data: module.sac_update(eager, data, eager_loop, args)),
                        ("whole", lambda data: whole(agent, data, loop, args))):
        if arm == "whole":  # as `--cuda-graph-whole` runs it: the steps captured apart, inside the whole capture too
            captured(module, monkeypatch)
        torch.manual_seed(1)  # one random stream for both
        for step in range(30):
            update(random_batch(module, step + 1, device))
    torch.cuda.synchronize()
    assert whole.graphs, f"{script}: no update was replayed"

    def state(agent, loop) -> list:
        tensors = CudaGraph.parameters(agent) + list(loop.losses.values())
        tensors += [t for adam in WholeUpdate.adams(agent) for s in adam.state.values() for t in s.values()]
        tensors += [m for x in vars(agent).values() for m in getattr(x, "masks", {}).values()]
        return [t.detach().cpu() for t in tensors]

    assert host_counts(agent, loop) == host_counts(eager, eager_loop)
    assert loop.losses.keys() == eager_loop.losses.keys()
    for a, b in zip(state(eager, eager_loop), state(agent, loop), strict=True):  # bit for bit: -0.0 is not 0.0
        assert torch.equal(a.view(torch.int32), b.view(torch.int32)) if a.dtype == torch.float32 else torch.equal(a, b)
