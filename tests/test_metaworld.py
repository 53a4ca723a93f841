"""Meta-World in the noisy environment (issue 70): metaworld's tasks made by `ene.make_env`, the mend of MuJoCo's
longer weld rows, the parity of our stack with metaworld's own MuJoCo, and the one line without metaworld.

The parity reference, `results/metaworld-parity/trajectories.npz`, was made under `mujoco==3.3.0` (metaworld's pin)
by `results/metaworld-parity/make_trajectories.py`, in an environment of its own. Over 500 steps of the same seeded
random actions our observations may differ from it by at most OBS_TOLERANCE and our rewards (0 to 10) by at most
REWARD_TOLERANCE; the success flags must be the same at every step. The two MuJoCo versions differ from the first
observation on (by about 2e-4: the 50 steps of the hand's reset), so the test cannot be bitwise."""
import importlib.util
import os
import sys

import mujoco
import numpy as np
import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.join(ROOT, "results", "metaworld-parity"))
import ene  # noqa: E402

needs_metaworld = pytest.mark.skipif(importlib.util.find_spec("metaworld") is None,
                                     reason=f"metaworld is not installed ({ene.METAWORLD_INSTALL})")
REFERENCE = os.path.join(ROOT, "results", "metaworld-parity", "trajectories.npz")
OBS_TOLERANCE, REWARD_TOLERANCE = 2e-3, 3e-2
TASKS = [str(name) for name in np.load(REFERENCE)["tasks"]]


@needs_metaworld
@pytest.mark.parametrize("task", TASKS)
def test_our_stack_reproduces_metaworlds_own_mujoco(task):
    import compare

    reference = np.load(REFERENCE)
    assert str(reference["mujoco"]) == "3.3.0" and int(reference["steps"]) == 500
    d = compare.differences(reference, task)
    assert d["obs"] <= OBS_TOLERANCE and d["reward"] <= REWARD_TOLERANCE and d["success_steps"] == 0, d


def test_the_parity_list_holds_the_tasks_the_docs_name():
    assert set(ene.METAWORLD_EXAMPLES) <= set(TASKS)
    with open(os.path.join(ROOT, "docs", "ene.md")) as f:
        docs = f.read()
    assert all(f"`{task}`" in docs for task in TASKS)


@needs_metaworld
def test_the_weld_mend_is_installed_only_where_rows_are_longer_and_keeps_mujocos_last_column():
    import metaworld.sawyer_xyz_env

    classes = ene.metaworld_classes()
    base = metaworld.sawyer_xyz_env.SawyerMocapBase
    assert mujoco.mjNEQDATA == 12 and base.reset_mocap_welds is ene.mend_mocap_welds
    task = classes["reach-v3-goal-observable"]()
    welds = task.model.eq_data[task.model.eq_type == mujoco.mjtEq.mjEQ_WELD]
    assert len(welds) and np.array_equal(welds[:, :11], np.tile(ene.METAWORLD_WELD, (len(welds), 1)))
    spec = mujoco.MjModel.from_xml_path(task.model_name)  # the weld rows as MuJoCo loads them
    loaded = spec.eq_data[spec.eq_type == mujoco.mjtEq.mjEQ_WELD]
    assert np.array_equal(welds[:, 11], loaded[:, 11])
    ene.metaworld_classes()  # a second call leaves the mend as it is
    assert base.reset_mocap_welds is ene.mend_mocap_welds


@needs_metaworld
def test_a_metaworld_task_is_an_ene_with_success_fixed_episodes_and_a_seeded_goal():
    env = ene.make_env("button-press-v3", 3, 0.9, episode_length=40)
    assert env.obs_dim_real == 39 and env.observation_space.shape == (ene.total_obs_dim(39, 0.9),)
    obs, _ = env.reset(seed=3)
    assert obs.dtype == np.float32
    for t in range(40):
        obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
        assert not terminated and truncated == (t == 39) and info["success"] in (0.0, 1.0)
    goal = obs[36:39]
    state = env.rng_state()
    second, _ = env.reset()
    assert not np.array_equal(second[36:39], goal)  # a new goal at every reset (B-Pref's)
    env.set_rng_state(state)
    assert np.array_equal(env.reset()[0][:39], second[:39])  # the generators decide it: exact resume
    again = ene.make_env("button-press-v3", 3, 0.9, episode_length=40)
    first, _ = again.reset(seed=3)
    assert np.array_equal(first, ene.make_env("button-press-v3", 3, 0.9, episode_length=40).reset(seed=3)[0])
    assert env.physics_state().shape == (task_state_size(env),)


def task_state_size(env) -> int:
    return mujoco.mj_stateSize(env.unwrapped.model, mujoco.mjtState.mjSTATE_PHYSICS)


@needs_metaworld
def test_a_metaworld_segment_is_drawn_upright_from_its_physics_states(monkeypatch):
    monkeypatch.setenv("MUJOCO_GL", "egl")  # no display here: Mesa's EGL
    env = ene.make_env("drawer-open-v3", 0, 0.5, episode_length=10)
    env.reset(seed=0)
    states = []
    for _ in range(3):
        states.append(env.physics_state())
        env.step(env.action_space.sample())
    frames = ene.render_states("drawer-open-v3", np.array(states))
    assert frames.shape == (3, 240, 320, 3) and frames.dtype == np.uint8
    # upright: the wooden table top lies in the frame's lower half (upside down, it would lie in the upper)
    r, g, b = (frames[0, ..., c].astype(int) for c in range(3))
    wood = (r > g + 20) & (g > b + 15) & (r > 80) & (r < 230)
    assert wood.sum() > 1000 and np.nonzero(wood)[0].mean() > 120


def test_a_metaworld_name_without_metaworld_says_what_to_install(monkeypatch):
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "metaworld" else real(name, *a))
    with pytest.raises(ValueError) as error:
        ene.check_env_args("button-press-v3", 0.9)
    assert str(error.value) == "--env-id button-press-v3: a Meta-World task needs metaworld: " + ene.METAWORLD_INSTALL
    with pytest.raises(ValueError, match="nor a Meta-World task"):
        ene.check_env_args("cheetah-runn", 0.9)


@needs_metaworld
def test_the_labelling_page_draws_a_metaworld_clip(tmp_path, monkeypatch):
    """A queries file of a Meta-World run, as `--teacher external` writes it: the app draws its clips."""
    monkeypatch.setenv("MUJOCO_GL", "egl")
    sys.path.insert(0, os.path.join(ROOT, "results", "label-session"))
    import label_app
    import memory_200

    run = str(tmp_path / "run")
    memory_200.write_run(run, "button-press-v3", 1, 1, 3)
    clip = label_app.Clips(run, 25, 10 ** 8).gif(0, 0, 1)
    assert clip[:6] == b"GIF89a" and len(clip) > 1000
