# docs: docs/ene.md
"""Extremely Noisy Environment (ENE), the one module every script shares.

An ENE (Grooten et al., "Automatic Noise Filtering with Dynamic Sparse Training in Deep RL", AAMAS 2023) takes a
dm_control task (`cheetah-run`) or a gymnasium MuJoCo task (`HalfCheetah-v5`) and appends task-irrelevant features to
its observation, so that a fraction `noise` of all features is noise:

    D_total = ceil(D_obs / (1 - noise))  (plain float arithmetic),  N_noise = D_total - D_obs

which reproduces the R2N paper's table exactly: cartpole 5 -> 51, walker 24 -> 241, cheetah 17 -> 171,
quadruped 78 -> 260 (the paper prints 68 by mistake), humanoid 67 -> 224.

Episodes have exactly `episode_length` steps, truncated, never terminated: reward learning cuts segments from whole
episodes. Gymnasium tasks that end an episode when the body falls run with `terminate_when_unhealthy=False`.

Noise features are i.i.d. N(0, 1) (`noise_type="gaussian"`) or imitate the real features (`"imitate"`: noise
feature i draws from the histogram of real feature i mod D_obs). Real features come first, noise after, no shuffle.

What the scripts use:
* `make_env(...)`: the wrapped env; `env.obs_dim_real`, `env.n_noise`, `env.noise_sampler` tell which columns are
  real (`0 .. obs_dim_real - 1`) and how to draw noise.
* `NoiseSampler.refresh_(x)`: the read-time noise redraw behind `--noise-resample`, ANF's code's variant. It
  overwrites the noise columns of stored observations (or of `[obs, action]` rows: the noise columns are the same)
  with fresh noise. By default the scripts do not call it: an observation keeps the noise the environment returned,
  as any environment's would in a buffer (B-Pref's included).
* `build_histograms(observations, path)` / `load_histograms(path)`: the `.npz` used by `--noise-type imitate`.
* `check_env_args(...)`: the input checks, raising `ValueError` with one line that names the flag.
* `env.rng_state()` / `env.set_rng_state(...)` and `replay_episode(...)`: the env's part of a script's `state.pt`.
* `EnvProcess(...)`: `make_env` in a process of its own; `step_async` / `step_wait` step several at once (evaluation).
* `env.physics_state()` and `render_states(env_id, states)`: the stored physics of queried segments, drawn again.
"""

import atexit
import dataclasses
import inspect
import logging
import math
import multiprocessing
import os
import signal
import warnings
from typing import Optional

import gymnasium as gym
import numpy as np
import torch

# dm_control tries the GLFW renderer first and GLFW warns when there is no display; headless runs need no renderer
# (set MUJOCO_GL=egl or osmesa to record videos), so the warning is only noise in every run's console.
warnings.filterwarnings("ignore", message=".*The DISPLAY environment variable is missing")
# gymnasium's half_cheetah.xml uses `settotalmass`, which MuJoCo deprecates: MuJoCo warns (through dm_control's absl
# logger) at every load of the model. It is gymnasium's to fix, not the user's.
logging.getLogger("absl").addFilter(lambda record: "'settotalmass' is deprecated" not in record.getMessage())

HISTOGRAM_BINS = 100
NOISE_TYPES = ("gaussian", "imitate")
GYM_EXAMPLES = ("HalfCheetah-v5", "Hopper-v5", "Walker2d-v5", "Ant-v5", "Humanoid-v5")  # ANF's tasks
# Meta-World tasks PEBBLE, SURF and RUNE report (v3 of their v2 tasks); every v3 task of metaworld 3.1.1 runs
METAWORLD_EXAMPLES = ("button-press-v3", "door-open-v3", "drawer-open-v3", "sweep-into-v3", "window-open-v3")
METAWORLD_INSTALL = "pip install --no-deps metaworld==3.1.1"


def total_obs_dim(obs_dim_real: int, noise: float) -> int:
    """Features seen by the agent for a noise fraction `noise` (ANF's formula, float64 ceil on purpose)."""
    return math.ceil(obs_dim_real / (1.0 - noise))


def num_noise_features(obs_dim_real: int, noise: float) -> int:
    """Number of noise features appended to `obs_dim_real` real ones."""
    return total_obs_dim(obs_dim_real, noise) - obs_dim_real


def dmc_tasks() -> list[str]:
    """All dm_control suite tasks as short ids (`cheetah-run`, `ball_in_cup-catch`, ...)."""
    from dm_control import suite

    return [f"{domain}-{task}" for domain, task in suite.ALL_TASKS]


def gym_mujoco_class(env_id: str) -> Optional[type]:
    """The class gymnasium registers as `env_id` if it is a MuJoCo task (`HalfCheetah-v5`), else None."""
    from gymnasium.envs.mujoco import MujocoEnv  # imports mujoco: not before a caller has set MUJOCO_GL

    spec = gym.registry.get(env_id)
    if spec is None:
        return None
    creator = spec.entry_point  # a class, a function, or the "module:name" of one
    if isinstance(creator, str):
        try:
            creator = gym.envs.registration.load_env_creator(creator)
        except Exception:  # a family whose dependencies are not installed (Box2D, ...)
            return None
    if isinstance(creator, type) and issubclass(creator, MujocoEnv):
        return creator
    return None  # another family, or MuJoCo's v2 and v3, which need mujoco-py


# Each suite's SAC settings, taken by the flags a run leaves unset (`suite_settings`). The scripts' flags give the
# same names. A flag set on the command line always wins.
SUITE_SETTINGS = {
    # The R2N paper's, tuned on dm_control (B-Pref's SAC at the paper's width): every committed run used them.
    "dm_control": dict(episode_length=1000, hidden_dim=1024, hidden_layers=2, batch_size=1024, policy_lr=1e-4,
                       q_lr=1e-4, alpha_lr=1e-4, init_temperature=0.1, target_update_freq=2),
    # B-Pref's Meta-World scripts: 3 x 256, batch 512, learning rates 3e-4 (the temperature's stays 1e-4),
    # 500-step episodes.
    "metaworld": dict(episode_length=500, hidden_dim=256, hidden_layers=3, batch_size=512, policy_lr=3e-4,
                      q_lr=3e-4, alpha_lr=1e-4, init_temperature=0.1, target_update_freq=2),
    # CleanRL's for gymnasium MuJoCo (its sac_continuous_action.py): 2 x 256, batch 256, learning rates 3e-4 (policy)
    # and 1e-3 (critics, temperature) from a temperature of 1, targets every step. ANF's (one rate 1e-3, batch 100,
    # L2 2e-4, a fixed temperature 0.2) learn far worse in 100 000 steps: results/suite-settings.
    "gymnasium": dict(episode_length=1000, hidden_dim=256, hidden_layers=2, batch_size=256, policy_lr=3e-4,
                      q_lr=1e-3, alpha_lr=1e-3, init_temperature=1.0, target_update_freq=1),
}


def suite(env_id: str) -> str:
    """The suite of a task's name: `metaworld`, `gymnasium` or `dm_control` (also for a name that is none: the
    input checks then name it)."""
    if is_metaworld_name(env_id):
        return "metaworld"
    return "gymnasium" if gym.registry.get(env_id) is not None else "dm_control"


def suite_settings(args):
    """A script's `args` with each SAC setting it leaves unset (None) taken from its task's suite
    (`SUITE_SETTINGS`)."""
    settings = SUITE_SETTINGS[suite(args.env_id)]
    return dataclasses.replace(args, **{key: value for key, value in settings.items() if getattr(args, key) is None})


def metaworld_tasks() -> list[str]:
    """Meta-World's v3 tasks with the goal in the observation (B-Pref's), by name (`button-press-v3`); [] without
    metaworld installed."""
    import importlib.util

    if importlib.util.find_spec("metaworld") is None:
        return []
    return [name.removesuffix("-goal-observable") for name in metaworld_classes()]


def is_metaworld_name(env_id: str) -> bool:
    """Whether `env_id` reads as a Meta-World task's name (lower case, `-v3`), metaworld installed or not."""
    return env_id.endswith("-v3") and env_id == env_id.lower() and gym.registry.get(env_id) is None


def metaworld_classes() -> dict:
    """metaworld's goal-observable task classes by name, with MuJoCo's weld rows mended (`mend_mocap_welds`)."""
    import metaworld.env_dict
    import metaworld.sawyer_xyz_env
    import mujoco

    base = metaworld.sawyer_xyz_env.SawyerMocapBase
    if mujoco.mjNEQDATA > len(METAWORLD_WELD) and base.reset_mocap_welds is not mend_mocap_welds:
        base.reset_mocap_welds = mend_mocap_welds
    return metaworld.env_dict.ALL_V3_ENVIRONMENTS_GOAL_OBSERVABLE


# The numbers metaworld 3.1.1 writes into each weld constraint: MuJoCo 3.3.0's 11 (anchor, relative pose, torque
# scale). MuJoCo 3.17's weld rows hold 12 (mjNEQDATA), so metaworld's own write fails at every task's creation.
METAWORLD_WELD = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, 5.0])


def mend_mocap_welds(self) -> None:
    """metaworld's `SawyerMocapBase.reset_mocap_welds`, writing its 11 numbers into the first 11 columns of each weld
    row. The 12th keeps the value MuJoCo loaded from the model. Installed only where MuJoCo's rows are longer."""
    import mujoco

    if self.model.nmocap > 0 and self.model.eq_data is not None:
        for i in range(self.model.eq_data.shape[0]):
            if self.model.eq_type[i] == mujoco.mjtEq.mjEQ_WELD:
                self.model.eq_data[i, : len(METAWORLD_WELD)] = METAWORLD_WELD


def gym_mujoco_tasks() -> list[str]:
    """Every gymnasium MuJoCo task registered (`HalfCheetah-v5`, `Hopper-v4`, ...)."""
    return [env_id for env_id in gym.registry if gym_mujoco_class(env_id) is not None]


def load_histograms(path: str) -> dict:
    """Load and validate a histogram file: `bin_edges (D, 101)` increasing, `probs (D, 100)` rows summing to 1."""
    if not os.path.isfile(path):
        raise ValueError(f"--noise-histograms: no such file: {path}")
    try:
        with np.load(path) as data:
            edges, probs = np.asarray(data["bin_edges"], np.float64), np.asarray(data["probs"], np.float64)
    except Exception as e:  # a zip that is not an npz, a missing key, ...
        raise ValueError(f"--noise-histograms: {path} is not a histogram .npz with bin_edges and probs ({e})") from None
    if probs.ndim != 2 or edges.shape != (probs.shape[0], probs.shape[1] + 1) or probs.shape[0] == 0:
        raise ValueError(
            f"--noise-histograms: {path} has bin_edges {edges.shape} and probs {probs.shape}; expected (D, B+1) and (D, B)"
        )
    if not (np.all(np.isfinite(edges)) and np.all(np.diff(edges, axis=1) >= 0)):
        raise ValueError(f"--noise-histograms: {path} has bin_edges that are not finite and non-decreasing")
    if np.any(probs < 0) or not np.allclose(probs.sum(1), 1.0, atol=1e-6):
        raise ValueError(f"--noise-histograms: {path} has probs that are negative or do not sum to 1 per feature")
    return {"bin_edges": edges, "probs": probs}


def build_histograms(observations: np.ndarray, path: Optional[str] = None, bins: int = HISTOGRAM_BINS) -> dict:
    """Per-feature histograms of real observations (N, D): `bins` equal-width bins over [min, max]; saved if `path`."""
    observations = np.asarray(observations, np.float64)
    if observations.ndim != 2 or len(observations) < 2:
        raise ValueError(f"build_histograms needs observations of shape (N >= 2, D), got {observations.shape}")
    edges = np.empty((observations.shape[1], bins + 1))
    probs = np.empty((observations.shape[1], bins))
    for i, column in enumerate(observations.T):
        low, high = column.min(), column.max()
        if high <= low:  # a constant feature: one narrow bin around its value
            low, high = low - 0.5e-6, high + 0.5e-6
        counts, edges[i] = np.histogram(column, bins=bins, range=(low, high))
        probs[i] = counts / counts.sum()
    histograms = {"bin_edges": edges, "probs": probs}
    if path is not None:
        np.savez(path, **histograms)
    return histograms


class NoiseSampler:
    """Draws the noise features: N(0, 1), or bin-then-uniform from the histogram of real feature i mod D_obs."""

    def __init__(self, obs_dim_real: int, n_noise: int, noise_type: str = "gaussian", histograms: Optional[dict] = None):
        self.obs_dim_real, self.n_noise, self.noise_type = obs_dim_real, n_noise, noise_type
        if noise_type == "imitate":
            if histograms["probs"].shape[0] != obs_dim_real:
                raise ValueError(
                    f"--noise-histograms describe {histograms['probs'].shape[0]} features, the task has {obs_dim_real}"
                )
            source = np.arange(n_noise) % obs_dim_real  # noise feature i imitates real feature i mod D_obs
            cdf = np.cumsum(histograms["probs"][source], axis=1)
            self.cdf = cdf / cdf[:, -1:]  # exact 1.0 at the end, so every uniform draw finds a bin
            self.edges = histograms["bin_edges"][source]
            # one sorted array for all features (feature i shifted by 2i) lets one searchsorted serve them all
            self.offsets = 2.0 * np.arange(n_noise)[:, None]
            self.flat_cdf = (self.cdf + self.offsets).ravel()
            self._torch_cache = {}

    def sample(self, rng: np.random.Generator, batch_shape: tuple = ()) -> np.ndarray:
        """Noise of shape (*batch_shape, n_noise), float32, from a numpy generator."""
        shape = (*batch_shape, self.n_noise)
        if self.noise_type == "gaussian":
            return rng.standard_normal(shape, dtype=np.float32)
        u = rng.random((self.n_noise, math.prod(batch_shape)))
        n_bins = self.cdf.shape[1]
        bins = np.searchsorted(self.flat_cdf, u + self.offsets, side="right") - n_bins * np.arange(self.n_noise)[:, None]
        bins = np.minimum(bins, n_bins - 1)
        low = np.take_along_axis(self.edges, bins, 1)
        high = np.take_along_axis(self.edges, bins + 1, 1)
        values = low + rng.random(low.shape) * (high - low)
        return values.T.reshape(shape).astype(np.float32)

    def sample_torch(self, batch_shape: tuple, device: torch.device) -> torch.Tensor:
        """Noise of shape (*batch_shape, n_noise), float32, on `device`, from torch's generator."""
        shape = (*batch_shape, self.n_noise)
        if self.noise_type == "gaussian":
            return torch.randn(shape, device=device)
        if device not in self._torch_cache:
            self._torch_cache[device] = (torch.as_tensor(self.cdf, device=device), torch.as_tensor(self.edges, device=device))
        cdf, edges = self._torch_cache[device]
        u = torch.rand(self.n_noise, math.prod(batch_shape), device=device, dtype=cdf.dtype)
        bins = torch.searchsorted(cdf, u, right=True).clamp_(max=cdf.shape[1] - 1)
        low, high = edges.gather(1, bins), edges.gather(1, bins + 1)
        values = low + torch.rand_like(low) * (high - low)
        return values.T.reshape(shape).float()

    def refresh_(self, x: torch.Tensor) -> torch.Tensor:
        """Overwrite the noise columns of stored rows `x[..., obs_dim_real : obs_dim_real + n_noise]` in place."""
        if self.n_noise:
            x[..., self.obs_dim_real : self.obs_dim_real + self.n_noise] = self.sample_torch(x.shape[:-1], x.device)
        return x


class NoisyObservation(gym.ObservationWrapper):
    """Appends fresh noise features to every observation (`reset` and `step`), from its own seeded generator."""

    def __init__(self, env: gym.Env, sampler: NoiseSampler, seed: int):
        super().__init__(env)
        self.noise_sampler, self.obs_dim_real, self.n_noise = sampler, sampler.obs_dim_real, sampler.n_noise
        self.noise_rng = np.random.default_rng(seed)
        dim = self.obs_dim_real + self.n_noise
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (dim,), np.float32)

    def observation(self, observation):
        return np.concatenate([observation, self.noise_sampler.sample(self.noise_rng)]).astype(np.float32)

    def rng_state(self) -> dict:
        """Every generator of the env: the task's (initial states), the noise features' and the action space's."""
        task_rng = self.unwrapped.np_random  # dm_control's is a RandomState, gymnasium's a Generator
        task = task_rng.bit_generator.state if isinstance(task_rng, np.random.Generator) else task_rng.get_state()
        return {"task": task, "noise": self.noise_rng.bit_generator.state,
                "action_space": self.action_space.np_random.bit_generator.state}

    def set_rng_state(self, state: dict):
        task_rng = self.unwrapped.np_random
        if isinstance(task_rng, np.random.Generator):
            task_rng.bit_generator.state = state["task"]
        else:
            task_rng.set_state(state["task"])
        self.noise_rng.bit_generator.state = state["noise"]
        self.action_space.np_random.bit_generator.state = state["action_space"]

    def physics_state(self) -> np.ndarray:
        """The MuJoCo state of the current step (qpos, qvel, act): what `render_states` needs to draw it again."""
        if hasattr(self.unwrapped, "_env"):  # a dm_control task, through shimmy
            return self.unwrapped._env.physics.get_state().copy()
        return mujoco_state(self.unwrapped.model, self.unwrapped.data)

    def step_async(self, action):
        """`step_async(action)` then `step_wait()` is `step(action)`: the interface of `EnvProcess`, which steps in a
        process of its own, so that a script steps several envs at once whichever kind they are."""
        self.pending_action = action

    def step_wait(self):
        return self.step(self.pending_action)


class EnvProcess:
    """`make_env(*args)` in a process of its own, for stepping several envs at once: `step_async(action)` on each,
    then `step_wait()` on each. `reset`, `step`, `rng_state`, `set_rng_state` and `close` are the env's, so a script
    uses it as the env, for exact resume too; an error in the env's process is raised here, with its message."""

    def __init__(self, *args):
        context = multiprocessing.get_context("spawn")  # forking a process that holds a CUDA context is unsafe
        self.pipe, child = context.Pipe()
        self.process = context.Process(target=serve_env, args=(child, args), daemon=True)
        self.process.start()
        child.close()
        # at exit, before multiprocessing joins its daemons: they ignore SIGTERM and end when the pipe closes
        atexit.register(self.pipe.close)

    def call(self, method: str, *args):
        self.pipe.send((method, args))
        return self.step_wait()

    def reset(self, seed: Optional[int] = None):
        return self.call("reset", seed)

    def step(self, action):
        return self.call("step", action)

    def step_async(self, action):
        self.pipe.send(("step", (action,)))

    def step_wait(self):
        try:
            failed, result = self.pipe.recv()
        except EOFError:
            raise RuntimeError(f"the env's process ended (exit code {self.process.exitcode})") from None
        if failed:
            raise RuntimeError(f"the env's process: {result}")
        return result

    def rng_state(self) -> dict:
        return self.call("rng_state")

    def set_rng_state(self, state: dict):
        self.call("set_rng_state", state)

    def close(self):
        self.call("close")
        self.pipe.close()
        self.process.join(timeout=30)
        if self.process.is_alive():
            self.process.kill()


def serve_env(pipe, args: tuple):
    """The loop of an `EnvProcess`: run the env's method named in each message, send back (failed, result)."""
    for stop in (signal.SIGINT, signal.SIGTERM, signal.SIGUSR2):  # the script's to handle (a cluster signals them all);
        signal.signal(stop, signal.SIG_IGN)  # it still needs its envs to save its state, and they end when it does
    try:
        env = make_env(*args)
    except Exception as e:  # told at the first call
        pipe.send((True, f"{type(e).__name__}: {e}"))
        return
    while True:
        try:
            method, args = pipe.recv()
        except EOFError:  # the script is gone (killed): so is the env
            return
        try:
            result = env.reset(seed=args[0]) if method == "reset" else getattr(env, method)(*args)
            pipe.send((False, result))
        except Exception as e:
            pipe.send((True, f"{type(e).__name__}: {e}"))
        if method == "close":
            return


def render_states(env_id: str, states: np.ndarray, height: int = 240, width: int = 320, physics=None) -> np.ndarray:
    """Frames (T, height, width, 3) uint8 of the physics `states` (T, D) of task `env_id`: from camera 0 (dm_control)
    or the model's tracking camera, as in videos (gymnasium). Needs a renderer: on a machine without a display set
    `MUJOCO_GL=egl` (or `osmesa`) before the first import of dm_control or mujoco. `physics`: a dm_control task's
    physics to draw with, kept by a caller that draws many clips (its renderer is made once); else one is made."""
    if env_id not in dmc_tasks():
        return render_gym_states(env_id, states, height, width)
    if physics is None:
        physics = dmc_physics(env_id)
    frames = []
    for state in states:
        with physics.reset_context():  # sets the state and recomputes positions for drawing
            physics.set_state(state)
        frames.append(physics.render(height, width, camera_id=0))
    return np.stack(frames)


def dmc_physics(env_id: str):
    """A dm_control task's physics, for `render_states`."""
    from dm_control import suite

    domain, task = env_id.split("-", 1)
    return suite.load(domain, task).physics


def render_gym_states(env_id: str, states: np.ndarray, height: int, width: int) -> np.ndarray:
    """`render_states` of a gymnasium MuJoCo or Meta-World task, with the camera of its videos."""
    meta = gym_mujoco_class(env_id) is None
    env = MetaWorldTask(env_id, 1, None) if meta else make_gym_task(env_id, 1)
    draw = MujocoFrames(env.unwrapped, height, width, *(("corner", True) if meta else ()))
    frames = np.stack([draw(state) for state in states])
    draw.close()
    env.close()
    return frames


def mujoco_state(model, data) -> np.ndarray:
    """The physics state (qpos, qvel, act: MuJoCo's mjSTATE_PHYSICS) of a gymnasium MuJoCo task."""
    import mujoco

    state = np.empty(mujoco.mj_stateSize(model, mujoco.mjtState.mjSTATE_PHYSICS))
    mujoco.mj_getState(model, data, state, mujoco.mjtState.mjSTATE_PHYSICS)
    return state


class MujocoFrames:
    """Frames of the physics states of a gymnasium MuJoCo task, from the model's tracking camera ("track"; in a model
    without one, gymnasium's free camera, placed from the model's initial state), or of a Meta-World task from its
    fixed "corner" camera. Meta-World's cameras draw upside down: `upright` flips their frames (Metaworld#516).

    It draws on an MjData of its own, set to the state: after a step, the task's own MjData holds the positions of the
    last substep's start, a little behind the state. So videos and the labelling page draw a state the same way."""

    def __init__(self, task, height: int, width: int, camera: str = "track", upright: bool = False):
        import mujoco
        from gymnasium.envs.mujoco.mujoco_rendering import MujocoRenderer

        self.model, self.upright = task.model, upright
        self.data = mujoco.MjData(self.model)
        mujoco.mj_forward(self.model, self.data)  # the model's initial state, positions included
        self.model.vis.global_.offwidth = max(self.model.vis.global_.offwidth, width)  # the frame fits the buffer
        self.model.vis.global_.offheight = max(self.model.vis.global_.offheight, height)
        config = task.mujoco_renderer.default_cam_config
        self.renderer = MujocoRenderer(self.model, self.data, config, width, height, camera_name=camera)
        self.renderer.render("rgb_array")  # a free camera is placed at the first frame: here, at the initial state

    def __call__(self, state: np.ndarray) -> np.ndarray:
        import mujoco

        mujoco.mj_setState(self.model, self.data, np.asarray(state, np.float64), mujoco.mjtState.mjSTATE_PHYSICS)
        mujoco.mj_forward(self.model, self.data)  # positions for drawing
        # another renderer of the process may have made its own GL context current, or freed it and left none
        self.renderer.viewer.make_context_current()
        frame = self.renderer.render("rgb_array")
        return np.ascontiguousarray(frame[::-1]) if self.upright else frame

    def close(self):
        # MuJoCo's drawing context deletes its GL objects in whichever GL context is current when it is garbage
        # collected, maybe another renderer's: it deletes them now, in its own
        self.renderer.viewer.make_context_current()
        self.renderer.viewer.con.free()
        self.renderer.close()


def replay_episode(env: NoisyObservation, seed: int, episode_start: Optional[dict], actions: list) -> np.ndarray:
    """Bring a fresh env to where a saved one was, for exact resume: its seeded first reset (`episode_start` None) or
    a reset from the generators saved at the episode's start, then the episode's actions again (MuJoCo is
    deterministic, so the physics, the noise stream and the last observation are those of the saved env)."""
    obs, _ = env.reset(seed=seed)
    if episode_start is not None:
        env.set_rng_state(episode_start)
        obs, _ = env.reset()
    for action in actions:
        obs = env.step(action)[0]
    return obs


def check_env_args(env_id: str, noise: float, noise_type: str = "gaussian", noise_histograms: Optional[str] = None):
    """Validate the environment flags; returns the loaded histograms (or None). Raises ValueError naming the flag."""
    if not 0.0 <= noise < 1.0:
        raise ValueError(f"--noise must be in [0, 1) (the fraction of features that are noise), got {noise}")
    if noise_type not in NOISE_TYPES:
        raise ValueError(f"--noise-type must be one of {NOISE_TYPES}, got {noise_type!r}")
    tasks = dmc_tasks()
    if env_id not in tasks and gym_mujoco_class(env_id) is None and env_id not in metaworld_tasks():
        if is_metaworld_name(env_id) and not metaworld_tasks():
            raise ValueError(f"--env-id {env_id}: a Meta-World task needs metaworld: {METAWORLD_INSTALL}")
        raise ValueError(
            f"--env-id {env_id!r} is neither a dm_control suite task (domain-task, e.g. {', '.join(tasks[:6])}), a "
            f"gymnasium MuJoCo task (e.g. {', '.join(GYM_EXAMPLES)}) nor a Meta-World task (e.g. "
            f"{', '.join(METAWORLD_EXAMPLES)})"
        )
    if noise_type == "imitate":
        if noise_histograms is None:
            raise ValueError("--noise-histograms is required with --noise-type imitate")
        return load_histograms(noise_histograms)
    return None


def make_dmc_task(env_id: str, episode_length: int, render_mode: Optional[str]) -> gym.Env:
    """A dm_control task through shimmy, its observation flattened, its episodes `episode_length` steps long."""
    import shimmy

    # importing shimmy imports dm_control's composer, which sets every DeprecationWarning to 'always'; with NumPy >= 2.5
    # dm_control's own array code then prints one at every env step. They are dm_control's to fix, not the user's.
    warnings.filterwarnings("ignore", category=DeprecationWarning, module="dm_control")
    gym.register_envs(shimmy)
    env = gym.make(
        f"dm_control/{env_id}-v0",
        max_episode_steps=episode_length,
        render_mode=render_mode,
        # dm_control's own limit is 1000 steps of 0.01 s to 0.025 s; lift it so `episode_length` decides
        task_kwargs={"time_limit": float("inf")},
    )
    return gym.wrappers.FlattenObservation(env)


class FixedHorizon(gym.Wrapper):
    """Never terminated: a task that has no `terminate_when_unhealthy` (the inverted pendulums) runs on past the state
    that would end its episode, so that every episode lasts `episode_length` steps."""

    def step(self, action):
        obs, reward, _, truncated, info = self.env.step(action)
        return obs, reward, False, truncated, info


class StateVideo(gym.Wrapper):
    """`render()` draws the current physics state with `MujocoFrames`: the frames `RecordVideo` films, at the size of
    dm_control's videos and of the labelling page's clips."""

    def __init__(self, env: gym.Env, height: int = 240, width: int = 320):
        super().__init__(env)
        self.draw = MujocoFrames(env.unwrapped, height, width)

    @property
    def render_mode(self):
        return "rgb_array"

    def render(self):
        return self.draw(mujoco_state(self.unwrapped.model, self.unwrapped.data))

    def close(self):
        self.draw.close()
        super().close()


def make_gym_task(env_id: str, episode_length: int, render_mode: Optional[str] = None) -> gym.Env:
    """A gymnasium MuJoCo task with a flat Box observation, its episodes `episode_length` steps long, never
    terminated; with `render_mode="rgb_array"`, `render()` draws its state as `render_states` does."""
    kwargs = {}
    if "terminate_when_unhealthy" in inspect.signature(gym_mujoco_class(env_id)).parameters:
        kwargs["terminate_when_unhealthy"] = False  # a fall is a state to learn from, not the end of the episode
    # gymnasium's own limit (1000 steps for most tasks) is replaced, so that `episode_length` decides
    try:
        env = gym.make(env_id, max_episode_steps=episode_length, **kwargs)
    except (ImportError, gym.error.Error) as e:  # a task this install cannot run: Pusher-v4 needs mujoco < 3
        reason = str(e).splitlines()[0]
        raise ValueError(f"--env-id {env_id}: gymnasium cannot make this task here ({reason})") from None
    space = env.observation_space
    if not (isinstance(space, gym.spaces.Box) and len(space.shape) == 1):
        env.close()
        raise ValueError(f"--env-id {env_id}: the noise is appended to a flat Box observation, and this task's is {space}")
    env = FixedHorizon(env)
    return StateVideo(env) if render_mode else env


class MetaWorldTask(gym.Wrapper):
    """A Meta-World task as B-Pref runs it: a new random goal and object position at every reset (`_freeze_rand_vec`
    off), drawn from the task's own generator (metaworld's default draws from NumPy's global one), so that a seed and
    `rng_state` decide them; `reset(seed=s)` seeds that generator (metaworld ignores a reset's seed); episodes of
    `episode_length` steps. `info["success"]` is the task's success flag of the step, as metaworld computes it."""

    def __init__(self, env_id: str, episode_length: int, render_mode: Optional[str]):
        task = metaworld_classes()[f"{env_id}-goal-observable"]()
        task._freeze_rand_vec, task.seeded_rand_vec = False, True
        task.max_path_length = episode_length  # metaworld stops a longer episode with an error: 500 by default
        super().__init__(gym.wrappers.TimeLimit(task, episode_length))
        self.draw = MujocoFrames(task, 240, 320, camera="corner", upright=True) if render_mode else None

    def reset(self, *, seed: Optional[int] = None, options: Optional[dict] = None):
        if seed is not None:
            self.unwrapped.seed(seed)
        return self.env.reset(options=options)

    @property
    def render_mode(self):
        return "rgb_array" if self.draw else None

    def render(self):
        return self.draw(mujoco_state(self.unwrapped.model, self.unwrapped.data))

    def close(self):
        if self.draw:
            self.draw.close()
        super().close()


def make_env(
    env_id: str,
    seed: int,
    noise: float = 0.0,
    noise_type: str = "gaussian",
    noise_histograms: Optional[str] = None,
    episode_length: int = 1000,
    video_folder: Optional[str] = None,
) -> NoisyObservation:
    """A dm_control task (`cheetah-run`) or a gymnasium MuJoCo task (`HalfCheetah-v5`) as a gymnasium env with flat
    float32 observations, actions in [-1, 1], `episode_length`-step episodes (truncated, never terminated) and the
    ENE noise appended.

    `seed` seeds the task on the first `reset()` (call `env.reset(seed=seed)`), the action space and the noise
    generator. Give the evaluation env a different seed for a different stream.
    """
    histograms = check_env_args(env_id, noise, noise_type, noise_histograms)
    if episode_length < 1:
        raise ValueError(f"--episode-length must be >= 1, got {episode_length}")
    render_mode = "rgb_array" if video_folder else None
    if env_id in dmc_tasks():
        env = make_dmc_task(env_id, episode_length, render_mode)
    elif gym_mujoco_class(env_id) is not None:
        env = make_gym_task(env_id, episode_length, render_mode)
    else:
        env = MetaWorldTask(env_id, episode_length, render_mode)
    bound = env.action_space.dtype.type(1.0)  # in the space's own dtype: gymnasium's is float32, dm_control's float64
    env = gym.wrappers.RescaleAction(env, -bound, bound)  # quadruped's and Humanoid's bounds are not +-1
    if video_folder:
        env = gym.wrappers.RecordVideo(env, video_folder, disable_logger=True)
    env.action_space.seed(seed)
    obs_dim_real = env.observation_space.shape[0]
    sampler = NoiseSampler(obs_dim_real, num_noise_features(obs_dim_real, noise), noise_type, histograms)
    return NoisyObservation(env, sampler, seed)
