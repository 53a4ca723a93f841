"""Each script's numerics, bit for bit, against the code that ran the CPU study (commit `REFERENCE_COMMIT`).

Issue 18 moved code around without changing what it computes; later changes to the eager CPU path must not change it
either (a change that does is a numerics change: it lands before the runs that use it, and this reference moves).
Each test runs the script as it was at the reference commit (with that commit's `ene.py`) and as it is now, with the
same tiny configuration through every phase, and compares every TensorBoard point but SPS and every checkpoint tensor.
"""
import os
import subprocess
import sys

import pytest
import torch

from test_resume import points
from test_scripts import ROOT

REFERENCE_COMMIT = "88b95d9"  # the cpu-study's code, before the layout change of issue 18

PBRL = ["--env-id", "cartpole-swingup", "--noise", "0.9", "--total-timesteps", "1500", "--learning-starts", "200",
        "--unsup-steps", "300", "--feedback-freq", "500", "--episode-length", "100", "--eval-freq", "750",
        "--eval-episodes", "2", "--segment-size", "20", "--max-feedback", "20", "--queries-per-round", "5",
        "--hidden-dim", "32", "--batch-size", "32", "--reward-hidden-dim", "16", "--reward-layers", "2",
        "--reward-epochs", "20", "--log-freq", "100"]
ORACLE = ["--env-id", "cartpole-swingup", "--noise", "0.9", "--total-timesteps", "1000", "--learning-starts", "200",
          "--episode-length", "100", "--eval-freq", "500", "--eval-episodes", "2", "--hidden-dim", "32",
          "--batch-size", "32", "--log-freq", "100"]
SPARSE = ["--reward-topology-period", "5", "--agent-topology-period", "100"]  # topology updates within the run
ARGS = {
    "pebble.py": PBRL, "r2n_pebble.py": PBRL + SPARSE, "set_pebble.py": PBRL + SPARSE, "static_pebble.py": PBRL,
    "l1_pebble.py": PBRL, "dropconnect_pebble.py": PBRL, "surf.py": PBRL + ["--surf-tau", "0.6"],
    "r2n_surf.py": PBRL + SPARSE + ["--surf-tau", "0.6"], "rune.py": PBRL, "r2n_rune.py": PBRL + SPARSE,
    "sac.py": ORACLE, "anf_sac.py": ORACLE + ["--agent-topology-period", "100"],
}


def reference_source(path: str) -> bytes:
    result = subprocess.run(["git", "show", f"{REFERENCE_COMMIT}:{path}"], cwd=ROOT, capture_output=True)
    if result.returncode != 0:
        pytest.skip(f"commit {REFERENCE_COMMIT} is not available here (no git history): {result.stderr.decode()[:80]}")
    return result.stdout


def checkpoint_differences(a, b, key=""):
    """The keys at which two checkpoints differ (tensors bitwise, other values by equality)."""
    if isinstance(a, torch.Tensor) or isinstance(b, torch.Tensor):
        same = isinstance(a, torch.Tensor) and isinstance(b, torch.Tensor) and a.dtype == b.dtype and torch.equal(a, b)
        return [] if same else [key]
    if isinstance(a, dict) and isinstance(b, dict):
        if set(a) != set(b):
            return [f"{key} (keys {sorted(set(a) ^ set(b))})"]
        return [d for name in a for d in checkpoint_differences(a[name], b[name], f"{key}/{name}")]
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)) and len(a) == len(b):
        return [d for i, (x, y) in enumerate(zip(a, b)) for d in checkpoint_differences(x, y, f"{key}[{i}]")]
    return [] if a == b else [key]


@pytest.mark.parametrize("script", list(ARGS))
def test_numerics_equal_the_reference(script, tmp_path):
    reference = tmp_path / "reference"
    reference.mkdir()
    for path in (script, "ene.py"):
        (reference / path).write_bytes(reference_source(path))
    current = tmp_path / "current"
    current.mkdir()
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONWARNINGS="ignore")
    args = ARGS[script] + ["--no-cuda", "--seed", "3", "--exp-name", "numerics", "--run-name", "numerics"]
    runs = {cwd: subprocess.Popen([sys.executable, str(code), *args], cwd=cwd, env=env, stdout=subprocess.DEVNULL,
                                  stderr=subprocess.PIPE, text=True)  # both at once: CI has two cores
            for cwd, code in ((reference, reference / script), (current, os.path.join(ROOT, script)))}
    for cwd, process in runs.items():
        _, stderr = process.communicate(timeout=600)
        assert process.returncode == 0, f"{cwd.name} {script}: {stderr[-2000:]}"

    logged = {cwd: points(cwd / "runs" / "numerics") for cwd in runs}
    assert sorted(logged[reference]) == sorted(logged[current]), "the two runs logged different tags"
    drifted = [tag for tag in logged[reference] if tag != "charts/SPS" and logged[reference][tag] != logged[current][tag]]
    assert not drifted, f"{script}: TensorBoard values differ from {REFERENCE_COMMIT}'s in {drifted}"

    checkpoints = [torch.load(cwd / "runs" / "numerics" / "numerics.cleanrl_model", weights_only=False) for cwd in runs]
    for checkpoint in checkpoints:  # the flags are the run's input, not its numerics (flags added since differ)
        del checkpoint["args"]
    differences = checkpoint_differences(*checkpoints)
    assert not differences, f"{script}: the final checkpoint differs from {REFERENCE_COMMIT}'s at {differences}"
