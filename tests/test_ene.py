"""Tests of ene.py, the Extremely Noisy Environment (spec: ALGORITHMS.md section 1)."""

import os
import re
import signal
import subprocess
import sys
import warnings

import gymnasium
import gymnasium.envs.mujoco.hopper_v5
import mujoco
import numpy as np
import pytest
import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
import ene  # noqa: E402

EPISODE = 20


def _rollout(env, seed, n_steps, actions=None):
    """Reset with `seed` and step `n_steps` times; returns the observations (n_steps + 1, D) and the actions used."""
    obs, _ = env.reset(seed=seed)
    observations = [obs]
    if actions is None:
        rng = np.random.default_rng(1234)
        actions = rng.uniform(-1.0, 1.0, (n_steps, *env.action_space.shape))
    for a in actions[:n_steps]:
        obs, _, _, _, _ = env.step(a)
        observations.append(obs)
    return np.stack(observations), actions


# ---------------------------------------------------------------- 1. dimensions


@pytest.mark.parametrize(
    "d_obs, noise, total", [(5, 0.9, 51), (24, 0.9, 241), (17, 0.9, 171), (78, 0.7, 260), (67, 0.7, 224)]
)
def test_dimension_table(d_obs, noise, total):
    assert ene.total_obs_dim(d_obs, noise) == total
    assert ene.num_noise_features(d_obs, noise) == total - d_obs
    assert ene.num_noise_features(d_obs, 0.0) == 0
    assert ene.total_obs_dim(d_obs, 0.0) == d_obs


@pytest.mark.parametrize("env_id, d_real, total", [("cartpole-swingup", 5, 51), ("cheetah-run", 17, 171)])
def test_make_env_shapes(env_id, d_real, total):
    env = ene.make_env(env_id, seed=0, noise=0.9, episode_length=EPISODE)
    assert env.obs_dim_real == d_real
    assert env.n_noise == total - d_real
    assert env.observation_space.shape == (total,)
    assert env.observation_space.dtype == np.float32
    obs, _ = env.reset(seed=0)
    assert obs.shape == (total,) and obs.dtype == np.float32
    obs, *_ = env.step(env.action_space.sample())
    assert obs.shape == (total,) and obs.dtype == np.float32
    assert env.noise_sampler.obs_dim_real == d_real and env.noise_sampler.n_noise == total - d_real
    env.close()


# ---------------------------------------------------------------- 2. fresh noise, real columns untouched


def test_noise_fresh_each_step_and_reset_and_real_columns_are_dmc():
    seed, n = 3, 10
    noisy = ene.make_env("cheetah-run", seed=seed, noise=0.9, episode_length=EPISODE)
    clean = ene.make_env("cheetah-run", seed=seed, noise=0.0, episode_length=EPISODE)
    d = noisy.obs_dim_real
    assert clean.obs_dim_real == d and clean.n_noise == 0 and clean.observation_space.shape == (d,)

    obs_noisy, actions = _rollout(noisy, seed, n)
    obs_clean, _ = _rollout(clean, seed, n, actions)
    assert obs_clean.shape == (n + 1, d)
    assert obs_noisy.shape == (n + 1, 171)
    # the real columns are exactly dm_control's features (the same as without noise)
    np.testing.assert_array_equal(obs_noisy[:, :d], obs_clean)
    # ... and they do change (the task is actually being stepped)
    assert not np.allclose(obs_clean[0], obs_clean[-1])

    noise = obs_noisy[:, d:]
    assert np.all(np.isfinite(noise))
    # fresh noise at every step: every pair of consecutive steps differs in (almost) every noise column
    for t in range(n):
        assert np.mean(noise[t] != noise[t + 1]) > 0.99

    # fresh noise at each reset, even with the same task seed
    first, _ = noisy.reset(seed=seed)
    second, _ = noisy.reset(seed=seed)
    np.testing.assert_array_equal(first[:d], second[:d])
    assert np.mean(first[d:] != second[d:]) > 0.99
    noisy.close()
    clean.close()


# ---------------------------------------------------------------- 3. seeding


def test_seeding_reproducible_and_seed_dependent():
    n = 8
    a = ene.make_env("cartpole-swingup", seed=7, noise=0.9, episode_length=EPISODE)
    b = ene.make_env("cartpole-swingup", seed=7, noise=0.9, episode_length=EPISODE)
    c = ene.make_env("cartpole-swingup", seed=8, noise=0.9, episode_length=EPISODE)
    obs_a, actions = _rollout(a, 7, n)
    obs_b, _ = _rollout(b, 7, n, actions)
    obs_c, _ = _rollout(c, 8, n, actions)
    np.testing.assert_array_equal(obs_a, obs_b)  # noise included
    d = a.obs_dim_real
    assert np.mean(obs_a[:, d:] != obs_c[:, d:]) > 0.99
    # the action space is seeded too
    assert np.array_equal(a.action_space.sample(), b.action_space.sample())
    for env in (a, b, c):
        env.close()


# ---------------------------------------------------------------- 4. Gaussian statistics


def test_gaussian_noise_statistics():
    sampler = ene.NoiseSampler(5, 46, "gaussian")
    x = sampler.sample(np.random.default_rng(0), (200,))
    assert x.shape == (200, 46) and x.dtype == np.float32
    single = sampler.sample(np.random.default_rng(0))
    assert single.shape == (46,) and single.dtype == np.float32
    torch.manual_seed(0)
    y = sampler.sample_torch((200,), torch.device("cpu"))
    assert y.shape == (200, 46) and y.dtype == torch.float32
    y = y.numpy()
    for values in (x, y):  # 9200 samples: the standard error of the mean is ~0.01, of the std ~0.007
        assert abs(values.mean()) < 0.05
        assert abs(values.std() - 1.0) < 0.05
        # Gaussian shape, not just the first two moments: P(|x| < 1) = 0.683, P(|x| > 2) = 0.0455
        assert abs(np.mean(np.abs(values) < 1.0) - 0.6827) < 0.02
        assert abs(np.mean(np.abs(values) > 2.0) - 0.0455) < 0.012
        # per-feature sanity: every column is standard normal too (200 samples each, generous bounds)
        assert np.all(np.abs(values.mean(0)) < 0.35)
        assert np.all(np.abs(values.std(0) - 1.0) < 0.3)
    # two draws differ
    assert not np.array_equal(x, sampler.sample(np.random.default_rng(1), (200,)))


# ---------------------------------------------------------------- 5. imitated noise


def _synthetic_observations(n=20000, seed=0):
    rng = np.random.default_rng(seed)
    bimodal = np.where(rng.random(n) < 0.3, rng.normal(-5.0, 0.3, n), rng.normal(4.0, 0.5, n))
    return np.stack(
        [
            rng.uniform(2.0, 3.0, n),  # 0: uniform on [2, 3]
            bimodal,  # 1: two modes, an empty gap between them
            rng.exponential(0.5, n) + 10.0,  # 2: exponential, shifted
            np.full(n, -7.0),  # 3: constant
        ],
        axis=1,
    )


def test_imitated_noise(tmp_path):
    obs = _synthetic_observations()
    d = obs.shape[1]
    path = str(tmp_path / "hist.npz")
    built = ene.build_histograms(obs, path)
    with np.load(path) as data:
        assert data["bin_edges"].shape == (d, 101)
        assert data["probs"].shape == (d, 100)
    hist = ene.load_histograms(path)
    np.testing.assert_allclose(hist["bin_edges"], built["bin_edges"])
    np.testing.assert_allclose(hist["probs"], built["probs"])
    np.testing.assert_allclose(hist["probs"].sum(1), 1.0)
    for i in range(d):
        assert hist["bin_edges"][i, 0] <= obs[:, i].min() and hist["bin_edges"][i, -1] >= obs[:, i].max()
    # edges span [min, max] for non-constant features
    np.testing.assert_allclose(hist["bin_edges"][:3, 0], obs[:, :3].min(0))
    np.testing.assert_allclose(hist["bin_edges"][:3, -1], obs[:, :3].max(0))

    n_noise = 10  # noise feature i imitates real feature i % 4
    sampler = ene.NoiseSampler(d, n_noise, "imitate", hist)
    n = 20000
    x_np = sampler.sample(np.random.default_rng(0), (n // 100, 100))
    assert x_np.shape == (n // 100, 100, n_noise) and x_np.dtype == np.float32
    x_np = x_np.reshape(n, n_noise)
    torch.manual_seed(0)
    x_t = sampler.sample_torch((n,), torch.device("cpu"))
    assert x_t.shape == (n, n_noise) and x_t.dtype == torch.float32
    x_t = x_t.numpy()
    single = sampler.sample(np.random.default_rng(1))
    assert single.shape == (n_noise,)

    for samples in (x_np, x_t):
        for i in range(n_noise):
            src = i % d
            edges, probs = hist["bin_edges"][src], hist["probs"][src]
            col = samples[:, i].astype(np.float64)
            lo, hi = obs[:, src].min(), obs[:, src].max()
            tol = 1e-5 * max(1.0, abs(lo), abs(hi))  # float32 rounding of the samples
            assert col.min() >= lo - tol and col.max() <= hi + tol, (i, col.min(), col.max(), lo, hi)
            if src == 3:  # constant feature
                np.testing.assert_allclose(col, -7.0, atol=1e-5)
                continue
            # bin frequencies of the samples match probs (std of a bin frequency <= sqrt(0.25 / n) ~ 0.0035)
            idx = np.clip(np.searchsorted(edges, col, side="right") - 1, 0, len(probs) - 1)
            freq = np.bincount(idx, minlength=len(probs)) / len(col)
            assert np.max(np.abs(freq - probs)) < 0.015, (i, np.max(np.abs(freq - probs)))
            # within a bin the value is uniform: its relative position in the bin has mean 1/2 and std 1/sqrt(12)
            width = edges[idx + 1] - edges[idx]
            position = np.clip((col - edges[idx]) / width, 0.0, 1.0)
            assert abs(position.mean() - 0.5) < 0.02 and abs(position.std() - 12 ** -0.5) < 0.02
            assert len(np.unique(col)) > 0.9 * len(col)
            # empty bins (the bimodal gap) get no samples, except float32 rounding at a bin boundary
            assert freq[probs == 0].sum() < 1e-3
            # and the marginal moments match the real feature
            assert abs(col.mean() - obs[:, src].mean()) < 0.05 * obs[:, src].std() + 1e-6
            assert abs(col.std() - obs[:, src].std()) < 0.05 * obs[:, src].std()

    # noise features with the same source feature are independent draws, not copies
    assert not np.array_equal(x_np[:, 0], x_np[:, 4])
    # the numpy sampler is reproducible from its generator
    np.testing.assert_array_equal(
        sampler.sample(np.random.default_rng(5), (50,)), sampler.sample(np.random.default_rng(5), (50,))
    )


def test_imitate_make_env(tmp_path):
    """make_env with --noise-type imitate: noise columns stay in the range of their source feature."""
    env = ene.make_env("cartpole-swingup", seed=0, noise=0.0, episode_length=EPISODE)
    obs, _ = _rollout(env, 0, EPISODE)
    env.close()
    obs = np.concatenate([obs, obs + 0.01])  # two rows are enough, but use a few more
    path = str(tmp_path / "cartpole.npz")
    ene.build_histograms(obs, path)
    env = ene.make_env("cartpole-swingup", seed=0, noise=0.9, noise_type="imitate", noise_histograms=path,
                       episode_length=EPISODE)
    assert env.observation_space.shape == (51,)
    noisy, _ = _rollout(env, 0, 10)
    d = env.obs_dim_real
    lo, hi = obs.min(0), obs.max(0)
    for i in range(env.n_noise):
        col = noisy[:, d + i]
        assert np.all(col >= lo[i % d] - 1e-5) and np.all(col <= hi[i % d] + 1e-5)
    env.close()


# ---------------------------------------------------------------- 6. refresh_


@pytest.mark.parametrize("noise_type", ["gaussian", "imitate"])
def test_refresh_only_changes_noise_columns(noise_type):
    d, n_noise, n_extra = 5, 46, 3
    hist = ene.build_histograms(_synthetic_observations(2000)[:, [0, 1, 2, 0, 1]]) if noise_type == "imitate" else None
    sampler = ene.NoiseSampler(d, n_noise, noise_type, hist)
    torch.manual_seed(0)
    x = torch.full((4, 6, d + n_noise + n_extra), 123.0)  # a batch of segments of [obs | action] rows
    x[..., :d] = torch.arange(d, dtype=torch.float32)
    x[..., d + n_noise :] = -torch.arange(1, n_extra + 1, dtype=torch.float32)
    before = x.clone()
    out = sampler.refresh_(x)
    assert out is x  # in place
    assert torch.equal(x[..., :d], before[..., :d])
    assert torch.equal(x[..., d + n_noise :], before[..., d + n_noise :])
    first = x[..., d : d + n_noise].clone()
    assert torch.all(first != 123.0)
    sampler.refresh_(x)
    second = x[..., d : d + n_noise]
    assert torch.equal(x[..., :d], before[..., :d])
    assert torch.equal(x[..., d + n_noise :], before[..., d + n_noise :])
    assert (first != second).float().mean() > 0.99
    # different rows get different noise
    assert (second[0, 0] != second[1, 1]).float().mean() > 0.99
    if noise_type == "gaussian":
        assert abs(second.mean().item()) < 0.2 and abs(second.std().item() - 1.0) < 0.2

    # no noise features: refresh_ is a no-op
    empty = ene.NoiseSampler(d, 0, "gaussian")
    y = torch.randn(3, d + n_extra)
    y0 = y.clone()
    empty.refresh_(y)
    assert torch.equal(y, y0)


# ---------------------------------------------------------------- 7. bad inputs


def _assert_one_line_value_error(fn, flag):
    with pytest.raises(ValueError) as info:
        fn()
    message = str(info.value)
    assert flag in message, message
    assert "\n" not in message, message
    return message


@pytest.mark.parametrize("noise", [1.0, -0.1, 1.5, float("nan")])
def test_bad_noise(noise):
    _assert_one_line_value_error(lambda: ene.check_env_args("cheetah-run", noise), "--noise")
    _assert_one_line_value_error(lambda: ene.make_env("cheetah-run", 0, noise=noise), "--noise")


@pytest.mark.parametrize("env_id", ["cheetah-fly", "foo", "cheetah_run", ""])
def test_bad_env_id(env_id):
    _assert_one_line_value_error(lambda: ene.check_env_args(env_id, 0.9), "--env-id")
    _assert_one_line_value_error(lambda: ene.make_env(env_id, 0, noise=0.9), "--env-id")


def test_good_args_pass():
    assert ene.check_env_args("cheetah-run", 0.0) is None
    assert ene.check_env_args("humanoid-stand", 0.7, "gaussian") is None
    assert "quadruped-walk" in ene.dmc_tasks() and "cartpole-swingup" in ene.dmc_tasks()


def test_bad_noise_type_and_missing_histograms(tmp_path):
    _assert_one_line_value_error(lambda: ene.check_env_args("cheetah-run", 0.9, "uniform"), "--noise-type")
    _assert_one_line_value_error(lambda: ene.check_env_args("cheetah-run", 0.9, "imitate"), "--noise-histograms")
    _assert_one_line_value_error(lambda: ene.make_env("cheetah-run", 0, 0.9, "imitate"), "--noise-histograms")
    missing = str(tmp_path / "nope.npz")
    _assert_one_line_value_error(lambda: ene.check_env_args("cheetah-run", 0.9, "imitate", missing), "--noise-histograms")
    _assert_one_line_value_error(lambda: ene.make_env("cheetah-run", 0, 0.9, "imitate", missing), "--noise-histograms")
    _assert_one_line_value_error(lambda: ene.load_histograms(str(tmp_path)), "--noise-histograms")  # a directory


def _bad_histogram_files(tmp_path):
    good = ene.build_histograms(_synthetic_observations(500)[:, :3])
    files = {}
    text = tmp_path / "text.npz"
    text.write_text("this is not a histogram\n1 2 3\n")
    files["text"] = text
    np.savez(tmp_path / "wrong_shapes.npz", bin_edges=np.zeros((3, 100)), probs=np.full((3, 100), 0.01))
    files["wrong_shapes"] = tmp_path / "wrong_shapes.npz"
    np.savez(tmp_path / "probs_1d.npz", bin_edges=good["bin_edges"], probs=good["probs"][0])
    files["probs_1d"] = tmp_path / "probs_1d.npz"
    np.savez(tmp_path / "not_one.npz", bin_edges=good["bin_edges"], probs=good["probs"] * 0.5)
    files["not_one"] = tmp_path / "not_one.npz"
    negative = good["probs"].copy()
    negative[:, 0] -= 0.1
    negative[:, 1] += 0.1
    np.savez(tmp_path / "negative.npz", bin_edges=good["bin_edges"], probs=negative)
    files["negative"] = tmp_path / "negative.npz"
    np.savez(tmp_path / "missing_key.npz", bin_edges=good["bin_edges"], p=good["probs"])
    files["missing_key"] = tmp_path / "missing_key.npz"
    np.savez(tmp_path / "decreasing.npz", bin_edges=good["bin_edges"][:, ::-1], probs=good["probs"])
    files["decreasing"] = tmp_path / "decreasing.npz"
    nan_edges = good["bin_edges"].copy()
    nan_edges[1, 5] = np.nan
    np.savez(tmp_path / "nan_edges.npz", bin_edges=nan_edges, probs=good["probs"])
    files["nan_edges"] = tmp_path / "nan_edges.npz"
    np.save(tmp_path / "plain.npy", good["probs"])
    files["plain_npy"] = tmp_path / "plain.npy"
    return files


def test_malformed_histogram_files(tmp_path):
    for name, path in _bad_histogram_files(tmp_path).items():
        path = str(path)
        msg = _assert_one_line_value_error(lambda: ene.load_histograms(path), "--noise-histograms")
        assert path in msg, (name, msg)
        _assert_one_line_value_error(lambda: ene.check_env_args("cartpole-swingup", 0.9, "imitate", path),
                                     "--noise-histograms")
    # one through make_env as well
    path = str(tmp_path / "not_one.npz")
    _assert_one_line_value_error(lambda: ene.make_env("cartpole-swingup", 0, 0.9, "imitate", path), "--noise-histograms")


def test_histograms_with_wrong_number_of_features(tmp_path):
    path = str(tmp_path / "three.npz")
    hist = ene.build_histograms(_synthetic_observations(500)[:, :3], path)
    _assert_one_line_value_error(lambda: ene.NoiseSampler(5, 46, "imitate", hist), "--noise-histograms")
    _assert_one_line_value_error(
        lambda: ene.make_env("cartpole-swingup", 0, 0.9, "imitate", path, episode_length=EPISODE), "--noise-histograms"
    )


def test_bad_episode_length():
    _assert_one_line_value_error(lambda: ene.make_env("cartpole-swingup", 0, 0.9, episode_length=0), "--episode-length")


def test_build_histograms_rejects_bad_input():
    with pytest.raises(ValueError):
        ene.build_histograms(np.zeros((1, 3)))
    with pytest.raises(ValueError):
        ene.build_histograms(np.zeros(10))


# ---------------------------------------------------------------- 8. episodes and actions


@pytest.mark.parametrize("env_id, noise", [("cartpole-swingup", 0.9), ("quadruped-walk", 0.7)])
def test_episode_length_and_action_space(env_id, noise):
    length = 30
    env = ene.make_env(env_id, seed=0, noise=noise, episode_length=length)
    space = env.action_space
    assert np.all(space.low == -1.0) and np.all(space.high == 1.0)
    for _ in range(2):  # two episodes in a row
        env.reset(seed=0)
        for t in range(1, length + 1):
            _, reward, terminated, truncated, _ = env.step(space.sample())
            assert np.isfinite(reward)
            assert not terminated, t
            assert bool(truncated) == (t == length), t
    env.close()


def test_quadruped_actions_are_rescaled():
    env = ene.make_env("quadruped-walk", seed=0, noise=0.7, episode_length=EPISODE)
    native = env.unwrapped.action_space
    assert not (np.all(native.low == -1.0) and np.all(native.high == 1.0))  # the reason for the rescale
    assert env.observation_space.shape == (260,) and env.obs_dim_real == 78
    # -1 and +1 reach the native bounds
    captured = []
    original_step = env.unwrapped.step

    def spy(action):
        captured.append(np.array(action, dtype=np.float64))
        return original_step(action)

    env.unwrapped.step = spy
    env.reset(seed=0)
    env.step(-np.ones(env.action_space.shape))
    env.step(np.ones(env.action_space.shape))
    env.unwrapped.step = original_step
    np.testing.assert_allclose(captured[0], native.low, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(captured[1], native.high, rtol=1e-6, atol=1e-6)
    env.close()


def test_dm_control_deprecation_warnings_stay_quiet():
    """shimmy imports dm_control's composer, which sets every DeprecationWarning to 'always'; with NumPy 2.5 dm_control's
    own code then warned at every env step. Its warnings are hidden, everyone else's are left as they were."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", DeprecationWarning)  # what composer's import does (the first import only)
        env = ene.make_env("cartpole-swingup", seed=0, noise=0.5, episode_length=EPISODE)
        env.reset(seed=0)
        warnings.warn_explicit("shape setter", DeprecationWarning, "index.py", 381, module="dm_control.mujoco.index")
        warnings.warn_explicit("ours", DeprecationWarning, "ours.py", 1, module="ours")
    assert [str(w.message) for w in caught if w.category is DeprecationWarning] == ["ours"]
    env.close()


def test_replay_episode_brings_a_fresh_env_where_the_saved_one_was():
    """The env's part of exact resume: generators saved at an episode's start plus its actions rebuild the env."""
    env = ene.make_env("cartpole-swingup", 3, 0.9, episode_length=20)
    env.reset(seed=3)
    for _ in range(20):  # a first episode, so that the saved start is not the seeded one
        env.step(env.action_space.sample())
    episode_start, actions = env.rng_state(), []
    obs, _ = env.reset()
    for _ in range(7):
        actions.append(env.action_space.sample())
        obs = env.step(actions[-1])[0]
    now = env.rng_state()
    fresh = ene.make_env("cartpole-swingup", 3, 0.9, episode_length=20)
    assert np.array_equal(ene.replay_episode(fresh, 3, episode_start, actions), obs)
    fresh.set_rng_state(now)
    for _ in range(30):  # the rest of the episode and the next one, actions from the restored action space
        action, fresh_action = env.action_space.sample(), fresh.action_space.sample()
        assert np.array_equal(action, fresh_action)
        step, fresh_step = env.step(action), fresh.step(fresh_action)
        assert np.array_equal(step[0], fresh_step[0]) and step[1:4] == fresh_step[1:4]
        if step[3]:
            assert np.array_equal(env.reset()[0], fresh.reset()[0])
    other = ene.make_env("cartpole-swingup", 4, 0.9, episode_length=20)  # a check that can fail: another seed
    assert not np.array_equal(ene.replay_episode(other, 4, None, actions), obs)


def test_env_process_steps_as_the_env_does_and_carries_its_generators():
    """`EnvProcess` is `make_env` in a process of its own: the same observations and rewards through `step_async` /
    `step_wait` and `step`, the same generators (`rng_state`), and a state set on it is the env's too."""
    args = ("cartpole-swingup", 3, 0.5, "gaussian", None, 30)
    local, remote = ene.make_env(*args), ene.EnvProcess(*args)
    try:
        for env in (local, remote):
            env.reset(seed=3)
        actions = np.random.default_rng(0).uniform(-1, 1, (40, 1)).astype(np.float32)
        for t, action in enumerate(actions):
            for env in (local, remote):
                env.step_async(action)
            expected, got = local.step_wait(), remote.step_wait()
            assert np.array_equal(expected[0], got[0]) and expected[1:4] == got[1:4], f"step {t}"
            if expected[3]:  # truncated after 30 steps: both start a new episode from their own generators
                assert np.array_equal(local.reset()[0], remote.reset()[0])
        state = local.rng_state()
        assert repr(remote.rng_state()) == repr(state)
        remote.set_rng_state(ene.make_env(*args).rng_state())  # back to the seeded generators
        assert repr(remote.rng_state()) != repr(state)
        remote.set_rng_state(state)
        assert np.array_equal(local.reset()[0], remote.reset()[0])
        assert np.array_equal(local.step(actions[0])[0], remote.step(actions[0])[0])
        with pytest.raises(RuntimeError, match="the env's process: "):
            remote.step(np.full(3, np.nan, dtype=np.float32))  # the wrong shape: the env's own error, passed on
    finally:
        remote.close()
    assert not remote.process.is_alive()


def test_env_process_ignores_stop_signals_and_ends_with_its_script():
    """A cluster signals every process of a job; the script handles the signal and still needs its envs to save
    its state. An env's process ends when the script's end of the pipe closes (the script exited or was killed)."""
    env = ene.EnvProcess("cartpole-swingup", 3, 0.5, "gaussian", None, 30)
    env.reset(seed=3)
    os.kill(env.process.pid, signal.SIGTERM)
    assert env.rng_state()["noise"]  # still answering
    env.pipe.close()
    env.process.join(timeout=30)
    assert env.process.exitcode == 0


def test_a_script_with_env_processes_exits_when_it_stops(tmp_path):
    """The way a stopped run ends (SystemExit with envs still open): the interpreter's exit must not wait forever on
    env processes that ignore SIGTERM. An env that cannot be made says why at the first call."""
    script = tmp_path / "stop.py"
    script.write_text(f"import sys\nsys.path.insert(0, {os.path.dirname(os.path.dirname(os.path.abspath(__file__)))!r})\n"
                      "import ene\n"
                      "if __name__ == '__main__':\n"
                      "    env = ene.EnvProcess('cartpole-swingup', 3, 0.5, 'gaussian', None, 30)\n"
                      "    env.reset(seed=3)\n"
                      "    raise SystemExit('stopped')\n")
    result = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=120)
    assert result.returncode == 1 and "stopped" in result.stderr
    broken = ene.EnvProcess("cartpole-swingup", 3, 0.5, "gaussian", None, 0)  # episode length 0: make_env refuses
    with pytest.raises(RuntimeError, match="the env's process: ValueError: --episode-length must be >= 1"):
        broken.reset(seed=3)


# ---------------------------------------------------------------- 9. gymnasium's MuJoCo tasks (issue 33)

GYM_DIMS = {  # real features, then all features at noise 0.7 and 0.9 (ANF's and the R2N paper's fractions)
    "HalfCheetah-v5": (17, 57, 171), "Hopper-v5": (11, 37, 111), "Walker2d-v5": (17, 57, 171),
    "Ant-v5": (105, 350, 1051), "Humanoid-v5": (348, 1160, 3481),
}


@pytest.mark.parametrize("env_id", list(GYM_DIMS))
def test_gym_task_dimensions(env_id):
    real, at_07, at_09 = GYM_DIMS[env_id]
    for noise, total in ((0.0, real), (0.7, at_07), (0.9, at_09)):
        env = ene.make_env(env_id, seed=0, noise=noise, episode_length=EPISODE)
        assert (env.obs_dim_real, env.n_noise, env.observation_space.shape) == (real, total - real, (total,))
        obs, _ = env.reset(seed=0)
        assert obs.shape == (total,) and obs.dtype == np.float32
        assert np.all(env.action_space.low == -1.0) and np.all(env.action_space.high == 1.0)
        env.close()


def test_gym_task_real_columns_are_gymnasiums_and_noise_is_fresh_standard_normal():
    """The real columns are gymnasium's own observation (float32), whatever the noise; the noise columns are N(0, 1)
    and fresh at every step."""
    n = 200
    noisy = ene.make_env("HalfCheetah-v5", seed=3, noise=0.9, episode_length=n)
    obs_noisy, actions = _rollout(noisy, 3, n)
    plain = gymnasium.make("HalfCheetah-v5")  # its bounds are +-1: the actions need no rescaling
    obs_plain = [plain.reset(seed=3)[0]] + [plain.step(a)[0] for a in actions]
    np.testing.assert_array_equal(obs_noisy[:, :17], np.float32(obs_plain))
    assert not np.allclose(obs_noisy[0, :17], obs_noisy[-1, :17])
    noise = obs_noisy[:, 17:]
    for t in range(n):
        assert np.mean(noise[t] != noise[t + 1]) > 0.99
    assert abs(noise.mean()) < 0.02 and abs(noise.std() - 1.0) < 0.02  # 201 x 154 draws: standard errors ~0.005
    assert abs(np.mean(np.abs(noise) < 1.0) - 0.6827) < 0.01
    noisy.close()
    plain.close()


def test_gym_task_imitated_noise(tmp_path):
    env = ene.make_env("Hopper-v5", seed=0, noise=0.0, episode_length=EPISODE)
    obs, _ = _rollout(env, 0, EPISODE)
    env.close()
    path = str(tmp_path / "hopper.npz")
    ene.build_histograms(obs, path)
    env = ene.make_env("Hopper-v5", seed=0, noise=0.9, noise_type="imitate", noise_histograms=path, episode_length=EPISODE)
    noisy, _ = _rollout(env, 0, EPISODE)
    lo, hi = obs.min(0), obs.max(0)
    for i in range(env.n_noise):
        source = i % 11
        assert np.all(noisy[:, 11 + i] >= lo[source] - 1e-5) and np.all(noisy[:, 11 + i] <= hi[source] + 1e-5)
    assert np.mean(noisy[1:, 11:] != noisy[:-1, 11:]) > 0.99
    env.close()


@pytest.mark.parametrize("env_id", ["Hopper-v5", "InvertedPendulum-v5"])
def test_gym_episodes_have_episode_length_steps_and_never_terminate(env_id):
    """Hopper falls under random actions (gymnasium would end the episode there) and its episode goes on, past
    gymnasium's own limit of 1000 steps too; InvertedPendulum has no terminate_when_unhealthy and goes on as well."""
    for length in (30, 1100):
        env = ene.make_env(env_id, seed=0, noise=0.5, episode_length=length)
        task = env.unwrapped
        fell = False
        for _ in range(2):  # two episodes in a row
            env.reset(seed=0)
            for t in range(1, length + 1):
                _, reward, terminated, truncated, _ = env.step(env.action_space.sample())
                fell = fell or not (task.is_healthy if env_id == "Hopper-v5" else abs(task.data.qpos[1]) <= 0.2)
                assert np.isfinite(reward) and not terminated, t
                assert bool(truncated) == (t == length), t
        assert fell or length == 30, "the body never fell: the test would not see a termination"
        env.close()
    if env_id == "Hopper-v5":  # gymnasium's own switch is off: its healthy reward is paid only while healthy
        assert ene.make_env(env_id, 0).unwrapped.spec.kwargs["terminate_when_unhealthy"] is False


def test_gym_physics_state_is_the_observed_state():
    """`physics_state()` before a step (what the scripts store with a query) is the state of the current observation:
    set on a fresh task, it gives the same real features."""
    env = ene.make_env("Hopper-v5", seed=5, noise=0.9, episode_length=EPISODE)
    obs, _ = env.reset(seed=5)
    fresh = ene.make_gym_task("Hopper-v5", EPISODE).unwrapped
    for _ in range(EPISODE):
        state = env.physics_state()
        assert state.shape == (fresh.model.nq + fresh.model.nv + fresh.model.na,)
        mujoco.mj_setState(fresh.model, fresh.data, state, mujoco.mjtState.mjSTATE_PHYSICS)
        mujoco.mj_forward(fresh.model, fresh.data)
        np.testing.assert_array_equal(np.float32(fresh._get_obs()), obs[:11])
        obs = env.step(env.action_space.sample())[0]
    env.close()


def test_gym_frames_drawn_again_from_stored_states_are_the_videos(tmp_path, monkeypatch):
    """The frames a video of the run films (RecordVideo's) and those `render_states` draws from the physics states
    stored during the run (at the labelling page's size, the videos' too) are the same, bit for bit."""
    monkeypatch.setenv("MUJOCO_GL", "egl")  # no display here: Mesa's EGL
    env = ene.make_env("Hopper-v5", seed=1, noise=0.9, episode_length=50, video_folder=str(tmp_path / "videos"))
    env.reset(seed=1)
    states = []
    for _ in range(8):
        states.append(env.physics_state())
        for _ in range(3):  # frames 3 steps apart: they differ clearly
            env.step(env.action_space.sample())
    filmed = np.stack(env.get_wrapper_attr("recorded_frames")[::3][:8])  # one at the reset, one after each step
    drawn = ene.render_states("Hopper-v5", np.stack(states))
    assert drawn.shape == filmed.shape == (8, 240, 320, 3) and drawn.dtype == np.uint8
    assert np.array_equal(drawn, filmed)
    assert np.abs(drawn[0].astype(int) - drawn[-1]).mean() > 1.0  # the frames show the motion (a check that can fail)
    # drawn after other states, a state gives the same frame: nothing carries over from one frame to the next
    assert np.array_equal(ene.render_states("Hopper-v5", np.stack(states[::-1]))[::-1], drawn)
    env.close()


def test_gym_replay_episode_and_generators():
    """Exact resume's env part on a gymnasium task: gymnasium's generator (reset noise) is in `rng_state`, and a fresh
    env replays a saved episode to the same observation, then goes on identically."""
    env = ene.make_env("Hopper-v5", 3, 0.9, episode_length=20)
    env.reset(seed=3)
    for _ in range(20):
        env.step(env.action_space.sample())
    episode_start, actions = env.rng_state(), []
    assert episode_start["task"]["bit_generator"] == "PCG64"  # gymnasium's own generator
    obs, _ = env.reset()
    for _ in range(7):
        actions.append(env.action_space.sample())
        obs = env.step(actions[-1])[0]
    now = env.rng_state()
    fresh = ene.make_env("Hopper-v5", 3, 0.9, episode_length=20)
    assert np.array_equal(ene.replay_episode(fresh, 3, episode_start, actions), obs)
    fresh.set_rng_state(now)
    for _ in range(40):  # the rest of the episode and the next one: the same reset noise, noise and actions
        action, fresh_action = env.action_space.sample(), fresh.action_space.sample()
        assert np.array_equal(action, fresh_action)
        step, fresh_step = env.step(action), fresh.step(fresh_action)
        assert np.array_equal(step[0], fresh_step[0]) and step[1:4] == fresh_step[1:4]
        if step[3]:
            assert np.array_equal(env.reset()[0], fresh.reset()[0])
    # a check that can fail: the same generators but gymnasium's, taken from another seed, give another start
    other = ene.make_env("Hopper-v5", 4, 0.9, episode_length=20)
    other.reset(seed=4)
    mixed = dict(episode_start, task=other.rng_state()["task"])
    replayed = ene.replay_episode(ene.make_env("Hopper-v5", 3, 0.9, episode_length=20), 3, mixed, actions)
    assert not np.array_equal(replayed[:11], obs[:11]) and np.array_equal(replayed[11:], obs[11:])


@pytest.mark.filterwarnings("ignore:.*is out of date:DeprecationWarning")  # gymnasium's advice to use v5, for v4
def test_every_gymnasium_mujoco_task_runs_with_the_noise():
    """Any registered MuJoCo task of gymnasium: flat float32 observations with the noise, fixed-length episodes; one
    this install cannot run (Pusher-v4 needs mujoco < 3) is refused with one line."""
    tasks = ene.gym_mujoco_tasks()
    assert set(GYM_DIMS) <= set(tasks) and "cheetah-run" not in tasks and "CartPole-v1" not in tasks
    for env_id in tasks:
        if env_id == "Pusher-v4":
            _assert_one_line_value_error(lambda: ene.make_env(env_id, 0, 0.5), "--env-id Pusher-v4")
            continue
        env = ene.make_env(env_id, seed=0, noise=0.5, episode_length=5)
        obs, _ = env.reset(seed=0)
        for t in range(5):
            obs, _, terminated, truncated, _ = env.step(env.action_space.sample())
            assert not terminated and bool(truncated) == (t == 4), env_id
        assert obs.dtype == np.float32 and obs.shape == (2 * env.obs_dim_real,), env_id
        env.close()


@pytest.mark.parametrize("env_id", ["CartPole-v1", "Hopper-v3", "hopper-v5", "HalfCheetah", "cheetah-run-v0"])
def test_unknown_id_lists_both_families(env_id):
    for make in (lambda: ene.check_env_args(env_id, 0.9), lambda: ene.make_env(env_id, 0, noise=0.9)):
        message = _assert_one_line_value_error(make, "--env-id")
        assert "dm_control" in message and "domain-task" in message, message
        assert "gymnasium MuJoCo" in message and "HalfCheetah-v5" in message, message


class DictObservationHopper(gymnasium.envs.mujoco.hopper_v5.HopperEnv):
    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        self.observation_space = gymnasium.spaces.Dict({"state": self.observation_space})


class ImageObservationHopper(gymnasium.envs.mujoco.hopper_v5.HopperEnv):
    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        self.observation_space = gymnasium.spaces.Box(0, 255, (64, 64, 3), np.uint8)


@pytest.mark.parametrize("task_class", [DictObservationHopper, ImageObservationHopper])
def test_observation_that_is_not_a_flat_box_is_refused(task_class, monkeypatch):
    env_id = f"test/{task_class.__name__}-v0"
    monkeypatch.setitem(gymnasium.registry, env_id, gymnasium.envs.registration.EnvSpec(env_id, task_class))
    assert ene.check_env_args(env_id, 0.9) is None  # a MuJoCo task: its observation shows once it is made
    message = _assert_one_line_value_error(lambda: ene.make_env(env_id, 0, noise=0.9), f"--env-id {env_id}")
    assert "flat Box" in message, message


SCRIPTS = ["sac.py", "anf_sac.py", "pebble.py", "r2n_pebble.py", "set_pebble.py", "static_pebble.py", "l1_pebble.py",
           "dropconnect_pebble.py", "surf.py", "r2n_surf.py", "rune.py", "r2n_rune.py"]


def test_suite_settings_fill_only_the_unset_flags_from_the_tasks_suite():
    """Each suite's SAC settings for the flags a run leaves unset; a flag that is set wins, 0 included; dm_control keeps
    the paper's settings, every committed run's."""
    import sac

    assert ene.suite("cheetah-run") == "dm_control" and ene.suite("HalfCheetah-v5") == "gymnasium"
    assert ene.suite("drawer-open-v3") == "metaworld"
    paper = dict(episode_length=1000, hidden_dim=1024, hidden_layers=2, batch_size=1024, policy_lr=1e-4, q_lr=1e-4,
                 alpha_lr=1e-4, init_temperature=0.1, target_update_freq=2)
    assert ene.SUITE_SETTINGS["dm_control"] == paper
    for env_id in ("cheetah-run", "HalfCheetah-v5", "drawer-open-v3"):
        settings = ene.SUITE_SETTINGS[ene.suite(env_id)]
        assert set(settings) == set(paper)
        args = ene.suite_settings(sac.Args(env_id=env_id))
        assert {key: getattr(args, key) for key in settings} == settings
        explicit = ene.suite_settings(sac.Args(env_id=env_id, hidden_dim=7, alpha_lr=0.0))
        assert (explicit.hidden_dim, explicit.alpha_lr, explicit.batch_size) == (7, 0.0, settings["batch_size"])
    assert ene.SUITE_SETTINGS["gymnasium"] != ene.SUITE_SETTINGS["metaworld"] != paper


def unset_docstrings(path: str) -> dict:
    """{flag: (DMC, Meta-World, gym)} from a script's Args docstrings that end in `unset: DMC a, Meta-World b, gym c`."""
    lines = open(os.path.join(os.path.dirname(ene.__file__), path)).read().split("\n")
    found = {}
    for field, doc in zip(lines, lines[1:]):
        match = re.search(r"unset: DMC (\S+), Meta-World (\S+), gym (\S+)\"\"\"$", doc)
        if match:
            found[field.split(":")[0].strip()] = tuple(float(value) for value in match.groups())
    return found


@pytest.mark.parametrize("script", SCRIPTS)
def test_every_scripts_help_gives_the_suites_settings(script):
    """`--help` says what an unset SAC flag becomes on each suite: each docstring matches `ene.SUITE_SETTINGS`."""
    expected = {key: tuple(float(ene.SUITE_SETTINGS[suite][key]) for suite in ("dm_control", "metaworld", "gymnasium"))
                for key in ene.SUITE_SETTINGS["dm_control"] if key != "episode_length"}
    assert unset_docstrings(script) == expected
