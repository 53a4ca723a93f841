"""Issue 91's study (results/surf-rune): the preset runs what PROTOCOL.md fixes, the power it quotes is what
`power.py` prints, and the first-seeds stop rule fires where the protocol says."""
import importlib.util
import math
import os
import subprocess
import sys

import pytest
from torch.utils.tensorboard import SummaryWriter

import benchmark
from test_scripts import ROOT

STUDY = os.path.join(ROOT, "results", "surf-rune")


def load_power():
    """The study's power.py under a name of its own (other studies have a `power` module too)."""
    spec = importlib.util.spec_from_file_location("surf_rune_power", os.path.join(STUDY, "power.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_preset_runs_the_protocols_arms_seeds_and_order():
    power = load_power()
    runs = benchmark.expand(benchmark.Args(preset="surf-rune"))
    seeds = {}
    for run in runs:
        seeds.setdefault(run.method, []).append(run.seed)
        assert (run.env_id, run.noise, run.budget) == ("cheetah-run", 0.9, 1000)
        command = " ".join(run.command)
        assert "--no-noise-resample" in command and "--resumable --diagnostics --query-log" in command
        assert ("--total-timesteps 250000 --hidden-dim 256 --batch-size 128 --eval-freq 10000 --feedback-freq 1200"
                in command)
        assert ("--no-sparse-reward" in command) == (run.method == power.AGENT)
    assert {arm: sorted(s) for arm, s in seeds.items()} == {arm: list(range(1, n + 1)) for arm, n in power.SEEDS.items()}
    assert len(runs) == 48
    methods = [run.method for run in runs]
    # stage 0 seed-major (RUNE's and SURF's arms), then the actor/critic-only arm
    assert methods[:4] == [power.RUNE, power.R2N_RUNE, power.SURF, power.R2N_SURF]
    assert methods[-10:] == [power.AGENT] * 10 and power.AGENT not in methods[:-10]
    assert [run.seed for run in runs[:-10]] == sorted(run.seed for run in runs[:-10])
    assert benchmark.RESULTS["surf-rune"] == "results/surf-rune/runs"


def test_power_is_the_noncentral_t_and_holm_lies_between_bonferroni_and_uncorrected():
    power = load_power()
    assert power.power(0.0, 50.0, 50.0, 8, 8) == pytest.approx(0.05, abs=1e-9)  # no effect: the test's size
    assert power.power(100.0, 50.0, 50.0, 8, 8) > power.power(100.0, 70.0, 50.0, 8, 8)
    means = power.planned_means(181.1)
    assert means[power.SURF] == pytest.approx(181.1 * 260.47 / 237.62)
    assert means[power.R2N_RUNE] / means[power.RUNE] == pytest.approx(410.94 / 202.37)
    sds = {arm: 80.0 for arm in power.SEEDS}  # large enough that no power is 1
    holm = power.holm_power(means, sds, power.SEEDS, reps=4000)
    for name, (high, low) in power.CONFIRMATORY.items():
        effect = means[high] - means[low]
        bound = power.power(effect, 80.0, 80.0, power.SEEDS[high], power.SEEDS[low], 0.025)
        uncorrected = power.power(effect, 80.0, 80.0, power.SEEDS[high], power.SEEDS[low], 0.05)
        assert bound - 0.03 <= holm[name] <= uncorrected + 0.03


def test_protocol_quotes_what_power_py_prints():
    printed = subprocess.run([sys.executable, os.path.join(STUDY, "power.py")], capture_output=True, text=True,
                             check=True).stdout.splitlines()
    protocol = open(os.path.join(STUDY, "PROTOCOL.md")).read()
    quoted = [line for line in printed if line.startswith(("reference arms", "planned means"))]
    sensitivity = printed.index(next(line for line in printed if line.startswith("sensitivity")))
    quoted += printed[sensitivity : sensitivity + 4]
    for line in quoted:
        assert line in protocol, f"PROTOCOL.md does not quote power.py's line: {line}"


def fake_run(folder, arm, seed, primary):
    path = os.path.join(folder, f"{arm}__cheetah-run__noise0.9__budget1000__seed{seed}")
    writer = SummaryWriter(path)
    for step, value in ((10_000, 20.0), (230_000, primary - 1.0), (240_000, primary), (250_000, primary + 1.0)):
        writer.add_scalar("eval/episodic_return", value, step)
    writer.close()
    open(os.path.join(path, "done"), "w").write("finished\n")


def stop_rule(folder):
    return subprocess.run([sys.executable, os.path.join(STUDY, "stop_rule.py"), str(folder)], capture_output=True,
                          text=True)


def test_stop_rule_fires_on_a_first_seed_at_the_pretraining_level(tmp_path):
    power = load_power()
    fake_run(tmp_path, power.SURF, 1, 180.0)
    fake_run(tmp_path, power.RUNE, 2, 10.0)  # not a first seed
    fake_run(tmp_path, power.AGENT, 1, 10.0)  # not an arm of the rule
    assert stop_rule(tmp_path).returncode == 0
    fake_run(tmp_path, power.R2N_RUNE, 1, 49.0)
    result = stop_rule(tmp_path)
    assert result.returncode == 1 and result.stdout.count("stop rule:") == 1
    assert f"{power.R2N_RUNE}__cheetah-run__noise0.9__budget1000__seed1 ended at 49.0" in result.stdout
    assert not math.isnan(power.primary(os.path.join(tmp_path, os.listdir(tmp_path)[0])))
