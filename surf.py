# Docs: docs/NAME.md in r2n, the R2N paper's reference implementation (NAME: this file's name)
"""A baseline of the R2N paper in an Extremely Noisy Environment: the PbRL method below, no R2N.
R2N paper: Muslimani et al., "Boosting Robustness in Preference-Based Reinforcement Learning with
Dynamic Sparsity", AAMAS 2025 (the authors' code: https://github.com/cmuslima/R2N).
PEBBLE (docs/pebble.md): Lee, Smith & Abbeel, "PEBBLE: Feedback-Efficient Interactive Reinforcement
Learning via Relabeling Experience and Unsupervised Pre-training", ICML 2021, with the R2N paper's
defaults: SAC pre-trained on a state-entropy reward, then a feedback round every `feedback_freq`
steps (labels, the reward ensemble trained on all of them, the replay buffer relabelled).
SURF (docs/surf.md): Park et al., "SURF: Semi-supervised Reward Learning with Data Augmentation
for Feedback-efficient Preference-based RL", ICLR 2022: `diff pebble.py surf.py` is SURF.
Choices where the paper is silent, and each step in detail: the docs page.
"""
import importlib.util  # also binds importlib
import math
import os
import random
import time
from collections import deque
from dataclasses import dataclass, field
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
    """the task: dm_control (cheetah-run), gymnasium MuJoCo (Hopper-v5), Meta-World (reach-v3)"""
    noise: float = 0.9
    """fraction of all observation features that are noise, in [0, 1)"""
    noise_type: Literal["gaussian", "imitate"] = "gaussian"
    """noise features: i.i.d. N(0, 1), or imitating the real features' histograms"""
    noise_resample: bool = False
    """redraw stored observations' noise at each read (ANF's code); off: as stored (B-Pref's)"""
    noise_histograms: Optional[str] = None
    """the `.npz` of real-feature histograms (`bin_edges`, `probs`) for `--noise-type imitate`"""
    episode_length: Optional[int] = None
    """steps per episode, truncated, never terminated; unset: Meta-World 500, else 1000"""

    # Algorithm specific arguments. An unset SAC setting is its suite's (`ene.SUITE_SETTINGS`):
    # the paper's on dm_control (DMC), B-Pref's on Meta-World, CleanRL's on gym.
    total_timesteps: int = 1_000_000
    """total environment steps"""
    buffer_size: int = 1_000_000
    """the replay memory buffer size"""
    gamma: float = 0.99
    """the discount factor gamma"""
    tau: float = 0.005
    """target smoothing coefficient"""
    batch_size: Optional[int] = None
    """the batch size of SAC updates; unset: DMC 1024, Meta-World 512, gym 256"""
    hidden_dim: Optional[int] = None
    """width of the hidden layers of actor and critics; unset: DMC 1024, Meta-World 256, gym 256"""
    hidden_layers: Optional[int] = None
    """hidden layers of actor and critics; unset: DMC 2, Meta-World 3, gym 2"""
    learning_starts: int = 1000
    """steps of uniform random actions before learning starts"""
    policy_lr: Optional[float] = None
    """the learning rate of the policy; unset: DMC 1e-4, Meta-World 3e-4, gym 3e-4"""
    q_lr: Optional[float] = None
    """the learning rate of the Q networks; unset: DMC 1e-4, Meta-World 3e-4, gym 1e-3"""
    alpha_lr: Optional[float] = None
    """the temperature's learning rate, 0: fixed; unset: DMC 1e-4, Meta-World 1e-4, gym 1e-3"""
    init_temperature: Optional[float] = None
    """initial temperature (target entropy -|A|); unset: DMC 0.1, Meta-World 0.1, gym 1"""
    weight_decay: float = 0.0
    """coupled L2 in the actor's and critics' Adam (ANF's on gym: 2e-4)"""
    actor_update_freq: int = 1
    """actor and temperature update every this many SAC updates"""
    target_update_freq: Optional[int] = None
    """target critics update every this many SAC updates; unset: DMC 2, Meta-World 2, gym 1"""
    reset_updates: int = 100
    """SAC updates right after the critic reset of the first feedback round"""
    unsup_steps: int = 9000
    """steps of unsupervised pre-training on the state-entropy reward"""
    knn_k: int = 5
    """k of the k-th nearest neighbour in the state-entropy reward"""
    max_feedback: int = 1000
    """total preference queries (the feedback budget)"""
    queries_per_round: Optional[int] = None
    """queries per feedback round (unset: max(1, max_feedback // 100), computed at runtime)"""
    feedback_freq: int = 5000
    """environment steps between feedback rounds"""
    segment_size: int = 50
    """length of the segments the teacher compares"""
    segment_episodes: int = 100
    """segments are drawn from the last this many complete episodes"""
    query_sampling: Literal["uniform", "disagreement", "entropy"] = "uniform"
    """how queries are chosen after the first (always uniform) round"""
    query_pool_multiplier: int = 10
    """disagreement/entropy sampling scores this many times more candidate pairs than it asks"""
    ensemble_size: int = 3
    """number of reward models"""
    reward_lr: float = 3e-3
    """the learning rate of the reward ensemble (one Adam over all members)"""
    reward_hidden_dim: int = 128
    """width of the reward models' hidden layers"""
    reward_layers: int = 4
    """number of hidden layers of each reward model"""
    reward_batch_size: int = 128
    """labelled pairs per reward-model minibatch"""
    reward_epochs: int = 50
    """epochs over all labels per round, as SURF's fixed step count ceil(epochs * labels / batch)"""
    relabel_batch_size: int = 16384
    """transitions per reward-ensemble forward pass when relabelling the replay buffer"""
    teacher_beta: float = -1.0
    """rationality: if > 0, Bernoulli(sigmoid(beta * return gap)) labels, else deterministic"""
    teacher_gamma: float = 1.0
    """teacher myopia: step h of H is weighted by gamma^(H-h)"""
    teacher_eps_mistake: float = 0.0
    """probability that the teacher flips a label"""
    teacher_eps_skip: float = 0.0
    """the teacher skips pairs where neither segment's return exceeds eps_skip * margin"""
    teacher_eps_equal: float = 0.0
    """the teacher labels a pair equal (0.5) if its returns differ by < eps_equal * margin"""
    surf_crop: int = 5
    """SURF: steps stored on each side of the teacher's segment; crops are segment_size +- this"""
    surf_unlabeled_ratio: int = 10
    """SURF: unlabelled pairs stored per query asked (uniform, never shown to the teacher)"""
    surf_tau: float = 0.99
    """SURF: a pseudo-label is kept where the member's preference probability is at least tau"""
    surf_lambda: float = 1.0
    """SURF: weight of the unlabelled (pseudo-label) loss"""
    surf_mu: int = 1
    """SURF: unlabelled pairs per reward step = surf_mu * reward_batch_size"""
    eval_freq: int = 5000
    """evaluate every this many environment steps (and at the end)"""
    eval_episodes: int = 10
    """deterministic evaluation episodes, true reward"""

    # Run settings: output, state and logging; only --compile and --tf32 change the numerics.
    # --teacher and --preferences say where the labels come from.
    exp_name: str = os.path.basename(__file__)[: -len(".py")]
    """the name of this experiment (run folder and checkpoint name)"""
    torch_deterministic: bool = True
    """if toggled, `torch.backends.cudnn.deterministic=True`"""
    cuda: bool = True
    """if toggled, cuda will be used when available"""
    compile: bool = False
    """torch.compile the SAC steps: faster on a GPU, numerics within float tolerance of eager"""
    tf32: bool = False
    """TF32 matmuls on a CUDA GPU (10-bit mantissas on tensor cores): faster, other numerics"""
    cuda_graph: bool = False
    """replay the SAC steps' gradients as CUDA graphs (GPU only): faster, eager's numbers"""
    cuda_graph_whole: bool = False
    """with --cuda-graph: the whole SAC update as one graph, Adam inside (not yet run on a GPU)"""
    parallel_eval: bool = False
    """step the evaluation envs at once, each in its own process: the same returns"""
    track: bool = False
    """if toggled, this experiment will be tracked with Weights and Biases"""
    wandb_project_name: str = "r2n"
    """the wandb's project name"""
    wandb_entity: Optional[str] = None
    """the entity (team) of wandb's project"""
    capture_video: bool = False
    """capture videos of the first evaluation env in `videos/{run_name}` (the `video` extra)"""
    save_model: bool = True
    """save the checkpoint `runs/{run_name}/{exp_name}.cleanrl_model` at every evaluation"""
    threads: Optional[int] = None
    """torch intra-op threads. Unset: 1 on CPU (runs share a machine), torch's default on GPU."""
    log_freq: int = 1000
    """log the SAC losses every this many steps (a host sync: docs/running.md)"""
    run_name: Optional[str] = None
    """the run folder `runs/{run_name}` (unset: `{env_id}__{exp_name}__{seed}__{time}`).
    With `--resumable`, a folder holding a `state.pt` is resumed."""
    resumable: bool = False
    """write `runs/{run_name}/state.pt` every `--state-minutes` and on SIGTERM: an exact resume"""
    state_minutes: float = 10.0
    """write `state.pt` every this many wall-time minutes (a 1024-wide state is about 1 GB)"""
    checkpoint_freq: Optional[int] = None
    """write `state.pt` every this many steps instead of by wall time (tests, exact comparisons)"""
    keep_state: bool = False
    """keep `state.pt` when the run ends (by default it is deleted then: the run needs no resume)"""
    query_log: bool = False
    """write every query asked, with its label, to `runs/{run_name}/preferences/`"""
    diagnostics: bool = False
    """log diagnostics: the input layers' weight on real features; PbRL: the reward's fit"""
    teacher: Literal["simulated", "external"] = "simulated"
    """B-Pref's simulated teacher, or a person via files (turns on --resumable, --query-log)"""
    preferences: Optional[str] = None
    """an earlier run's `preferences/` (or one `.npz`): its labels come first, in the budget"""


# ALGO LOGIC: the agent's networks
def mlp(in_dim: int, hidden_dim: int, hidden_layers: int, out_dim: int) -> nn.Sequential:
    """Linear layers and ReLUs, orthogonal weights, zero biases; net[0] is the input layer."""
    dims, layers = [in_dim] + [hidden_dim] * hidden_layers + [out_dim], []
    for fan_in, fan_out in zip(dims[:-1], dims[1:]):
        layers += [nn.Linear(fan_in, fan_out), nn.ReLU()]
        nn.init.orthogonal_(layers[-2].weight)
        nn.init.zeros_(layers[-2].bias)
    return nn.Sequential(*layers[:-1])  # no ReLU after the output layer


class SoftQNetwork(nn.Module):
    """Q(s, a): MLP on [obs, action]; its first Linear is the input layer."""

    def __init__(self, obs_dim: int, act_dim: int, hidden_dim: int, hidden_layers: int = 2):
        super().__init__()
        self.net = mlp(obs_dim + act_dim, hidden_dim, hidden_layers, 1)

    def forward(self, obs, actions):
        return self.net(torch.cat([obs, actions], 1)).squeeze(-1)


LOG_STD_MAX = 2
LOG_STD_MIN = -5


class Actor(nn.Module):
    """Tanh-squashed Gaussian policy; log-std squashed into [LOG_STD_MIN, LOG_STD_MAX]."""

    def __init__(self, obs_dim: int, act_dim: int, hidden_dim: int, hidden_layers: int = 2):
        super().__init__()
        self.net = mlp(obs_dim, hidden_dim, hidden_layers, 2 * act_dim)

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
def evaluate(actor: Actor, envs: list, device: torch.device) -> tuple:
    """One deterministic episode per env, stepped in lockstep (one batched forward). Returns the
    true returns and, on Meta-World, whether each episode succeeded at any step (else NaN)."""
    obs = np.stack([env.reset()[0] for env in envs])
    returns, running = np.zeros(len(envs)), np.ones(len(envs), dtype=bool)
    success = np.full(len(envs), np.nan)
    while running.any():
        mean, _ = actor(torch.as_tensor(obs, device=device))
        torch.randn_like(mean)  # get_action's unused draw: keeps training's random stream
        actions = torch.tanh(mean).cpu().numpy()
        # MuJoCo would raise on them: a NaN return, which stops the run
        if not np.isfinite(actions).all():
            return np.full(len(envs), np.nan), success
        stepping = np.flatnonzero(running)
        for i in stepping:  # all at once when they are processes (`--parallel-eval`)
            envs[i].step_async(actions[i])
        for i in stepping:
            obs[i], reward, terminated, truncated, info = envs[i].step_wait()
            returns[i] += reward
            success[i] = np.fmax(success[i], info.get("success", np.nan))
            running[i] = not (terminated or truncated)
    return returns, success


# ALGO LOGIC: PEBBLE's storage: replay buffer (relabelled in place), episodes, labelled pairs
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
    """Preallocated circular transition buffer. Rewards are the ensemble's, relabelled in place."""

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

    @torch.no_grad()
    def relabel(self, reward_fn, chunk: int):
        """Rewrite every stored reward with `reward_fn([obs, action])`, even after a wrap."""
        for start in range(0, self.size, chunk):
            rows = slice(start, min(start + chunk, self.size))
            inputs = torch.cat([read_noisy(self.obs[rows], self.noise), self.actions[rows]], 1)
            self.rewards[rows] = reward_fn(inputs)


class EpisodeStore:
    """Last `max_episodes` whole episodes to cut segments from: [obs, action] rows, true rewards."""

    def __init__(self, max_episodes: int, episode_length: int, obs_dim: int, act_dim: int,
                 device: torch.device):
        self.slots = max_episodes + 1  # one slot is being written, the others hold whole episodes
        self.inputs = torch.zeros((self.slots, episode_length, obs_dim + act_dim), device=device)
        self.true_rewards = torch.zeros((self.slots, episode_length), device=device)
        # labelling by hand only: the host-side MuJoCo states, to draw a queried segment again
        self.physics = np.zeros((self.slots, episode_length, 0))
        self.max_episodes, self.episode_length, self.obs_dim = max_episodes, episode_length, obs_dim
        self.n_complete, self.t = 0, 0

    def add(self, obs, action, true_reward: float, physics: Optional[np.ndarray] = None):
        """Append one step. Episodes last `episode_length` steps: DMC episodes never end early."""
        slot = self.n_complete % self.slots
        self.inputs[slot, self.t, : self.obs_dim], self.inputs[slot, self.t, self.obs_dim :] = (
            obs, action
        )
        self.true_rewards[slot, self.t] = true_reward
        if physics is not None:
            if self.physics.shape[2] != len(physics):
                self.physics = np.zeros((self.slots, self.episode_length, len(physics)))
            self.physics[slot, self.t] = physics
        self.t += 1
        if self.t == self.episode_length:
            self.n_complete, self.t = self.n_complete + 1, 0

    def sample_segments(self, n_pairs: int, length: int, with_physics: bool = False):
        """Segment pairs; each side draws its episode and start independently. Returns (n, 2, H, D),
        (n, 2, H) and, with `with_physics`, their physics states (n, 2, H, P) in numpy."""
        device = self.inputs.device
        n_available = min(self.n_complete, self.max_episodes)
        episodes = (
            self.n_complete - 1 - torch.randint(0, n_available, (n_pairs, 2), device=device)
        ) % self.slots
        starts = torch.randint(0, self.episode_length - length + 1, (n_pairs, 2), device=device)
        steps = starts.unsqueeze(-1) + torch.arange(length, device=device)
        episodes = episodes.unsqueeze(-1)
        segments = self.inputs[episodes, steps], self.true_rewards[episodes, steps]
        return (
            (*segments, self.physics[episodes.cpu().numpy(), steps.cpu().numpy()])
            if with_physics else segments
        )


class PreferenceBuffer:
    """Segment pairs `(n, 2, S, obs+act)` with y = P[segment 1 preferred] in {0, 0.5, 1}
    (unused for unlabelled pairs). SURF stores S = H + 2 * crop steps, the teacher's
    H = `segment_size` in the middle; S is that of the first pairs added."""

    def __init__(self, capacity: int, segment_size: int, input_dim: int, device: torch.device,
                 noise=None):
        # steps allocated at the first add
        self.segments = torch.zeros((capacity, 2, 0, input_dim), device=device)
        self.labels = torch.zeros(capacity, device=device)
        self.size, self.noise, self.segment_size = 0, noise, segment_size

    def add(self, segments: torch.Tensor, labels: torch.Tensor):
        if self.segments.shape[2] == 0:
            self.segments = self.segments.new_zeros((len(self.labels), *segments.shape[1:]))
        n = len(labels)
        self.segments[self.size : self.size + n], self.labels[self.size : self.size + n] = (
            segments, labels
        )
        self.size += n

    def read(self, indices: torch.Tensor):
        return read_noisy(self.segments[indices], self.noise), self.labels[indices]


# ALGO LOGIC: reward ensemble, Bradley-Terry loss, teacher, query selection, state entropy
class RewardEnsemble(nn.Module):
    """`ensemble_size` reward MLPs on [obs, action] in one pass: LeakyReLU hidden, tanh output."""

    def __init__(self, input_dim: int, hidden_dim: int, n_hidden: int, ensemble_size: int):
        super().__init__()
        dims = [input_dim] + [hidden_dim] * n_hidden + [1]
        self.weights = nn.ParameterList()  # [0]: the input layer, (E, hidden, input) like nn.Linear
        self.biases = nn.ParameterList()
        for fan_in, fan_out in zip(dims[:-1], dims[1:]):
            bound = 1 / math.sqrt(fan_in)  # nn.Linear's default initialisation, per member
            self.weights.append(
                nn.Parameter(torch.empty(ensemble_size, fan_out, fan_in).uniform_(-bound, bound))
            )
            self.biases.append(
                nn.Parameter(torch.empty(ensemble_size, 1, fan_out).uniform_(-bound, bound))
            )
        self.ensemble_size = ensemble_size

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Rewards (E, N) per member of rows x: (N, D) shared by all, or (E, N, D) one set each."""
        if x.dim() == 2:
            x = x.expand(self.ensemble_size, *x.shape)
        for i, (weight, bias) in enumerate(zip(self.weights, self.biases)):
            x = torch.baddbmm(bias, x, weight.transpose(1, 2))
            x = F.leaky_relu(x) if i < len(self.weights) - 1 else torch.tanh(x)
        return x.squeeze(-1)

    def mean_reward(self, x: torch.Tensor) -> torch.Tensor:
        """The agent's reward: the ensemble mean."""
        return self(x).mean(0)

    def member_state_dicts(self) -> list:
        return [
            {name: value[e] for name, value in self.state_dict().items()}
            for e in range(self.ensemble_size)
        ]


def preference_loss(returns: torch.Tensor, labels: torch.Tensor) -> torch.Tensor:
    """Bradley-Terry cross-entropy per member. returns (E, B, 2) segment sums;
    labels (E, B) = P[segment 1 preferred]."""
    log_probs = F.log_softmax(returns, dim=-1)
    return -((1 - labels) * log_probs[..., 0] + labels * log_probs[..., 1]).mean(-1)


def temporal_crop(
    shape: tuple, stored: int, segment_size: int, crop: int, device: torch.device
) -> torch.Tensor:
    """SURF's temporal crop of pairs of `stored`-step segments as a 0/1 step mask (*shape, 2,
    stored). One length per pair in segment_size +- crop; independent start offsets per segment."""
    lengths = torch.randint(
        segment_size - crop, segment_size + crop + 1, (*shape, 1, 1), device=device
    )
    # uniform in [0, stored - L]
    starts = (torch.rand((*shape, 2, 1), device=device) * (stored - lengths + 1)).long()
    steps = torch.arange(stored, device=device)
    return ((steps >= starts) & (steps < starts + lengths)).float()


def pseudo_labels(returns: torch.Tensor, tau: float):
    """SURF's pseudo-labels from a member's returns (..., 2): the preferred segment (1.0 if segment
    1), and whether its preference probability reaches tau (the pairs whose label is kept)."""
    confidence, preferred = returns.softmax(-1).max(-1)
    return preferred.float(), confidence >= tau


def pseudo_label_loss(
    returns: torch.Tensor, targets: torch.Tensor, kept: torch.Tensor
) -> torch.Tensor:
    """SURF's unlabelled loss per member: cross-entropy of returns (E, B, 2) with pseudo-labels
    (E, B) where kept, averaged over the whole minibatch (unkept pairs count 0, FixMatch style)."""
    log_probs = F.log_softmax(returns, dim=-1)
    return -(kept * ((1 - targets) * log_probs[..., 0] + targets * log_probs[..., 1])).mean(-1)


def surf_iterations(n_labels: int, epochs: int, batch_size: int) -> int:
    """Reward steps of a SURF round: `epochs` passes over the labels, fixed, no early stop."""
    return math.ceil(epochs * n_labels / batch_size)


def member_minibatches(n: int, members: int, batch_size: int, device: torch.device):
    """Endless minibatch indices (E, B) into n items: an independent shuffle per member, a new one
    after each pass (the last minibatch of a pass may be short)."""
    while True:
        order = torch.rand(members, n, device=device).argsort(1)
        for start in range(0, n, batch_size):
            yield order[:, start : start + batch_size]


def train_reward(
    model: RewardEnsemble, optimizer, prefs: PreferenceBuffer, unlabeled: PreferenceBuffer,
    batch_size: int, epochs: int, crop: int, tau: float, lam: float, mu: int,
):
    """A SURF reward round, per member: `surf_iterations` steps of the Bradley-Terry loss on cropped
    labelled pairs plus `lam` x the pseudo-label loss on `mu * batch_size` cropped unlabelled pairs.
    Returns mean member loss and accuracy (last pass over labels), epochs, pseudo-labelled share."""
    n, members, device = prefs.size, model.ensemble_size, prefs.labels.device
    central = slice(crop, crop + prefs.segment_size)
    iterations = surf_iterations(n, epochs, batch_size)
    labeled_batches = member_minibatches(n, members, batch_size, device)
    unlabeled_batches = (member_minibatches(unlabeled.size, members, batch_size * mu, device)
                         if unlabeled.size else None)
    loss_sum, correct, strict, seen, kept, pseudo = torch.zeros(6, device=device)
    pairs = 0
    for iteration in range(iterations):
        segments, labels = prefs.read(next(labeled_batches))  # (E, B, 2, S, D), (E, B)
        rewards = model(segments.flatten(1, 3)).view(*segments.shape[:4])  # per step, (E, B, 2, S)
        crops = temporal_crop(labels.shape, segments.shape[3], prefs.segment_size, crop, device)
        returns = (rewards * crops).sum(-1)
        member_losses = preference_loss(returns, labels)
        unlabeled_losses = torch.zeros_like(member_losses)
        if unlabeled_batches is not None:
            segments_u, _ = unlabeled.read(next(unlabeled_batches))
            rewards_u = model(segments_u.flatten(1, 3)).view(*segments_u.shape[:4])
            # uncropped central steps
            targets, confident = pseudo_labels(rewards_u[..., central].detach().sum(-1), tau)
            crops_u = temporal_crop(
                targets.shape, segments_u.shape[3], prefs.segment_size, crop, device
            )
            unlabeled_losses = pseudo_label_loss((rewards_u * crops_u).sum(-1), targets, confident)
            kept, pseudo = kept + confident.sum(), pseudo + confident.numel()
        optimizer.zero_grad()
        (member_losses + lam * unlabeled_losses).sum().backward()
        optimizer.step()
        pairs += labels.shape[1]
        if iteration >= iterations - math.ceil(n / batch_size):  # last pass: PEBBLE's last epoch
            is_strict = labels != 0.5  # equal pairs train towards [0.5, 0.5]; no answer is right
            correct += (((returns[..., 1] > returns[..., 0]) == (labels > 0.5)) & is_strict).sum()
            strict += is_strict.sum()
            loss_sum += member_losses.detach().sum() * labels.shape[1]
            seen += labels.numel()
    accuracy = (correct / strict).item()  # NaN when every label is "equal"
    return (loss_sum / seen).item(), accuracy, pairs / n, (kept / pseudo.clamp_min(1)).item()


def teacher(rewards0, rewards1, margin: float, beta: float, gamma: float, eps_mistake: float,
            eps_skip: float, eps_equal: float):
    """B-Pref's simulated teacher on true per-step rewards (n, H).
    Returns (kept pairs mask, labels in {0, 0.5, 1})."""
    returns0, returns1 = rewards0.sum(1), rewards1.sum(1)
    keep = torch.ones_like(returns0, dtype=torch.bool)
    if eps_skip > 0:  # skip pairs where neither segment is good enough
        keep = torch.maximum(returns0, returns1) > eps_skip * margin
    equal = (returns0 - returns1).abs() < eps_equal * margin
    horizon = rewards0.shape[1]
    weights = gamma ** torch.arange(
        horizon - 1, -1, -1, device=rewards0.device, dtype=rewards0.dtype
    )
    discounted0, discounted1 = (rewards0 * weights).sum(1), (rewards1 * weights).sum(1)
    if beta > 0:
        labels = torch.bernoulli(torch.sigmoid(beta * (discounted1 - discounted0)))
    else:
        labels = (discounted1 > discounted0).float()  # ties prefer segment 0
    mistakes = torch.rand_like(labels) < eps_mistake
    labels = torch.where(mistakes, 1 - labels, labels)
    labels = torch.where(equal, torch.full_like(labels, 0.5), labels)
    return keep, labels


def simulated_teacher(true_rewards: torch.Tensor, recent_returns, args: Args) -> tuple:
    """B-Pref's simulated teacher on a round's pairs of segments' true rewards:
    (answered mask, labels). Its margin is the mean of the last 10 episodes' returns, scaled to a
    segment's length."""
    margin = (float(np.mean(recent_returns)) * args.segment_size / args.episode_length
              if recent_returns else 0.0)
    return teacher(
        true_rewards[:, 0], true_rewards[:, 1], margin, args.teacher_beta, args.teacher_gamma,
        args.teacher_eps_mistake, args.teacher_eps_skip, args.teacher_eps_equal,
    )


@torch.no_grad()
def select_queries(model: RewardEnsemble, store: EpisodeStore, n_queries: int, segment_size: int,
                   sampling: str, pool_multiplier: int, noise=None, crop: int = 0,
                   with_physics: bool = False):
    """Segment pairs to ask about: uniform, or the most uncertain of a larger pool (disagreement /
    entropy). SURF: segments of segment_size + 2 * crop steps, scored on the central ones."""
    if sampling == "uniform":
        return store.sample_segments(n_queries, segment_size + 2 * crop, with_physics)
    stored = segment_size + 2 * crop
    segments, true_rewards, *physics = store.sample_segments(
        n_queries * pool_multiplier, stored, with_physics
    )
    inputs = read_noisy(segments[:, :, crop : crop + segment_size], noise)
    returns = model(inputs.flatten(0, 2)).view(model.ensemble_size, *inputs.shape[:3]).sum(-1)
    p = returns.softmax(-1)[..., 1]  # each member's P[segment 1 preferred], (E, pool)
    if sampling == "disagreement":
        score = p.std(0, correction=0)
    else:  # entropy: the mean of the members' binary entropies
        score = -(p * p.clamp_min(1e-12).log() + (1 - p) * (1 - p).clamp_min(1e-12).log()).mean(0)
    top = score.topk(n_queries).indices
    return segments[top], true_rewards[top], *(states[top.cpu().numpy()] for states in physics)


class RunningMeanStd:
    """Running mean and variance over batches (Chan et al.'s parallel merge), kept on the device."""

    def __init__(self, device: torch.device):
        self.mean = torch.zeros((), device=device)
        self.var = torch.zeros((), device=device)
        self.count = 0

    def update(self, x: torch.Tensor):
        batch_mean, batch_var, n = x.mean(), x.var(correction=0), x.numel()
        delta, total = batch_mean - self.mean, self.count + n
        self.var = (self.var * self.count + batch_var * n
                    + delta**2 * self.count * n / total) / total
        self.mean = self.mean + delta * n / total
        self.count = total

    @property
    def std(self) -> torch.Tensor:
        return self.var.sqrt()


@torch.no_grad()
def knn_distance(samples: torch.Tensor, points: torch.Tensor, k: int,
                 chunk: int = 16384) -> torch.Tensor:
    """L2 distance from each sample to its k-th nearest neighbour among `points`, itself excluded.
    Samples are rows of `points`, so the nearest one, at distance 0, is skipped."""
    nearest = None
    for part in points.split(chunk):
        d = (torch.cdist(samples, part) if nearest is None
             else torch.cat([nearest, torch.cdist(samples, part)], 1))
        nearest = d.topk(min(k + 1, d.shape[1]), dim=1, largest=False).values
    return nearest[:, k]


def state_entropy_reward(indices: torch.Tensor, points: torch.Tensor, k: int,
                         stats: RunningMeanStd) -> torch.Tensor:
    """PEBBLE's intrinsic reward for rows `indices` of `points`: k-NN distance / running std."""
    distances = knn_distance(points[indices], points, k)
    stats.update(distances)
    return distances / stats.std



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
    qf1 = SoftQNetwork(obs_dim, act_dim, args.hidden_dim, args.hidden_layers).to(device)
    qf2 = SoftQNetwork(obs_dim, act_dim, args.hidden_dim, args.hidden_layers).to(device)
    # foreach: the multi-tensor Adam, bitwise the CPU's default single-tensor one and faster
    q_optimizer = optim.Adam(
        list(qf1.parameters()) + list(qf2.parameters()), lr=args.q_lr,
        weight_decay=args.weight_decay, foreach=True
    )
    qf1_target = SoftQNetwork(obs_dim, act_dim, args.hidden_dim, args.hidden_layers).to(device)
    qf2_target = SoftQNetwork(obs_dim, act_dim, args.hidden_dim, args.hidden_layers).to(device)
    qf1_target.load_state_dict(qf1.state_dict())
    qf2_target.load_state_dict(qf2.state_dict())
    return qf1, qf2, q_optimizer, qf1_target, qf2_target


def make_agent(obs_dim: int, act_dim: int, args: Args, device: torch.device) -> Agent:
    actor = Actor(obs_dim, act_dim, args.hidden_dim, args.hidden_layers).to(device)
    actor_optimizer = optim.Adam(actor.parameters(), lr=args.policy_lr,
                                 weight_decay=args.weight_decay, foreach=True)
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
    total_feedback: int = 0  # queries asked, counted against the budget
    labeled_feedback: int = 0  # labels obtained (a skipping teacher gives fewer)
    episode_return: float = 0.0
    episode_length: int = 0
    # resume only: the env's RNG state at the episode's start (None: the seeded first
    # reset), and the episode's actions so far, to replay the episode on a resume
    episode_start: Optional[dict] = None
    episode_actions: list = field(default_factory=list)
    recent_returns: deque = field(default_factory=lambda: deque(maxlen=10))  # the teacher's margin
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
    reward_model: RewardEnsemble, episodes: EpisodeStore, physics: np.ndarray,
):
    """Write one step into the run's storage, with the reward the agent learns from."""
    # the reward the agent learns from: the model's, never the true reward
    rb.add(obs, action, next_obs, terminated, true_reward,
           reward_model.mean_reward(torch.cat([obs, action]).unsqueeze(0))[0])
    episodes.add(obs, action, true_reward, physics)


def sac_update(agent: Agent, data: Batch, loop: Loop, args: Args):
    """One SAC update: critics, then (every `actor_update_freq`) actor and temperature, then (every
    `target_update_freq`) the targets. The losses stay on the device, in `loop.losses`.

    `--compile` and `--cuda-graph` replace the three step functions it calls (`critic_gradients`,
    `actor_gradients`, `target_update`) with compiled or captured versions of themselves. From the
    step on which Adam's host scalars settle, `--cuda-graph-whole` replays it whole, Adam inside."""
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


def feedback_round(sampling: str, loop: Loop, args: Args, reward_model: RewardEnsemble,
                   reward_optimizer, episodes: EpisodeStore, prefs: PreferenceBuffer,
                   rb: ReplayBuffer, ask, unlabeled: PreferenceBuffer) -> dict:
    """Ask a round of queries, train the reward ensemble on all labels, relabel the whole buffer.
    `ask(segments, true_rewards, physics, shown)` answers the pairs on their steps `shown`, the
    central ones (the crop pads them): (answered mask, labels), as `simulated_teacher` does.
    Returns the reward training's scalars by tag (none before a label)."""
    n_queries = min(args.queries_per_round, args.max_feedback - loop.total_feedback)
    segments, true_rewards, physics = select_queries(
        reward_model, episodes, n_queries, args.segment_size, sampling, args.query_pool_multiplier,
        rb.noise, args.surf_crop, with_physics=True,
    )
    central = slice(args.surf_crop, args.surf_crop + args.segment_size)  # what the teacher sees
    keep, labels = ask(segments, true_rewards, physics, central)
    prefs.add(segments[keep], labels[keep])
    unlabeled_segments, _ = episodes.sample_segments(
        n_queries * args.surf_unlabeled_ratio, args.segment_size + 2 * args.surf_crop
    )
    no_labels = torch.zeros(len(unlabeled_segments), device=unlabeled_segments.device)
    unlabeled.add(unlabeled_segments, no_labels)
    loop.total_feedback, loop.labeled_feedback = loop.total_feedback + n_queries, prefs.size
    trained = {}
    if prefs.size:  # a round may yield no label at all (skipping teacher)
        loss, accuracy, epochs, pseudo_label_rate = train_reward(
            reward_model, reward_optimizer, prefs, unlabeled,
            args.reward_batch_size, args.reward_epochs,
            args.surf_crop, args.surf_tau, args.surf_lambda, args.surf_mu,
        )
        trained = {"pbrl/reward_loss": loss, "pbrl/pseudo_label_rate": pseudo_label_rate,
                   "pbrl/reward_accuracy": accuracy, "pbrl/reward_epochs": epochs}
        if math.isnan(accuracy):  # every label is "equal": none is right, no accuracy to log
            del trained["pbrl/reward_accuracy"]
    rb.relabel(reward_model.mean_reward, args.relabel_batch_size)
    return trained


def feedback_due(step: int, pebble_start: int, loop: Loop, args: Args) -> bool:
    """Whether step `step` begins with a feedback round: the first at `pebble_start`, then one every
    `feedback_freq` steps while the budget lasts."""
    return step == pebble_start or (
        step > pebble_start and (step - pebble_start) % args.feedback_freq == 0
        and loop.total_feedback < args.max_feedback
    )


def save_checkpoint(path: str, args: Args, global_step: int, saved: dict, dims: tuple):
    """The trained networks of the `saved` objects, for
    evaluation and debugging (`state.pt` resumes a run)."""
    agent = saved["agent"]
    checkpoint = {
        "args": vars(args), "global_step": global_step + 1, "actor": agent.actor.state_dict(),
        "qf1": agent.qf1.state_dict(), "qf2": agent.qf2.state_dict(),
        "log_alpha": agent.log_alpha.detach().cpu(),
        **dict(zip(("obs_dim_real", "obs_dim", "act_dim"), dims)),
        "reward_models": saved["reward_model"].member_state_dicts(),
    }
    torch.save(checkpoint, path)


# FLAGS: bad input fails fast, before anything is written
def validate_args(args: Args) -> None:
    """Fail fast on bad input, before anything is written:
    a ValueError with one line naming the flag."""
    ene.check_env_args(args.env_id, args.noise, args.noise_type, args.noise_histograms)
    if args.track and importlib.util.find_spec("wandb") is None:
        raise ValueError("--track needs wandb: pip install -e '.[wandb]'")
    harness_flags = {"--cuda-graph": args.cuda_graph}  # the flags that need the harness's package
    harness_flags |= {"--resumable": args.resumable, "--diagnostics": args.diagnostics}
    harness_flags |= {"--query-log": args.query_log, "--preferences": args.preferences,
                      "--teacher external": args.teacher == "external"}
    given = [flag for flag, on in harness_flags.items() if on]
    if given and importlib.util.find_spec("r2n_harness") is None:  # a copy of this file without it
        raise ValueError(f"{given[0]} needs the package r2n_harness: run this in R2N's repository")
    if args.teacher == "external":  # a person's labels: bound to their queries, never lost
        args.resumable = args.query_log = True
    if args.tf32 and not (args.cuda and torch.cuda.is_available()):
        raise ValueError("--tf32: TF32 matmuls need a CUDA GPU, and this run is on the CPU")
    if args.cuda_graph_whole and not args.cuda_graph:
        raise ValueError("--cuda-graph-whole needs --cuda-graph")
    if args.cuda_graph and not (args.cuda and torch.cuda.is_available()):
        raise ValueError("--cuda-graph: CUDA graphs need a CUDA GPU, and this run is on the CPU")
    if args.run_name is not None and (args.run_name in ("", ".", "..") or "/" in args.run_name):
        raise ValueError(f"--run-name must be a folder name without '/', got {args.run_name!r}")
    if args.checkpoint_freq is not None and args.checkpoint_freq < 1:
        raise ValueError(f"--checkpoint-freq must be >= 1, got {args.checkpoint_freq}")
    if not args.state_minutes > 0:
        raise ValueError(f"--state-minutes must be > 0, got {args.state_minutes}")
    for flag in ("checkpoint_freq", "keep_state"):
        if getattr(args, flag) not in (None, False) and not args.resumable:
            raise ValueError(f"--{flag.replace('_', '-')} writes state.pt: it needs --resumable")
    if args.max_feedback < 1:
        raise ValueError(f"--max-feedback {args.max_feedback} is smaller than one query")
    if args.queries_per_round is None:
        args.queries_per_round = max(1, args.max_feedback // 100)
    if args.queries_per_round < 1:
        raise ValueError(f"--queries-per-round must be >= 1, got {args.queries_per_round}")
    if not 1 <= args.segment_size <= args.episode_length:
        raise ValueError(
            f"--segment-size {args.segment_size} is longer than an episode "
            f"(--episode-length {args.episode_length})"
        )
    if args.learning_starts <= args.knn_k:
        raise ValueError(
            f"--learning-starts {args.learning_starts} must exceed --knn-k {args.knn_k}"
        )
    if args.total_timesteps <= args.learning_starts + args.unsup_steps:
        raise ValueError(
            f"--total-timesteps {args.total_timesteps} leaves no step for feedback after "
            f"--learning-starts + --unsup-steps = {args.learning_starts + args.unsup_steps}"
        )
    if args.learning_starts + args.unsup_steps < args.episode_length:
        raise ValueError(
            f"--learning-starts + --unsup-steps = {args.learning_starts + args.unsup_steps} must "
            f"cover one episode (--episode-length {args.episode_length}): the first feedback round "
            f"cuts segments from complete episodes"
        )
    if args.buffer_size < args.batch_size:
        raise ValueError(
            f"--buffer-size {args.buffer_size} is smaller than --batch-size {args.batch_size}"
        )
    if not 0 <= args.surf_crop < args.segment_size:
        raise ValueError(
            f"--surf-crop must be in [0, --segment-size {args.segment_size}), got {args.surf_crop}"
        )
    if args.segment_size + 2 * args.surf_crop > args.episode_length:
        raise ValueError(
            f"--surf-crop {args.surf_crop}: stored segments of --segment-size + 2 * --surf-crop = "
            f"{args.segment_size + 2 * args.surf_crop} steps exceed an episode "
            f"(--episode-length {args.episode_length})"
        )
    if args.surf_unlabeled_ratio < 0:
        raise ValueError(f"--surf-unlabeled-ratio must be >= 0, got {args.surf_unlabeled_ratio}")
    if not 0.0 <= args.surf_tau <= 1.0:
        raise ValueError(f"--surf-tau must be in [0, 1], got {args.surf_tau}")
    if args.surf_lambda < 0.0:
        raise ValueError(f"--surf-lambda must be >= 0, got {args.surf_lambda}")
    if args.surf_mu < 1:
        raise ValueError(f"--surf-mu must be >= 1, got {args.surf_mu}")
    if not 0.0 < args.teacher_gamma <= 1.0:
        raise ValueError(f"--teacher-gamma must be in (0, 1], got {args.teacher_gamma}")
    for flag in ("teacher_eps_mistake", "teacher_eps_skip", "teacher_eps_equal"):
        if not 0.0 <= getattr(args, flag) <= 1.0:
            raise ValueError(
                f"--{flag.replace('_', '-')} must be in [0, 1], got {getattr(args, flag)}"
            )
    for flag in (
        "episode_length", "ensemble_size", "reward_layers", "reward_epochs", "feedback_freq",
        "eval_freq", "eval_episodes", "segment_episodes", "log_freq", "actor_update_freq",
        "target_update_freq", "hidden_layers",
    ):
        if getattr(args, flag) < 1:
            raise ValueError(f"--{flag.replace('_', '-')} must be >= 1, got {getattr(args, flag)}")
    for flag in ("policy_lr", "q_lr", "alpha_lr", "weight_decay"):
        if getattr(args, flag) < 0:
            raise ValueError(f"--{flag.replace('_', '-')} must be >= 0, got {getattr(args, flag)}")


def uses_run(args: Args) -> bool:
    """Whether a flag asks for the run harness's hooks (`r2n_harness.run`)."""
    flags = ("resumable", "query_log", "diagnostics", "preferences")  # those this script has
    return any(getattr(args, flag, None) for flag in flags)


# RUN: the run folder, the logs, the NaN stop. The run harness (resume, the query log, the
# diagnostics, a person's labels) is the package `r2n_harness`, imported only by its flags.
def harness(module: str):
    """A module of the run harness's package `r2n_harness`, imported only for the flag that needs it
    (`validate_args` has checked that the package is there)."""
    return importlib.import_module(f"r2n_harness.{module}")


def make_run_folder(args) -> str:
    """Create `runs/{run_name}` and return its name, by default `{env_id}__{exp_name}__{seed}__{unix
    time}`. If a run that started in the same second took it (the runs of a sweep differ in flags
    that the name does not show), the next second's."""
    unix_time = int(time.time())
    while True:
        run_name = args.run_name or f"{args.env_id}__{args.exp_name}__{args.seed}__{unix_time}"
        try:
            os.makedirs(f"runs/{run_name}")  # atomic: exactly one of two racing runs gets it
            return run_name
        except FileExistsError:
            if args.run_name:
                resumable = os.path.exists(f"runs/{run_name}/state.pt") and not args.resumable
                raise ValueError(f"--run-name {run_name}: runs/{run_name} exists" + (
                    " and holds a state.pt: add --resumable to resume it" if resumable else
                    " and holds no state.pt to resume (the run finished, or stopped before its "
                    "first state); choose another name or move the folder")) from None
            unix_time += 1


def open_writer(args, run_name: str, resume_step: Optional[int]) -> SummaryWriter:
    """The run's TensorBoard writer (and W&B with `--track`). A resumed run hides the
    points the interrupted one logged after its state (TensorBoard's purge_step)."""
    if args.track:
        import wandb

        wandb.init(project=args.wandb_project_name, entity=args.wandb_entity,
                   sync_tensorboard=True, config=vars(args), name=run_name, id=run_name,
                   resume="allow", monitor_gym=True, save_code=True)
    writer = SummaryWriter(f"runs/{run_name}", purge_step=resume_step)
    if resume_step is None:
        table = "\n".join([f"|{key}|{value}|" for key, value in vars(args).items()])
        writer.add_text("hyperparameters", f"|param|value|\n|-|-|\n{table}")
    return writer


class NonFinite(Exception):
    """A non-finite value: the run writes its checkpoint
    and stops with exit code 1 and one line naming it."""


def check_finite(values: dict, step: int):
    bad = next((name for name, value in values.items() if not math.isfinite(value)), None)
    if bad is not None:
        raise NonFinite(f"non-finite {bad} ({values[bad]}) at step {step}")


class Progress:
    """The console's progress line: at each phase change and at most every `interval` seconds of
    training, the step of the total, the phase, SPS since the last line, the ETA at that rate, the
    feedback used of `budget` (PbRL) and the last evaluation's return. Host values only: no sync."""

    def __init__(self, total_steps: int, phases: dict, last_phase: str, step: int, seconds: float,
                 budget: Optional[int] = None, interval: float = 30.0):
        # `phases`: each phase's name and the step it ends at, in order; then `last_phase`
        self.total_steps, self.phases, self.last_phase = total_steps, phases, last_phase
        self.step, self.time, self.budget, self.interval = step, seconds, budget, interval
        self.phase = None

    def update(self, step: int, loop: Loop, start_time: float):
        """At `step`; `start_time`: the training clock's start, plus any waits for labels."""
        seconds = time.time() - start_time
        phase = next((name for name, end in self.phases.items() if step < end), self.last_phase)
        if phase == self.phase and seconds - self.time < self.interval:
            return
        moved = step > self.step and seconds > self.time
        sps = (step - self.step) / (seconds - self.time) if moved else 0.0
        eta = self.duration((self.total_steps - step) / sps) if sps else "?"
        feedback = f" | feedback {loop.total_feedback}/{self.budget}" if self.budget else ""
        line = f"progress: step {step}/{self.total_steps} ({100 * step / self.total_steps:.0f}%)"
        line += f" | {phase} | {sps:.0f} SPS | ETA {eta}{feedback} | eval return "
        eval_return = loop.last_eval.get("eval/episodic_return")
        print(line + ("-" if eval_return is None else f"{eval_return:.1f}"), flush=True)
        self.phase, self.step, self.time = phase, step, seconds

    @staticmethod
    def duration(seconds: float) -> str:
        minutes, hours = int(seconds) // 60 % 60, int(seconds) // 3600
        return (f"{hours // 24}d{hours % 24:02d}h" if hours >= 24
                else f"{hours}h{minutes:02d}m" if hours else f"{minutes}m")


def log_evaluation(writer: SummaryWriter, global_step: int, actor: Actor, envs: list,
                   device: torch.device, start_time: float, loop: Loop, args: Args, more: dict):
    """Evaluate the policy, log its tags and `more` (kept in `loop.last_eval`: a resume logs them
    again), print a console line, and stop on a non-finite return. `start_time`: the training
    clock's start, so that SPS counts training time only."""
    started = time.time()
    returns, success = evaluate(actor, envs, device)
    eval_return = float(returns.mean())
    sps = int((global_step + 1) / (time.time() - start_time))
    loop.last_eval = {"eval/episodic_return": eval_return, "charts/SPS": sps} | more
    if not np.isnan(success).any():  # a task with a success flag (Meta-World)
        loop.last_eval["eval/success_rate"] = float(success.mean())
    for tag, value in loop.last_eval.items():
        writer.add_scalar(tag, value, global_step + 1)
    print(f"step={global_step + 1} eval_return={eval_return:.2f} SPS={sps} "
          f"eval_seconds={time.time() - started:.2f} feedback={loop.total_feedback}/"
          f"{args.max_feedback} labels={loop.labeled_feedback}", flush=True)
    check_finite({"eval/episodic_return": eval_return}, global_step)


def log_losses(writer: SummaryWriter, global_step: int, losses: dict):
    """The latest losses (`losses/`), read from the device in one sync, and the NaN stop."""
    logged = dict(zip([f"losses/{name}" for name in losses],
                      torch.stack(list(losses.values())).tolist()))
    for tag, value in logged.items():
        writer.add_scalar(tag, value, global_step)
    check_finite(logged, global_step)


def log_round(writer: SummaryWriter, global_step: int, trained: dict, loop: Loop):
    """A feedback round's tags: the reward training's and the feedback counts; the NaN stop."""
    trained |= {"pbrl/total_feedback": loop.total_feedback,
                "pbrl/labeled_feedback": loop.labeled_feedback}
    for tag, value in trained.items():
        writer.add_scalar(tag, value, global_step)
    check_finite(trained, global_step)


if __name__ == "__main__":
    args = ene.suite_settings(tyro.cli(Args))  # unset SAC settings: the task's suite's
    try:  # bad input fails here, with one line, before any output is written
        validate_args(args)
        env = ene.make_env(args.env_id, args.seed, args.noise, args.noise_type,
                           args.noise_histograms, args.episode_length)
        # the run harness, for its flags: resume, the query log, diagnostics, a person's labels
        stored_steps = args.segment_size + 2 * args.surf_crop  # a query's steps, with the crop's
        run = (harness("run").Run(args, env, make_run_folder, stored_steps) if uses_run(args)
               else None)
        run_name = run.name if run else make_run_folder(args)
    except ValueError as e:
        raise SystemExit(f"{args.exp_name}: error: {e}")
    checkpoint_path = f"runs/{run_name}/{args.exp_name}.cleanrl_model"
    video_folder = run.video_folder if run else f"videos/{run_name}"
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
    writer = open_writer(args, run_name, run and run.start_step)

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
        if args.cuda_graph_whole:  # the whole update, Adam inside, once settled
            sac_update = harness("cuda_graph").WholeUpdate(sac_update)

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
    reward_model = RewardEnsemble(obs_dim + act_dim, args.reward_hidden_dim, args.reward_layers,
                                  args.ensemble_size).to(device)
    reward_optimizer = optim.Adam(reward_model.parameters(), lr=args.reward_lr, foreach=True)
    rb = ReplayBuffer(args.buffer_size, obs_dim, act_dim, device, noise)
    episodes = EpisodeStore(args.segment_episodes, args.episode_length, obs_dim, act_dim, device)
    prefs = PreferenceBuffer(args.max_feedback, args.segment_size, obs_dim + act_dim, device, noise)
    # SURF's unlabelled pairs, labels unused
    unlabeled = PreferenceBuffer(args.max_feedback * args.surf_unlabeled_ratio, args.segment_size,
                                 obs_dim + act_dim, device, noise)
    entropy_stats = RunningMeanStd(device)
    loop = Loop()
    # everything the loop changes, by name (what `--resumable` saves and restores)
    saved = dict(agent=agent, reward_model=reward_model, reward_optimizer=reward_optimizer, rb=rb,
                 episodes=episodes, prefs=prefs, entropy_stats=entropy_stats,
                 unlabeled=unlabeled, loop=loop)

    def ask(segments, true_rewards, physics, shown):
        """A feedback round's teacher: B-Pref's simulated one, on the steps `shown`."""
        return simulated_teacher(true_rewards[:, :, shown], loop.recent_returns, args)

    # TRY NOT TO MODIFY: start the game (the harness may continue it from its saved state)
    if run:
        obs, start_step, elapsed = run.start(saved, [env, *eval_envs], device, writer)
        ask = run.teacher(ask)  # the query log, or a person's labels
    else:
        (obs, _), start_step, elapsed = env.reset(seed=args.seed), 0, 0.0
    start_time = time.time() - elapsed  # SPS counts the time spent training only
    obs = torch.as_tensor(obs, device=device)
    pebble_start = args.learning_starts + args.unsup_steps
    progress = Progress(args.total_timesteps, {"random": args.learning_starts,
                                               "pre-training": pebble_start}, "PbRL",
                        start_step, elapsed, args.max_feedback)
    try:
        for global_step in range(start_step, args.total_timesteps):
            if run:
                run.step_starts(global_step, start_time)
            progress.update(global_step, loop, start_time + (run.waited if run else 0.0))
            # ALGO LOGIC: put action logic here
            if global_step < args.learning_starts:
                action = env.action_space.sample()
                action = torch.as_tensor(action, dtype=torch.float32, device=device)
            else:
                action = act(agent.actor, obs)

            # TRY NOT TO MODIFY: execute the game and log data.
            env_action = action.cpu().numpy()
            check_finite({"action": float(env_action.sum())}, global_step)  # on the host: no sync
            physics = env.physics_state()  # of `obs`, to render the step again if it is queried
            next_obs, true_reward, terminated, truncated, _ = env.step(env_action)
            loop.episode_actions.append(env_action)
            next_obs = torch.as_tensor(next_obs, device=device)
            store(
                rb, obs, action, next_obs, terminated, float(true_reward),
                reward_model, episodes, physics,
            )
            loop.episode_return += float(true_reward)
            loop.episode_length += 1
            obs = next_obs  # CRUCIAL step easy to overlook
            if terminated or truncated:
                writer.add_scalar("charts/episodic_return", loop.episode_return, global_step)
                writer.add_scalar("charts/episodic_length", loop.episode_length, global_step)
                loop.recent_returns.append(loop.episode_return)
                loop.episode_start, loop.episode_actions = env.rng_state(), []
                obs, _ = env.reset()
                obs = torch.as_tensor(obs, device=device)
                loop.episode_return, loop.episode_length = 0.0, 0

            # ALGO LOGIC: training.
            if global_step >= args.learning_starts:
                if global_step < pebble_start:  # unsupervised pre-training, state-entropy reward
                    data = rb.sample(args.batch_size)
                    points = read_noisy(rb.obs[: rb.size], noise)
                    intrinsic_reward = state_entropy_reward(data.indices, points, args.knn_k,
                                                            entropy_stats)
                    sac_update(agent, data._replace(rewards=intrinsic_reward), loop, args)
                    loop.losses["state_entropy_reward"] = intrinsic_reward.mean()
                elif global_step == pebble_start:  # the first round; a fresh critic on its reward
                    trained = feedback_round("uniform", loop, args, reward_model, reward_optimizer,
                                             episodes, prefs, rb, ask, unlabeled)
                    log_round(writer, global_step, trained, loop)
                    agent.qf1, agent.qf2, agent.q_optimizer, agent.qf1_target, agent.qf2_target = (
                        make_critic(obs_dim, act_dim, args, device)
                    )
                    for _ in range(args.reset_updates):
                        sac_update(agent, rb.sample(args.batch_size), loop, args)
                else:
                    if feedback_due(global_step, pebble_start, loop, args):
                        trained = feedback_round(args.query_sampling, loop, args, reward_model,
                                                 reward_optimizer, episodes, prefs, rb, ask,
                                                 unlabeled)
                        log_round(writer, global_step, trained, loop)
                    sac_update(agent, rb.sample(args.batch_size), loop, args)

                if global_step % args.log_freq == 0:
                    log_losses(writer, global_step, loop.losses)

            if (global_step + 1) % args.eval_freq == 0 or global_step + 1 == args.total_timesteps:
                log_evaluation(writer, global_step, agent.actor, eval_envs, device,
                               start_time + (run.waited if run else 0.0), loop, args,
                               run.eval_tags() if run else {})
                if args.save_model:
                    save_checkpoint(checkpoint_path, args, global_step, saved, dims)

            if run:  # `state.pt` when due, at a stop signal, and before a person's round
                run.step_ends(global_step, obs, start_time, run.external is not None
                              and feedback_due(global_step + 1, pebble_start, loop, args))
    except NonFinite as e:  # the checkpoint is written first, for debugging
        save_checkpoint(checkpoint_path, args, global_step, saved, dims)
        message = f"error: {e}; checkpoint for debugging: {checkpoint_path}"
        if run:
            raise run.stop(message)
        writer.close()
        raise SystemExit(f"{args.exp_name}: {message}")

    for each in (env, *eval_envs):
        each.close()
    writer.close()
    if run:  # last: a kill before this leaves a state to resume
        run.finish()
