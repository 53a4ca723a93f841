"""Issue 91's study (results/surf-rune): the preset runs what PROTOCOL.md fixes, the power it quotes is what
`power.py` prints, the first-seeds stop rule fires where the protocol says, the sessions' schedule, and the analysis:
the tests as the protocol fixes them, on synthetic runs whose primary metrics are known, against scipy; the refusal
before every run is in; the diagnostics."""
import glob
import importlib.util
import json
import math
import os
import shutil
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from scipy import stats
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


# The analysis (hypotheses.py, diagnostics.py, analyze.sh) on synthetic runs whose primary metrics are known, and the
# sessions' schedule (schedule.py). Each runs in a subprocess: other studies have modules of the same names.
ARM_SEEDS = {"pebble_stored_noise": 8, "r2n_pebble_stored_noise": 10, "surf_stored_noise": 8,
             "r2n_surf_stored_noise": 10, "r2n_surf_agent_only_stored_noise": 10, "rune_stored_noise": 10,
             "r2n_rune_stored_noise": 10}
MEANS = {"pebble_stored_noise": 180.0, "r2n_pebble_stored_noise": 258.0, "surf_stored_noise": 200.0,
         "r2n_surf_stored_noise": 300.0, "r2n_surf_agent_only_stored_noise": 280.0, "rune_stored_noise": 150.0,
         "r2n_rune_stored_noise": 190.0}
SPARSE_REWARD = ("r2n_pebble_stored_noise", "r2n_surf_stored_noise", "r2n_rune_stored_noise")


def synthetic_run(folder, arm, seed, primary, relevant=0.5, threads=1):
    """A finished run whose last 3 evaluations average `primary`, with the diagnostics' tags (chance 0.13)."""
    path = os.path.join(folder, f"{arm}__cheetah-run__noise0.9__budget1000__seed{seed}")
    writer = SummaryWriter(path)
    hparams = dict(exp_name=arm, seed=seed, env_id="cheetah-run", noise=0.9, max_feedback=1000,
                   total_timesteps=250_000, threads=threads)  # the table analyze.py reads a run's settings from
    writer.add_text("hyperparameters", "|param|value|\n|-|-|\n" + "\n".join(f"|{k}|{v}|" for k, v in hparams.items()))
    for step, value in ((230_000, primary - 1.0), (240_000, primary), (250_000, primary + 1.0)):
        writer.add_scalar("eval/episodic_return", value, step)
        for net in ("actor", "qf1", "qf2", "reward0", "reward1", "reward2"):
            writer.add_scalar(f"features/{net}/chance", 0.13, step)
            writer.add_scalar(f"features/{net}/relevant_weight_frac", relevant, step)
            writer.add_scalar(f"sparse/{net}/relevant_active_frac", relevant, step)
            if arm in SPARSE_REWARD and net.startswith("reward"):
                writer.add_scalar(f"sparse/{net}/topology_updates", 197.0 if "surf" in arm else 5.0, step)
        if "surf" in arm:
            writer.add_scalar("pbrl/pseudo_label_rate", 0.7, step)
        if "rune" in arm:
            writer.add_scalar("pbrl/beta", 0.04, step)
            writer.add_scalar("losses/rune_bonus", 0.02, step)
    writer.close()
    open(os.path.join(path, "done"), "w").write(f"exit code 0\ncommand python x.py --seed {seed} --threads {threads}"
                                                f"\ncpu AMD EPYC, torch CPU capability AVX512\n")


def synthetic_study(tmp_path, skip=None, means=MEANS):
    """The reference arms' first 8 seeds in `reference/`, R2N-PEBBLE's 9-10 in `which/`, the study's in `runs/`."""
    rng, values = np.random.default_rng(1), {}
    for arm, n in ARM_SEEDS.items():
        values[arm] = np.round(means[arm] + 40 * rng.standard_normal(n), 3)
        for seed, value in enumerate(values[arm], 1):
            folder = ("reference" if seed <= 8 else "which") if arm in ("pebble_stored_noise",
                                                                        "r2n_pebble_stored_noise") else "runs"
            if (arm, seed) != skip:
                synthetic_run(tmp_path / folder, arm, seed, value, threads=2 if "surf" in arm else 1)
    return values


def study_script(tmp_path, script, *extra):
    return subprocess.run([sys.executable, os.path.join(STUDY, script), "--reference", str(tmp_path / "reference"),
                           "--which-sparsity", str(tmp_path / "which"), "--runs", str(tmp_path / "runs"), *extra],
                          capture_output=True, text=True, timeout=300)


def test_hypotheses_refuse_until_every_run_is_in(tmp_path):
    synthetic_study(tmp_path, skip=("r2n_surf_agent_only_stored_noise", 4))
    result = study_script(tmp_path, "hypotheses.py", "--out", str(tmp_path / "h.md"))
    assert result.returncode == 1 and "r2n_surf_agent_only_stored_noise (9 of 10)" in result.stderr, result.stderr
    assert len(result.stderr.strip().splitlines()) == 1 and not os.path.exists(tmp_path / "h.md")
    analyze_sh = subprocess.run(["bash", os.path.join(STUDY, "analyze.sh")], cwd=ROOT, capture_output=True, text=True)
    landed = len(glob.glob(os.path.join(STUDY, "runs", "*", "done")))
    if landed < 48:
        assert analyze_sh.returncode == 1 and f"{landed} of the 48 runs are in" in analyze_sh.stderr


def welch_upper(a, b):
    va, vb = a.var(ddof=1) / len(a), b.var(ddof=1) / len(b)
    df = (va + vb) ** 2 / (va ** 2 / (len(a) - 1) + vb ** 2 / (len(b) - 1))
    return a.mean() - b.mean(), a.mean() - b.mean() + stats.t.ppf(0.95, df) * np.sqrt(va + vb)


def test_hypotheses_are_the_protocols_tests(tmp_path):
    values = synthetic_study(tmp_path)
    result = study_script(tmp_path, "hypotheses.py", "--out", str(tmp_path / "h.md"))
    assert result.returncode == 0, result.stderr
    text = (tmp_path / "h.md").read_text()
    lines = text.splitlines()
    # H1-H2: one-tailed Welch, each R2N arm above its method, Holm over the two
    p = {h: stats.ttest_ind(values[high], values[low], equal_var=False, alternative="greater").pvalue
         for h, high, low in (("H1", "r2n_surf_stored_noise", "surf_stored_noise"),
                              ("H2", "r2n_rune_stored_noise", "rune_stored_noise"))}
    order = sorted(p, key=p.get)
    holm = dict(zip(order, np.maximum.accumulate([min(1, (2 - k) * p[h]) for k, h in enumerate(order)])))
    for h in p:
        row = next(line for line in lines if line.startswith(f"| {h} |"))
        assert f"| {p[h]:.4f} | {holm[h]:.4f} |" in row, (row, p[h], holm[h])
        assert row.endswith("| yes |") == (holm[h] < 0.05)
    assert "| +145.2 |" in next(line for line in lines if line.startswith("| H1 |"))  # the paper's difference
    # E1: R2N-SURF minus its actor/critic-only arm, the Welch interval and the reading fixed before the runs
    delta, upper = welch_upper(values["r2n_surf_stored_noise"], values["r2n_surf_agent_only_stored_noise"])
    assert f"= {delta:+.1f}, one-sided 95% bounds" in text and f"upper {upper:+.1f}" in text
    # the two schedules side by side: 5 topology updates a run on PEBBLE's rounds, 197 on SURF's
    assert "| which-sparsity (PEBBLE's reward rounds) | -1.0 | +38.8 | 5.0 ± 0.0 (10 runs) |" in text
    assert f"| this study (SURF's reward rounds) | {delta:+.1f} | {upper:+.1f} | 197.0 ± 0.0 (10 runs) |" in text
    # the arms' table: ours (mean ± SE, Student's 95% CI) beside the paper's, with CPUs and threads from `done`
    for arm, v in values.items():
        se = v.std(ddof=1) / np.sqrt(len(v))
        half = stats.t.ppf(0.975, len(v) - 1) * se
        row = next(line for line in lines if line.startswith(f"| `{arm}` |"))
        assert f"| {len(v)} | {v.mean():.1f} ± {se:.1f} | [{v.mean() - half:.1f}, {v.mean() + half:.1f}] |" in row
        if arm not in ("pebble_stored_noise", "r2n_pebble_stored_noise"):
            threads = "2 threads" if "surf" in arm else "1 thread"
            assert row.endswith(f"| AMD EPYC, torch CPU capability AVX512, {threads} ×{len(v)} |"), row
    assert "| 405.68 ± 18.38 |" in next(line for line in lines if line.startswith("| `r2n_surf_stored_noise` |"))
    # E3: ratios beside the paper's; E4: R2N-PEBBLE's gain with the stored-noise study's own 8 seeds a side
    surf_ratio = values["surf_stored_noise"].mean() / values["pebble_stored_noise"].mean()
    assert f"| ×{surf_ratio:.3f} | ×1.096 |" in text
    gain = values["r2n_pebble_stored_noise"][:8].mean() - values["pebble_stored_noise"].mean()
    assert f"`r2n_pebble_stored_noise` - `pebble_stored_noise` | {gain:+.1f} | +167.0 |" in text


@pytest.mark.parametrize("delta_mean, expected", [
    (120.0, "R2N's sparse reward adds to the return where its topology moves"),
    (-60.0, "it adds nothing at this scale"),
    (-20.0, "this study cannot tell: R2N's sparse reward adds at most"),
])
def test_e1_reading_is_the_one_fixed_before_the_runs(tmp_path, delta_mean, expected):
    means = dict(MEANS, r2n_surf_agent_only_stored_noise=MEANS["r2n_surf_stored_noise"] - delta_mean)
    values = synthetic_study(tmp_path, means=means)
    assert study_script(tmp_path, "hypotheses.py", "--out", str(tmp_path / "h.md")).returncode == 0
    text = (tmp_path / "h.md").read_text()
    delta, upper = welch_upper(values["r2n_surf_stored_noise"], values["r2n_surf_agent_only_stored_noise"])
    assert f"**Reading, as fixed before the runs: {expected}" in text
    if expected.startswith("this study"):
        assert f"adds at most {upper:.1f}.**" in text


def test_e1_constants_are_the_protocols_and_which_sparsitys():
    power = load_power()
    pebble = power.arm_values(power.REFERENCE, "pebble_stored_noise").mean()
    means = power.planned_means(pebble)
    source = open(os.path.join(STUDY, "hypotheses.py")).read()
    assert f"E1_EFFECT = {means[power.R2N_SURF] - means[power.AGENT]:.1f}\n" in source
    assert "+46.2" in open(os.path.join(STUDY, "PROTOCOL.md")).read()
    which = open(os.path.join(ROOT, "results", "which-sparsity", "analysis", "hypotheses.md")).read()
    assert "WHICH_SPARSITY_E1 = (-1.0, 38.8)\n" in source
    assert "Δ = R2N-PEBBLE - actor/critic-only = -1.0" in which and "upper +38.8" in which


def test_diagnostics_name_a_sparse_layer_at_chance(tmp_path):
    synthetic_study(tmp_path)
    folder = tmp_path / "runs"
    for name in os.listdir(folder):  # the actor/critic-only arm's actor never leaves chance
        if name.startswith("r2n_surf_agent_only_stored_noise__"):
            os.remove(os.path.join(folder, name, "done"))
    for seed in range(1, 11):
        synthetic_run(folder, "r2n_surf_agent_only_stored_noise", f"{seed}x", 250.0, relevant=0.1305)
    result = study_script(tmp_path, "diagnostics.py", "--out", str(tmp_path / "d.md"))
    assert result.returncode == 0, result.stderr
    text = (tmp_path / "d.md").read_text()
    assert "`r2n_surf_agent_only_stored_noise`: `sparse/actor/relevant_active_frac` is at chance" in text
    assert "r2n_surf_stored_noise`: `sparse" not in text  # its layers moved (0.5 > 0.13)
    assert "| `r2n_surf_stored_noise` | 10 | 197.0 ± 0.0 (10 runs) |" in text
    assert "| `surf_stored_noise` | 8 | none (dense reward) |" in text
    surf = next(line for line in text.splitlines() if line.startswith("| `surf_stored_noise` |") and "mean" in line)
    assert "0.700 ± 0.000; mean 0.700 ± 0.000" in surf
    assert "| `surf_stored_noise` | 0 of 8 | - | - | - |" in text  # no members.json yet


def test_diagnostics_count_constant_reward_members(tmp_path):
    synthetic_study(tmp_path)
    member = {"label_accuracy": 1.0, "share_at_bound": 0.5, "median_abs_preactivation": 3.0, "constant": False}
    dead = dict(member, label_accuracy=0.5, share_at_bound=1.0, constant=True)
    for seed, members in ((1, [dead, member, member]), (2, [member, member, member])):
        path = tmp_path / "runs" / f"surf_stored_noise__cheetah-run__noise0.9__budget1000__seed{seed}" / "members.json"
        path.write_text(json.dumps(members))
    result = study_script(tmp_path, "diagnostics.py", "--out", str(tmp_path / "d.md"))
    assert result.returncode == 0, result.stderr
    text = (tmp_path / "d.md").read_text()
    # 2 runs: one constant member in one run; at the bound (2/3 and 1/2 of the rewards); accuracy (5/6 and 1)
    assert "| `surf_stored_noise` | 2 of 8 | 1 (1) | 0.583 ± 0.083 | 0.917 ± 0.083 |" in text
    assert "| `rune_stored_noise` | 0 of 10 | - | - | - |" in text


def schedule(runs):
    result = subprocess.run([sys.executable, os.path.join(STUDY, "schedule.py"), str(runs)], capture_output=True,
                            text=True, check=True, timeout=120)
    return result.stdout.split(), result.stderr


def load_schedule():
    """The study's schedule.py in this process, with this study's power.py as its `power` (other studies have one)."""
    saved = sys.modules.get("power")
    sys.modules["power"] = load_power()
    try:
        spec = importlib.util.spec_from_file_location("surf_rune_schedule", os.path.join(STUDY, "schedule.py"))
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
    finally:
        if saved is None:
            del sys.modules["power"]
        else:
            sys.modules["power"] = saved
    return module


def run_in(folder, arm, seed):
    """A run that is in, as far as the schedule looks: its folder with a `done` file."""
    path = os.path.join(folder, f"{arm}__cheetah-run__noise0.9__budget1000__seed{seed}")
    os.makedirs(path)
    open(os.path.join(path, "done"), "w").write("exit code 0\n")


def cut_off(scratch, arm, seed):
    """A run that a session's end cut off: its `state.pt` in the launcher's scratch folder."""
    run_id = f"{arm}__cheetah-run__noise0.9__budget1000__seed{seed}"
    os.makedirs(os.path.join(scratch, run_id, "runs", run_id))
    open(os.path.join(scratch, run_id, "runs", run_id, "state.pt"), "wb").close()


def test_schedule_gives_two_pairs_at_one_thread_in_the_protocols_order_and_the_cut_off_family_first(tmp_path):
    """Each plan: two pairs at one thread, of the family furthest behind (SURF's on a tie), in the preset's order;
    the family whose run was cut off first, while this machine keeps its state."""
    power = load_power()
    runs, scratch = tmp_path / "runs", tmp_path / "scratch"
    runs.mkdir()
    scratch.mkdir()
    args, said = schedule(runs)  # nothing in: SURF's family, on the tie
    assert args == ["--preset", "surf-rune", "--methods", power.SURF, power.R2N_SURF, "--seeds", "1", "2",
                    "--threads", "1", "--workers", "2"] and said == ""
    for seed in (1, 2, 3, 4):
        for arm in (power.RUNE, power.R2N_RUNE):
            run_in(runs, arm, seed)  # RUNE's 8/20 in, SURF's 0/28
    cut_off(scratch, power.RUNE, 5)
    run_in(runs, power.SURF, 1)
    schedule_module = load_schedule()
    plan = lambda: schedule_module.next_session(str(runs), str(scratch))  # noqa: E731
    # RUNE seed 5's state is on this machine: RUNE goes on, though SURF's family is further behind
    assert plan()[3:] == [power.RUNE, power.R2N_RUNE, "--seeds", "5", "6", "--threads", "1", "--workers", "2"]
    # without it, SURF's family; half a pair in, so the grid covers the three runs that are next, not a fifth; the
    # launcher goes seed by seed, the methods in the order named: SURF seed 2 before R2N-SURF seed 2, as planned
    assert schedule_module.next_session(str(runs))[3:] == [power.SURF, power.R2N_SURF, "--seeds", "1", "2",
                                                            "--threads", "1", "--workers", "2"]
    assert subprocess.run([sys.executable, os.path.join(STUDY, "schedule.py"), str(runs), str(scratch)],
                          capture_output=True, text=True, check=True, timeout=120).stdout.split()[6:8] == ["5", "6"]


def test_schedule_never_starts_a_run_outside_the_preset_and_ends_with_the_actor_critic_only_arm(tmp_path):
    """SURF is planned for seeds 1-8, R2N-SURF for 1-10: the methods x seeds grid must not reach SURF seed 9. Once
    both arms are in, the actor/critic-only arm; a blocked family waits; nothing once every run is in."""
    power, schedule_module = load_power(), load_schedule()
    for run in benchmark.expand(benchmark.Args(preset="surf-rune")):
        if run.method in (power.SURF, power.R2N_SURF) and run.seed <= 7 or run.method in (power.RUNE, power.R2N_RUNE):
            run_in(tmp_path, run.method, run.seed)
    plan = lambda: schedule_module.next_session(str(tmp_path))  # noqa: E731
    assert plan()[3:9] == [power.SURF, power.R2N_SURF, "--seeds", "8", "--threads", "1"]
    run_in(tmp_path, power.SURF, 8)
    run_in(tmp_path, power.R2N_SURF, 8)
    assert plan()[3:8] == [power.R2N_SURF, "--seeds", "9", "10", "--threads"]
    run_in(tmp_path, power.R2N_SURF, 9)
    run_in(tmp_path, power.R2N_SURF, 10)
    assert plan()[3:10] == [power.AGENT, "--seeds", "1", "2", "3", "4", "--threads"]
    schedule_module.BLOCKED = {"surf": "a reason"}
    assert plan() == []
    schedule_module.BLOCKED = {}
    for seed in range(1, 11):
        run_in(tmp_path, power.AGENT, seed)
    assert plan() == []


@pytest.mark.parametrize("last_line, stopped, chained", [
    ("4 runs finished, 0 skipped as already finished, 0 failed", False, True),
    ("2 runs finished, 0 skipped as already finished, 2 stopped or not started (the same command resumes them), "
     "0 failed", False, False),
    ("3 runs finished, 0 skipped as already finished, 1 failed", False, False),
    ("4 runs finished, 0 skipped as already finished, 0 failed", True, False),
    ("Traceback (most recent call last):", False, False),
])
def test_watcher_starts_the_next_plan_only_when_every_run_of_its_launcher_finished(tmp_path, last_line, stopped,
                                                                                     chained):
    """continue.sh's watcher, once its launcher has stopped: the next plan (continue.sh again, same worktree) when its
    launcher's last line says every run finished; not after a stopped or failed run, a crash, or under `STOPPED`."""
    repo, work = tmp_path / "repo", tmp_path / "work"
    subprocess.run(["git", "init", "-q", str(repo)], check=True)
    study = repo / "results" / "surf-rune"
    study.mkdir(parents=True)
    (study / "PROTOCOL.md").write_text("the protocol\n")
    subprocess.run(["git", "add", "results"], cwd=repo, check=True)
    subprocess.run(["git", "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-q", "-m", "protocol"], cwd=repo,
                   check=True)
    (study / "continue.sh").write_text('echo "$@" > chained.txt\n')  # stands for the next plan's start
    if stopped:
        (study / "STOPPED").write_text("the stop rule fired\n")
    launcher = subprocess.Popen(["true"])  # a launcher that has stopped: the watcher makes one pass
    launcher.wait()
    work.mkdir()
    (work / "launcher.pid").write_text(f"{launcher.pid}\n")
    (work / "launcher.log").write_text(f"running 4 runs, 2 at a time\n{last_line}\n")
    subprocess.run(["bash", os.path.join(STUDY, "continue.sh"), "--watch", str(work)], cwd=repo, check=True,
                   timeout=60, capture_output=True)
    assert (repo / "chained.txt").exists() == chained
    if chained:
        assert (repo / "chained.txt").read_text().split() == [str(work)]


def tiny_run_with_a_constant_member(folder, crop=2):
    """A run folder as a SURF run leaves it: a final model whose reward member 0 tanh holds at +1 on every input
    (its output bias 1e4), and labelled pairs whose labels member 1 gets right on the central steps only."""
    import surf  # the repository's, for its RewardEnsemble
    import torch
    torch.manual_seed(0)
    obs_dim, act_dim = 6, 2
    model = surf.RewardEnsemble(obs_dim + act_dim, 16, 2, 3)
    with torch.no_grad():
        model.biases[-1][0] += 1e4
    os.makedirs(os.path.join(folder, "preferences"))
    rows = torch.randn(40, 2, 6 + 2 * crop, obs_dim + act_dim)
    with torch.no_grad():
        returns = model(rows[:, :, crop:rows.shape[2] - crop].reshape(-1, obs_dim + act_dim))[1].view(40, 2, -1).sum(-1)
    labels = (returns[:, 1] > returns[:, 0]).float().numpy()
    labels[:3], labels[3] = 0.5, np.nan  # an equal and a skipped query's labels: left out of the accuracy
    for i in range(4):  # four rounds of 10 pairs, named as the query log names them
        part = slice(10 * i, 10 * (i + 1))
        np.savez(os.path.join(folder, "preferences", f"{i}.npz"), obs=rows[part, :, :, :obs_dim].numpy(),
                 actions=rows[part, :, :, obs_dim:].numpy(), labels=labels[part])
    torch.save({"args": {"reward_hidden_dim": 16, "reward_layers": 2, "surf_crop": crop}, "global_step": 300,
                "obs_dim": obs_dim, "act_dim": act_dim, "reward_models": model.member_state_dicts()},
               os.path.join(folder, "surf_stored_noise.cleanrl_model"))


def test_members_names_a_member_that_tanh_holds_constant(tmp_path):
    tiny_run_with_a_constant_member(tmp_path / "run")
    result = subprocess.run([sys.executable, os.path.join(STUDY, "members.py"), str(tmp_path / "run"),
                             str(tmp_path / "members.json")], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert "1 of 3 members constant" in result.stdout
    members = json.loads((tmp_path / "members.json").read_text())
    assert [m["constant"] for m in members] == [True, False, False] and {m["step"] for m in members} == {300}
    assert members[0]["share_at_bound"] == 1.0 and members[0]["median_abs_preactivation"] > 9000
    assert members[1]["label_accuracy"] == 1.0  # its labels, on the central steps, equal labels left out
    assert members[0]["label_accuracy"] == 0.5  # a constant member ties every pair: half right
    assert members[1]["share_at_bound"] < 1 and 0 < members[1]["median_abs_preactivation"] < 100


def test_members_reads_the_labelled_steps_of_surfs_longer_segments(tmp_path):
    """SURF stores `surf_crop` steps either side of the ones the teacher labelled: only those count."""
    tiny_run_with_a_constant_member(tmp_path / "run")
    spec = importlib.util.spec_from_file_location("surf_rune_members", os.path.join(STUDY, "members.py"))
    members = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(members)
    rows, labels = members.labelled_pairs(str(tmp_path / "run"), 2)
    assert rows.shape == (40, 2, 6, 8) and labels.shape == (40,)
    whole, _ = members.labelled_pairs(str(tmp_path / "run"), 0)
    assert whole.shape == (40, 2, 10, 8) and np.array_equal(whole[:, :, 2:8].numpy(), rows.numpy())


def test_grow_probe_sees_a_member_that_leans_on_stored_noise(tmp_path):
    """grow_probe.py on a sparse member that reads one noise column (large weights) and keeps tiny weights on the
    relevant ones: its labels hold on the stored noise only, RigL would drop only relevant weights, and regrow none:
    the zero weights' noise columns, 100 times larger as stored, carry the largest gradient."""
    import surf
    import torch
    torch.manual_seed(0)
    real, obs_dim, act_dim = 2, 6, 2  # columns 0-1 real, 2-5 noise, 6-7 actions: chance 4 / 8
    model = surf.RewardEnsemble(obs_dim + act_dim, 16, 2, 3)
    with torch.no_grad():
        weight = model.weights[0]
        weight.zero_()
        weight[:, :, [0, 1, 6, 7]] = 1e-3
        weight[:, :, 2] = (1.0 + torch.randn(3, 16).abs()) * torch.randn(3, 16).sign()
    folder = tmp_path / "run"
    os.makedirs(folder / "preferences")
    rows = torch.randn(40, 2, 6, obs_dim + act_dim)
    rows[..., 3:6] *= 100  # the model reads none of them: the labels do not change
    with torch.no_grad():
        returns = model(rows.reshape(-1, obs_dim + act_dim))[0].view(40, 2, -1).sum(-1)
    labels = (returns[:, 1] > returns[:, 0]).float().numpy()
    np.savez(folder / "preferences" / "0.npz", obs=rows[..., :obs_dim].numpy(), actions=rows[..., obs_dim:].numpy(),
             labels=labels)
    torch.save({"args": {"reward_hidden_dim": 16, "reward_layers": 2}, "global_step": 300, "obs_dim_real": real,
                "obs_dim": obs_dim, "act_dim": act_dim, "reward_models": model.member_state_dicts()},
               folder / "r2n_surf_stored_noise.cleanrl_model")
    result = subprocess.run([sys.executable, os.path.join(STUDY, "grow_probe.py"), str(folder)], capture_output=True,
                            text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    probe = json.loads(result.stdout)
    assert probe["run"] == "run" and probe["step"] == 300 and probe["chance"] == 0.5
    stored, fresh = probe["stored"], probe["fresh"]
    assert stored["accuracy"][0] == 1.0 and fresh["accuracy"][0] < 0.8  # the labels hold on the stored noise only
    assert stored["active_share"] == fresh["active_share"] == [0.8] * 3  # 64 of 80 active weights are relevant
    assert stored["drop_share"] == [1.0] * 3 and stored["grow_share"] == stored["regrown"] == [0.0] * 3
    assert all(0 < share < 1 for share in stored["grad_share"] + fresh["grad_share"])


def watcher_repo(tmp_path):
    """A repository with the protocol committed and the scripts the watcher runs, and a worktree folder beside it.
    Returns (repo, work, the study's folder, an environment in which git can commit)."""
    repo, work = tmp_path / "repo", tmp_path / "work"
    subprocess.run(["git", "init", "-q", str(repo)], check=True)
    study = repo / "results" / "surf-rune"
    study.mkdir(parents=True)
    (study / "PROTOCOL.md").write_text("the protocol\n")
    for name in ("members.py", "stop_rule.py", "power.py"):
        os.symlink(os.path.join(STUDY, name), study / name)
    os.symlink(os.path.join(ROOT, "analyze.py"), repo / "analyze.py")
    env = dict(os.environ, GIT_AUTHOR_NAME="t", GIT_AUTHOR_EMAIL="t@t", GIT_COMMITTER_NAME="t",
               GIT_COMMITTER_EMAIL="t@t", PATH=os.path.dirname(sys.executable) + os.pathsep + os.environ["PATH"])
    subprocess.run(["git", "add", "."], cwd=repo, check=True)
    subprocess.run(["git", "commit", "-q", "-m", "protocol"], cwd=repo, check=True, env=env)
    return repo, work, study, env


def stopped_launcher(work):
    """A launcher that has stopped, after a crash: the watcher makes one pass and starts no next plan."""
    launcher = subprocess.Popen(["true"])
    launcher.wait()
    (work / "launcher.pid").write_text(f"{launcher.pid}\n")
    (work / "launcher.log").write_text("running 1 run\nTraceback (most recent call last):\n")


def test_watcher_commits_a_finished_run_with_its_members(tmp_path):
    """The watcher copies a finished run into `runs/`, adds `members.json` from the final model in the worktree's
    scratch folder, and commits both; the first-seeds stop rule does not fire on a seed-2 run."""
    repo, work, study, env = watcher_repo(tmp_path)
    run_id = "surf_stored_noise__cheetah-run__noise0.9__budget1000__seed2"
    tiny_run_with_a_constant_member(work / "logs" / "scratch" / run_id / "runs" / run_id)
    finished = work / "results" / "surf-rune" / "runs" / run_id
    finished.mkdir(parents=True)
    (finished / "done").write_text("exit code 0\ncpu AMD EPYC, torch CPU capability AVX512\nseconds 9\n")
    stopped_launcher(work)
    subprocess.run(["bash", os.path.join(STUDY, "continue.sh"), "--watch", str(work)], cwd=repo, check=True,
                   timeout=120, capture_output=True, env=env)
    committed = subprocess.run(["git", "show", "--name-only", "--format=%s", "HEAD"], cwd=repo, capture_output=True,
                               text=True, check=True).stdout.split()
    assert f"results/surf-rune/runs/{run_id}/done" in committed
    assert f"results/surf-rune/runs/{run_id}/members.json" in committed
    assert [m["constant"] for m in json.loads((study / "runs" / run_id / "members.json").read_text())] == [
        True, False, False]
    assert not (study / "STOPPED").exists()


LAUNCHER_STUB = """import os, signal, sys, time
if "--dry-run" in sys.argv:
    sys.exit(print("1 run would start"))
signal.signal(signal.SIGTERM, lambda *_: (open("terminated", "w").close(), sys.exit(1)))
open("pid", "w").write(str(os.getpid()))
time.sleep(60)
"""


def start_on_a_stub_launcher(tmp_path, before=None, pgrep=None, *options):
    """`continue.sh [options]` in a repository whose `benchmark.py` is LAUNCHER_STUB; `before(repo)` runs first, and
    `pgrep`, if given, is the script of a `pgrep` put first on PATH. Returns (repo, work, continue.sh's stdout)."""
    repo, work = tmp_path / "repo", tmp_path / "work"
    subprocess.run(["git", "init", "-q", str(repo)], check=True)
    study = repo / "results" / "surf-rune"
    study.mkdir(parents=True)
    (study / "PROTOCOL.md").write_text("the protocol\n")
    (repo / "benchmark.py").write_text(LAUNCHER_STUB)  # stands for the launcher, in the worktree at that commit
    (study / "schedule.py").write_text('print("--preset surf-rune")\n')
    subprocess.run(["git", "add", "."], cwd=repo, check=True)
    subprocess.run(["git", "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-q", "-m", "protocol"], cwd=repo,
                   check=True)
    path = [os.path.dirname(sys.executable), os.environ["PATH"]]
    if pgrep is not None:
        (tmp_path / "bin").mkdir()
        (tmp_path / "bin" / "pgrep").write_text(pgrep)
        os.chmod(tmp_path / "bin" / "pgrep", 0o755)
        path.insert(0, str(tmp_path / "bin"))
    if before:
        before(repo)
    result = subprocess.run(["bash", os.path.join(STUDY, "continue.sh"), *options, str(work)], cwd=repo, check=True,
                            timeout=60, env=dict(os.environ, PATH=os.pathsep.join(path)), capture_output=True, text=True)
    for _ in range(0 if "--dry-run" in options else 100):  # the launcher has started when the stub wrote its pid
        if (work / "pid").exists() and (work / "pid").read_text():
            break
        time.sleep(0.1)
    return repo, work, result.stdout


def stop_everything_in(work):
    if shutil.which("pkill"):  # the launcher, if a test failed, and the watcher (it would end within a minute)
        subprocess.run(["pkill", "-f", str(work)])


def test_continue_sh_records_the_launchers_own_pid_so_that_sigterm_reaches_it(tmp_path):
    """`launcher.pid` is what the stop rule and a session's end send SIGTERM to: the launcher's process, not a shell
    around it (a shell would die alone and leave the launcher and its runs going)."""
    try:
        repo, work, _ = start_on_a_stub_launcher(tmp_path)
        pid = int((work / "launcher.pid").read_text())
        assert pid == int((work / "pid").read_text())
        os.kill(pid, signal.SIGTERM)
        for _ in range(100):
            if (work / "terminated").exists():
                break
            time.sleep(0.1)
        assert (work / "terminated").exists()
    finally:
        stop_everything_in(tmp_path / "work")


def test_continue_sh_keeps_one_watcher(tmp_path):
    """A watcher still trying to commit when the next start comes gives way to the new one (a watcher keeps no state),
    and `watcher.pid` names the new one."""
    old = subprocess.Popen(["bash", "-c", "sleep 60; true", "stands-for-a-watcher", "--watch"])  # bash stays
    def earlier_watcher(repo):  # the worktree of an earlier start, with its watcher's pid
        subprocess.run(["git", "worktree", "add", "-q", "--detach", str(tmp_path / "work"), "HEAD"], cwd=repo, check=True)
        (tmp_path / "work" / "watcher.pid").write_text(f"{old.pid}\n")
        os.symlink(os.path.join(STUDY, "continue.sh"), repo / "results" / "surf-rune" / "continue.sh")  # the new one
    try:
        _, work, _ = start_on_a_stub_launcher(tmp_path, earlier_watcher)
        assert old.wait(timeout=10) == -signal.SIGTERM
        new = int((work / "watcher.pid").read_text())
        assert new != old.pid and "--watch" in open(f"/proc/{new}/cmdline").read()
    finally:
        old.kill()
        stop_everything_in(tmp_path / "work")


@pytest.mark.parametrize("git_running, age, options, removed", [
    (False, 120, (), True), (True, 120, (), False), (False, 5, (), False), (False, 120, ("--dry-run",), False)])
def test_continue_sh_removes_a_stale_index_lock_only_when_no_git_command_runs(tmp_path, git_running, age, options,
                                                                              removed):
    """A session's end can kill the watcher's `git commit` and leave `.git/index.lock`: every later commit would fail
    on it. The next start removes it, unless a git command is running or the lock is younger than a minute (then it
    may be a running command's); a dry run changes nothing."""
    def lock(repo):
        (repo / ".git" / "index.lock").write_text("")
        os.utime(repo / ".git" / "index.lock", (time.time() - age, time.time() - age))
    try:
        repo, work, out = start_on_a_stub_launcher(tmp_path, lock, "#!/bin/sh\necho 4242\n" if git_running else
                                                   "#!/bin/sh\nexit 1\n", *options)
        assert (repo / ".git" / "index.lock").exists() != removed
        assert ("removed a stale" in out) == removed
    finally:
        stop_everything_in(tmp_path / "work")


def test_watcher_tries_a_failed_commit_again_at_its_next_pass(tmp_path):
    """A commit that fails (here `git commit` fails once) leaves the run pending and unstaged (a later commit of the
    checkout would take it in under its own message): the watcher does not end, and its next pass commits the run."""
    repo, work, study, env = watcher_repo(tmp_path)
    run_id = "rune_stored_noise__cheetah-run__noise0.9__budget1000__seed3"
    finished = work / "results" / "surf-rune" / "runs" / run_id
    finished.mkdir(parents=True)
    (finished / "done").write_text("exit code 0\ncpu AMD EPYC, torch CPU capability AVX512\nseconds 9\n")
    (tmp_path / "bin").mkdir()
    (tmp_path / "bin" / "git").write_text(f"""#!/bin/sh
if [ "$1" = commit ] && [ ! -e {tmp_path}/failed ]; then touch {tmp_path}/failed; exit 1; fi
if [ "$1" = add ] && [ -e {tmp_path}/failed ]; then {shutil.which("git")} diff --cached --name-only > {tmp_path}/staged; fi
exec {shutil.which("git")} "$@"
""")
    os.chmod(tmp_path / "bin" / "git", 0o755)
    stopped_launcher(work)
    result = subprocess.run(["bash", os.path.join(STUDY, "continue.sh"), "--watch", str(work)], cwd=repo, check=True,
                            timeout=120, capture_output=True, text=True,
                            env=dict(env, PATH=f"{tmp_path / 'bin'}{os.pathsep}{env['PATH']}", WATCH_TRIES="1",
                                     WATCH_PAUSE="0", WATCH_PASS="1"))
    assert (tmp_path / "failed").exists()
    assert (tmp_path / "staged").read_text() == ""  # what the index held at the next pass's `git add`
    assert f"could not commit {run_id}: tried again in a minute" in result.stdout
    assert result.stdout.index("could not commit") < result.stdout.index(f"committed {run_id}")
    assert subprocess.run(["git", "cat-file", "-e", f"HEAD:results/surf-rune/runs/{run_id}/done"], cwd=repo).returncode == 0


@pytest.mark.parametrize("broken", [False, True])
def test_watcher_stops_the_launcher_when_the_stop_rule_fires_and_not_when_the_rule_crashes(tmp_path, broken):
    """A seed-1 SURF run at 20 fires the first-seeds stop rule: the watcher sends the launcher SIGTERM and writes
    `STOPPED`. A stop_rule.py that crashes (exit 1, no "stop rule:" line) stops nothing, and the log says so."""
    repo, work, study, env = watcher_repo(tmp_path)
    if broken:
        os.remove(study / "stop_rule.py")
        (study / "stop_rule.py").write_text("raise ImportError('no module named torch')\n")
    synthetic_run(work / "results" / "surf-rune" / "runs", "surf_stored_noise", 1, 20.0)
    launcher = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        (work / "launcher.pid").write_text(f"{launcher.pid}\n")
        (work / "launcher.log").write_text("running 4 runs, 2 at a time\n")
        watcher = subprocess.Popen(["bash", os.path.join(STUDY, "continue.sh"), "--watch", str(work)], cwd=repo,
                                   env=dict(env, WATCH_PASS="1"), stdout=subprocess.PIPE, text=True)
        if not broken:
            assert launcher.wait(timeout=60) == -signal.SIGTERM
            out, _ = watcher.communicate(timeout=60)
            assert "stop rule: surf_stored_noise__cheetah-run__noise0.9__budget1000__seed1 ended at 20.0" in out
            assert "launcher stopped" in out and (study / "STOPPED").exists()
        else:
            for _ in range(300):
                if (study / "runs" / "surf_stored_noise__cheetah-run__noise0.9__budget1000__seed1" / "done").exists():
                    break
                time.sleep(0.1)
            time.sleep(3)  # the watcher's pass is over: it commits, reads the rule, and sleeps a second
            assert launcher.poll() is None and not (study / "STOPPED").exists()
            launcher.kill()
            launcher.wait()  # reaped: a zombie would still answer the watcher's `kill -0`
            out, _ = watcher.communicate(timeout=60)
            assert "stop_rule.py failed, the stop rule is unchecked after surf_stored_noise" in out
    finally:
        launcher.kill()


def test_continue_sh_refuses_without_the_projects_venv(tmp_path):
    (tmp_path / "bin").mkdir()
    (tmp_path / "bin" / "python").write_text("#!/bin/sh\nexit 1\n")  # a python without torch
    os.chmod(tmp_path / "bin" / "python", 0o755)
    result = subprocess.run(["bash", os.path.join(STUDY, "continue.sh"), "--dry-run"], cwd=ROOT, capture_output=True,
                            text=True, timeout=60, env=dict(os.environ, PATH=f"{tmp_path / 'bin'}{os.pathsep}"
                                                                             f"{os.environ['PATH']}"))
    assert result.returncode == 1 and "activate the project's venv first" in result.stderr


def test_watcher_commits_a_run_whose_earlier_commit_failed(tmp_path):
    """A run copied here whose commit failed (its `done` here, not in HEAD) is committed at the watcher's next pass:
    "committed" is what HEAD holds, not what the folder holds."""
    repo, work, study, env = watcher_repo(tmp_path)
    run_id = "rune_stored_noise__cheetah-run__noise0.9__budget1000__seed3"
    done = "exit code 0\ncpu AMD EPYC, torch CPU capability AVX512\nseconds 9\n"
    for folder in (work / "results" / "surf-rune" / "runs" / run_id, study / "runs" / run_id):
        folder.mkdir(parents=True)  # in the worktree, and copied here by a pass whose commit failed
        (folder / "done").write_text(done)
    subprocess.run(["git", "add", "."], cwd=repo, check=True)  # even staged: only HEAD counts
    stopped_launcher(work)
    result = subprocess.run(["bash", os.path.join(STUDY, "continue.sh"), "--watch", str(work)], cwd=repo, check=True,
                            timeout=120, capture_output=True, text=True, env=env)
    assert f"committed {run_id}" in result.stdout
    assert subprocess.run(["git", "cat-file", "-e", f"HEAD:results/surf-rune/runs/{run_id}/done"], cwd=repo).returncode == 0


def test_committed_analysis_is_what_the_committed_runs_give(tmp_path):
    """Once all 48 runs are in, `analysis/` is committed, and its tests and diagnostics are what the scripts make of
    the committed runs now. Before, it holds no test."""
    landed = len(glob.glob(os.path.join(STUDY, "runs", "*", "done")))
    committed = os.path.join(STUDY, "analysis", "hypotheses.md")
    assert landed <= 48 and os.path.exists(committed) == (landed == 48), \
        f"{landed} of 48 runs are in: run `bash results/surf-rune/analyze.sh` once all are, and commit analysis/"
    if landed < 48:
        return
    for script, name in (("hypotheses.py", "hypotheses.md"), ("diagnostics.py", "diagnostics.md")):
        subprocess.run([sys.executable, os.path.join(STUDY, script), "--out", str(tmp_path / name)], check=True,
                       capture_output=True, timeout=300)
        with open(os.path.join(STUDY, "analysis", name)) as f:
            assert (tmp_path / name).read_text() == f.read(), f"run `bash results/surf-rune/analyze.sh`: {name}"


def test_analyze_sh_writes_the_whole_analysis_once_every_run_is_in(tmp_path):
    """analyze.sh end to end on 48 synthetic runs, in a copy of the repository's layout: analyze.py's tables and curves,
    the tests, the power achieved and the diagnostics, each where the protocol says."""
    root = tmp_path / "root"
    study = root / "results" / "surf-rune"
    os.makedirs(study)
    for name in ("analyze.sh", "power.py", "hypotheses.py", "diagnostics.py"):
        os.symlink(os.path.join(STUDY, name), study / name)
    os.symlink(os.path.join(ROOT, "analyze.py"), root / "analyze.py")
    synthetic_study(tmp_path)
    for name, folder in (("stored-noise", "reference"), ("which-sparsity", "which")):
        os.makedirs(root / "results" / name)
        os.symlink(tmp_path / folder, root / "results" / name / "runs")
    os.symlink(tmp_path / "runs", study / "runs")
    result = subprocess.run(["bash", str(study / "analyze.sh")], cwd=root, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-2000:]
    analysis = study / "analysis"
    for name in ("primary.md", "hypotheses.md", "power-achieved.txt", "diagnostics.md"):
        assert (analysis / name).stat().st_size > 0, name
    primary = (analysis / "primary.md").read_text()
    # R2N-SURF and the actor/critic-only arm are tested against SURF, R2N-RUNE against RUNE; nothing else is
    rows = [line.split("|") for line in primary.splitlines() if line.startswith("| ") and "_stored_noise |" in line]
    tested = sorted(row[3].strip() for row in rows if row[5].strip())
    assert tested == ["r2n_rune_stored_noise", "r2n_surf_agent_only_stored_noise", "r2n_surf_stored_noise"], primary
    assert len(rows) == 7 and "against the baseline (`surf_stored_noise`; r2n_rune_stored_noise=rune_stored_noise" in primary
    assert "r2n_surf_stored_noise: n 10" in (analysis / "power-achieved.txt").read_text()
