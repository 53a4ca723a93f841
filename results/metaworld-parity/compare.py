"""Our stack against trajectories made under metaworld's own MuJoCo (`make_trajectories.py`): for each task, the
largest difference of the observations (the reset's and every step's), of the rewards, and the steps whose success
flags differ. From the repository root, in this project's environment:

    python results/metaworld-parity/compare.py /tmp/all.npz    # a file made with make_trajectories.py --all

`all-tasks.txt` is its output for every v3 task; `tests/test_metaworld.py` holds the listed tasks to a tolerance."""
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
import ene  # noqa: E402


def replay(reference, name: str) -> tuple:
    """(observations, rewards, success flags) of our env on the reference's seed and actions, noise 0."""
    seed, steps = int(reference["seed"]), int(reference["steps"])
    env = ene.make_env(name, seed, 0.0, episode_length=steps)
    obs, rewards, success = [env.reset(seed=seed)[0]], [], []
    for action in reference[f"{name}/actions"]:
        o, r, _, _, info = env.step(action)
        obs.append(o)
        rewards.append(r)
        success.append(info["success"])
    env.close()
    return np.array(obs), np.array(rewards), np.array(success, np.float32)


def differences(reference, name: str) -> dict:
    obs, rewards, success = replay(reference, name)
    return {"obs": float(np.abs(obs - reference[f"{name}/obs"]).max()),
            "first_obs": float(np.abs(obs[0] - reference[f"{name}/obs"][0]).max()),
            "reward": float(np.abs(rewards - reference[f"{name}/rewards"]).max()),
            "success_steps": int((success != reference[f"{name}/success"]).sum())}


if __name__ == "__main__":
    reference = np.load(sys.argv[1])
    rows = sorted(((differences(reference, str(name)), str(name)) for name in reference["tasks"]),
                  key=lambda row: row[0]["obs"])
    print(f"# {len(rows)} tasks, {int(reference['steps'])} steps, seed {int(reference['seed'])}; reference MuJoCo "
          f"{reference['mujoco']}, ours {__import__('mujoco').__version__}")
    print("| task | observation | first observation | reward | steps whose success differs |\n|---|---|---|---|---|")
    for d, name in rows:
        print(f"| {name} | {d['obs']:.2e} | {d['first_obs']:.1e} | {d['reward']:.2e} | {d['success_steps']} |")
