"""metaworld's scripted drawer-open policy through `ene.make_env`, at noise 0 and 0.9: does the ENE's Meta-World path
(reset, goal, actions, 500-step episodes, the success flag) let a policy that can open the drawer open it?"""
import numpy as np
from metaworld.policies import SawyerDrawerOpenV3Policy

import ene

policy = SawyerDrawerOpenV3Policy()
for noise in (0.0, 0.9):
    returns, successes, firsts = [], [], []
    for i in range(10):
        seed = 1 + 1000 * (i + 1)  # sac.py's evaluation seeds at --seed 1
        env = ene.make_env("drawer-open-v3", seed, noise, episode_length=500)
        obs, _ = env.reset(seed=seed)
        total, first, steps = 0.0, None, 0
        for t in range(500):
            # the policy reads the 39 real features, which come first; the noise features follow them
            action = np.clip(policy.get_action(obs[:39].astype(np.float64)), -1, 1).astype(np.float32)
            obs, reward, terminated, truncated, info = env.step(action)
            total, steps = total + reward, steps + 1
            if info["success"] and first is None:
                first = t + 1
            if terminated or truncated:
                break
        returns.append(total)
        successes.append(first is not None)
        firsts.append(first)
    print(f"noise {noise}: {env.observation_space.shape[0]} features, success rate {np.mean(successes):.2f}, "
          f"mean return {np.mean(returns):.1f}, episodes of {steps} steps, first success at steps {firsts}")
