"""How much the oracles' trained networks answer to the noise columns alone (the stop rule's bug search).

`python results/stored-noise/noise_sensitivity.py SCRATCH [--episodes 1] [--redraws 8]`: SCRATCH is the study's
working folder (`logs/scratch` of the `benchmark.py` call that ran it), which keeps each run's checkpoint. For every
finished oracle run there (`sac_stored_noise`, `anf_sac_stored_noise`), it loads the final checkpoint, runs the
deterministic policy for `--episodes` episodes of cheetah-run at noise 0.9, and at every visited state draws the
noise columns again `--redraws` times, the real features kept. Per run, the share of the variance that is the
redraws' (the mean over states of the variance across redraws, over the whole variance of states and redraws):
- of the deterministic action (per action dimension, then averaged);
- of Q1 at the action the policy took.
A network that reads only the real features has a share of 0. Prints a markdown table."""
import argparse
import glob
import importlib
import os
import sys

import numpy as np
import torch

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, ROOT)
import ene  # noqa: E402

ARMS = {"sac_stored_noise": "sac", "anf_sac_stored_noise": "anf_sac"}


def noise_share(values: np.ndarray) -> float:
    """values (states, redraws, dims): the redraws' share of the variance, averaged over dims."""
    within = values.var(axis=1).mean(axis=0)
    total = values.reshape(-1, values.shape[-1]).var(axis=0)
    return float((within / total).mean())


@torch.no_grad()
def sensitivity(checkpoint_path: str, script: str, episodes: int, redraws: int, seed: int) -> dict:
    module = importlib.import_module(script)
    checkpoint = torch.load(checkpoint_path, map_location="cpu", weights_only=False)
    args = checkpoint["args"]
    obs_dim, act_dim = checkpoint["obs_dim"], checkpoint["act_dim"]
    actor = module.Actor(obs_dim, act_dim, args["hidden_dim"], args.get("hidden_layers", 2))
    actor.load_state_dict(checkpoint["actor"])
    qf1 = module.SoftQNetwork(obs_dim, act_dim, args["hidden_dim"], args.get("hidden_layers", 2))
    qf1.load_state_dict(checkpoint["qf1"])
    env = ene.make_env(args["env_id"], seed=seed, noise=args["noise"])
    rng = np.random.default_rng(seed + 1)
    real, states, returns = env.obs_dim_real, [], []
    for episode in range(episodes):
        obs, _ = env.reset(seed=seed + episode)
        done, total = False, 0.0
        while not done:
            states.append(obs)
            action = actor.get_action(torch.as_tensor(obs).unsqueeze(0))[2][0].numpy()
            obs, reward, terminated, truncated, _ = env.step(action)
            total += reward
            done = terminated or truncated
        returns.append(total)
    states = np.stack(states)
    redrawn = np.repeat(states[:, None, :], redraws, axis=1)
    redrawn[..., real:real + env.n_noise] = env.noise_sampler.sample(rng, (len(states), redraws))
    flat = torch.as_tensor(redrawn.reshape(-1, obs_dim))
    actions = actor.get_action(flat)[2].reshape(len(states), redraws, act_dim)
    taken = actor.get_action(torch.as_tensor(states))[2]
    q = qf1(flat, taken.repeat_interleave(redraws, 0)).reshape(len(states), redraws, 1)
    return dict(action=noise_share(actions.numpy()), q=noise_share(q.numpy()), ret=float(np.mean(returns)),
                states=len(states))


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("scratch")
    parser.add_argument("--episodes", type=int, default=1)
    parser.add_argument("--redraws", type=int, default=8)
    parser.add_argument("--seed", type=int, default=12345)
    args = parser.parse_args()
    torch.set_num_threads(1)
    print("| run | states | return of the deterministic policy | redraws' share of the action's variance | "
          "of Q1's |")
    print("|---|---|---|---|---|")
    for arm, script in ARMS.items():
        for folder in sorted(glob.glob(os.path.join(args.scratch, f"{arm}__*"))):
            run_id = os.path.basename(folder)
            found = glob.glob(os.path.join(folder, "runs", run_id, "*.cleanrl_model"))
            if not os.path.exists(os.path.join(folder, "runs", run_id, "state.pt")) and found:
                result = sensitivity(found[0], script, args.episodes, args.redraws, args.seed)
                print(f"| {run_id} | {result['states']} | {result['ret']:.1f} | {result['action']:.3f} | "
                      f"{result['q']:.3f} |")


if __name__ == "__main__":
    main()
