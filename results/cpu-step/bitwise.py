"""Issue 44 (CPU part): which lighter CPU steps are bitwise identical to today's numerics.

Standalone; reads the scripts (sac.py, pebble.py, r2n_pebble.py) through their own functions and classes, changes none.
Run from the repository root, on one thread:

    OMP_NUM_THREADS=1 .venv/bin/python results/cpu-step/bitwise.py        # all: bitwise.json (~5 min)
    OMP_NUM_THREADS=1 .venv/bin/python results/cpu-step/bitwise.py time   # timings only, 11 blocks: timing.json

(a) act: an action-only act (no log-prob) against the script's `act`, and an action-only deterministic evaluation
    action against `get_action(obs)[2]`: the actions bit for bit, and the global RNG state after them.
(b) Adam: `foreach=True` and `fused=True` against the default (on CPU: the single-tensor path), 200 of the script's
    own `sac_update` steps on its own agent (`make_agent`, the studies' sizes), every parameter, Adam moment and loss
    compared bit for bit; the reward ensemble's Adam too (r2n_pebble's masked one, with RigL updates).
(c) time per call of each, in one process, interleaved blocks, medians.
Writes results/cpu-step/bitwise.json.
"""
import importlib
import json
import os
import statistics
import sys
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")
import torch  # noqa: E402

torch.set_num_threads(1)
ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, ROOT)

OBS_DIM, ACT_DIM = 171, 6  # cheetah-run at --noise 0.9: ceil(17 / 0.1) = 171 features; 6 actions
HIDDEN, BATCH = 256, 128
EVAL_ENVS = 10
MODULES = ("sac", "pebble", "r2n_pebble")
CPU = torch.device("cpu")
OUT = {}


def bits(t: torch.Tensor) -> torch.Tensor:
    """The tensor's bit pattern (so -0.0 != 0.0 and NaNs compare by payload)."""
    t = t.detach().contiguous()
    return t.view({torch.float32: torch.int32, torch.float64: torch.int64}[t.dtype]) if t.is_floating_point() else t


def same_bits(a, b) -> bool:
    return a.shape == b.shape and a.dtype == b.dtype and torch.equal(bits(a), bits(b))


def args_for(m, **extra):
    """The studies' config: --env-id cheetah-run --noise 0.9 --hidden-dim 256 --batch-size 128 --no-noise-resample."""
    return m.ene.suite_settings(m.Args(env_id="cheetah-run", noise=0.9, hidden_dim=HIDDEN, batch_size=BATCH,
                                       noise_resample=False, threads=1, cuda=False, **extra))


def timeit(fns: dict, calls: int, blocks: int = 7) -> dict:
    """Seconds per call of each fn: `blocks` rounds, each running every fn `calls` times in turn; the median."""
    times = {name: [] for name in fns}
    for _ in range(blocks):
        for name, fn in fns.items():
            start = time.perf_counter()
            for _ in range(calls):
                fn()
            times[name].append((time.perf_counter() - start) / calls)
    return {name: statistics.median(t) for name, t in times.items()}


# ---------------------------------------------------------------------------------------------------------------- (a)
@torch.no_grad()
def act_light(actor, obs: torch.Tensor) -> torch.Tensor:
    """The candidate: today's act without the log-prob (same draw, same ops on x)."""
    mean, log_std = actor(obs.unsqueeze(0))
    eps = torch.randn_like(mean)
    return torch.tanh(mean + log_std.exp() * eps)[0]


@torch.inference_mode()
def act_light_inference(actor, obs: torch.Tensor) -> torch.Tensor:
    mean, log_std = actor(obs.unsqueeze(0))
    eps = torch.randn_like(mean)
    return torch.tanh(mean + log_std.exp() * eps)[0]


@torch.no_grad()
def eval_today(actor, obs: torch.Tensor) -> torch.Tensor:
    return actor.get_action(obs)[2]  # what `evaluate` does


@torch.no_grad()
def eval_light(actor, obs: torch.Tensor) -> torch.Tensor:
    """The candidate: tanh(mean) only; the draw today's get_action makes is kept, so the RNG advances as before."""
    mean = actor.net(obs).chunk(2, dim=-1)[0]
    torch.randn_like(mean)
    return torch.tanh(mean)


@torch.no_grad()
def eval_light_forward(actor, obs: torch.Tensor) -> torch.Tensor:
    """The same through the actor's forward (its log-std computed, unused): the form recommended."""
    mean, _ = actor(obs)
    torch.randn_like(mean)
    return torch.tanh(mean)


@torch.no_grad()
def eval_light_nodraw(actor, obs: torch.Tensor) -> torch.Tensor:
    """tanh(mean) without the draw: same actions, but the RNG is left where it was (shown to differ)."""
    return torch.tanh(actor.net(obs).chunk(2, dim=-1)[0])


def rollout(fn, actor, observations, seed: int):
    """Actions for each observation in turn, with the loop's other draws (a batch index, a
    RigL-like rand) in between; returns (actions, other draws, RNG state after)."""
    torch.manual_seed(seed)
    actions, others = [], []
    for obs in observations:
        actions.append(fn(actor, obs))
        others.append(torch.randint(0, 10_000, (BATCH,)).float())
        others.append(torch.randn(BATCH, ACT_DIM))
    return torch.stack(actions), torch.cat([o.flatten() for o in others]), torch.get_rng_state()


def part_a():
    results = {}
    gen = torch.Generator().manual_seed(123)
    for name in MODULES:
        m = importlib.import_module(name)
        torch.manual_seed(0)
        agent = m.make_agent(OBS_DIM, ACT_DIM, args_for(m), CPU)  # r2n: its masked input layer
        actor = agent.actor
        for scale_name, scale in (("init", 1.0), ("weights x3", 3.0)):  # x3: larger means, tanh near saturation
            if scale != 1.0:
                with torch.no_grad():
                    for p in actor.parameters():
                        p.mul_(scale)
            single = [torch.randn(OBS_DIM, generator=gen) * 2 for _ in range(2000)]
            batched = [torch.randn(EVAL_ENVS, OBS_DIM, generator=gen) * 2 for _ in range(500)]
            today = rollout(lambda a, o: m.act(a, o), actor, single, 7)
            rows = {}
            for cand, fn in (("act_light", act_light), ("act_light_inference", act_light_inference)):
                got = rollout(fn, actor, single, 7)
                rows[cand] = dict(actions=same_bits(today[0], got[0]), other_draws=same_bits(today[1], got[1]),
                                  rng_state=torch.equal(today[2], got[2]), n=len(single))
            today_e = rollout(eval_today, actor, batched, 11)
            for cand, fn in (("eval_light", eval_light), ("eval_light_forward", eval_light_forward),
                             ("eval_light_nodraw", eval_light_nodraw)):
                got = rollout(fn, actor, batched, 11)
                rows[cand] = dict(actions=same_bits(today_e[0], got[0]), other_draws=same_bits(today_e[1], got[1]),
                                  rng_state=torch.equal(today_e[2], got[2]), n=len(batched))
            results[f"{name} ({scale_name})"] = rows
        print(name, json.dumps({k: v for k, v in results.items() if k.startswith(name)}, indent=1), flush=True)
    OUT["a_act"] = results


def part_a_time(blocks: int = 7):
    """(c) for (a): per call, interleaved blocks, same process."""
    results = {}
    gen = torch.Generator().manual_seed(321)
    for name in MODULES:
        m = importlib.import_module(name)
        torch.manual_seed(0)
        actor = m.make_agent(OBS_DIM, ACT_DIM, args_for(m), CPU).actor
        obs1 = torch.randn(OBS_DIM, generator=gen)
        obs10 = torch.randn(EVAL_ENVS, OBS_DIM, generator=gen)
        t = timeit({"act today": lambda: m.act(actor, obs1), "act_light": lambda: act_light(actor, obs1),
                    "act_light_inference": lambda: act_light_inference(actor, obs1),
                    "eval today": lambda: eval_today(actor, obs10), "eval_light": lambda: eval_light(actor, obs10),
                    "eval_light_forward": lambda: eval_light_forward(actor, obs10)},
                   calls=400, blocks=blocks)
        results[f"{name} time_us"] = {k: round(v * 1e6, 2) for k, v in t.items()}
        results[f"{name} ratio"] = {
            "act_light / act today": round(t["act_light"] / t["act today"], 3),
            "act_light_inference / act today": round(t["act_light_inference"] / t["act today"], 3),
            "eval_light / eval today": round(t["eval_light"] / t["eval today"], 3),
            "eval_light_forward / eval today": round(t["eval_light_forward"] / t["eval today"], 3),
        }
        print(name, json.dumps({k: v for k, v in results.items() if k.startswith(name)}), flush=True)
    OUT["c_time_act"] = results


# ---------------------------------------------------------------------------------------------------------------- (b)
def rebuild(opt, **kw):
    """The same Adam over the same parameters (same order, same hyperparameters), with `kw` (foreach/fused)."""
    (group,) = opt.param_groups
    assert not opt.state, "rebuild before the first step"
    return torch.optim.Adam(group["params"], lr=group["lr"], betas=group["betas"], eps=group["eps"],
                            weight_decay=group["weight_decay"], amsgrad=group["amsgrad"], maximize=group["maximize"],
                            **kw)


def inner(opt):
    return getattr(opt, "optimizer", opt)  # r2n_pebble's SparseOptimizer wraps an Adam


def set_inner(opt, new):
    if hasattr(opt, "optimizer"):
        opt.optimizer = new
        return opt
    return new


def with_variant(agent, kw, fields=("actor_optimizer", "q_optimizer", "a_optimizer")):
    if kw:
        for field in fields:
            opt = getattr(agent, field)
            setattr(agent, field, set_inner(opt, rebuild(inner(opt), **kw)))
    return agent


def agent_tensors(agent) -> dict:
    out = {}
    for net in ("actor", "qf1", "qf2", "qf1_target", "qf2_target"):
        for pname, p in getattr(agent, net).named_parameters():
            out[f"{net}.{pname}"] = p
    out["log_alpha"], out["alpha"] = agent.log_alpha, agent.alpha
    for field in ("actor_optimizer", "q_optimizer", "a_optimizer"):
        opt = getattr(agent, field)
        for i, p in enumerate(inner(opt).param_groups[0]["params"]):
            for key, value in inner(opt).state[p].items():
                out[f"{field}[{i}].{key}"] = value.float() if key == "step" else value
        for mname, mask in getattr(opt, "masks", {}).items():
            out[f"{field}.mask.{mname}"] = mask
    return out


def batches(n: int, seed: int):
    g = torch.Generator().manual_seed(seed)
    out = []
    for _ in range(n):
        out.append(dict(obs=torch.randn(BATCH, OBS_DIM, generator=g), actions=torch.rand(BATCH, ACT_DIM, generator=g) * 2 - 1,
                        rewards=torch.randn(BATCH, generator=g), next_obs=torch.randn(BATCH, OBS_DIM, generator=g),
                        dones=torch.zeros(BATCH), indices=torch.randint(0, 1000, (BATCH,), generator=g)))
    return out


def train_agent(m, args, kw, data):
    torch.manual_seed(0)
    agent = with_variant(m.make_agent(OBS_DIM, ACT_DIM, args, CPU), kw)
    loop = m.Loop()
    torch.manual_seed(1)
    losses = []
    for d in data:
        m.sac_update(agent, m.Batch(**d), loop, args)
        losses.append(torch.stack([loop.losses[k] for k in sorted(loop.losses)]))
    return agent, torch.stack(losses)


def compare(ref: dict, got: dict) -> dict:
    differing = [k for k in ref if not same_bits(ref[k], got[k])]
    max_diff = max((float((ref[k].detach().double() - got[k].detach().double()).abs().max()) for k in differing), default=0.0)
    return dict(bitwise=not differing, n_tensors=len(ref), differing=len(differing), max_abs_diff=max_diff,
                first_differing=differing[:3])


VARIANTS = {"foreach=True": dict(foreach=True), "fused=True": dict(fused=True)}


def part_b(steps: int = 200):
    results = {}
    data = batches(steps, 5)
    configs = [(name, {}) for name in MODULES] + [("r2n_pebble", dict(agent_topology_period=50))]  # + 4 RigL updates
    for name, extra in configs:
        m = importlib.import_module(name)
        args = args_for(m, **extra)
        label = name + (" agent_topology_period=50" if extra else "")
        ref_agent, ref_losses = train_agent(m, args, {}, data)
        ref = agent_tensors(ref_agent)
        assert inner(ref_agent.q_optimizer).param_groups[0]["foreach"] in (None, False)
        row = {}
        for vname, kw in VARIANTS.items():
            agent, losses = train_agent(m, args, kw, data)
            got = agent_tensors(agent)
            row[vname] = compare(ref, got)
            first = next((i for i in range(steps) if not same_bits(ref_losses[i], losses[i])), None)
            row[vname]["losses_bitwise"] = first is None
            row[vname]["first_step_losses_differ"] = first
        results[label] = row
        print(label, json.dumps(row), flush=True)
    OUT["b_adam_sac_update"] = results


def part_b_reward(steps: int = 40, pairs: int = 16):
    """The reward ensemble's Adam: pebble's dense one, r2n_pebble's masked one (RigL every 10 steps here)."""
    results = {}
    g = torch.Generator().manual_seed(9)
    segs = [torch.randn(3, pairs, 2, 50, OBS_DIM + ACT_DIM, generator=g) for _ in range(steps)]
    labels = [torch.randint(0, 2, (3, pairs), generator=g).float() for _ in range(steps)]

    def run(m, kw, sparse: bool):
        torch.manual_seed(0)
        model = m.RewardEnsemble(OBS_DIM + ACT_DIM, 128, 4, 3)
        opt = torch.optim.Adam(model.parameters(), lr=3e-3, **kw)
        if sparse:
            opt = m.SparseOptimizer(opt, {"reward": model.weights[0]}, 0.8, 0.2, 10)
        torch.manual_seed(1)
        for s, lab in zip(segs, labels):
            returns = model(s.flatten(1, 3)).view(*lab.shape, 2, -1).sum(-1)
            loss = m.preference_loss(returns, lab)
            opt.zero_grad()
            loss.sum().backward()
            opt.step()
        out = {f"p.{k}": v for k, v in model.named_parameters()}
        for i, p in enumerate(inner(opt).param_groups[0]["params"]):
            for key, value in inner(opt).state[p].items():
                out[f"state[{i}].{key}"] = value.float() if key == "step" else value
        return out

    for name, sparse in (("pebble", False), ("r2n_pebble", True)):
        m = importlib.import_module(name)
        ref = run(m, {}, sparse)
        results[name] = {v: compare(ref, run(m, kw, sparse)) for v, kw in VARIANTS.items()}
        print("reward", name, json.dumps(results[name]), flush=True)
    OUT["b_adam_reward"] = results


def part_b_options(steps: int = 200):
    """Not used by the scripts (they pass lr only: weight_decay 0, amsgrad False), for completeness."""
    results = {}
    for opts in (dict(), dict(weight_decay=1e-2), dict(amsgrad=True)):
        def run(kw):
            m = importlib.import_module("sac")
            torch.manual_seed(0)
            actor = m.Actor(OBS_DIM, ACT_DIM, HIDDEN)
            opt = torch.optim.Adam(actor.parameters(), lr=1e-4, **opts, **kw)
            g = torch.Generator().manual_seed(3)
            for _ in range(steps):
                for p in actor.parameters():
                    p.grad = torch.randn(p.shape, generator=g) * 1e-2
                opt.step()
            return {k: v for k, v in actor.named_parameters()}
        ref = run({})
        results[json.dumps(opts)] = {v: compare(ref, run(kw))["bitwise"] for v, kw in VARIANTS.items()}
    print("options", json.dumps(results), flush=True)
    OUT["b_adam_options"] = results


# ---------------------------------------------------------------------------------------------------------------- (c)
def part_c(blocks: int = 7):
    """Per call of `optimizer.step()` (the raw Adam) on the scripts' optimisers, and of one whole `sac_update`;
    "foreach q+actor": foreach=True on the critics' and the actor's Adam only, log_alpha's left as it is."""
    results = {}
    for name in ("sac", "r2n_pebble"):
        m = importlib.import_module(name)
        args = args_for(m)
        data = batches(1, 5)[0]
        agents = {}
        for vname, kw in {"default": {}, **VARIANTS, "foreach q+actor": dict(foreach=True)}.items():
            fields = ("actor_optimizer", "q_optimizer") + (() if vname == "foreach q+actor" else ("a_optimizer",))
            torch.manual_seed(0)
            agents[vname] = with_variant(m.make_agent(OBS_DIM, ACT_DIM, args, CPU), kw, fields)
            m.sac_update(agents[vname], m.Batch(**data), m.Loop(), args)  # grads and state exist
        for field in ("q_optimizer", "actor_optimizer", "a_optimizer"):
            t = timeit({v: inner(getattr(a, field)).step for v, a in agents.items() if v != "foreach q+actor"},
                       calls=200, blocks=blocks)
            results[f"{name} {field}.step"] = dict(
                us={k: round(v * 1e6, 1) for k, v in t.items()},
                ratio={k: round(v / t["default"], 3) for k, v in t.items()})
        loops = {v: m.Loop() for v in agents}
        batch = m.Batch(**data)
        t = timeit({v: (lambda a=a, lp=loops[v]: m.sac_update(a, batch, lp, args)) for v, a in agents.items()},
                   calls=30, blocks=blocks)
        results[f"{name} sac_update"] = dict(us={k: round(v * 1e6, 1) for k, v in t.items()},
                                             ratio={k: round(v / t["default"], 3) for k, v in t.items()})
        print(name, json.dumps({k: v for k, v in results.items() if k.startswith(name)}), flush=True)
    m = importlib.import_module("r2n_pebble")
    models = {}
    for vname, kw in {"default": {}, **VARIANTS}.items():
        torch.manual_seed(0)
        model = m.RewardEnsemble(OBS_DIM + ACT_DIM, 128, 4, 3)
        opt = torch.optim.Adam(model.parameters(), lr=3e-3, **kw)
        for p in model.parameters():
            p.grad = torch.randn_like(p) * 1e-2
        opt.step()
        models[vname] = opt
    t = timeit({v: o.step for v, o in models.items()}, calls=200, blocks=blocks)
    results["reward_optimizer.step"] = dict(us={k: round(v * 1e6, 1) for k, v in t.items()},
                                            ratio={k: round(v / t["default"], 3) for k, v in t.items()})
    print("reward", json.dumps(results["reward_optimizer.step"]), flush=True)
    OUT["c_time"] = results


if __name__ == "__main__":
    start = time.time()
    OUT["env"] = dict(torch=torch.__version__, threads=torch.get_num_threads(), obs_dim=OBS_DIM, act_dim=ACT_DIM,
                      hidden=HIDDEN, batch=BATCH)
    # `time`: the timings (c) alone, with more blocks (the machine is shared: its load drifts)
    timing_only = sys.argv[1:] == ["time"]
    if not timing_only:
        part_a()
        part_b()
        part_b_reward()
        part_b_options()
    part_a_time(11 if timing_only else 7)
    part_c(11 if timing_only else 7)
    OUT["seconds"] = round(time.time() - start, 1)
    out_name = "timing.json" if timing_only else "bitwise.json"
    with open(os.path.join(os.path.dirname(os.path.abspath(__file__)), out_name), "w") as f:
        json.dump(OUT, f, indent=1)
    print("seconds", OUT["seconds"])
