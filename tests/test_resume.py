"""Exact resume (docs/running.md: "Resuming a run"): a run killed at a random moment after its first `state.pt` and started
again with the same command ends exactly as an uninterrupted run: the same points in TensorBoard (SPS aside, whose
values are wall-clock), no duplicate, no gap, and bitwise-identical final weights. Also: a kill during the write of
the state, SIGTERM, and the checks on `--run-name` and on flags that changed."""
import glob
import os
import random
import re
import shutil
import signal
import subprocess
import sys
import time

import pytest
import torch
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from test_scripts import DEVICE, ROOT, SPARSE_TINY, TINY

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

# TINY, shortened: feedback rounds at 500 and 750 steps, evaluations at 400, 800 and 900, a state every 150 steps
# (the first at 150, during the random steps).
RESUME = ["--total-timesteps", "900", "--feedback-freq", "250", "--eval-freq", "400", "--checkpoint-freq", "150",
          "--resumable", "--query-log", "--diagnostics"]  # and what the harness saves and logs
ORACLE = [
    "--env-id", "cartpole-swingup", "--noise", "0.9", "--total-timesteps", "900", "--learning-starts", "200",
    "--episode-length", "100", "--eval-freq", "400", "--eval-episodes", "2", "--hidden-dim", "32", "--batch-size", "32",
    "--log-freq", "100", DEVICE, "--checkpoint-freq", "150", "--resumable", "--diagnostics",
]
ARGS = {
    "sac.py": ORACLE,
    "anf_sac.py": ORACLE + ["--agent-topology-period", "100"],
    "pebble.py": TINY + RESUME,
    "r2n_pebble.py": TINY + RESUME + SPARSE_TINY,
    "set_pebble.py": TINY + RESUME + SPARSE_TINY,
    "static_pebble.py": TINY + RESUME,
    "l1_pebble.py": TINY + RESUME,
    "dropconnect_pebble.py": TINY + RESUME,
    "surf.py": TINY + RESUME + ["--surf-tau", "0.6"],
    "r2n_surf.py": TINY + RESUME + SPARSE_TINY + ["--surf-tau", "0.6"],
    "rune.py": TINY + RESUME,
    "r2n_rune.py": TINY + RESUME + SPARSE_TINY,
}


def start(script, cwd, run_name, *extra, wrapper=None):
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONWARNINGS="ignore")
    command = [os.path.join(ROOT, script), *ARGS[script], "--run-name", run_name, *extra]
    command = [sys.executable, "-c", wrapper, *command] if wrapper else [sys.executable, *command]
    return subprocess.Popen(command, cwd=cwd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def run(script, cwd, run_name, *extra):
    process = start(script, cwd, run_name, *extra)
    stdout, stderr = process.communicate(timeout=600)
    assert process.returncode == 0, stderr[-3000:]
    return stdout, stderr


def points(run_dir):
    """tag -> [(step, value)] as TensorBoard shows them (the reader applies the purge of a resumed run)."""
    events = EventAccumulator(str(run_dir), size_guidance={"scalars": 0})
    events.Reload()
    return {tag: [(e.step, e.value) for e in events.Scalars(tag)] for tag in events.Tags()["scalars"]}


def tensors(checkpoint, prefix=""):
    if isinstance(checkpoint, torch.Tensor):
        yield prefix, checkpoint
    elif isinstance(checkpoint, (dict, list)):
        for key, value in checkpoint.items() if isinstance(checkpoint, dict) else enumerate(checkpoint):
            yield from tensors(value, f"{prefix}/{key}")


def assert_same_run(script, reference, resumed, eval_steps=(400, 800, 900)):
    """The same points (SPS: the same steps), evaluations at `eval_steps`, bitwise the same checkpoint tensors."""
    expected, actual = points(reference), points(resumed)
    assert sorted(expected) == sorted(actual)
    for tag in expected:
        if tag == "charts/SPS":
            assert [s for s, _ in actual[tag]] == [s for s, _ in expected[tag]]
        else:
            assert actual[tag] == expected[tag], f"{script}: {tag} differs"
    assert [s for s, _ in actual["eval/episodic_return"]] == list(eval_steps)
    name = script[:-3]
    expected = dict(tensors(torch.load(f"{reference}/{name}.cleanrl_model", weights_only=False)))
    actual = dict(tensors(torch.load(f"{resumed}/{name}.cleanrl_model", weights_only=False)))
    assert sorted(expected) == sorted(actual) and expected
    for key in expected:
        assert torch.equal(expected[key], actual[key]), f"{script}: checkpoint tensor {key} differs"


def wait_for(path, process):
    while not os.path.exists(path):
        assert process.poll() is None, process.communicate()[1][-3000:]
        time.sleep(0.02)


def training_time_after_first_state(script, cwd, run_name):
    """Run to the end; the seconds from its first `state.pt` to the deletion of the last one, that is, the stretch
    in which a kill leaves a state to resume (the teardown after the deletion is not in it)."""
    process = start(script, cwd, run_name)
    state = cwd / "runs" / run_name / "state.pt"
    wait_for(state, process)
    first = time.monotonic()
    while os.path.exists(state) and process.poll() is None:
        time.sleep(0.01)
    seconds = time.monotonic() - first
    _, stderr = process.communicate(timeout=600)
    assert process.returncode == 0, stderr[-3000:]
    return seconds


def kill_at_a_random_moment(script, cwd, run_name, window):
    """Start the run and SIGKILL it at a random moment of its first `window` seconds with a state.
    A kill that comes after the run ended leaves no state: the run starts again, with the draw
    inside the time that run took (under load a run can be faster than the reference)."""
    folder = cwd / "runs" / run_name
    for _ in range(5):
        process = start(script, cwd, run_name)
        wait_for(folder / "state.pt", process)
        delay = random.uniform(0.0, 0.7 * window)
        time.sleep(delay)  # not a wait for anything: the kill comes at a random moment
        process.send_signal(signal.SIGKILL)
        process.communicate()
        if os.path.exists(folder / "state.pt"):
            return
        shutil.rmtree(folder)
        window = delay
    pytest.fail(f"{script}: five runs ended before a kill inside their stretch: lengthen the run")


@pytest.mark.parametrize("script", list(ARGS))
def test_killed_at_a_random_moment_resumes_exactly(script, tmp_path):
    window = training_time_after_first_state(script, tmp_path, "reference")
    kill_at_a_random_moment(script, tmp_path, "killed", window)
    stdout, _ = run(script, tmp_path, "killed")  # the same command again
    resumed_at = int(re.search(r"resuming runs/killed/state\.pt at step (\d+)", stdout).group(1))
    saved = re.search(r"state saved after step \d+: \d+\.\d\d GB in \d+\.\d s", stdout)
    # A state every 150 steps: the last is at step 750, so a run resumed there has none left to save.
    assert bool(saved) == (resumed_at < 750), (resumed_at, stdout)
    assert_same_run(script, tmp_path / "runs" / "reference", tmp_path / "runs" / "killed")
    assert not os.path.exists(tmp_path / "runs" / "killed" / "state.pt")  # deleted at the end without --keep-state
    assert len(glob.glob(str(tmp_path / "runs" / "killed" / "events.out.tfevents.*"))) == 2


# torch.save, patched in the run: the second state is cut off after a few bytes by a SIGKILL of the process itself
KILL_DURING_WRITE = """
import os, runpy, signal, sys, torch
save, calls = torch.save, []
def cut_save(obj, f, *args, **kwargs):
    if getattr(f, "name", "").endswith("state.pt.tmp"):
        calls.append(f.name)
        if len(calls) == 2:
            f.write(b"PK\\x03\\x04 half a state")
            f.flush()
            os.kill(os.getpid(), signal.SIGKILL)
    return save(obj, f, *args, **kwargs)
torch.save = cut_save
sys.argv = sys.argv[1:]
sys.path.insert(0, os.path.dirname(sys.argv[0]))
runpy.run_path(sys.argv[0], run_name="__main__")
"""


def test_a_kill_during_the_write_keeps_the_previous_state(tmp_path):
    run("pebble.py", tmp_path, "reference")
    process = start("pebble.py", tmp_path, "cut", wrapper=KILL_DURING_WRITE)
    process.communicate(timeout=600)
    assert process.returncode == -signal.SIGKILL
    folder = tmp_path / "runs" / "cut"
    assert (folder / "state.pt.tmp").read_bytes().startswith(b"PK\x03\x04 half")
    assert torch.load(folder / "state.pt", weights_only=False)["global_step"] == 150  # the first state, intact
    stdout, _ = run("pebble.py", tmp_path, "cut")
    assert "resuming runs/cut/state.pt at step 150" in stdout
    assert_same_run("pebble.py", tmp_path / "runs" / "reference", folder)


def test_sigterm_saves_the_state_and_exits_then_resumes_exactly(tmp_path):
    run("r2n_pebble.py", tmp_path, "reference", "--keep-state")
    assert torch.load(tmp_path / "runs" / "reference" / "state.pt", weights_only=False)["global_step"] == 900
    process = start("r2n_pebble.py", tmp_path, "stopped")
    wait_for(tmp_path / "runs" / "stopped" / "state.pt", process)
    process.send_signal(signal.SIGTERM)
    _, stderr = process.communicate(timeout=600)
    assert process.returncode == 1
    assert "stopped by SIGTERM after step" in stderr and "--run-name stopped to resume" in stderr
    step = int(stderr.split("after step ")[1].split(";")[0])
    assert torch.load(tmp_path / "runs" / "stopped" / "state.pt", weights_only=False)["global_step"] == step
    stdout, _ = run("r2n_pebble.py", tmp_path, "stopped", "--threads", "1", "--log-freq", "100")  # may change
    assert f"resuming runs/stopped/state.pt at step {step}" in stdout
    assert_same_run("r2n_pebble.py", tmp_path / "runs" / "reference", tmp_path / "runs" / "stopped")


def test_videos_of_a_resumed_run_go_to_a_folder_of_their_own(tmp_path, monkeypatch):
    """`--capture-video` across a resume: the first start's clip stays, the second start's clips go to
    `videos/{run}/resumed-at-{step}/` (nothing overwritten), and filming changes no number."""
    monkeypatch.setenv("MUJOCO_GL", "egl")  # no display here: Mesa's EGL (.ci/run installs it)
    run("pebble.py", tmp_path, "reference")
    process = start("pebble.py", tmp_path, "filmed", "--capture-video")
    videos = tmp_path / "videos" / "filmed"
    wait_for(videos / "rl-video-episode-0.mp4", process)  # the evaluation at step 400 (RecordVideo: episodes 0, 1, 8, ...)
    process.send_signal(signal.SIGTERM)
    _, stderr = process.communicate(timeout=600)
    assert process.returncode == 1, stderr[-3000:]
    step = int(stderr.split("after step ")[1].split(";")[0])
    assert 400 <= step < 800, f"stopped at step {step}, past the next evaluation: lengthen the run"
    run("pebble.py", tmp_path, "filmed", "--capture-video")
    clips = sorted(p.relative_to(videos).as_posix() for p in videos.rglob("*.mp4"))
    assert clips == ["resumed-at-%d/rl-video-episode-%d.mp4" % (step, i) for i in (0, 1)] + ["rl-video-episode-0.mp4"]
    for clip in clips:
        data = (videos / clip).read_bytes()
        assert data[4:8] == b"ftyp" and len(data) > 1000, clip  # an MP4 with frames, not an empty file
    assert_same_run("pebble.py", tmp_path / "runs" / "reference", tmp_path / "runs" / "filmed")


def test_run_name_errors_are_one_line_and_lose_nothing(tmp_path):
    process = start("sac.py", tmp_path, "a")
    wait_for(tmp_path / "runs" / "a" / "state.pt", process)
    process.send_signal(signal.SIGKILL)
    process.communicate()
    before = sorted(os.listdir(tmp_path / "runs" / "a"))
    cases = [
        (["--seed", "2", "--noise", "0.5"], "a", "differs in --seed 1 (now 2), --noise 0.9 (now 0.5)"),
        ([], "a/b", "--run-name must be a folder name"),
        (["--checkpoint-freq", "0"], "c", "--checkpoint-freq must be >= 1"),
        (["--state-minutes", "0"], "c", "--state-minutes must be > 0"),
    ]
    for extra, name, message in cases:
        process = start("sac.py", tmp_path, name, *extra)
        _, stderr = process.communicate(timeout=120)
        assert process.returncode == 1 and message in stderr, stderr
        assert len(stderr.strip().splitlines()) == 1, stderr
    assert sorted(os.listdir(tmp_path / "runs" / "a")) == before
    (tmp_path / "runs" / "done").mkdir()  # a folder without a state: a finished run, never overwritten
    process = start("sac.py", tmp_path, "done")
    _, stderr = process.communicate(timeout=120)
    assert process.returncode == 1 and "holds no state.pt to resume" in stderr
    # a state saved before a flag existed: the flag counts at its default (here --tau, dropped from the saved flags)
    state = torch.load(tmp_path / "runs" / "a" / "state.pt", weights_only=False)
    del state["args"]["tau"], state["args"]["hidden_layers"]  # the second: two hidden layers then, as now
    torch.save(state, tmp_path / "runs" / "a" / "state.pt")
    process = start("sac.py", tmp_path, "a", "--tau", "0.01")
    _, stderr = process.communicate(timeout=120)
    assert process.returncode == 1 and "differs in --tau 0.005 (now 0.01)" in stderr, stderr
    process = start("sac.py", tmp_path, "a")
    stdout, stderr = process.communicate(timeout=300)
    assert process.returncode == 0 and "resuming runs/a/state.pt" in stdout, stderr
    (tmp_path / "runs" / "old").mkdir()  # a state of the layout before issue 18: refused, with the version to use
    old_state = {"args": state["args"], "global_step": 150, "loop": (0, 0.0, 0, {}, {}, None, [])}
    torch.save(old_state, tmp_path / "runs" / "old" / "state.pt")
    process = start("sac.py", tmp_path, "old")
    _, stderr = process.communicate(timeout=120)
    assert process.returncode == 1 and "written by an older version" in stderr and len(stderr.strip().splitlines()) == 1
    (tmp_path / "runs" / "a").rename(tmp_path / "runs" / "a-done")
    process = start("sac.py", tmp_path, "a")  # a new run in the same name: killed right after its first state
    wait_for(tmp_path / "runs" / "a" / "state.pt", process)
    process.send_signal(signal.SIGKILL)
    process.communicate()
    (tmp_path / "runs" / "a" / "state.pt").write_bytes(b"not a state")
    process = start("sac.py", tmp_path, "a")
    _, stderr = process.communicate(timeout=120)
    assert process.returncode == 1 and "cannot read runs/a/state.pt" in stderr


def test_state_is_written_by_wall_time_or_every_n_steps(monkeypatch):
    """`--state-minutes` after the last state (a clock, not the step count), `--checkpoint-freq` steps if given."""
    sys.path.insert(0, ROOT)
    import pebble
    from r2n_harness import resume
    from r2n_harness.resume import state_due

    now = [1000.0]
    monkeypatch.setattr(resume.time, "monotonic", lambda: now[0])
    args = pebble.Args(total_timesteps=100, state_minutes=1.0)
    assert not state_due(10, args, last_state=1000.0)
    now[0] = 1059.9
    assert not state_due(11, args, last_state=1000.0)
    now[0] = 1060.0
    assert state_due(12, args, last_state=1000.0)
    assert not state_due(99, args, last_state=0.0)  # the last step: only with --keep-state
    args.keep_state = True
    assert state_due(99, args, last_state=now[0])
    args.checkpoint_freq = 25
    assert state_due(24, args, last_state=now[0]) and not state_due(25, args, last_state=0.0)
