"""The run harness's hooks (`r2n_harness.run`) in every script: with `--resumable --query-log --diagnostics` each script
logs the diagnostics, prints its progress, writes its query log and leaves no `state.pt` at the end. That the hooks
change no number is tested on r2n_pebble.py (test_scripts.py) and, bit for bit against the reference, in
test_numerics.py; the state and the resume in test_resume.py."""
import glob
import os
import sys
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from test_oracles import AGENT_NETS, ORACLE_TINY  # noqa: E402
from test_scripts import (DIAGNOSTIC_TAGS, HARNESS, PBRL_ALL, SPARSE_NETS, SPARSE_TINY, TINY,  # noqa: E402
                          check_diagnostics, check_features, run_script, scalars)

SHORT = ["--total-timesteps", "1000", "--eval-freq", "500"]  # one feedback round, at 500; evaluations at 500, 1000
SPARSE_AGENT = ("r2n_pebble.py", "set_pebble.py", "r2n_surf.py", "r2n_rune.py")
ARGS = {script: TINY + SHORT + (SPARSE_TINY if script in SPARSE_AGENT else []) for script in PBRL_ALL}
ARGS |= {"sac.py": ORACLE_TINY + ["--noise", "0.9"] + SHORT, "anf_sac.py": ORACLE_TINY + ["--noise", "0.9"] + SHORT +
         ["--agent-topology-period", "100"]}


@pytest.fixture(scope="module")
def harnessed(tmp_path_factory):
    """script -> (run folder, process result) of a short run with the harness's hooks, two at a time."""
    cwds = {script: tmp_path_factory.mktemp(script[:-3]) for script in ARGS}
    flags = {script: HARNESS if script in PBRL_ALL else ["--resumable", "--diagnostics"] for script in ARGS}
    with ThreadPoolExecutor(2) as pool:
        futures = {script: pool.submit(run_script, script, args + flags[script] + ["--run-name", "h"], cwds[script],
                                       False) for script, args in ARGS.items()}
        return {script: (cwds[script] / "runs" / "h", future.result()) for script, future in futures.items()}


@pytest.mark.parametrize("script", list(ARGS))
def test_the_harness_hooks_log_and_write_what_their_flags_ask(script, harnessed):
    run_dir, result = harnessed[script]
    assert result.returncode == 0, result.stderr[-3000:]
    values = scalars(str(run_dir))
    pbrl = script in PBRL_ALL
    nets = SPARSE_NETS if pbrl else AGENT_NETS
    features = sorted(f"features/{net}/{m}" for net in nets for m in ("relevant_weight_frac", "chance"))
    assert sorted(tag for tag in values if tag.startswith("features/")) == features
    check_features(values, nets)
    assert [p.split(" | ")[1] for p in result.stdout.splitlines() if p.startswith("progress:")][:1] == ["random"]
    assert not os.path.exists(run_dir / "state.pt")  # deleted at the end (no --keep-state)
    if not pbrl:
        assert not [tag for tag in values if tag in DIAGNOSTIC_TAGS] and not os.path.exists(run_dir / "preferences")
        return
    check_diagnostics(values)
    assert len(values["pbrl/reward_steps"]) == 1
    (log,) = glob.glob(str(run_dir / "preferences" / "*.npz"))
    queries = np.load(log)
    steps = 20 + (2 * 5 if "surf" in script else 0)  # SURF keeps its crop's steps around the segment shown
    assert queries["obs"].shape[:3] == (5, 2, steps) and not np.isnan(queries["labels"]).any()
    assert queries["steps"].tolist() == [500] * 5
