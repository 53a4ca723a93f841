# Docs: docs/NAME.md in r2n, the R2N paper's reference implementation (NAME: this file's name)
"""Real-feature histograms for `--noise-type imitate` (docs/make_histograms.md), from a noise-free SAC.
R2N paper: Muslimani et al., "Boosting Robustness in Preference-Based Reinforcement Learning with
Dynamic Sparsity", AAMAS 2025 (the authors' code: https://github.com/cmuslima/R2N).

The R2N paper's imitating noise (after ANF, Grooten et al., AAMAS 2023): noise feature i draws from
the histogram of real feature i mod D_obs. This command makes that histogram file from deterministic
rollouts of a noise-free SAC policy. It loads a checkpoint saved by `sac.py` trained with `--noise 0`
(`runs/{run_name}/sac.cleanrl_model`), rebuilds the actor with `sac.Actor`, runs the deterministic
policy tanh(mean) on the noise-free task and writes `ene.build_histograms(observations, --output)`:
`bin_edges (D_obs, 101)` and `probs (D_obs, 100)`, 100 equal-width bins over each feature's [min, max]
(the paper gives no bin count).

Choices where the paper is silent: the observations are those the policy acts on (the first of each episode
included, the last one after truncation not), `--num-observations` of them exactly, from consecutive
`--episode-length`-step episodes of one env seeded with `--seed` (the first `reset` seeded, later ones continue the
task's random stream), so the file is a function of checkpoint and flags. The checkpoint must be noise-free
(`obs_dim == obs_dim_real`): the histograms describe the real features as a policy that never saw noise visits
them; any script's checkpoint qualifies (all share `sac.py`'s actor), a noisy one is refused with one line.

    python sac.py --env-id cheetah-run --noise 0
    python make_histograms.py --checkpoint runs/cheetah-run__sac__1__*/sac.cleanrl_model --output cheetah-run.npz
"""
import os
from dataclasses import dataclass
from typing import Optional

import numpy as np
import torch
import tyro

import ene
import sac


@dataclass
class Args:
    checkpoint: str
    """the `.cleanrl_model` saved by `sac.py --noise 0` (a dict with `args`, `actor`, `obs_dim_real`, `obs_dim`, `act_dim`)"""
    output: Optional[str] = None
    """the histogram `.npz` to write; computed at runtime when left unset: `{env_id}_histograms.npz`"""
    num_observations: int = 10_000
    """observations collected from the rollouts (the paper's ~10 000)"""
    episode_length: int = 1000
    """environment steps per rollout episode"""
    seed: int = 1
    """seed of the rollout env (the policy is deterministic)"""
    env_id: Optional[str] = None
    """the task (dm_control or gymnasium MuJoCo); computed at runtime when left unset: the checkpoint's `--env-id`"""


def load_actor(path: str) -> tuple:
    """The checkpoint's actor (on the CPU, eval mode) and its `args` dict; ValueError with one line if unusable."""
    if not os.path.isfile(path):
        raise ValueError(f"--checkpoint: no such file: {path}")
    try:
        checkpoint = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as e:  # not a torch file, truncated, ...
        raise ValueError(f"--checkpoint: {path} is not a torch checkpoint ({type(e).__name__})") from None
    keys = ("args", "actor", "obs_dim_real", "obs_dim", "act_dim")
    if not (isinstance(checkpoint, dict) and all(key in checkpoint for key in keys) and isinstance(checkpoint["args"], dict)):
        raise ValueError(f"--checkpoint: {path} is not a checkpoint of sac.py (expected the keys {', '.join(keys)})")
    obs_dim_real, obs_dim, act_dim = checkpoint["obs_dim_real"], checkpoint["obs_dim"], checkpoint["act_dim"]
    if obs_dim != obs_dim_real:
        raise ValueError(
            f"--checkpoint: {path} was trained with noise ({obs_dim - obs_dim_real} noise features); histograms need "
            f"a noise-free policy: train one with `python sac.py --noise 0`"
        )
    actor = sac.Actor(obs_dim, act_dim, checkpoint["args"].get("hidden_dim", 1024),
                      checkpoint["args"].get("hidden_layers", 2))
    try:
        actor.load_state_dict(checkpoint["actor"])
    except Exception:  # another architecture or width
        raise ValueError(f"--checkpoint: {path} holds an actor that does not fit sac.Actor({obs_dim}, {act_dim})") from None
    return actor.eval(), checkpoint["args"]


@torch.no_grad()
def rollout_observations(actor: sac.Actor, env, num_observations: int, seed: int) -> tuple:
    """The first `num_observations` observations the deterministic policy acts on, (N, D) float32, over consecutive
    episodes (the first `reset` seeded with `seed`); also the true returns of the episodes completed on the way."""
    observations, returns, episode_return = [], [], 0.0
    obs, _ = env.reset(seed=seed)
    while len(observations) < num_observations:
        observations.append(obs)
        action = actor.get_action(torch.as_tensor(obs).unsqueeze(0))[2][0].numpy()
        obs, reward, terminated, truncated, _ = env.step(action)
        episode_return += float(reward)
        if terminated or truncated:
            returns.append(episode_return)
            obs, episode_return = env.reset()[0], 0.0
    return np.stack(observations), returns


def main(args: Args) -> str:
    """Check the flags and the checkpoint, roll out, write the histograms; returns the output path."""
    if args.num_observations < 2:
        raise ValueError(f"--num-observations must be >= 2, got {args.num_observations}")
    if args.output is not None and not args.output.endswith(".npz"):
        raise ValueError(f"--output must end in .npz (numpy would append it), got {args.output}")
    actor, train_args = load_actor(args.checkpoint)
    env_id = args.env_id or train_args.get("env_id")
    env = ene.make_env(env_id, args.seed, noise=0.0, episode_length=args.episode_length)
    if env.obs_dim_real != actor.net[0].in_features:
        raise ValueError(
            f"--env-id {env_id} has {env.obs_dim_real} observation features, the checkpoint's actor reads "
            f"{actor.net[0].in_features}"
        )
    output = args.output or f"{env_id}_histograms.npz"
    observations, returns = rollout_observations(actor, env, args.num_observations, args.seed)
    env.close()
    if os.path.dirname(output):
        os.makedirs(os.path.dirname(output), exist_ok=True)
    ene.build_histograms(observations, output)
    mean_return = f"{np.mean(returns):.2f}" if returns else "n/a (no episode completed)"
    print(
        f"wrote {output}: {observations.shape[1]} features x {ene.HISTOGRAM_BINS} bins from {len(observations)} "
        f"observations of {env_id}; mean return of the {len(returns)} complete episodes {mean_return}",
        flush=True,
    )
    return output


if __name__ == "__main__":
    torch.set_num_threads(1)
    cli_args = tyro.cli(Args)
    try:
        main(cli_args)
    except ValueError as e:
        raise SystemExit(f"make_histograms: error: {e}")
