"""Trajectories of Meta-World tasks under metaworld's own MuJoCo (`mujoco==3.3.0`), for the parity test of
`tests/test_metaworld.py`: our stack (MuJoCo 3.17, `ene.py`'s weld mend) must reproduce them within its tolerance.

Run it in an environment of its own, with metaworld's pins and not this project:

    python3 -m venv /tmp/mw33 && /tmp/mw33/bin/pip install mujoco==3.3.0 metaworld==3.1.1 packaging
    /tmp/mw33/bin/python results/metaworld-parity/make_trajectories.py results/metaworld-parity/trajectories.npz

Each task is made as `ene.MetaWorldTask` makes it (goal observable, a new goal at each reset from the task's own
generator, seeded by `seed`), reset once, and stepped `STEPS` times with seeded uniform random actions in [-1, 1]. It
stores the observations (the reset's and each step's), rewards and success flags, with the actions and the versions.
With `--all`, every v3 task (`compare.py` then says which agree); by default the parity test's list, `TASKS`."""
import sys

import metaworld
import mujoco
import numpy as np
from metaworld.env_dict import ALL_V3_ENVIRONMENTS_GOAL_OBSERVABLE

TASKS = ("button-press-v3", "door-open-v3", "drawer-open-v3", "sweep-into-v3", "window-open-v3", "hammer-v3",
         "window-close-v3", "reach-v3", "push-v3", "plate-slide-v3")  # the parity test's list (docs/ene.md)
STEPS, SEED = 500, 7


def trajectory(name: str) -> dict:
    task = ALL_V3_ENVIRONMENTS_GOAL_OBSERVABLE[f"{name}-goal-observable"]()
    task._freeze_rand_vec, task.seeded_rand_vec = False, True
    task.seed(SEED)
    obs = [task.reset()[0]]
    actions = np.random.default_rng(SEED).uniform(-1, 1, (STEPS, *task.action_space.shape)).astype(np.float32)
    rewards, success = [], []
    for action in actions:
        o, r, _, _, info = task.step(action)
        obs.append(o)
        rewards.append(r)
        success.append(info["success"])
    return {f"{name}/obs": np.array(obs, np.float32), f"{name}/rewards": np.array(rewards),
            f"{name}/success": np.array(success, np.float32), f"{name}/actions": actions}


if __name__ == "__main__":
    path = sys.argv[1]
    names = [n.removesuffix("-goal-observable") for n in ALL_V3_ENVIRONMENTS_GOAL_OBSERVABLE] if "--all" in sys.argv \
        else TASKS
    arrays = {}
    for name in names:
        arrays.update(trajectory(name))
    np.savez_compressed(path, tasks=np.array(names), steps=STEPS, seed=SEED, mujoco=mujoco.__version__,
                        metaworld=metaworld.__version__ if hasattr(metaworld, "__version__") else "3.1.1", **arrays)
    print(f"wrote {path}: {len(names)} tasks of {STEPS} steps, MuJoCo {mujoco.__version__}")
