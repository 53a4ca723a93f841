"""Every script on gymnasium's MuJoCo tasks (issue 33) and on Meta-World's (issue 70): a smoke run through every phase
on HalfCheetah-v5, on a task that normally ends its episodes when the body falls (Hopper-v5) and on button-press-v3
(its success rate logged), with the noise appended, and exact resume after a SIGKILL on Hopper-v5 and on
button-press-v3 (a new goal at every reset, from the generators the state keeps)."""
import importlib.util
import math

import pytest
import torch

import ene
import test_resume
from test_layout import ORACLES, PBRL
from test_scripts import DEVICE, run_script, scalars

# Every phase in 300 steps: random (0-99), pre-training (100-199), one feedback round with the critic reset at 200,
# SAC updates on the learned reward, an evaluation and the checkpoint at 300. Episodes of 50 steps: at 200, four
# complete ones to cut segments from. A small buffer keeps each process small.
GYM_TINY = [
    "--noise", "0.9", "--total-timesteps", "300", "--learning-starts", "100", "--episode-length", "50",
    "--eval-freq", "300", "--eval-episodes", "1", "--hidden-dim", "32", "--batch-size", "32", "--log-freq", "100",
    "--buffer-size", "1000", DEVICE,
]
PBRL_TINY = [
    "--unsup-steps", "100", "--feedback-freq", "200", "--segment-size", "10", "--max-feedback", "5",
    "--queries-per-round", "5", "--reward-hidden-dim", "16", "--reward-layers", "2", "--reward-epochs", "20",
    "--reset-updates", "10",
]
EXTRA = {  # the sparse scripts update their topologies within the run; SURF keeps pseudo-labels
    "r2n_pebble.py": ["--reward-topology-period", "5", "--agent-topology-period", "50"],
    "set_pebble.py": ["--reward-topology-period", "5", "--agent-topology-period", "50"],
    "r2n_surf.py": ["--reward-topology-period", "5", "--agent-topology-period", "50", "--surf-tau", "0.6"],
    "r2n_rune.py": ["--reward-topology-period", "5", "--agent-topology-period", "50"],
    "surf.py": ["--surf-tau", "0.6"],
    "anf_sac.py": ["--agent-topology-period", "50"],
}
TASKS = {"HalfCheetah-v5": (17, 171, 6), "Hopper-v5": (11, 111, 3),  # real features, all features at 0.9, actions
         "button-press-v3": (39, 391, 4)}
METAWORLD = pytest.mark.skipif(importlib.util.find_spec("metaworld") is None, reason="metaworld is not installed")
ENV_IDS = [pytest.param(env_id, marks=METAWORLD) if env_id.endswith("-v3") else env_id for env_id in TASKS]
SAC_TAGS = ["eval/episodic_return", "charts/episodic_return", "charts/episodic_length", "losses/qf1_loss",
            "losses/qf2_loss", "losses/actor_loss", "losses/alpha", "features/actor/relevant_weight_frac"]
PBRL_TAGS = ["losses/state_entropy_reward", "pbrl/total_feedback", "pbrl/labeled_feedback", "pbrl/reward_loss",
             "pbrl/reward_accuracy", "pbrl/reward_true_corr", "pbrl/heldout_accuracy"]


def args_of(script, env_id):
    return ["--env-id", env_id, *GYM_TINY, *(PBRL_TINY if script in PBRL else []), *EXTRA.get(script, [])]


@pytest.mark.parametrize("env_id", ENV_IDS)
@pytest.mark.parametrize("script", PBRL + ORACLES)
def test_smoke_reaches_every_phase(script, env_id, tmp_path):
    harness = ["--resumable", "--diagnostics"]  # the features' chance and the progress lines
    result = run_script(script, args_of(script, env_id) + harness + ["--run-name", "smoke", "--exp-name", "smoke"],
                        tmp_path)
    values = scalars(str(tmp_path / "runs" / "smoke"))
    expected = SAC_TAGS + (PBRL_TAGS if script in PBRL else []) + (["eval/success_rate"] if env_id.endswith("-v3") else [])
    missing = [tag for tag in expected if tag not in values]
    assert not missing, f"missing tags {missing}"
    for tag, points in values.items():
        assert all(math.isfinite(v) for v in points), f"{tag} has non-finite values {points}"
    # episodes of exactly --episode-length steps, on Hopper too, whose body falls under random actions
    assert values["charts/episodic_length"] == [50] * len(values["charts/episodic_length"])
    assert len(values["charts/episodic_length"]) == 6
    assert len(values["eval/episodic_return"]) == 1 and result.stdout.count("eval_return=") == 1
    assert ("eval/success_rate" in values) == env_id.endswith("-v3")  # a task with a success flag only
    assert all(v in (0.0, 1.0) for v in values.get("eval/success_rate", []))  # of one evaluation episode
    real, total, actions = TASKS[env_id]
    assert values["features/actor/chance"] == [pytest.approx(real / total)]  # the real columns are the task's
    if script in PBRL:
        progress = [line.split(" | ")[1] for line in result.stdout.splitlines() if line.startswith("progress:")]
        assert progress[:3] == ["random", "pre-training", "PbRL"]
        assert values["pbrl/total_feedback"] == [5] and values["pbrl/labeled_feedback"] == [5]

    checkpoint = torch.load(tmp_path / "runs" / "smoke" / "smoke.cleanrl_model", weights_only=False)
    assert (checkpoint["obs_dim_real"], checkpoint["obs_dim"], checkpoint["act_dim"]) == (real, total, actions)
    assert checkpoint["global_step"] == 300
    # the SAC settings the run left unset are its suite's (3 hidden layers on Meta-World); the flags it set win
    settings = {**ene.SUITE_SETTINGS[ene.suite(env_id)], "hidden_dim": 32, "batch_size": 32, "episode_length": 50}
    assert {key: checkpoint["args"][key] for key in settings} == settings


# States every 50 steps from 50 on, through the random steps, pre-training, the feedback round at 200 and the SAC
# updates on the learned reward; evaluations at 200 and 400.
RESUME = ["--checkpoint-freq", "50", "--total-timesteps", "400", "--eval-freq", "200", "--resumable"]


@pytest.mark.parametrize("env_id", ["Hopper-v5", pytest.param("button-press-v3", marks=METAWORLD)])
def test_killed_at_a_random_moment_resumes_exactly_on_a_gymnasium_task(env_id, tmp_path, monkeypatch):
    """test_resume's test on Hopper-v5 and button-press-v3 with the noise: the env's generators (gymnasium's and
    metaworld's among them) and its replayed episode bring a killed run back to where it was, and it ends exactly as
    an uninterrupted run."""
    script = "pebble.py"
    monkeypatch.setitem(test_resume.ARGS, script, args_of(script, env_id) + RESUME)
    window = test_resume.training_time_after_first_state(script, tmp_path, "reference")
    test_resume.kill_at_a_random_moment(script, tmp_path, "killed", window)
    stdout, _ = test_resume.run(script, tmp_path, "killed")
    assert "resuming runs/killed/state.pt at step" in stdout
    test_resume.assert_same_run(script, tmp_path / "runs" / "reference", tmp_path / "runs" / "killed", [200, 400])
