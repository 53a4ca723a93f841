"""Scripts end to end: smoke runs that reach every phase, their tags and checkpoint, determinism, bad input."""
import glob
import math
import os
import re
import shutil
import subprocess
import sys

import pytest
import torch
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PBRL_SCRIPTS = ["pebble.py", "r2n_pebble.py"]
SPARSE_SCRIPTS = ["r2n_pebble.py"]
# CI has no GPU, so the script tests run on the CPU; R2N_TEST_CUDA=1 runs them on the GPU, R2N_TEST_CUDA=graph on the
# GPU with `--cuda-graph` (docs/running.md: "Testing on a GPU")
DEVICE = {"1": "--cuda", "graph": "--cuda-graph"}.get(os.environ.get("R2N_TEST_CUDA"), "--no-cuda")

# Tiny but complete: random steps (0-199), pre-training (200-499), first feedback round + critic reset at 500,
# rounds every 500 steps until the budget of 20 is spent (5 per round), SAC updates, evaluation and checkpoint
# every 1000 steps. Sparse scripts: reward topology every 5 reward steps, agent topology every 100 SAC steps.
TINY = [
    "--env-id", "cartpole-swingup", "--noise", "0.9", "--total-timesteps", "3000", "--learning-starts", "200",
    "--unsup-steps", "300", "--feedback-freq", "500", "--episode-length", "100", "--eval-freq", "1000",
    "--eval-episodes", "2", "--segment-size", "20", "--max-feedback", "20", "--queries-per-round", "5",
    "--hidden-dim", "32", "--batch-size", "32", "--reward-hidden-dim", "16", "--reward-layers", "2",
    "--reward-epochs", "20", "--log-freq", "100", DEVICE,
]
SPARSE_TINY = ["--reward-topology-period", "5", "--agent-topology-period", "100"]

COMMON_TAGS = [
    "eval/episodic_return", "charts/episodic_return", "charts/episodic_length", "charts/SPS",
    "losses/qf1_loss", "losses/qf2_loss", "losses/qf_loss", "losses/actor_loss", "losses/alpha", "losses/alpha_loss",
    "losses/state_entropy_reward",
    "pbrl/total_feedback", "pbrl/labeled_feedback", "pbrl/reward_loss", "pbrl/reward_accuracy", "pbrl/reward_epochs",
]
DIAGNOSTIC_TAGS = ["pbrl/reward_steps", "pbrl/reward_true_corr", "pbrl/heldout_accuracy"]  # --diagnostics
HARNESS = ["--resumable", "--query-log", "--diagnostics"]  # the run harness's hooks, none of which changes a number
SPARSE_NETS = ["actor", "qf1", "qf2", "reward0", "reward1", "reward2"]
SPARSE_TAGS = [f"sparse/{net}/{m}" for net in SPARSE_NETS for m in ("relevant_degree", "noise_degree", "relevant_active_frac")]
TOPOLOGY_TAGS = [f"sparse/{net}/topology_updates" for net in SPARSE_NETS]  # Static logs 0
# every script, dense or sparse: the input layers' weight share on relevant columns, and its chance level
FEATURE_TAGS = [f"features/{net}/{m}" for net in SPARSE_NETS for m in ("relevant_weight_frac", "chance")]  # the same


def check_diagnostics(values):
    """The PbRL diagnostics of every feedback round: cumulative reward steps, correlation, held-out accuracy."""
    steps = values["pbrl/reward_steps"]
    assert len(steps) == len(values["pbrl/total_feedback"]) and steps[0] > 0
    assert all(a <= b for a, b in zip(steps, steps[1:])), steps  # cumulative
    assert all(-1 <= v <= 1 for v in values["pbrl/reward_true_corr"])
    assert all(0 <= v <= 1 for v in values["pbrl/heldout_accuracy"])


def check_features(values, nets):
    """`features/{net}/*` at every evaluation: a share in (0, 1) and the chance level of cartpole-swingup at 0.9."""
    for net in nets:
        assert len(values[f"features/{net}/relevant_weight_frac"]) == len(values["eval/episodic_return"])
        assert all(0 < v < 1 for v in values[f"features/{net}/relevant_weight_frac"])
        chance = 5 / 51 if net == "actor" else 6 / 52  # 5 real of 51 features, plus the 1 action column
        assert values[f"features/{net}/chance"] == pytest.approx([chance] * len(values["eval/episodic_return"]))


# A copied script: the script and ene.py alone in a folder, run where this project cannot be imported (its editable
# install's finder removed, nothing of it on the path), as in a user's own work with the design card's packages.
COPIED = """import importlib.util, os, runpy, sys
sys.meta_path[:] = [finder for finder in sys.meta_path if "__editable__" not in repr(finder)]
sys.argv, sys.path[0] = sys.argv[1:], os.path.dirname(sys.argv[1])
sys.path[:] = [path for path in sys.path if not os.path.isdir(os.path.join(path or ".", "r2n_harness"))]
assert importlib.util.find_spec("r2n_harness") is None and importlib.util.find_spec("analyze") is None
runpy.run_path(sys.argv[0], run_name="__main__")
"""


def run_script(script, args, cwd, check=True, copied=False):
    """Run `script` in `cwd`; `copied`: a copy of it with ene.py, without this project (`COPIED`), unless its flags
    ask for the run harness (R2N_TEST_CUDA=graph's `--cuda-graph`)."""
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONWARNINGS="ignore")
    command = [sys.executable, os.path.join(ROOT, script), *args]
    if copied and DEVICE != "--cuda-graph":
        folder = os.path.join(cwd, "copied")
        os.makedirs(folder, exist_ok=True)
        for name in (script, "ene.py"):
            shutil.copy(os.path.join(ROOT, name), folder)
        env.pop("PYTHONPATH", None)
        command = [sys.executable, "-c", COPIED, os.path.join(folder, script), *args]
    return subprocess.run(command, cwd=cwd, env=env, capture_output=True, text=True, check=check, timeout=600)


def scalars(run_dir):
    events = EventAccumulator(run_dir, size_guidance={"scalars": 0})
    events.Reload()
    return {tag: [e.value for e in events.Scalars(tag)] for tag in events.Tags()["scalars"]}


def tiny_args(script):
    return TINY + (SPARSE_TINY if script in SPARSE_SCRIPTS else [])


def check_progress(stdout: str, phases=("random", "pre-training", "PbRL")):
    """A default run's progress lines: one at each phase change, the second (past the random steps) with a rate and
    an ETA, before the first evaluation line."""
    progress = [line for line in stdout.splitlines() if line.startswith("progress:")]
    assert [line.split(" | ")[1] for line in progress[: len(phases)]] == list(phases), progress
    assert re.search(r"\| \d+ SPS \| ETA \d+m", progress[1]), progress[1]
    assert stdout.index("progress:") < stdout.index("eval_return=")
    assert ("feedback" in progress[0]) == ("PbRL" in phases)


@pytest.mark.parametrize("script", PBRL_SCRIPTS)
def test_smoke_reaches_every_phase(script, tmp_path):
    """A copy of the script, with ene.py alone and without this project, runs its method through every phase, and
    with its default flags it writes what the method writes and nothing of the harness's."""
    result = run_script(script, tiny_args(script) + ["--exp-name", "smoke"], tmp_path, copied=True)
    (run_dir,) = glob.glob(str(tmp_path / "runs" / "*"))
    values = scalars(run_dir)

    expected = COMMON_TAGS + (SPARSE_TAGS + TOPOLOGY_TAGS if script in SPARSE_SCRIPTS else [])
    missing = [tag for tag in expected if tag not in values]
    assert not missing, f"missing tags {missing}"
    for tag in expected:
        assert all(math.isfinite(v) for v in values[tag]), f"{tag} has non-finite values {values[tag]}"
    assert not [tag for tag in values if tag in DIAGNOSTIC_TAGS or tag.startswith("features/")]
    assert sorted(os.listdir(run_dir))[1:] == ["smoke.cleanrl_model"]  # the event file, the checkpoint
    check_progress(result.stdout)  # the script's own progress line, without the harness

    # pre-training logged its intrinsic reward; every feedback round ran; the whole budget was asked
    assert values["pbrl/total_feedback"] == [5, 10, 15, 20]
    assert values["pbrl/labeled_feedback"][-1] == 20
    assert len(values["eval/episodic_return"]) == 3  # at 1000, 2000, 3000
    assert result.stdout.count("eval_return=") == 3

    checkpoint = torch.load(os.path.join(run_dir, "smoke.cleanrl_model"), weights_only=False)
    for key in ("args", "actor", "qf1", "qf2", "reward_models", "obs_dim_real", "obs_dim", "act_dim"):
        assert key in checkpoint
    assert (checkpoint["obs_dim_real"], checkpoint["obs_dim"], checkpoint["act_dim"]) == (5, 51, 1)
    assert len(checkpoint["reward_models"]) == 3
    assert checkpoint["global_step"] == 3000

    # the checkpoint loads into the script's own networks
    sys.path.insert(0, ROOT)
    module = __import__(script[:-3])
    actor = module.Actor(51, 1, 32)
    actor.load_state_dict(checkpoint["actor"])
    qf1 = module.SoftQNetwork(51, 1, 32)
    qf1.load_state_dict(checkpoint["qf1"])

    if script in SPARSE_SCRIPTS:
        masks = checkpoint["masks"]
        assert sorted(masks) == sorted(SPARSE_NETS)
        for name, mask in masks.items():
            n = mask.numel()
            assert mask.sum().item() == n - math.floor(0.8 * n), name
        # masked weights are exactly zero in the saved networks
        assert torch.all(checkpoint["actor"]["net.0.weight"][masks["actor"] == 0] == 0)
        assert torch.all(checkpoint["qf1"]["net.0.weight"][masks["qf1"] == 0] == 0)
        for e in range(3):
            assert torch.all(checkpoint["reward_models"][e]["weights.0"][masks[f"reward{e}"] == 0] == 0)
        # topology updates happened: the reward members' connectivity moved between evaluations
        assert len(set(values["sparse/reward0/relevant_active_frac"])) > 1


@pytest.mark.skipif(DEVICE == "--no-cuda", reason="the script tests run on the CPU (R2N_TEST_CUDA=1: on the GPU)")
def test_gpu_runs_have_a_gpu():
    assert torch.cuda.is_available(), "R2N_TEST_CUDA=1 but torch sees no GPU: the tests would run on the CPU"


def test_same_seed_same_run_with_or_without_the_harness(tmp_path):
    """The same seed twice, once with the harness's hooks (state, query log, diagnostics): every point of the method is
    the same, and the harness adds its diagnostics and its files, not a second progress line."""
    args = tiny_args("r2n_pebble.py") + ["--total-timesteps", "1500", "--eval-freq", "750", "--seed", "7"]
    runs, outputs = [], []
    for i, extra in enumerate(([], HARNESS)):
        outputs.append(run_script("r2n_pebble.py", args + ["--run-name", f"det{i}", *extra], tmp_path).stdout)
        runs.append(scalars(str(tmp_path / "runs" / f"det{i}")))
    assert len(runs[0]["eval/episodic_return"]) == 2
    assert all(runs[0][tag] == runs[1][tag] for tag in runs[0] if tag != "charts/SPS")
    added = sorted(set(runs[1]) - set(runs[0]))
    assert added == sorted(DIAGNOSTIC_TAGS + FEATURE_TAGS), added
    values = runs[1]
    check_diagnostics(values)
    check_features(values, SPARSE_NETS)
    # one reward topology update every 5 reward optimiser steps (the last round precedes the last evaluation)
    assert values["sparse/reward0/topology_updates"][-1] == values["pbrl/reward_steps"][-1] // 5 > 0
    assert sorted(os.listdir(tmp_path / "runs" / "det1" / "preferences")) == ["0.npz", "1.npz"]
    # progress: a line at every phase change, with ETA, before the first evaluation; one line, not the harness's too
    for output in outputs:
        progress = [line for line in output.splitlines() if line.startswith("progress:")]
        assert [p.split(" | ")[1] for p in progress[:3]] == ["random", "pre-training", "PbRL"]
        assert output.index("progress:") < output.index("eval_return=")
        assert re.search(r"\| \d+ SPS \| ETA \d+m \|", progress[1]) and "feedback 0/20" in progress[1], progress[1]
        assert len([p for p in progress if p.startswith("progress: step 0/")]) == 1


def test_evaluation_envs_in_processes_give_the_same_run(tmp_path):
    """`--parallel-eval` steps the evaluation envs at once in processes of their own: every point is the same."""
    args = tiny_args("pebble.py") + ["--total-timesteps", "1500", "--eval-freq", "750", "--eval-episodes", "3"]
    runs = []
    for i, extra in enumerate(([], ["--parallel-eval"])):
        run_script("pebble.py", args + ["--run-name", f"eval{i}", *extra], tmp_path)
        runs.append(scalars(str(tmp_path / "runs" / f"eval{i}")))
    assert len(runs[0]["eval/episodic_return"]) == 2
    assert runs[0].keys() == runs[1].keys()
    assert all(runs[0][tag] == runs[1][tag] for tag in runs[0] if tag != "charts/SPS")


@pytest.mark.parametrize(
    "bad, flag",
    [
        (["--noise", "1.0"], "--noise"),
        (["--env-id", "cheetah-fly"], "--env-id"),
        (["--max-feedback", "0"], "--max-feedback"),
        (["--segment-size", "500"], "--segment-size"),
        (["--noise-type", "imitate"], "--noise-histograms"),
        (["--noise-type", "imitate", "--noise-histograms", "missing.npz"], "--noise-histograms"),
    ],
)
def test_bad_input_fails_fast_with_one_line(bad, flag, tmp_path):
    result = run_script("r2n_pebble.py", TINY + bad, tmp_path, check=False)
    assert result.returncode != 0
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and flag in lines[0], result.stderr
    assert not os.path.exists(tmp_path / "runs"), "nothing is written before the input is checked"


@pytest.mark.parametrize("script", PBRL_SCRIPTS)
def test_help_documents_every_flag(script, tmp_path):
    result = run_script(script, ["--help"], tmp_path)
    for flag in ("--env-id", "--noise", "--noise-resample", "--max-feedback", "--queries-per-round", "--teacher-beta"):
        assert flag in result.stdout
    if script in SPARSE_SCRIPTS:
        for flag in ("--sparse-reward", "--no-sparse-agent", "--reward-sparsity", "--agent-topology-period"):
            assert flag in result.stdout


PBRL_ALL = ["pebble.py", "r2n_pebble.py", "set_pebble.py", "static_pebble.py", "l1_pebble.py", "dropconnect_pebble.py",
            "surf.py", "r2n_surf.py", "rune.py", "r2n_rune.py"]


def check_harness_flag_stops_a_copy(script, args, flag, cwd):
    """Copied without this project, `script` given a flag that needs the run harness's package stops before training
    with one line that names the flag and the package; nothing is written."""
    if DEVICE == "--cuda-graph":
        pytest.skip("R2N_TEST_CUDA=graph: every run asks for the harness's --cuda-graph")
    result = run_script(script, args, cwd, check=False, copied=True)
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert result.returncode != 0 and len(lines) == 1, result.stderr
    assert f"{flag} needs the package r2n_harness" in lines[0], lines
    assert not os.path.exists(os.path.join(cwd, "runs"))


@pytest.mark.parametrize("script", PBRL_ALL)
def test_a_copied_script_stops_at_a_harness_flag_with_one_line(script, tmp_path):
    check_harness_flag_stops_a_copy(script, TINY + ["--teacher", "external"], "--teacher external", tmp_path)
    check_harness_flag_stops_a_copy(script, TINY + ["--preferences", "prefs"], "--preferences", tmp_path)
    for flag in HARNESS:
        check_harness_flag_stops_a_copy(script, TINY + [flag], flag, tmp_path)
