# docs: docs/ene.md
"""Extremely Noisy Environment (ENE), the one module every script shares.

An ENE (Grooten et al., "Automatic Noise Filtering with Dynamic Sparse Training in Deep RL", AAMAS 2023) takes a
dm_control task and appends task-irrelevant features to its observation, so that a fraction `noise` of all
features is noise:

    D_total = ceil(D_obs / (1 - noise))  (plain float arithmetic),  N_noise = D_total - D_obs

which reproduces the R2N paper's table exactly: cartpole 5 -> 51, walker 24 -> 241, cheetah 17 -> 171,
quadruped 78 -> 260 (the paper prints 68 by mistake), humanoid 67 -> 224.

Noise features are i.i.d. N(0, 1) (`noise_type="gaussian"`) or imitate the real features (`"imitate"`: noise
feature i draws from the histogram of real feature i mod D_obs). Real features come first, noise after, no shuffle.

What the scripts use:
* `make_env(...)`: the wrapped env; `env.obs_dim_real`, `env.n_noise`, `env.noise_sampler` tell which columns are
  real (`0 .. obs_dim_real - 1`) and how to draw noise.
* `NoiseSampler.refresh_(x)`: the read-time noise redraw behind `--noise-resample`. It overwrites the noise
  columns of stored observations (or of `[obs, action]` rows: the noise columns are the same) with fresh noise.
* `build_histograms(observations, path)` / `load_histograms(path)`: the `.npz` used by `--noise-type imitate`.
* `check_env_args(...)`: the input checks, raising `ValueError` with one line that names the flag.
* `env.rng_state()` / `env.set_rng_state(...)` and `replay_episode(...)`: the env's part of a script's `state.pt`.
* `EnvProcess(...)`: `make_env` in a process of its own; `step_async` / `step_wait` step several at once (evaluation).
* `env.physics_state()` and `render_states(env_id, states)`: the stored physics of queried segments, drawn again.
"""

import atexit
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

HISTOGRAM_BINS = 100
NOISE_TYPES = ("gaussian", "imitate")


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
        return {"task": self.unwrapped.np_random.get_state(), "noise": self.noise_rng.bit_generator.state,
                "action_space": self.action_space.np_random.bit_generator.state}

    def set_rng_state(self, state: dict):
        self.unwrapped.np_random.set_state(state["task"])
        self.noise_rng.bit_generator.state = state["noise"]
        self.action_space.np_random.bit_generator.state = state["action_space"]

    def physics_state(self) -> np.ndarray:
        """The MuJoCo state of the current step (qpos, qvel, act): what `render_states` needs to draw it again."""
        return self.unwrapped._env.physics.get_state().copy()

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


def render_states(env_id: str, states: np.ndarray, height: int = 240, width: int = 320) -> np.ndarray:
    """Frames (T, height, width, 3) uint8 of the physics `states` (T, D) of task `env_id`, from camera 0. Needs a
    renderer: on a machine without a display set `MUJOCO_GL=egl` (or `osmesa`) before the first import of dm_control."""
    from dm_control import suite

    domain, task = env_id.split("-", 1)
    physics = suite.load(domain, task).physics
    frames = []
    for state in states:
        with physics.reset_context():  # sets the state and recomputes positions for drawing
            physics.set_state(state)
        frames.append(physics.render(height, width, camera_id=0))
    return np.stack(frames)


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
    if env_id not in tasks:
        raise ValueError(f"--env-id {env_id!r} is not a dm_control suite task; use domain-task, e.g. {', '.join(tasks[:6])}")
    if noise_type == "imitate":
        if noise_histograms is None:
            raise ValueError("--noise-histograms is required with --noise-type imitate")
        return load_histograms(noise_histograms)
    return None


def make_env(
    env_id: str,
    seed: int,
    noise: float = 0.0,
    noise_type: str = "gaussian",
    noise_histograms: Optional[str] = None,
    episode_length: int = 1000,
    video_folder: Optional[str] = None,
) -> NoisyObservation:
    """A dm_control task (`cheetah-run`) as a gymnasium env with flat float32 observations, actions in [-1, 1],
    `episode_length`-step episodes (truncated, never terminated) and the ENE noise appended.

    `seed` seeds the task on the first `reset()` (call `env.reset(seed=seed)`), the action space and the noise
    generator. Give the evaluation env a different seed for a different stream.
    """
    histograms = check_env_args(env_id, noise, noise_type, noise_histograms)
    if episode_length < 1:
        raise ValueError(f"--episode-length must be >= 1, got {episode_length}")
    import shimmy

    # importing shimmy imports dm_control's composer, which sets every DeprecationWarning to 'always'; with NumPy >= 2.5
    # dm_control's own array code then prints one at every env step. They are dm_control's to fix, not the user's.
    warnings.filterwarnings("ignore", category=DeprecationWarning, module="dm_control")
    gym.register_envs(shimmy)
    env = gym.make(
        f"dm_control/{env_id}-v0",
        max_episode_steps=episode_length,
        render_mode="rgb_array" if video_folder else None,
        # dm_control's own limit is 1000 steps of 0.01 s to 0.025 s; lift it so `episode_length` decides
        task_kwargs={"time_limit": float("inf")},
    )
    env = gym.wrappers.FlattenObservation(env)
    env = gym.wrappers.RescaleAction(env, -1.0, 1.0)  # quadruped's bounds are not +-1
    if video_folder:
        env = gym.wrappers.RecordVideo(env, video_folder, disable_logger=True)
    env.action_space.seed(seed)
    obs_dim_real = env.observation_space.shape[0]
    sampler = NoiseSampler(obs_dim_real, num_noise_features(obs_dim_real, noise), noise_type, histograms)
    return NoisyObservation(env, sampler, seed)
