# docs and experiment results can be found in README.md, in the section named after this file
"""SAC on the true reward, in an Extremely Noisy Environment: the oracle of the preference-based scripts.

Haarnoja et al., "Soft Actor-Critic Algorithms and Applications" (2018), exactly the SAC inside `pebble.py` (same
networks, update, flags and defaults, from the R2N paper's appendix; Muslimani et al., AAMAS 2025), but the replay
buffer stores the environment's reward instead of a learned one. It is `pebble.py` with the preference learning
deleted, so `diff sac.py pebble.py` shows only PEBBLE: reward ensemble, teacher, queries, preference buffer, episode
store, state-entropy pre-training, feedback rounds, relabelling and the critic reset. The loop, one iteration per
env step:

1. `global_step < learning_starts`: uniform random actions, no learning.
2. then one SAC update per step on the true reward.
Evaluation every `eval_freq` steps: `eval_episodes` deterministic episodes on separate envs, true reward.

Two uses: the upper bound ("SAC with the true reward") for the PbRL curves at the same `--noise`, and, with
`--noise 0`, the noise-free policy whose deterministic rollouts give the histograms of `--noise-type imitate`
(`make_histograms.py`). Choices where the paper is silent: those of `pebble.py` that concern SAC (`--noise-resample`
redraws the noise columns of replay minibatches, as ANF does; the critics bootstrap on `terminated` only);
`make_critic` stays a function (PEBBLE resets the critic) so that the shared code is byte-identical.

Only `ene.py`, the noisy environment, is shared with the other scripts; `--help` documents every flag.
"""
import importlib.util
import math
import os
import random
import time
from dataclasses import dataclass
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
    exp_name: str = os.path.basename(__file__)[: -len(".py")]
    """the name of this experiment (run folder and checkpoint name)"""
    seed: int = 1
    """seed of the experiment"""
    torch_deterministic: bool = True
    """if toggled, `torch.backends.cudnn.deterministic=True`"""
    cuda: bool = True
    """if toggled, cuda will be used when available"""
    track: bool = False
    """if toggled, this experiment will be tracked with Weights and Biases"""
    wandb_project_name: str = "r2n"
    """the wandb's project name"""
    wandb_entity: Optional[str] = None
    """the entity (team) of wandb's project"""
    capture_video: bool = False
    """whether to capture videos of the first evaluation env (`videos/{run_name}`; needs the `video` extra)"""
    save_model: bool = True
    """whether to save the checkpoint `runs/{run_name}/{exp_name}.cleanrl_model` (at every evaluation)"""
    threads: Optional[int] = None
    """torch intra-op threads; unset: 1 on CPU (several runs share a machine), torch's default on GPU"""
    log_freq: int = 1000
    """log the SAC losses every `log_freq` steps (the only host syncs of the training loop)"""

    # Environment arguments
    env_id: str = "cheetah-run"
    """the dm_control task, as domain-task"""
    noise: float = 0.9
    """fraction of all observation features that are noise, in [0, 1)"""
    noise_type: Literal["gaussian", "imitate"] = "gaussian"
    """noise features: i.i.d. N(0, 1), or imitating the real features' histograms"""
    noise_resample: bool = True
    """redraw the noise columns of stored observations whenever they are read back (ANF's semantics)"""
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


def validate_args(args: Args) -> None:
    """Fail fast on bad input, before anything is written: a ValueError with one line naming the flag."""
    ene.check_env_args(args.env_id, args.noise, args.noise_type, args.noise_histograms)
    if args.track and importlib.util.find_spec("wandb") is None:
        raise ValueError("--track needs wandb: pip install -e '.[wandb]'")
    if args.buffer_size < args.batch_size:
        raise ValueError(f"--buffer-size {args.buffer_size} is smaller than --batch-size {args.batch_size}")
    for flag in ("episode_length", "eval_freq",
                 "eval_episodes", "log_freq", "actor_update_freq", "target_update_freq"):
        if getattr(args, flag) < 1:
            raise ValueError(f"--{flag.replace('_', '-')} must be >= 1, got {getattr(args, flag)}")


# TRY NOT TO MODIFY: the run folder
def make_run_folder(env_id: str, exp_name: str, seed: int) -> str:
    """Create `runs/{env_id}__{exp_name}__{seed}__{unix_time}` and return its name. If a run that started in the same
    second took that folder (runs of a sweep differ in noise or budget, which the name does not show), try the next."""
    unix_time = int(time.time())
    while True:
        run_name = f"{env_id}__{exp_name}__{seed}__{unix_time}"
        try:
            os.makedirs(f"runs/{run_name}")  # atomic: exactly one of two racing runs gets the folder
            return run_name
        except FileExistsError:
            unix_time += 1


# TRY NOT TO MODIFY: console progress
class Progress:
    """A console line at every phase change and at most every `interval` seconds: step / total, phase, SPS since the
    last line, ETA at that rate, feedback used and the latest evaluation return. It reads the clock and host values
    only, so it adds no host sync to the training loop."""

    def __init__(self, total_steps: int, budget: Optional[int] = None, interval: float = 30.0):
        self.total_steps, self.budget, self.interval = total_steps, budget, interval
        self.phase, self.time, self.step, self.eval_return = None, time.monotonic(), 0, None

    def update(self, step: int, phase: str, feedback: Optional[int] = None):
        now = time.monotonic()
        if phase == self.phase and now - self.time < self.interval:
            return
        sps = (step - self.step) / (now - self.time) if step > self.step and now > self.time else 0.0
        line = f"progress: step {step}/{self.total_steps} ({100 * step / self.total_steps:.0f}%) | {phase} | "
        line += f"{sps:.0f} SPS | ETA {self.duration((self.total_steps - step) / sps) if sps else '?'}"
        if self.budget is not None:
            line += f" | feedback {feedback}/{self.budget}"
        line += " | eval return " + ("-" if self.eval_return is None else f"{self.eval_return:.1f}")
        print(line, flush=True)
        self.phase, self.time, self.step = phase, now, step

    @staticmethod
    def duration(seconds: float) -> str:
        minutes, hours = int(seconds) // 60 % 60, int(seconds) // 3600
        return f"{hours // 24}d{hours % 24:02d}h" if hours >= 24 else f"{hours}h{minutes:02d}m" if hours else f"{minutes}m"


# TRY NOT TO MODIFY: replay storage, on the device
def read_noisy(x: torch.Tensor, noise: Optional[ene.NoiseSampler]) -> torch.Tensor:
    """Stored rows as the networks read them: with `--noise-resample`, a copy with fresh noise columns."""
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
        self.true_rewards = torch.zeros(capacity, device=device)  # for diagnostics only: the agent never reads it
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
        obs, next_obs = read_noisy(self.obs[idx], self.noise), read_noisy(self.next_obs[idx], self.noise)
        return Batch(obs, self.actions[idx], self.rewards[idx], next_obs, self.dones[idx], idx)


# ALGO LOGIC: initialize agent here:
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
        # the Gaussian log-density written out: torch.distributions validates its arguments, a host sync per call
        log_prob = -0.5 * eps.pow(2) - log_std - 0.5 * math.log(2 * math.pi)
        log_prob -= 2 * (math.log(2) - x - F.softplus(-2 * x))  # log|d tanh(x)/dx|, numerically stable
        return torch.tanh(x), log_prob.sum(-1), torch.tanh(mean)


@torch.no_grad()
def evaluate(actor: Actor, envs: list, device: torch.device) -> np.ndarray:
    """One deterministic episode per env, stepped in lockstep (one batched forward); returns true returns."""
    obs = np.stack([env.reset()[0] for env in envs])
    returns, running = np.zeros(len(envs)), np.ones(len(envs), dtype=bool)
    while running.any():
        actions = actor.get_action(torch.as_tensor(obs, device=device))[2].cpu().numpy()
        if not np.isfinite(actions).all():  # MuJoCo would raise on them: a NaN return, which stops the run
            return np.full(len(envs), np.nan)
        for i in np.flatnonzero(running):
            obs[i], reward, terminated, truncated, _ = envs[i].step(actions[i])
            returns[i] += reward
            running[i] = not (terminated or truncated)
    return returns


if __name__ == "__main__":
    args = tyro.cli(Args)
    try:  # bad input fails here, with one line, before any output is written
        validate_args(args)
        env = ene.make_env(args.env_id, args.seed, args.noise, args.noise_type, args.noise_histograms, args.episode_length)
    except ValueError as e:
        raise SystemExit(f"{args.exp_name}: error: {e}")
    run_name = make_run_folder(args.env_id, args.exp_name, args.seed)
    eval_envs = [
        ene.make_env(
            args.env_id, args.seed + 1000 * (i + 1), args.noise, args.noise_type, args.noise_histograms,
            args.episode_length, f"videos/{run_name}" if args.capture_video and i == 0 else None,
        )
        for i in range(args.eval_episodes)
    ]
    for i, eval_env in enumerate(eval_envs):
        eval_env.reset(seed=args.seed + 1000 * (i + 1))

    if args.track:
        import wandb

        wandb.init(
            project=args.wandb_project_name,
            entity=args.wandb_entity,
            sync_tensorboard=True,
            config=vars(args),
            name=run_name,
            monitor_gym=True,
            save_code=True,
        )
    writer = SummaryWriter(f"runs/{run_name}")
    writer.add_text(
        "hyperparameters",
        "|param|value|\n|-|-|\n%s" % ("\n".join([f"|{key}|{value}|" for key, value in vars(args).items()])),
    )

    # TRY NOT TO MODIFY: seeding
    random.seed(args.seed)
    np.random.seed(args.seed)
    torch.manual_seed(args.seed)
    torch.backends.cudnn.deterministic = args.torch_deterministic

    device = torch.device("cuda" if torch.cuda.is_available() and args.cuda else "cpu")
    if args.threads is not None or device.type == "cpu":
        torch.set_num_threads(args.threads or 1)  # several runs per machine: default threads oversubscribe the cores

    obs_dim_real, obs_dim, act_dim = env.obs_dim_real, env.observation_space.shape[0], env.action_space.shape[0]
    noise = env.noise_sampler if args.noise_resample else None

    # ALGO LOGIC: agent
    def make_critic():
        """Fresh Q1, Q2, their optimiser and targets (PEBBLE resets the critic at the first feedback round)."""
        qf1 = SoftQNetwork(obs_dim, act_dim, args.hidden_dim).to(device)
        qf2 = SoftQNetwork(obs_dim, act_dim, args.hidden_dim).to(device)
        q_optimizer = optim.Adam(list(qf1.parameters()) + list(qf2.parameters()), lr=args.q_lr)
        qf1_target = SoftQNetwork(obs_dim, act_dim, args.hidden_dim).to(device)
        qf2_target = SoftQNetwork(obs_dim, act_dim, args.hidden_dim).to(device)
        qf1_target.load_state_dict(qf1.state_dict())
        qf2_target.load_state_dict(qf2.state_dict())
        return qf1, qf2, q_optimizer, qf1_target, qf2_target

    actor = Actor(obs_dim, act_dim, args.hidden_dim).to(device)
    actor_optimizer = optim.Adam(actor.parameters(), lr=args.policy_lr)
    qf1, qf2, q_optimizer, qf1_target, qf2_target = make_critic()
    target_entropy = -float(act_dim)
    log_alpha = torch.tensor(math.log(args.init_temperature), device=device, requires_grad=True)
    alpha = log_alpha.detach().exp()
    a_optimizer = optim.Adam([log_alpha], lr=args.alpha_lr)

    # ALGO LOGIC: storage
    rb = ReplayBuffer(args.buffer_size, obs_dim, act_dim, device, noise)
    sac_updates = 0

    def sac_update(data: Batch) -> dict:
        """One SAC gradient step: critics, then actor and temperature, then Polyak targets. Losses stay on device."""
        global sac_updates
        with torch.no_grad():
            next_actions, next_log_pi, _ = actor.get_action(data.next_obs)
            next_q = torch.min(qf1_target(data.next_obs, next_actions), qf2_target(data.next_obs, next_actions))
            target_q = data.rewards + (1 - data.dones) * args.gamma * (next_q - alpha * next_log_pi)
        qf1_values, qf2_values = qf1(data.obs, data.actions), qf2(data.obs, data.actions)
        qf1_loss, qf2_loss = F.mse_loss(qf1_values, target_q), F.mse_loss(qf2_values, target_q)
        q_optimizer.zero_grad()
        (qf1_loss + qf2_loss).backward()
        q_optimizer.step()
        sac_updates += 1
        losses.update(qf1_values=qf1_values.mean().detach(), qf2_values=qf2_values.mean().detach(),
                      qf1_loss=qf1_loss.detach(), qf2_loss=qf2_loss.detach(), qf_loss=(qf1_loss + qf2_loss).detach() / 2)

        if sac_updates % args.actor_update_freq == 0:
            pi, log_pi, _ = actor.get_action(data.obs)
            actor_loss = (alpha * log_pi - torch.min(qf1(data.obs, pi), qf2(data.obs, pi))).mean()
            actor_optimizer.zero_grad()
            actor_loss.backward()
            actor_optimizer.step()
            alpha_loss = (-log_alpha.exp() * (log_pi.detach() + target_entropy)).mean()
            a_optimizer.zero_grad()
            alpha_loss.backward()
            a_optimizer.step()
            alpha.copy_(log_alpha.detach().exp())
            losses.update(actor_loss=actor_loss.detach(), alpha=alpha.clone(), alpha_loss=alpha_loss.detach())

        if sac_updates % args.target_update_freq == 0:
            with torch.no_grad():
                online = list(qf1.parameters()) + list(qf2.parameters())
                torch._foreach_lerp_(list(qf1_target.parameters()) + list(qf2_target.parameters()), online, args.tau)
        return losses

    def save_checkpoint():
        checkpoint = {
            "args": vars(args),
            "global_step": global_step + 1,
            "actor": actor.state_dict(),
            "qf1": qf1.state_dict(),
            "qf2": qf2.state_dict(),
            "log_alpha": log_alpha.detach().cpu(),
            "obs_dim_real": obs_dim_real,
            "obs_dim": obs_dim,
            "act_dim": act_dim,
        }
        torch.save(checkpoint, f"runs/{run_name}/{args.exp_name}.cleanrl_model")

    def stop_if_not_finite(values: dict):
        """A non-finite value ends the run, exit code 1, with one line naming it; the checkpoint is written first."""
        bad = next((name for name, value in values.items() if not math.isfinite(value)), None)
        if bad is not None:
            save_checkpoint()
            writer.close()
            raise SystemExit(
                f"{args.exp_name}: error: non-finite {bad} ({values[bad]}) at step {global_step}; "
                f"checkpoint for debugging: runs/{run_name}/{args.exp_name}.cleanrl_model"
            )

    # TRY NOT TO MODIFY: start the game
    start_time = time.time()
    progress = Progress(args.total_timesteps)
    obs, _ = env.reset(seed=args.seed)
    obs = torch.as_tensor(obs, device=device)
    episode_return, episode_length, losses = 0.0, 0, {}
    for global_step in range(args.total_timesteps):
        progress.update(global_step, "random" if global_step < args.learning_starts else "SAC")
        # ALGO LOGIC: put action logic here
        if global_step < args.learning_starts:
            action = torch.as_tensor(env.action_space.sample(), dtype=torch.float32, device=device)
        else:
            with torch.no_grad():
                action = actor.get_action(obs.unsqueeze(0))[0][0]

        # TRY NOT TO MODIFY: execute the game and log data.
        env_action = action.cpu().numpy()
        stop_if_not_finite({"action": float(env_action.sum())})  # on the host already: no extra sync
        next_obs, true_reward, terminated, truncated, _ = env.step(env_action)
        next_obs = torch.as_tensor(next_obs, device=device)
        rb.add(obs, action, next_obs, terminated, float(true_reward), float(true_reward))
        episode_return, episode_length = episode_return + float(true_reward), episode_length + 1
        obs = next_obs  # CRUCIAL step easy to overlook
        if terminated or truncated:
            writer.add_scalar("charts/episodic_return", episode_return, global_step)
            writer.add_scalar("charts/episodic_length", episode_length, global_step)
            obs, _ = env.reset()
            obs = torch.as_tensor(obs, device=device)
            episode_return, episode_length = 0.0, 0

        # ALGO LOGIC: training.
        if global_step >= args.learning_starts:
            sac_update(rb.sample(args.batch_size))

            if global_step % args.log_freq == 0:
                logged = dict(zip([f"losses/{name}" for name in losses], torch.stack(list(losses.values())).tolist()))
                for tag, value in logged.items():
                    writer.add_scalar(tag, value, global_step)
                stop_if_not_finite(logged)

        if (global_step + 1) % args.eval_freq == 0 or global_step + 1 == args.total_timesteps:
            eval_return = float(evaluate(actor, eval_envs, device).mean())
            sps = int((global_step + 1) / (time.time() - start_time))
            writer.add_scalar("eval/episodic_return", eval_return, global_step + 1)
            writer.add_scalar("charts/SPS", sps, global_step + 1)
            print(f"step={global_step + 1} eval_return={eval_return:.2f} SPS={sps}", flush=True)
            progress.eval_return = eval_return
            stop_if_not_finite({"eval/episodic_return": eval_return})
            if args.save_model:
                save_checkpoint()

    env.close()
    for eval_env in eval_envs:
        eval_env.close()
    writer.close()
