"""Where a saved `sac.py` policy gets to on drawer-open-v3: its 10 deterministic evaluation episodes (sac.py's
evaluation seeds at --seed 1), with metaworld's own measures of each step (`info`). The drawer is open, and the
episode a success, once `obj_to_target` is at most 0.03.
Usage: python rollout.py runs/<run>/sac.cleanrl_model"""
import sys

import numpy as np
import torch

import ene
import sac

torch.set_num_threads(1)
checkpoint = torch.load(sys.argv[1], weights_only=False)
args = checkpoint["args"]
actor = sac.Actor(checkpoint["obs_dim"], checkpoint["act_dim"], args["hidden_dim"], args["hidden_layers"])
actor.load_state_dict(checkpoint["actor"])
print(f"{sys.argv[1]}: step {checkpoint['global_step']}, noise {args['noise']}")
for i in range(10):
    seed = args["seed"] + 1000 * (i + 1)
    env = ene.make_env(args["env_id"], seed, args["noise"], args["noise_type"],
                       episode_length=args["episode_length"])
    obs, _ = env.reset(seed=seed)
    total, distances, near = 0.0, [], []
    for _ in range(args["episode_length"]):
        with torch.no_grad():
            mean, _ = actor(torch.as_tensor(obs[None]))
        obs, reward, terminated, truncated, info = env.step(torch.tanh(mean)[0].numpy())
        total += reward
        distances.append(info["obj_to_target"])
        near.append(info["near_object"])
    print(f"episode {i}: return {total:.0f}, drawer to target {distances[0]:.3f} at the start, closest "
          f"{min(distances):.3f}, {distances[-1]:.3f} at the end; hand near the handle at {np.mean(near):.0%} of steps")
