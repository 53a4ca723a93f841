"""A long run you can trust: no host sync in the hot loop, non-finite values stop the run, the log-probability."""
import glob
import os
import random
import runpy
import sys

import numpy as np
import pytest
import torch

from test_scripts import DEVICE, ROOT, SPARSE_TINY, TINY, run_script

import benchmark  # noqa: E402
import pebble  # noqa: E402

Progress = pebble.Progress  # every script's, byte for byte

# Tensor methods that read a tensor back to the host (a device sync on a GPU).
HOST_READS = ["item", "tolist", "cpu", "numpy", "__bool__", "__float__", "__int__"]
# Functions of the training loop that must not read back: the SAC update and the replay buffer's add and sample.
CHECKED = {"sac_update", "ReplayBuffer.add", "ReplayBuffer.sample"}


def run_in_process_recording_host_reads(script, args, tmp_path, monkeypatch):
    """Run `script` in this process with every host read recorded as (the checked function it came from, or None)."""
    path = os.path.join(ROOT, script)
    reads = []

    def recording(name, original):
        def wrapper(self, *a, **k):
            caller = sys._getframe(1)
            # torch's optimisers read their step counter, a host tensor even on a GPU: not a device sync
            if f"{os.sep}torch{os.sep}optim{os.sep}" not in caller.f_code.co_filename:
                frame, inside = caller, None
                while frame is not None:
                    if frame.f_code.co_filename == path:
                        if frame.f_code.co_name == "rigl_update_":
                            inside = None  # a topology update, once per period, not per step: tolerated
                            break
                        owner = frame.f_locals.get("self")  # Python 3.10 has no co_qualname
                        where = frame.f_code.co_name if owner is None else f"{type(owner).__name__}.{frame.f_code.co_name}"
                        if where in CHECKED:
                            inside = where
                    frame = frame.f_back
                reads.append((name, inside))
            return original(self, *a, **k)

        return wrapper

    for name in HOST_READS:
        monkeypatch.setattr(torch.Tensor, name, recording(name, getattr(torch.Tensor, name)))
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "argv", [path, *args])
    python_state, numpy_state = random.getstate(), np.random.get_state()
    with torch.random.fork_rng():  # the script seeds every generator: give the other tests theirs back
        runpy.run_path(path, run_name="__main__")
    random.setstate(python_state)
    np.random.set_state(numpy_state)
    return reads


SAC_TINY = ["--env-id", "cartpole-swingup", "--learning-starts", "200", "--episode-length", "100", "--eval-episodes", "1",
            "--hidden-dim", "32", "--batch-size", "32", "--log-freq", "100", DEVICE]


@pytest.mark.parametrize("script", ["pebble.py", "r2n_pebble.py", "sac.py"])
def test_sac_update_and_replay_buffer_never_read_back_to_the_host(script, tmp_path, monkeypatch):
    args = (SAC_TINY if script == "sac.py" else TINY) + ["--total-timesteps", "800", "--eval-freq", "800"]
    args += SPARSE_TINY if script == "r2n_pebble.py" else []
    reads = run_in_process_recording_host_reads(script, args, tmp_path, monkeypatch)
    assert ("cpu", None) in reads  # the guard is active: the action sent to the env is read back, outside them
    offending = sorted({read for read in reads if read[1] is not None})
    assert not offending, f"host reads inside the hot loop's functions: {offending}"


@pytest.mark.parametrize("script", ["pebble.py", "sac.py"])
def test_non_finite_loss_stops_the_run_with_one_line_and_a_checkpoint(script, tmp_path):
    args = (SAC_TINY if script == "sac.py" else TINY) + ["--q-lr", "1e30", "--log-freq", "10", "--exp-name", "nan"]
    result = run_script(script, args, tmp_path, check=False)
    assert result.returncode == 1
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, result.stderr
    assert lines[0].startswith("nan: error: non-finite ") and " at step " in lines[0], lines[0]
    assert benchmark.NON_FINITE.findall(result.stderr)  # the launcher keeps such a run with what it reached
    quantity = lines[0].split("non-finite ")[1].split(" ")[0]
    assert quantity.startswith(("losses/", "action", "eval/")), quantity
    assert "eval_return=" not in result.stdout  # it stopped long before the first evaluation
    (checkpoint,) = glob.glob(str(tmp_path / "runs" / "*" / "nan.cleanrl_model"))
    assert "actor" in torch.load(checkpoint, weights_only=False)


def test_log_probability_is_the_tanh_squashed_gaussian_density():
    torch.manual_seed(0)
    actor = pebble.Actor(7, 3, 16)
    obs = torch.randn(64, 7) * 3
    torch.manual_seed(1)
    action, log_prob, deterministic = actor.get_action(obs)
    torch.manual_seed(1)
    mean, log_std = actor(obs)
    x = mean + log_std.exp() * torch.randn_like(mean)
    x64 = x.double()  # the reference in float64, where log(1 - tanh^2) does not underflow to -inf
    normal = torch.distributions.Normal(mean.double(), log_std.exp().double(), validate_args=False)
    expected = (normal.log_prob(x64) - torch.log(1 - torch.tanh(x64) ** 2)).sum(-1).float()
    torch.testing.assert_close(action, torch.tanh(x))
    torch.testing.assert_close(log_prob, expected, rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(deterministic, torch.tanh(mean))
    assert log_prob.requires_grad  # the actor loss differentiates through it


def test_progress_duration_text():
    assert Progress.duration(90) == "1m" and Progress.duration(3 * 3600 + 600) == "3h10m"
    assert Progress.duration(50 * 3600) == "2d02h"


def progress_at(progress, monkeypatch, step: int, seconds: float, last_eval: dict, feedback: int = 0):
    """`progress.update` at `step`, `seconds` of training after its clock's start (0), time itself faked."""
    monkeypatch.setattr(pebble.time, "time", lambda: seconds)
    loop = pebble.Loop(total_feedback=feedback, last_eval=last_eval)
    progress.update(step, loop, 0.0)


def test_progress_prints_at_phase_changes_and_reports_sps_eta(capsys, monkeypatch):
    progress = Progress(10_000, {"random": 500, "pre-training": 2000}, "PbRL", step=0, seconds=0.0, budget=400)
    progress_at(progress, monkeypatch, 0, 0.0, {})
    progress_at(progress, monkeypatch, 1000, 40.0, {})  # pre-training: 1000 steps in 40 s of training, 25 SPS, 6 min
    progress_at(progress, monkeypatch, 1001, 40.0, {"eval/episodic_return": 12.34})  # same phase, 0 s later: none
    progress_at(progress, monkeypatch, 1500, 70.0, {"eval/episodic_return": 12.34})  # 30 s later: a line
    progress_at(progress, monkeypatch, 2000, 71.0, {"eval/episodic_return": 12.34}, 10)  # a new phase: at once
    lines = capsys.readouterr().out.splitlines()
    assert lines == [
        "progress: step 0/10000 (0%) | random | 0 SPS | ETA ? | feedback 0/400 | eval return -",
        "progress: step 1000/10000 (10%) | pre-training | 25 SPS | ETA 6m | feedback 0/400 | eval return -",
        "progress: step 1500/10000 (15%) | pre-training | 17 SPS | ETA 8m | feedback 0/400 | eval return 12.3",
        "progress: step 2000/10000 (20%) | PbRL | 500 SPS | ETA 0m | feedback 10/400 | eval return 12.3",
    ]


def test_progress_resumes_from_the_saved_step_and_time(capsys, monkeypatch):
    """A resumed run's first rate counts from its saved step and training time; the oracles have no budget."""
    progress = Progress(10_000, {"random": 500}, "SAC", step=4000, seconds=200.0)
    progress_at(progress, monkeypatch, 4000, 200.0, {"eval/episodic_return": 50.0})
    progress_at(progress, monkeypatch, 4600, 230.0, {"eval/episodic_return": 50.0})
    assert capsys.readouterr().out.splitlines() == [
        "progress: step 4000/10000 (40%) | SAC | 0 SPS | ETA ? | eval return 50.0",
        "progress: step 4600/10000 (46%) | SAC | 20 SPS | ETA 4m | eval return 50.0",
    ]


@pytest.mark.parametrize("script", ["pebble.py", "surf.py", "sac.py"])
def test_progress_counts_training_time_only(script):
    """The main loop hands the progress line its training clock: a person's waits for labels (`run.waited`) left out,
    as the evaluation's SPS leaves them out."""
    source = open(os.path.join(ROOT, script)).read()
    assert source.count("progress.update(global_step, loop, start_time + (run.waited if run else 0.0))") == 1


def test_evaluation_of_a_non_finite_policy_returns_nan_instead_of_crashing_mujoco():
    import ene

    actor = pebble.Actor(51, 1, 16)
    with torch.no_grad():
        actor.net[0].weight.fill_(float("nan"))
    envs = [ene.make_env("cartpole-swingup", seed, 0.9, "gaussian", None, 20) for seed in (1, 2)]
    returns, success = pebble.evaluate(actor, envs, torch.device("cpu"))  # MuJoCo raises on a NaN control
    assert returns.shape == (2,) and np.isnan(returns).all() and np.isnan(success).all()  # no success flag here
