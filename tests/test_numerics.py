"""Each script's numerics, bit for bit, against the code that ran the CPU study (commit `REFERENCE_COMMIT`).

Issue 18 moved code around without changing what it computes; later changes to the eager CPU path must not change it
either (a change that does is a numerics change: it lands before the runs that use it, and this reference moves).
Each test runs the script as it was at the reference commit (with that commit's `ene.py`) and as it is now, with the
same tiny configuration through every phase, and compares every TensorBoard point but SPS and every checkpoint entry.

Both noise variants are pinned. `--noise-resample` (the reference's default) gives the reference's redrawn runs in
every script. The default, the noise stored, gives the reference's `--no-noise-resample` runs, the numerics of the
stored-noise study, in the four scripts that study ran (the other eight share their storage code byte for byte).

`target_update` sets subnormal target weights to zero; the reference kept them. A run with a fast Polyak average
drives them into the subnormals, and its points and checkpoint are still the reference's.
"""
import os
import subprocess
import sys

import pytest
import torch

from test_resume import points
from test_scripts import ROOT

import r2n_harness.diagnostics as diagnostics  # noqa: E402 (test_scripts puts the repository on the path)

REFERENCE_COMMIT = "88b95d9"  # the code of the cpu-study, before the layout change of issue 18

# Through every phase in 1500 steps: random (0-199), pre-training (200-499), feedback rounds at 500 and 1000 (critic
# reset at 500), SAC updates, evaluations at 750 and 1500, the checkpoint at the end. The oracles: 1000 steps.
PBRL = ["--env-id", "cartpole-swingup", "--noise", "0.9", "--total-timesteps", "1500", "--learning-starts", "200",
        "--unsup-steps", "300", "--feedback-freq", "500", "--episode-length", "100", "--eval-freq", "750",
        "--eval-episodes", "2", "--segment-size", "20", "--max-feedback", "20", "--queries-per-round", "5",
        "--hidden-dim", "32", "--batch-size", "32", "--reward-hidden-dim", "16", "--reward-layers", "2",
        "--reward-epochs", "20", "--log-freq", "100"]
ORACLE = ["--env-id", "cartpole-swingup", "--noise", "0.9", "--total-timesteps", "1000", "--learning-starts", "200",
          "--episode-length", "100", "--eval-freq", "500", "--eval-episodes", "2", "--hidden-dim", "32",
          "--batch-size", "32", "--log-freq", "100"]
SPARSE = ["--reward-topology-period", "5", "--agent-topology-period", "100"]  # topology updates within the run
SURF = ["--surf-tau", "0.6"]  # pseudo-labels are kept (0.99 keeps none this early)
ARGS = {
    "pebble.py": PBRL, "r2n_pebble.py": PBRL + SPARSE, "set_pebble.py": PBRL + SPARSE, "static_pebble.py": PBRL,
    "l1_pebble.py": PBRL, "dropconnect_pebble.py": PBRL, "surf.py": PBRL + SURF, "r2n_surf.py": PBRL + SPARSE + SURF,
    "rune.py": PBRL, "r2n_rune.py": PBRL + SPARSE,
    "sac.py": ORACLE, "anf_sac.py": ORACLE + ["--agent-topology-period", "100"],
}
RUN = ["--no-cuda", "--seed", "3", "--exp-name", "numerics", "--run-name", "numerics"]  # runs/numerics
# variant -> (the current script's flags, the reference's flags) for the same environment
VARIANTS = {"redrawn": (["--noise-resample"], []), "stored, the default": ([], ["--no-noise-resample"])}
STORED_NOISE_STUDY = ("pebble.py", "r2n_pebble.py", "sac.py", "anf_sac.py")
CASES = [(script, "redrawn") for script in ARGS] + [(script, "stored, the default") for script in STORED_NOISE_STUDY]
# The checkpoint's `args` equal the reference's but for flags added or re-defaulted since that only say when state.pt
# is written (issue 19: --state-minutes added, --checkpoint-freq from 10000 to None); none touches training.
NOT_TRAINING = ("state_minutes", "checkpoint_freq")
# Tags added since that only read the weights (`features/`) or a batch (RUNE's bonus); every other tag is compared
# bitwise.
ADDED_TAGS = ("features/", "losses/rune_bonus")
ADDED_FLAGS = {"compile": False, "tf32": False, "cuda_graph": False, "parallel_eval": False,  # added since, off there
               "cuda_graph_whole": False, "hidden_layers": 2, "weight_decay": 0.0}  # added since, as they were there
# Flags that became the run harness's constants, at the same values (`r2n_harness.diagnostics`): no number changes.
HARNESS_CONSTANTS = {"diagnostic_transitions": diagnostics.TRANSITIONS, "diagnostic_pairs": diagnostics.PAIRS}
# The harness's hooks were always on there (state.pt, the query log, the diagnostics); here their flags turn them on.
HARNESS = {"resumable": True, "query_log": True, "diagnostics": True}
ADDED_FLAGS |= HARNESS


def reference_source(path: str) -> bytes:
    try:
        result = subprocess.run(["git", "show", f"{REFERENCE_COMMIT}:{path}"], cwd=ROOT, capture_output=True)
    except FileNotFoundError:
        pytest.skip("git is not installed: the reference code cannot be read")
    if result.returncode != 0:
        reason = (result.stderr.decode().strip().splitlines() or ["?"])[0]
        pytest.skip(f"commit {REFERENCE_COMMIT} is not available here (a copy without history?): {reason}")
    return result.stdout


def checkpoint_differences(a, b, key=""):
    """The keys at which two checkpoints differ (tensors bitwise, with their dtype; other values by equality)."""
    if isinstance(a, torch.Tensor) or isinstance(b, torch.Tensor):
        same = isinstance(a, torch.Tensor) and isinstance(b, torch.Tensor) and a.dtype == b.dtype and torch.equal(a, b)
        return [] if same else [key]
    if isinstance(a, dict) and isinstance(b, dict):
        if set(a) != set(b):
            return [f"{key} (keys {sorted(set(a) ^ set(b), key=str)})"]
        return [d for name in a for d in checkpoint_differences(a[name], b[name], f"{key}/{name}")]
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)) and len(a) == len(b):
        return [d for i, (x, y) in enumerate(zip(a, b)) for d in checkpoint_differences(x, y, f"{key}[{i}]")]
    return [] if type(a) is type(b) and a == b else [f"{key} ({a!r} vs {b!r})"]


def run_both(script, variant, reference, current, extra=()):
    """The reference and the current script at once (CI has two cores); a failure names the run and its stderr."""
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONWARNINGS="ignore")
    runs = {}
    current_flags, reference_flags = VARIANTS[variant]
    try:
        harness = ["--resumable", "--diagnostics"] + (["--query-log"] if script not in ("sac.py", "anf_sac.py") else [])
        for cwd, code, flags in ((reference, reference / script, reference_flags),
                                 (current, os.path.join(ROOT, script), current_flags + harness)):
            runs[cwd] = subprocess.Popen([sys.executable, str(code), *ARGS[script], *flags, *extra, *RUN], cwd=cwd, env=env,
                                         stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        for cwd, process in runs.items():
            _, stderr = process.communicate(timeout=600)
            assert process.returncode == 0, f"{cwd.name} {script} failed: {stderr[-2000:]}"
    finally:
        for process in runs.values():  # the other run, when one failed or timed out
            if process.poll() is None:
                process.kill()
                process.communicate()


def folders(script, tmp_path):
    """A folder for each run: the reference's holds its script and ene.py, which that script imports."""
    reference, current = tmp_path / "reference", tmp_path / "current"
    reference.mkdir()
    current.mkdir()
    for path in (script, "ene.py"):
        (reference / path).write_bytes(reference_source(path))
    return reference, current


def assert_same_run(script, reference, current):
    """Every TensorBoard point but SPS and every checkpoint entry of the two runs are the same, bit for bit."""
    old, new = (points(cwd / "runs" / "numerics") for cwd in (reference, current))
    added = sorted(tag for tag in set(new) - set(old) if tag.startswith(ADDED_TAGS))
    assert added, f"{script}: the diagnostics added since {REFERENCE_COMMIT} are not logged"
    new = {tag: value for tag, value in new.items() if tag not in added}
    assert set(old) == set(new), (f"{script}: tags only in {REFERENCE_COMMIT}'s run {sorted(set(old) - set(new))}, "
                                  f"only in the current run {sorted(set(new) - set(old))}")
    drifted = {}
    for tag in sorted(old):
        if tag != "charts/SPS" and old[tag] != new[tag]:
            first = next((i for i, (a, b) in enumerate(zip(old[tag], new[tag])) if a != b), None)
            drifted[tag] = (f"{len(old[tag])} vs {len(new[tag])} points" if first is None
                            else f"(step, value) {old[tag][first]} vs {new[tag][first]}")
    assert not drifted, f"{script}: TensorBoard values differ from {REFERENCE_COMMIT}'s (first difference) {drifted}"

    old, new = (torch.load(cwd / "runs" / "numerics" / "numerics.cleanrl_model", weights_only=False)
                for cwd in (reference, current))
    old_args, new_args = ({k: v for k, v in c.pop("args").items() if k not in NOT_TRAINING} for c in (old, new))
    old_args.update({k: v for k, v in ADDED_FLAGS.items() if k in new_args})  # flags added since, at their defaults
    for key, value in HARNESS_CONSTANTS.items():  # the reference's flag, at the harness's constant
        assert old_args.pop(key, value) == value, f"{script}: {REFERENCE_COMMIT}'s {key} is not the harness's {value}"
    absent = object()
    changed = sorted(k for k in old_args.keys() | new_args.keys() if old_args.get(k, absent) != new_args.get(k, absent))
    assert not changed, f"{script}: the checkpoint's args differ from {REFERENCE_COMMIT}'s in {changed}"
    differences = checkpoint_differences(old, new)
    assert not differences, f"{script}: the final checkpoint differs from {REFERENCE_COMMIT}'s at {differences}"


@pytest.mark.parametrize("script, variant", CASES)
def test_numerics_equal_the_reference(script, variant, tmp_path):
    reference, current = folders(script, tmp_path)
    run_both(script, variant, reference, current)
    assert_same_run(script, reference, current)


@pytest.mark.parametrize("script", ["r2n_pebble.py"])
def test_zeroing_subnormal_targets_changes_no_number(script, tmp_path):
    """`target_update` sets the target critics' subnormal weights to zero. With a fast Polyak average (`--tau 0.3`)
    pruned connections' target weights reach the subnormals within the run and stay there in the reference (0.7 times
    the smallest subnormal rounds back to it). Every point and checkpoint entry is still the reference's, bit for bit,
    and the final targets differ from the reference's only where those hold a subnormal, which is zero here."""
    reference, current = folders(script, tmp_path)
    run_both(script, "stored, the default", reference, current, extra=["--tau", "0.3", "--keep-state"])
    assert_same_run(script, reference, current)
    old, new = (torch.load(cwd / "runs" / "numerics" / "state.pt", weights_only=False)["objects"]
                for cwd in (reference, current))
    new = new["agent"]  # the reference's state keeps the agent's objects at its top level
    def subnormal(weight):
        return (weight != 0) & (weight.abs() < torch.finfo(weight.dtype).tiny)

    stuck = 0
    for name in ("qf1_target", "qf2_target"):
        for key, weight in old[name].items():
            stuck += int(subnormal(weight).sum())
            zeroed = torch.where(subnormal(weight), torch.zeros_like(weight), weight)
            assert torch.equal(zeroed, new[name][key]), (name, key)
            assert not subnormal(new[name][key]).any(), (name, key)
    assert stuck, "no target weight of the reference's run reached the subnormals: the test tests nothing"
