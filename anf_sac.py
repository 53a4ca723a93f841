# docs and experiment results: docs/NAME.md, NAME being the name of this file without .py
"""ANF-SAC (docs/anf_sac.md): the SAC below with sparse input layers rewired by RigL (ANF PATCH).
R2N paper: Muslimani et al., "Boosting Robustness in Preference-Based Reinforcement Learning with
Dynamic Sparsity", AAMAS 2025 (the authors' code: https://github.com/cmuslima/R2N).

SAC: Haarnoja et al., "Soft Actor-Critic Algorithms and Applications" (2018), exactly the SAC inside
`pebble.py` (networks, update, flags and defaults from the R2N paper's appendix), but the replay
buffer stores the env's reward, not a learned one: `diff sac.py pebble.py` shows only PEBBLE. The
loop, one iteration per env step:

1. `global_step < learning_starts`: uniform random actions, no learning.
2. then one SAC update per step on the true reward.
Evaluation every `eval_freq` steps: `eval_episodes` deterministic episodes on own envs, true reward.

Two uses: the upper bound ("SAC with the true reward") for PbRL curves at equal `--noise`, with the
noise redrawn (with it stored, SAC falls below PEBBLE at the studies' scale); with `--noise 0`, a
noise-free policy whose deterministic rollouts give `--noise-type imitate` its histograms
(`make_histograms.py`). Choices where the paper is silent, from `pebble.py`: a stored observation
keeps its noise (`--noise-resample` redraws it in replay minibatches, like ANF's code). Critics
bootstrap on `terminated` only. `make_critic` stays a function (PEBBLE resets critics) for
byte-identical shared code.

Only `ene.py`, the noisy environment, is shared with the other scripts.
`--help` documents every flag.
"""
# ANF PATCH: SAC with sparse input layers, the oracle of R2N's sparse agent: ANF (Grooten et al.,
# "Automatic Noise Filtering with Dynamic Sparse Training in Deep Reinforcement Learning", AAMAS
# 2023; code: https://github.com/bramgrooten/automatic-noise-filtering) with the agent half of the
# R2N patch (`diff pebble.py r2n_pebble.py`) unchanged, minus its reward half. Actor, Q1 and Q2
# keep 20% of their input-layer weights (independent random masks). Every 1000 SAC optimiser steps
# RigL drops the 5% smallest active weights and grows as many where the dense gradient is largest.
# The R2N paper contradicts itself here: its table gives RigL for ANF-SAC, its text says ANF is
# based on SET; ANF's public code regrows at random, as SET does. Masked weights, gradients and
# Adam moments stay 0; grown ones start at 0, moments too. Target critics: dense Polyak copies.
# `--agent-sparsity 0` keeps dense layers but still draws the masks, so it is not sac.py's run for
# a seed. `diff sac.py anf_sac.py` shows the patch.
import dataclasses
import importlib
import importlib.util
import math
import os
import random
import signal
import time
from collections import deque
from dataclasses import dataclass, field, fields
from typing import Literal, NamedTuple, Optional

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F
import torch.optim as optim
import tyro
from torch.utils.tensorboard import SummaryWriter

import ene


@dataclass
class Args:
    seed: int = 1
    """seed of the experiment"""

    # Environment arguments
    env_id: str = "cheetah-run"
    """the task: dm_control as domain-task (cheetah-run), or gymnasium MuJoCo (Hopper-v5, ...)"""
    noise: float = 0.9
    """fraction of all observation features that are noise, in [0, 1)"""
    noise_type: Literal["gaussian", "imitate"] = "gaussian"
    """noise features: i.i.d. N(0, 1), or imitating the real features' histograms"""
    noise_resample: bool = False
    """redraw the noise columns of stored observations each time they are read (ANF's code);
    off, the default, they are stored as the environment returned them (B-Pref's buffers)"""
    noise_histograms: Optional[str] = None
    """the `.npz` of real-feature histograms (`bin_edges`, `probs`) for `--noise-type imitate`"""
    episode_length: int = 1000
    """environment steps per episode (episodes are truncated, never terminated)"""

    # Algorithm specific arguments
    total_timesteps: int = 1_000_000
    """total environment steps"""
    buffer_size: int = 1_000_000
    """the replay memory buffer size"""
    gamma: float = 0.99
    """the discount factor gamma"""
    tau: float = 0.005
    """target smoothing coefficient"""
    batch_size: int = 1024
    """the batch size of SAC updates"""
    hidden_dim: int = 1024
    """width of the two hidden layers of actor and critics"""
    learning_starts: int = 1000
    """steps of uniform random actions before learning starts"""
    policy_lr: float = 1e-4
    """the learning rate of the policy network optimizer"""
    q_lr: float = 1e-4
    """the learning rate of the Q network optimizer"""
    alpha_lr: float = 1e-4
    """the learning rate of the temperature"""
    init_temperature: float = 0.1
    """initial entropy temperature alpha (learned, target entropy -|A|)"""
    actor_update_freq: int = 1
    """actor and temperature update every this many SAC updates"""
    target_update_freq: int = 2
    """target critics update every this many SAC updates"""
    eval_freq: int = 5000
    """evaluate every this many environment steps (and at the end)"""
    eval_episodes: int = 10
    """deterministic evaluation episodes, true reward"""

    # Run settings: where the run writes, what it keeps, how it is watched. None of them changes
    # what it learns, but --compile and --tf32 change its floating-point numerics.
    exp_name: str = os.path.basename(__file__)[: -len(".py")]
    """the name of this experiment (run folder and checkpoint name)"""
    torch_deterministic: bool = True
    """if toggled, `torch.backends.cudnn.deterministic=True`"""
    cuda: bool = True
    """if toggled, cuda will be used when available"""
    compile: bool = False
    """torch.compile the SAC steps (critic, actor and temperature, target). Faster on a GPU.
    Numerics are within float tolerance of eager.
    analyze.py never averages or compares runs with other numerics flags."""
    tf32: bool = False
    """TF32 matmuls on a CUDA GPU (10-bit mantissas on tensor cores).
    Faster; numerics differ from FP32."""
    cuda_graph: bool = False
    """replay the SAC steps' gradients as CUDA graphs (GPU only).
    Faster; the same numbers as eager on that GPU."""
    parallel_eval: bool = False
    """step the evaluation envs at once, each in its own process.
    Faster where cores are free; the same returns."""
    track: bool = False
    """if toggled, this experiment will be tracked with Weights and Biases"""
    wandb_project_name: str = "r2n"
    """the wandb's project name"""
    wandb_entity: Optional[str] = None
    """the entity (team) of wandb's project"""
    capture_video: bool = False
    """whether to capture videos of the first evaluation env (`videos/{run_name}`).
    Needs the `video` extra."""
    save_model: bool = True
    """whether to save the checkpoint `runs/{run_name}/{exp_name}.cleanrl_model`.
    It is written at every evaluation."""
    threads: Optional[int] = None
    """torch intra-op threads. Unset: 1 on CPU (runs share a machine), torch's default on GPU."""
    log_freq: int = 1000
    """log the SAC losses every `log_freq` steps, a host sync; the loop's others are each step's
    action for the env and the reads of a feedback round and of a topology update"""
    run_name: Optional[str] = None
    """the run folder `runs/{run_name}` (unset: `{env_id}__{exp_name}__{seed}__{time}`).
    A folder holding a `state.pt` is resumed."""
    state_minutes: float = 10.0
    """write the full training state `runs/{run_name}/state.pt` every this many wall-time minutes.
    It is written after the step that ends the interval, and on SIGTERM / SIGUSR2.
    A 1024-wide state is about 1 GB, so keep writes rare."""
    checkpoint_freq: Optional[int] = None
    """write `state.pt` every this many steps instead of by wall time (tests, exact comparisons)"""
    keep_state: bool = False
    """keep `state.pt` when the run ends (by default it is deleted then: the run needs no resume)"""

    # ANF arguments: dynamic sparse training (RigL) of the input layers of actor and critics
    agent_sparsity: float = 0.8
    """fraction of the actor's and critics' input-layer weights that are zero"""
    agent_drop_fraction: float = 0.05
    """share of actor/critic input-layer active weights dropped and regrown per topology update"""
    agent_topology_period: int = 1000
    """SAC optimiser steps between topology updates of actor and critics"""


def validate_args(args: Args) -> None:
    """Fail fast on bad input, before anything is written:
    a ValueError with one line naming the flag."""
    ene.check_env_args(args.env_id, args.noise, args.noise_type, args.noise_histograms)
    if args.track and importlib.util.find_spec("wandb") is None:
        raise ValueError("--track needs wandb: pip install -e '.[wandb]'")
    harness_flags = {"--cuda-graph": args.cuda_graph}  # the flags that need the harness's package
    given = [flag for flag, on in harness_flags.items() if on]
    if given and importlib.util.find_spec("r2n_harness") is None:  # a copy of this file without it
        raise ValueError(f"{given[0]} needs the package r2n_harness: run this in R2N's repository")
    if args.tf32 and not (args.cuda and torch.cuda.is_available()):
        raise ValueError("--tf32: TF32 matmuls need a CUDA GPU, and this run is on the CPU")
    if args.cuda_graph and not (args.cuda and torch.cuda.is_available()):
        raise ValueError("--cuda-graph: CUDA graphs need a CUDA GPU, and this run is on the CPU")
    if args.run_name is not None and (args.run_name in ("", ".", "..") or "/" in args.run_name):
        raise ValueError(f"--run-name must be a folder name without '/', got {args.run_name!r}")
    if args.checkpoint_freq is not None and args.checkpoint_freq < 1:
        raise ValueError(f"--checkpoint-freq must be >= 1, got {args.checkpoint_freq}")
    if not args.state_minutes > 0:
        raise ValueError(f"--state-minutes must be > 0, got {args.state_minutes}")
    if args.buffer_size < args.batch_size:
        raise ValueError(
            f"--buffer-size {args.buffer_size} is smaller than --batch-size {args.batch_size}"
        )
    if not 0.0 <= args.agent_sparsity < 1.0:
        raise ValueError(f"--agent-sparsity must be in [0, 1), got {args.agent_sparsity}")
    if not 0.0 <= args.agent_drop_fraction <= 1.0:
        raise ValueError(f"--agent-drop-fraction must be in [0, 1], got {args.agent_drop_fraction}")
    for flag in (
        "agent_topology_period", "episode_length", "eval_freq",
        "eval_episodes", "log_freq", "actor_update_freq", "target_update_freq",
    ):
        if getattr(args, flag) < 1:
            raise ValueError(f"--{flag.replace('_', '-')} must be >= 1, got {getattr(args, flag)}")


# ALGO LOGIC: the agent's networks
def layer_init(layer: nn.Linear) -> nn.Linear:
    nn.init.orthogonal_(layer.weight)
    nn.init.zeros_(layer.bias)
    return layer


class SoftQNetwork(nn.Module):
    """Q(s, a): MLP on [obs, action]; its first Linear is the input layer."""

    def __init__(self, obs_dim: int, act_dim: int, hidden_dim: int):
        super().__init__()
        self.net = nn.Sequential(
            layer_init(nn.Linear(obs_dim + act_dim, hidden_dim)),
            nn.ReLU(),
            layer_init(nn.Linear(hidden_dim, hidden_dim)),
            nn.ReLU(),
            layer_init(nn.Linear(hidden_dim, 1)),
        )

    def forward(self, obs, actions):
        return self.net(torch.cat([obs, actions], 1)).squeeze(-1)


LOG_STD_MAX = 2
LOG_STD_MIN = -5


class Actor(nn.Module):
    """Tanh-squashed Gaussian policy; log-std squashed into [LOG_STD_MIN, LOG_STD_MAX]."""

    def __init__(self, obs_dim: int, act_dim: int, hidden_dim: int):
        super().__init__()
        self.net = nn.Sequential(
            layer_init(nn.Linear(obs_dim, hidden_dim)),
            nn.ReLU(),
            layer_init(nn.Linear(hidden_dim, hidden_dim)),
            nn.ReLU(),
            layer_init(nn.Linear(hidden_dim, 2 * act_dim)),
        )

    def forward(self, obs):
        mean, log_std = self.net(obs).chunk(2, dim=-1)
        log_std = LOG_STD_MIN + 0.5 * (LOG_STD_MAX - LOG_STD_MIN) * (torch.tanh(log_std) + 1)
        return mean, log_std

    def get_action(self, obs):
        """A sampled action, its log-probability, and the deterministic action tanh(mean)."""
        mean, log_std = self(obs)
        eps = torch.randn_like(mean)
        x = mean + log_std.exp() * eps
        # the Gaussian log-density written out: torch.distributions
        # validates its arguments, a host sync per call
        log_prob = -0.5 * eps.pow(2) - log_std - 0.5 * math.log(2 * math.pi)
        # log|d tanh(x)/dx|, numerically stable
        log_prob -= 2 * (math.log(2) - x - F.softplus(-2 * x))
        return torch.tanh(x), log_prob.sum(-1), torch.tanh(mean)


@torch.no_grad()
def evaluate(actor: Actor, envs: list, device: torch.device) -> np.ndarray:
    """One deterministic episode per env, stepped in
    lockstep (one batched forward); returns true returns."""
    obs = np.stack([env.reset()[0] for env in envs])
    returns, running = np.zeros(len(envs)), np.ones(len(envs), dtype=bool)
    while running.any():
        mean, _ = actor(torch.as_tensor(obs, device=device))
        torch.randn_like(mean)  # get_action's unused draw: keeps training's random stream
        actions = torch.tanh(mean).cpu().numpy()
        # MuJoCo would raise on them: a NaN return, which stops the run
        if not np.isfinite(actions).all():
            return np.full(len(envs), np.nan)
        stepping = np.flatnonzero(running)
        for i in stepping:  # all at once when they are processes (`--parallel-eval`)
            envs[i].step_async(actions[i])
        for i in stepping:
            obs[i], reward, terminated, truncated, _ = envs[i].step_wait()
            returns[i] += reward
            running[i] = not (terminated or truncated)
    return returns


# ALGO LOGIC: the replay buffer, on the device
def read_noisy(x: torch.Tensor, noise: Optional[ene.NoiseSampler]) -> torch.Tensor:
    """Stored rows as the networks read them: with
    `--noise-resample`, a copy with fresh noise columns."""
    return x if noise is None else noise.refresh_(x.clone())


class Batch(NamedTuple):
    obs: torch.Tensor
    actions: torch.Tensor
    rewards: torch.Tensor
    next_obs: torch.Tensor
    dones: torch.Tensor
    indices: torch.Tensor


class ReplayBuffer:
    """Preallocated circular buffer of transitions; rewards are the environment's."""

    def __init__(self, capacity: int, obs_dim: int, act_dim: int, device: torch.device, noise=None):
        self.obs = torch.zeros((capacity, obs_dim), device=device)
        self.next_obs = torch.zeros((capacity, obs_dim), device=device)
        self.actions = torch.zeros((capacity, act_dim), device=device)
        self.rewards = torch.zeros(capacity, device=device)
        # for diagnostics only: the agent never reads it
        self.true_rewards = torch.zeros(capacity, device=device)
        self.dones = torch.zeros(capacity, device=device)
        self.capacity, self.pos, self.size, self.noise = capacity, 0, 0, noise

    def add(self, obs, action, next_obs, terminated: bool, true_reward: float, reward):
        self.obs[self.pos], self.actions[self.pos], self.next_obs[self.pos] = obs, action, next_obs
        self.dones[self.pos], self.true_rewards[self.pos] = float(terminated), true_reward
        self.rewards[self.pos] = reward
        self.pos = (self.pos + 1) % self.capacity
        self.size = min(self.size + 1, self.capacity)

    def sample(self, batch_size: int) -> Batch:
        idx = torch.randint(0, self.size, (batch_size,), device=self.obs.device)
        obs = read_noisy(self.obs[idx], self.noise)
        next_obs = read_noisy(self.next_obs[idx], self.noise)
        return Batch(obs, self.actions[idx], self.rewards[idx], next_obs, self.dones[idx], idx)


# SPARSE LOGIC: input-layer masks, masked Adam steps, RigL topology updates, connectivity
def random_mask(shape: torch.Size, sparsity: float, device: torch.device) -> torch.Tensor:
    """0/1 mask with N - floor(sparsity * N) active per matrix (last two dims), drawn uniformly."""
    n = shape[-2] * shape[-1]
    scores = torch.rand(*shape[:-2], n, device=device)
    active = scores.topk(n - math.floor(sparsity * n), dim=-1).indices
    mask = torch.zeros_like(scores).scatter_(-1, active, 1.0)
    return mask.view(shape)


def top_k_random_ties(scores: torch.Tensor, k: int) -> torch.Tensor:
    """Indices of the k largest scores per row; equal scores are ordered at random."""
    shuffle = torch.rand_like(scores).argsort(-1)
    order = scores.gather(-1, shuffle).sort(dim=-1, descending=True, stable=True).indices[..., :k]
    return shuffle.gather(-1, order)


@torch.no_grad()
def rigl_update_(weight: torch.Tensor, mask: torch.Tensor, dense_grad: torch.Tensor,
                 drop_fraction: float, moments: list) -> None:
    """RigL, per matrix: drop the floor(d * n_active) active weights of smallest |w|. Grow as many
    where the dense gradient is largest among positions not kept (a just-dropped one may regrow).
    Grown weights and dropped or grown positions' Adam `moments` are zeroed; counts never change."""
    size = weight.shape[-2] * weight.shape[-1]
    w, m, g = weight.view(-1, size), mask.view(-1, size), dense_grad.view(-1, size)
    n_drop = math.floor(drop_fraction * int(m[0].sum()))
    if n_drop == 0:
        return
    drop = top_k_random_ties(torch.where(m.bool(), -w.abs(), -torch.inf), n_drop)
    kept = m.scatter(1, drop, 0.0)
    grow = top_k_random_ties(torch.where(kept.bool(), -torch.inf, g.abs()), n_drop)
    new_mask = kept.scatter(1, grow, 1.0)
    assert torch.equal(new_mask.sum(1), m.sum(1)), "a topology update changed the active count"
    w.mul_(kept)
    for moment in moments:
        moment.view(-1, size).mul_(kept)
    m.copy_(new_mask)


class SparseOptimizer:
    """Wraps an optimizer over sparse input layers (`layers`: name -> weight); sparsity 0 is dense.
    Each step masks the gradients (Adam moments stay 0 where the mask is 0, so masked weights stay
    exactly 0) and re-applies them. Every `period` steps: RigL with that step's dense gradient."""

    def __init__(self, optimizer: optim.Optimizer, layers: dict, sparsity: float,
                 drop_fraction: float, period: int):
        self.optimizer, self.layers, self.sparsity = optimizer, layers, sparsity
        self.drop_fraction, self.period, self.steps = drop_fraction, period, 0
        self.topology_updates = 0
        self.masks = {name: random_mask(weight.shape, sparsity, weight.device)
                      for name, weight in layers.items()}
        with torch.no_grad():
            for name, weight in layers.items():
                weight.mul_(self.masks[name])

    def zero_grad(self):
        self.optimizer.zero_grad()

    def step(self):
        if self.sparsity == 0:
            return self.optimizer.step()
        self.steps += 1
        update_topology = self.steps % self.period == 0
        self.topology_updates += update_topology
        dense_grads = ({name: weight.grad.clone() for name, weight in self.layers.items()}
                       if update_topology else {})
        for name, weight in self.layers.items():
            weight.grad.mul_(self.masks[name])
        self.optimizer.step()
        with torch.no_grad():
            for name, weight in self.layers.items():
                weight.mul_(self.masks[name])
        for name, grad in dense_grads.items():
            state = self.optimizer.state[self.layers[name]]
            rigl_update_(self.layers[name], self.masks[name], grad, self.drop_fraction,
                         [state["exp_avg"], state["exp_avg_sq"]])

    def named_matrices(self, tensors: dict):
        """(name, matrix) per sparse matrix; a stacked `reward` gives `reward0`, `reward1`, ..."""
        for name, tensor in tensors.items():
            yield from ([(f"{name}{i}", t) for i, t in enumerate(tensor)]
                        if tensor.dim() == 3 else [(name, tensor)])


@torch.no_grad()
def connectivity(weight: torch.Tensor, obs_dim_real: int, obs_dim: int) -> dict:
    """ANF's metric for an input layer (out, in) on [real obs | noise | action]: mean non-zero
    weights per relevant column (real features, actions) and per noise column; share of non-zero
    weights on relevant columns (chance: relevant / all columns)."""
    degree = (weight != 0).sum(0).float()
    column = torch.arange(weight.shape[1], device=weight.device)
    relevant = (column < obs_dim_real) | (column >= obs_dim)
    metrics = {"relevant_degree": degree[relevant].mean(),
               "relevant_active_frac": degree[relevant].sum() / degree.sum()}
    if (~relevant).any():
        metrics["noise_degree"] = degree[~relevant].mean()
    return metrics


# ALGO LOGIC: the agent, and the steps of training
# (top-level functions: what a captured GPU step replays)
@dataclass
class Agent:
    """SAC's networks, temperature and optimisers.
    The critic fields are replaced when PEBBLE resets the critic."""
    actor: Actor
    actor_optimizer: optim.Optimizer
    qf1: SoftQNetwork
    qf2: SoftQNetwork
    q_optimizer: optim.Optimizer
    qf1_target: SoftQNetwork
    qf2_target: SoftQNetwork
    log_alpha: torch.Tensor
    alpha: torch.Tensor  # exp(log_alpha), detached and updated in place
    a_optimizer: optim.Optimizer
    target_entropy: float


def make_critic(obs_dim: int, act_dim: int, args: Args, device: torch.device) -> tuple:
    """Fresh Q1, Q2, their optimiser and targets (PEBBLE
    resets the critic at the first feedback round)."""
    qf1 = SoftQNetwork(obs_dim, act_dim, args.hidden_dim).to(device)
    qf2 = SoftQNetwork(obs_dim, act_dim, args.hidden_dim).to(device)
    # foreach: the multi-tensor Adam, bitwise the CPU's default single-tensor one and faster
    q_optimizer = optim.Adam(
        list(qf1.parameters()) + list(qf2.parameters()), lr=args.q_lr, foreach=True
    )
    q_optimizer = SparseOptimizer(q_optimizer, {"qf1": qf1.net[0].weight, "qf2": qf2.net[0].weight},
                                  args.agent_sparsity, args.agent_drop_fraction,
                                  args.agent_topology_period)
    qf1_target = SoftQNetwork(obs_dim, act_dim, args.hidden_dim).to(device)
    qf2_target = SoftQNetwork(obs_dim, act_dim, args.hidden_dim).to(device)
    qf1_target.load_state_dict(qf1.state_dict())
    qf2_target.load_state_dict(qf2.state_dict())
    return qf1, qf2, q_optimizer, qf1_target, qf2_target


def make_agent(obs_dim: int, act_dim: int, args: Args, device: torch.device) -> Agent:
    actor = Actor(obs_dim, act_dim, args.hidden_dim).to(device)
    actor_optimizer = optim.Adam(actor.parameters(), lr=args.policy_lr, foreach=True)
    actor_optimizer = SparseOptimizer(actor_optimizer, {"actor": actor.net[0].weight},
                                      args.agent_sparsity,
                                      args.agent_drop_fraction, args.agent_topology_period)
    qf1, qf2, q_optimizer, qf1_target, qf2_target = make_critic(obs_dim, act_dim, args, device)
    log_alpha = torch.tensor(math.log(args.init_temperature), device=device, requires_grad=True)
    a_optimizer = optim.Adam([log_alpha], lr=args.alpha_lr)
    return Agent(actor, actor_optimizer, qf1, qf2, q_optimizer, qf1_target, qf2_target, log_alpha,
                 log_alpha.detach().exp(), a_optimizer, target_entropy=-float(act_dim))


def critic_gradients(agent: Agent, data: Batch, gamma: float) -> dict:
    """The gradients (`.grad`) of both critics' losses towards the soft Bellman target.
    Returns the losses, on the device."""
    with torch.no_grad():
        next_actions, next_log_pi, _ = agent.actor.get_action(data.next_obs)
        qf1_next_target = agent.qf1_target(data.next_obs, next_actions)
        qf2_next_target = agent.qf2_target(data.next_obs, next_actions)
        next_q = torch.min(qf1_next_target, qf2_next_target)
        target_q = data.rewards + (1 - data.dones) * gamma * (next_q - agent.alpha * next_log_pi)
    qf1_values = agent.qf1(data.obs, data.actions)
    qf2_values = agent.qf2(data.obs, data.actions)
    qf1_loss = F.mse_loss(qf1_values, target_q)
    qf2_loss = F.mse_loss(qf2_values, target_q)
    agent.q_optimizer.zero_grad()
    (qf1_loss + qf2_loss).backward()
    return dict(
        qf1_values=qf1_values.mean().detach(),
        qf2_values=qf2_values.mean().detach(),
        qf1_loss=qf1_loss.detach(),
        qf2_loss=qf2_loss.detach(),
        qf_loss=(qf1_loss + qf2_loss).detach() / 2,
    )


def actor_gradients(agent: Agent, data: Batch) -> dict:
    """The gradients of the actor's loss, and of the temperature's towards the target entropy.
    Returns the losses."""
    pi, log_pi, _ = agent.actor.get_action(data.obs)
    qf1_pi = agent.qf1(data.obs, pi)
    qf2_pi = agent.qf2(data.obs, pi)
    min_qf_pi = torch.min(qf1_pi, qf2_pi)
    actor_loss = (agent.alpha * log_pi - min_qf_pi).mean()
    agent.actor_optimizer.zero_grad()
    # The actor's gradients alone: the critics' weight gradients would be discarded.
    actor_loss.backward(inputs=list(agent.actor.parameters()))
    alpha_loss = (-agent.log_alpha.exp() * (log_pi.detach() + agent.target_entropy)).mean()
    agent.a_optimizer.zero_grad()
    alpha_loss.backward()
    return dict(actor_loss=actor_loss.detach(), alpha_loss=alpha_loss.detach())


@torch.no_grad()
def target_update(agent: Agent, tau: float):
    """Polyak averaging of the target critics. A pruned connection's target weight decays by
    1 - tau per update into the subnormal floats, where rounding keeps it, and a CPU matmul over
    subnormals is a hundred times slower. Such weights are set to zero: no sum they join changes."""
    online = list(agent.qf1.parameters()) + list(agent.qf2.parameters())
    targets = list(agent.qf1_target.parameters()) + list(agent.qf2_target.parameters())
    torch._foreach_lerp_(targets, online, tau)
    for target in targets:
        target.masked_fill_(target.abs() < torch.finfo(target.dtype).tiny, 0.0)


@dataclass
class Loop:
    """The main loop's own variables, saved in `state.pt` with the objects."""
    sac_updates: int = 0
    episode_return: float = 0.0
    episode_length: int = 0
    # resume only: the env's RNG state at the episode's start (None: the seeded first
    # reset), and the episode's actions so far, to replay the episode on a resume
    episode_start: Optional[dict] = None
    episode_actions: list = field(default_factory=list)
    # the latest losses, on the device: read every `log_freq` steps
    losses: dict = field(default_factory=dict)
    # the last evaluation's tags: logged again after a resume's purge
    last_eval: dict = field(default_factory=dict)


@torch.no_grad()
def act(actor: Actor, obs: torch.Tensor) -> torch.Tensor:
    """The policy's sampled action for one observation."""
    mean, log_std = actor(obs.unsqueeze(0))
    # get_action's draw, without the log-probability that acting never uses
    return torch.tanh(mean + log_std.exp() * torch.randn_like(mean))[0]


@torch.no_grad()
def store(
    rb: ReplayBuffer, obs, action, next_obs, terminated: bool, true_reward: float,
):
    """Write one step into the run's storage, with the reward the agent learns from."""
    rb.add(obs, action, next_obs, terminated, true_reward,
           true_reward)  # an oracle learns from the true reward itself


def sac_update(agent: Agent, data: Batch, loop: Loop, args: Args):
    """One SAC update: critics, then (every `actor_update_freq`) actor and temperature, then (every
    `target_update_freq`) the targets. The losses stay on the device, in `loop.losses`.

    `--compile` and `--cuda-graph` replace the three step functions it calls (`critic_gradients`,
    `actor_gradients`, `target_update`) with compiled or captured versions of themselves.
    The optimiser steps always run eagerly."""
    loop.losses.update(critic_gradients(agent, data, args.gamma))
    agent.q_optimizer.step()
    loop.sac_updates += 1
    if loop.sac_updates % args.actor_update_freq == 0:
        losses = actor_gradients(agent, data)
        agent.actor_optimizer.step()
        agent.a_optimizer.step()
        agent.alpha.copy_(agent.log_alpha.detach().exp())
        loop.losses.update(
            actor_loss=losses["actor_loss"],
            alpha=agent.alpha.clone(),
            alpha_loss=losses["alpha_loss"],
        )
    if loop.sac_updates % args.target_update_freq == 0:
        target_update(agent, args.tau)


def save_checkpoint(path: str, args: Args, global_step: int, saved: dict, dims: tuple):
    """The trained networks of the `saved` objects, for
    evaluation and debugging (`state.pt` resumes a run)."""
    agent = saved["agent"]
    checkpoint = {
        "args": vars(args), "global_step": global_step + 1, "actor": agent.actor.state_dict(),
        "qf1": agent.qf1.state_dict(), "qf2": agent.qf2.state_dict(),
        "log_alpha": agent.log_alpha.detach().cpu(),
        **dict(zip(("obs_dim_real", "obs_dim", "act_dim"), dims)),
        "masks": {name: mask.cpu() for opt in (agent.actor_optimizer, agent.q_optimizer)
                  for name, mask in opt.named_matrices(opt.masks)},
    }
    torch.save(checkpoint, path)


# RUN PLUMBING: the run folder, progress, `state.pt` (exact resume), the NaN stop;
# in the PbRL scripts, the query log, the label files and the reward diagnostics.
# The same in every script (sac.py, anf_sac.py: a subset); tested.
def harness(module: str):
    """A module of the run harness's package `r2n_harness`, imported only for the flag that needs it
    (`validate_args` has checked that the package is there)."""
    return importlib.import_module(f"r2n_harness.{module}")


def make_run_folder(env_id: str, exp_name: str, seed: int) -> str:
    """Create `runs/{env_id}__{exp_name}__{seed}__{unix_time}` and return its name.
    If a run that started in the same second took that folder (runs of a sweep
    differ in noise or budget, which the name does not show), try the next."""
    unix_time = int(time.time())
    while True:
        run_name = f"{env_id}__{exp_name}__{seed}__{unix_time}"
        try:
            # atomic: exactly one of two racing runs gets the folder
            os.makedirs(f"runs/{run_name}")
            return run_name
        except FileExistsError:
            unix_time += 1



class Progress:
    """A console line at every phase change and at most every `interval` seconds of
    training: step / total, phase, SPS since the last line, ETA at that rate, feedback
    used and the latest evaluation return. Its clock is the run's training time
    (`seconds`, waits for labels excluded), and it reads host values only, so it adds no
    host sync to the training loop. With `on_step`, it also calls `on_step(step, seconds)`
    at every step: the labelling page's status of a run that a person labels."""

    def __init__(
        self, total_steps: int, budget: Optional[int] = None, interval: float = 30.0, on_step=None
    ):
        self.total_steps = total_steps
        self.budget = budget
        self.interval = interval
        self.on_step = on_step
        self.phase, self.time, self.step, self.eval_return = None, 0.0, 0, None

    def update(self, step: int, phase: str, seconds: float, feedback: Optional[int] = None):
        if self.on_step is not None:
            self.on_step(step, seconds)
        now = seconds
        if phase == self.phase and now - self.time < self.interval:
            return
        moved = step > self.step and now > self.time
        sps = (step - self.step) / (now - self.time) if moved else 0.0
        percent = 100 * step / self.total_steps
        line = f"progress: step {step}/{self.total_steps} ({percent:.0f}%) | {phase} | "
        eta = self.duration((self.total_steps - step) / sps) if sps else "?"
        line += f"{sps:.0f} SPS | ETA {eta}"
        if self.budget is not None:
            line += f" | feedback {feedback}/{self.budget}"
        line += " | eval return " + ("-" if self.eval_return is None else f"{self.eval_return:.1f}")
        print(line, flush=True)
        self.phase, self.time, self.step = phase, now, step

    @staticmethod
    def duration(seconds: float) -> str:
        minutes, hours = int(seconds) // 60 % 60, int(seconds) // 3600
        return (
            f"{hours // 24}d{hours % 24:02d}h" if hours >= 24
            else f"{hours}h{minutes:02d}m" if hours
            else f"{minutes}m"
        )


# the training state `state.pt`, for exact resume (docs/running.md: "Resuming a run")
# the flags a resume may change, and no others: none of them touches training
RESUMABLE_FLAGS = (
    "threads", "cuda", "track", "wandb_project_name", "wandb_entity", "capture_video", "save_model",
    "log_freq", "state_minutes", "checkpoint_freq", "keep_state", "parallel_eval",
)


def open_run(args) -> tuple:
    """The run folder, and the saved state when `--run-name`
    names a folder holding a `state.pt` (else None)."""
    if args.run_name is None:
        return make_run_folder(args.env_id, args.exp_name, args.seed), None
    path = f"runs/{args.run_name}/state.pt"
    if not os.path.exists(path):
        if os.path.exists(f"runs/{args.run_name}"):
            raise ValueError(
                f"--run-name {args.run_name}: runs/{args.run_name} holds no state.pt to resume "
                "(the run finished, or stopped before its first state); "
                "choose another name or move the folder"
            )
        os.makedirs(f"runs/{args.run_name}")
        return args.run_name, None
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
    # a flag added since: its default
    saved = {**{field.name: field.default for field in fields(args)}, **state["args"]}
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
    return args.run_name, state


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



def open_writer(args, run_name: str, resume: Optional[dict]) -> SummaryWriter:
    """The run's TensorBoard writer (and W&B with `--track`). A resumed run hides the
    points the interrupted one logged after its state (TensorBoard's purge_step)."""
    if args.track:
        import wandb

        wandb.init(
            project=args.wandb_project_name,
            entity=args.wandb_entity,
            sync_tensorboard=True,
            config=vars(args),
            name=run_name,
            id=run_name,
            resume="allow",
            monitor_gym=True,
            save_code=True,
        )
    writer = SummaryWriter(f"runs/{run_name}", purge_step=resume["global_step"] if resume else None)
    if resume is None:
        table = "\n".join([f"|{key}|{value}|" for key, value in vars(args).items()])
        writer.add_text("hyperparameters", f"|param|value|\n|-|-|\n{table}")
    return writer


def catch_stop_signals() -> list:
    """SIGTERM and SIGUSR2 (SLURM, submitit: preemption, time limit) are noted in the
    returned list; the loop then saves the state at the end of its step and exits."""
    stop_signals = []
    for signum in (signal.SIGTERM, signal.SIGUSR2):
        signal.signal(
            signum, lambda signum, frame: stop_signals.append(signal.Signals(signum).name)
        )
    return stop_signals


class Stopped(Exception):
    """SIGTERM or SIGUSR2: the state is saved; the run exits
    with exit code 1 and one line saying how to resume."""


class NonFinite(Exception):
    """A non-finite value: the run writes its checkpoint
    and stops with exit code 1 and one line naming it."""


def check_finite(values: dict, step: int):
    bad = next((name for name, value in values.items() if not math.isfinite(value)), None)
    if bad is not None:
        raise NonFinite(f"non-finite {bad} ({values[bad]}) at step {step}")


def log_evaluation(writer: SummaryWriter, global_step: int, eval_return: float, eval_seconds: float,
                   sps: int, shares: dict, loop, progress: Progress, counts: str = ""):
    """An evaluation's tags (kept in `loop.last_eval`, logged again after a resume's purge), its
    console line (`counts`: the PbRL scripts' feedback) and the NaN stop."""
    loop.last_eval = {"eval/episodic_return": eval_return, "charts/SPS": sps} | shares
    for tag, value in loop.last_eval.items():
        writer.add_scalar(tag, value, global_step + 1)
    print(f"step={global_step + 1} eval_return={eval_return:.2f} SPS={sps} "
          f"eval_seconds={eval_seconds:.2f}{counts}", flush=True)
    progress.eval_return = eval_return
    check_finite({"eval/episodic_return": eval_return}, global_step)


def log_losses(writer: SummaryWriter, global_step: int, losses: dict):
    """The latest losses (`losses/`), read from the device in one sync, and the NaN stop."""
    logged = dict(zip([f"losses/{name}" for name in losses],
                      torch.stack(list(losses.values())).tolist()))
    for tag, value in logged.items():
        writer.add_scalar(tag, value, global_step)
    check_finite(logged, global_step)


def save_state(path: str, args, global_step: int, elapsed: float, obs: torch.Tensor, saved: dict,
               device: torch.device, envs: list, writer: SummaryWriter):
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


def restore_run(
    resume: Optional[dict], saved: dict, envs: list, args, device: torch.device,
    writer: SummaryWriter, progress: Progress, state_path: str,
) -> tuple:
    """Start, or continue from the saved state: restore the `saved` objects, replay the
    running episode on `envs[0]` to where the saved run was, then restore the generators.
    Returns (observation, first step, seconds trained)."""
    loop = saved["loop"]
    if resume is not None:
        for name, obj in saved.items():
            load_state_(obj, resume["objects"][name])
        loop.losses = {name: value.to(device) for name, value in loop.losses.items()}
    obs = ene.replay_episode(envs[0], args.seed, loop.episode_start, loop.episode_actions)
    if resume is None:
        return obs, 0, 0.0
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
    progress.step = resume["global_step"]
    progress.time = resume["elapsed"]
    # the purge hid the step's evaluation
    if start_step % args.eval_freq == 0 or start_step == args.total_timesteps:
        for tag, value in loop.last_eval.items():
            writer.add_scalar(tag, value, start_step)
    progress.eval_return = loop.last_eval.get("eval/episodic_return")
    print(f"resuming {state_path} at step {start_step}", flush=True)
    return obs, start_step, resume["elapsed"]

def input_layers(agent) -> dict:
    """The input layers of the actor and of both critics, by the names the logs use."""
    return {name: getattr(agent, name).net[0].weight for name in ("actor", "qf1", "qf2")}


@torch.no_grad()
def relevant_weight_frac(weight: torch.Tensor, obs_dim_real: int, obs_dim: int) -> tuple:
    """The share of an input layer's absolute weight on relevant columns, and its chance level.

    The layer is (out, in) on [real obs | noise | action]. Relevant columns are the real features
    and the actions, as in `relevant_active_frac`. Chance is the relevant columns' share of all
    columns. A zero weight adds nothing, so a sparse layer counts its active weights only."""
    column = torch.arange(weight.shape[-1], device=weight.device)
    relevant = (column < obs_dim_real) | (column >= obs_dim)
    magnitude = weight.abs().sum(0)
    return magnitude[relevant].sum() / magnitude.sum(), relevant.float().mean()


def weight_shares(layers: dict, obs_dim_real: int, obs_dim: int) -> dict:
    """The tags `features/{net}/relevant_weight_frac` and
    `features/{net}/chance` of each layer, as floats.

    It reads the weights only, so a run's numbers are the same with or without it.
    One host sync per call."""
    values = {}
    for name, weight in layers.items():
        frac, chance = relevant_weight_frac(weight, obs_dim_real, obs_dim)
        values[f"features/{name}/relevant_weight_frac"] = frac
        values[f"features/{name}/chance"] = chance
    return dict(zip(values, torch.stack(list(values.values())).tolist()))


if __name__ == "__main__":
    args = tyro.cli(Args)
    try:  # bad input fails here, with one line, before any output is written
        validate_args(args)
        env = ene.make_env(args.env_id, args.seed, args.noise, args.noise_type,
                           args.noise_histograms, args.episode_length)
        run_name, resume = open_run(args)  # resume: the saved state of an interrupted run, or None
    except ValueError as e:
        raise SystemExit(f"{args.exp_name}: error: {e}")
    run_folder, state_path = f"runs/{run_name}", f"runs/{run_name}/state.pt"
    checkpoint_path = f"{run_folder}/{args.exp_name}.cleanrl_model"
    video_folder = f"videos/{run_name}" + (f"/resumed-at-{resume['global_step']}" if resume else "")
    eval_envs = [
        (ene.EnvProcess if args.parallel_eval else ene.make_env)(
            args.env_id, args.seed + 1000 * (i + 1), args.noise, args.noise_type,
            args.noise_histograms, args.episode_length,
            video_folder if args.capture_video and i == 0 else None,
        )
        for i in range(args.eval_episodes)
    ]
    for i, eval_env in enumerate(eval_envs):
        eval_env.reset(seed=args.seed + 1000 * (i + 1))
    writer = open_writer(args, run_name, resume)

    # TRY NOT TO MODIFY: seeding
    random.seed(args.seed)
    np.random.seed(args.seed)
    torch.manual_seed(args.seed)
    torch.backends.cudnn.deterministic = args.torch_deterministic
    torch.backends.cuda.matmul.allow_tf32 = args.tf32  # False is torch's default: FP32 matmuls
    steps = critic_gradients, actor_gradients, target_update  # `sac_update` calls them by name:
    if args.compile:  # compiled from here on,
        critic_gradients, actor_gradients, target_update = steps = tuple(map(torch.compile, steps))
    if args.cuda_graph:  # and replayed as CUDA graphs (of the compiled ones with `--compile`)
        torch.cuda.set_stream(torch.cuda.Stream())  # on a stream of its own, as a capture needs
        critic_gradients, actor_gradients, target_update = map(harness("cuda_graph").CudaGraph,
                                                               steps)

    device = torch.device("cuda" if torch.cuda.is_available() and args.cuda else "cpu")
    if args.threads is not None or device.type == "cpu":  # default threads oversubscribe cores
        torch.set_num_threads(args.threads or 1)

    obs_dim_real = env.obs_dim_real
    obs_dim = env.observation_space.shape[0]
    act_dim = env.action_space.shape[0]
    dims = obs_dim_real, obs_dim, act_dim  # recorded in each checkpoint
    noise = env.noise_sampler if args.noise_resample else None

    # ALGO LOGIC: the agent, and what it learns from
    agent = make_agent(obs_dim, act_dim, args, device)
    rb = ReplayBuffer(args.buffer_size, obs_dim, act_dim, device, noise)
    loop = Loop()
    # everything the loop changes, by name: `state.pt` saves and restores exactly these
    saved = dict(agent=agent, rb=rb, loop=loop)

    # TRY NOT TO MODIFY: start the game, or continue it from the saved state
    stop_signals = catch_stop_signals()
    progress = Progress(args.total_timesteps)
    obs, start_step, elapsed = restore_run(resume, saved, [env, *eval_envs], args, device, writer,
                                           progress, state_path)
    del resume
    start_time = time.time() - elapsed  # SPS counts the time spent training only
    obs = torch.as_tensor(obs, device=device)
    last_state = time.monotonic()  # the clock of `--state-minutes`
    try:
        for global_step in range(start_step, args.total_timesteps):
            phase = "random" if global_step < args.learning_starts else "SAC"
            progress.update(global_step, phase, time.time() - start_time)
            # ALGO LOGIC: put action logic here
            if global_step < args.learning_starts:
                action = env.action_space.sample()
                action = torch.as_tensor(action, dtype=torch.float32, device=device)
            else:
                action = act(agent.actor, obs)

            # TRY NOT TO MODIFY: execute the game and log data.
            env_action = action.cpu().numpy()
            check_finite({"action": float(env_action.sum())}, global_step)  # on the host: no sync
            next_obs, true_reward, terminated, truncated, _ = env.step(env_action)
            loop.episode_actions.append(env_action)
            next_obs = torch.as_tensor(next_obs, device=device)
            store(
                rb, obs, action, next_obs, terminated, float(true_reward),
            )
            loop.episode_return += float(true_reward)
            loop.episode_length += 1
            obs = next_obs  # CRUCIAL step easy to overlook
            if terminated or truncated:
                writer.add_scalar("charts/episodic_return", loop.episode_return, global_step)
                writer.add_scalar("charts/episodic_length", loop.episode_length, global_step)
                loop.episode_start, loop.episode_actions = env.rng_state(), []
                obs, _ = env.reset()
                obs = torch.as_tensor(obs, device=device)
                loop.episode_return, loop.episode_length = 0.0, 0

            # ALGO LOGIC: training.
            if global_step >= args.learning_starts:
                sac_update(agent, rb.sample(args.batch_size), loop, args)

                if global_step % args.log_freq == 0:
                    log_losses(writer, global_step, loop.losses)

            if (global_step + 1) % args.eval_freq == 0 or global_step + 1 == args.total_timesteps:
                eval_start = time.time()
                eval_return = float(evaluate(agent.actor, eval_envs, device).mean())
                eval_seconds = time.time() - eval_start
                sps = int((global_step + 1) / (time.time() - start_time))
                shares = weight_shares(input_layers(agent), obs_dim_real, obs_dim)
                for opt in (agent.actor_optimizer, agent.q_optimizer):
                    for name, weight in opt.named_matrices(opt.layers):
                        for tag, value in connectivity(weight, obs_dim_real, obs_dim).items():
                            writer.add_scalar(f"sparse/{name}/{tag}", value.item(), global_step + 1)
                        writer.add_scalar(f"sparse/{name}/topology_updates", opt.topology_updates,
                                          global_step + 1)
                log_evaluation(writer, global_step, eval_return, eval_seconds, sps, shares, loop,
                               progress)
                if args.save_model:
                    save_checkpoint(checkpoint_path, args, global_step, saved, dims)

            if stop_signals or state_due(global_step, args, last_state):
                save_state(state_path, args, global_step, time.time() - start_time, obs, saved,
                           device, [env, *eval_envs], writer)
                last_state = time.monotonic()
                if stop_signals:
                    raise Stopped(f"stopped by {stop_signals[0]} after step {global_step + 1}; "
                                  f"state saved in {state_path}: run the same command with "
                                  f"--run-name {run_name} to resume")
    except (Stopped, NonFinite) as e:
        if isinstance(e, NonFinite):  # the checkpoint is written first, for debugging
            save_checkpoint(checkpoint_path, args, global_step, saved, dims)
            e = f"error: {e}; checkpoint for debugging: {checkpoint_path}"
        writer.close()
        raise SystemExit(f"{args.exp_name}: {e}")

    for each in (env, *eval_envs):
        each.close()
    writer.close()
    # last: a kill before this leaves a state to resume
    if not args.keep_state and os.path.exists(state_path):
        # the run is complete: what it leaves is the event file and the checkpoint
        os.remove(state_path)
