"""Issue 69's analysis (results/which-sparsity): the tests as PROTOCOL.md fixes them, on synthetic runs whose primary
metrics are known, against scipy; the refusal before every run is in; the diagnostics' stop rule."""
import importlib.util
import os
import subprocess
import sys

import numpy as np
from scipy import stats
from torch.utils.tensorboard import SummaryWriter

from test_scripts import ROOT

STUDY = os.path.join(ROOT, "results", "which-sparsity")
SEEDS = {"pebble_stored_noise": 8, "r2n_pebble_stored_noise": 10, "r2n_pebble_reward_only_stored_noise": 10,
         "dropconnect_pebble_stored_noise": 8, "l1_pebble_stored_noise": 8, "r2n_pebble_agent_only_stored_noise": 10,
         "set_pebble_stored_noise": 8, "static_pebble_stored_noise": 8}
MEANS = {"pebble_stored_noise": 180.0, "r2n_pebble_stored_noise": 260.0, "r2n_pebble_reward_only_stored_noise": 170.0,
         "dropconnect_pebble_stored_noise": 150.0, "l1_pebble_stored_noise": 240.0,
         "r2n_pebble_agent_only_stored_noise": 265.0, "set_pebble_stored_noise": 262.0,
         "static_pebble_stored_noise": 250.0}


def fake_run(folder, arm, seed, primary, relevant=0.5):
    """A finished run whose last 3 evaluations average `primary`; its connectivity `relevant`, chance 0.13."""
    path = os.path.join(folder, f"{arm}__cheetah-run__noise0.9__budget1000__seed{seed}")
    writer = SummaryWriter(path)
    for step, value in ((230_000, primary - 1.0), (240_000, primary), (250_000, primary + 1.0)):
        writer.add_scalar("eval/episodic_return", value, step)
        for net in ("actor", "qf1", "reward0"):
            writer.add_scalar(f"features/{net}/chance", 0.13, step)
            writer.add_scalar(f"features/{net}/relevant_weight_frac", relevant, step)
            writer.add_scalar(f"sparse/{net}/relevant_active_frac", relevant, step)
    writer.close()
    open(os.path.join(path, "done"), "w").write("finished\n")


def make_study(tmp_path, skip=None):
    """Synthetic runs: the reference arms' first 8 seeds in `reference/`, the rest in `runs/`; metric -> values."""
    rng, values = np.random.default_rng(1), {}
    for arm, n in SEEDS.items():
        values[arm] = np.round(MEANS[arm] + 40 * rng.standard_normal(n), 3)
        for seed, value in enumerate(values[arm], 1):
            reference = arm in ("pebble_stored_noise", "r2n_pebble_stored_noise") and seed <= 8
            if (arm, seed) != skip:
                fake_run(tmp_path / ("reference" if reference else "runs"), arm, seed, value)
    return values


def hypotheses(tmp_path, *extra):
    return subprocess.run([sys.executable, os.path.join(STUDY, "hypotheses.py"), "--reference",
                           str(tmp_path / "reference"), "--runs", str(tmp_path / "runs"), *extra],
                          capture_output=True, text=True, timeout=300)


def test_hypotheses_refuse_until_every_run_is_in(tmp_path):
    make_study(tmp_path, skip=("l1_pebble_stored_noise", 3))
    result = hypotheses(tmp_path, "--out", str(tmp_path / "h.md"))
    assert result.returncode == 1 and "l1_pebble_stored_noise (7 of 8)" in result.stderr, result.stderr
    assert len(result.stderr.strip().splitlines()) == 1 and not os.path.exists(tmp_path / "h.md")


def test_hypotheses_are_the_protocols_tests(tmp_path):
    values = make_study(tmp_path)
    result = hypotheses(tmp_path, "--out", str(tmp_path / "h.md"))
    assert result.returncode == 0, result.stderr
    text = (tmp_path / "h.md").read_text()
    r2n = values["r2n_pebble_stored_noise"]
    # H1-H3: one-tailed Welch, Holm over the three
    p = {h: stats.ttest_ind(values[arm], r2n, equal_var=False, alternative="less").pvalue for h, arm in (
        ("H1", "r2n_pebble_reward_only_stored_noise"), ("H2", "dropconnect_pebble_stored_noise"),
        ("H3", "l1_pebble_stored_noise"))}
    order = sorted(p, key=p.get)
    holm = dict(zip(order, np.maximum.accumulate([min(1, (3 - k) * p[h]) for k, h in enumerate(order)])))
    for h in p:
        row = next(line for line in text.splitlines() if line.startswith(f"| {h} |"))
        assert f"| {p[h]:.4f} | {holm[h]:.4f} |" in row, (row, p[h], holm[h])
        assert row.endswith("| yes |") == (holm[h] < 0.05)
    # E1: the Welch interval of R2N - agent-only, and the reading fixed before the runs
    agent = values["r2n_pebble_agent_only_stored_noise"]
    delta = r2n.mean() - agent.mean()
    va, vb = r2n.var(ddof=1) / len(r2n), agent.var(ddof=1) / len(agent)
    df = (va + vb) ** 2 / (va ** 2 / (len(r2n) - 1) + vb ** 2 / (len(agent) - 1))
    upper = delta + stats.t.ppf(0.95, df) * np.sqrt(va + vb)
    assert f"Δ = R2N-PEBBLE - actor/critic-only = {delta:+.1f}" in text and f"upper {upper:+.1f}" in text
    p_e1 = stats.ttest_ind(agent, r2n, equal_var=False, alternative="less").pvalue
    expected = ("the reward's sparsity adds nothing at this scale" if delta <= 0 and upper < 38.6
                else "the reward's sparsity adds to the gain" if p_e1 < 0.05
                else f"this study cannot tell: the reward's sparsity adds at most {upper:.1f}")
    assert f"**Reading, as fixed before the runs: {expected}.**" in text
    # the arms' table: ours (mean ± SE, Student's 95% CI) beside the paper's, each relative to R2N-PEBBLE
    for arm, v in values.items():
        se = v.std(ddof=1) / np.sqrt(len(v))
        half = stats.t.ppf(0.975, len(v) - 1) * se
        row = next(line for line in text.splitlines() if line.startswith(f"| `{arm}` |"))
        assert f"| {len(v)} | {v.mean():.1f} ± {se:.1f} | [{v.mean() - half:.1f}, {v.mean() + half:.1f}] |" in row
        assert f"| {v.mean() / r2n.mean():.2f} |" in row and row.endswith("| not recorded ×%d |" % len(v)), row
    paper = next(line for line in text.splitlines() if line.startswith("| `r2n_pebble_agent_only_stored_noise` |"))
    assert "| 327.33 ± 17.82 | 0.85 |" in paper
    # E5: two-sided Welch
    p_set = stats.ttest_ind(values["set_pebble_stored_noise"], r2n, equal_var=False).pvalue
    assert f"{p_set:.4f} (two-sided)" in text


def test_holm_power_takes_each_arms_own_sd():
    # by path: other studies have a `power` module too
    spec = importlib.util.spec_from_file_location("which_sparsity_power", os.path.join(STUDY, "power.py"))
    power = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(power)
    seeds = {arm: plan[3] for arm, plan in power.ARMS.items()}
    wide = power.holm_power(260.0, 10.0, 10, seeds, reps=4000, arm_sds={"l1_pebble_stored_noise": 400.0})
    # at SD 10 the planned effects (80 to 110 points) are certain to be found; at SD 400 for L1 alone they are not
    assert wide["dropconnect_pebble_stored_noise"] > 0.99 and wide["r2n_pebble_reward_only_stored_noise"] > 0.99
    assert wide["l1_pebble_stored_noise"] < 0.3
    # one-tailed at 0.05, Holm's power is at least Bonferroni's bound and at most the uncorrected test's
    holm = power.holm_power(260.0, 60.0, 10, seeds)
    for arm in power.CONFIRMATORY:
        effect = (1 - power.ARMS[arm][0] / power.PAPER_R2N) * 260.0
        bound = power.power(effect, 60.0, seeds[arm], 10, 0.05 / 3)
        assert bound - 0.02 < holm[arm] < power.power(effect, 60.0, seeds[arm], 10) + 0.02, (arm, bound, holm)


def test_diagnostics_name_a_sparse_layer_at_chance(tmp_path):
    make_study(tmp_path)
    folder = tmp_path / "runs"
    for name in os.listdir(folder):  # the agent-only arm's actor never leaves chance
        if name.startswith("r2n_pebble_agent_only_stored_noise__"):
            os.remove(os.path.join(folder, name, "done"))
    for seed in range(1, 11):
        fake_run(folder, "r2n_pebble_agent_only_stored_noise", f"{seed}x", 250.0, relevant=0.1305)
    result = subprocess.run([sys.executable, os.path.join(STUDY, "diagnostics.py"), "--reference",
                             str(tmp_path / "reference"), "--runs", str(folder), "--out", str(tmp_path / "d.md")],
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    text = (tmp_path / "d.md").read_text()
    assert "`r2n_pebble_agent_only_stored_noise`: `sparse/actor/relevant_active_frac` is at chance" in text
    assert "r2n_pebble_reward_only_stored_noise`: `sparse" not in text  # its layers moved (0.5 > 0.13)


def test_continue_commits_each_finished_run_once(tmp_path):
    """continue.sh's watcher: a finished run in the worktree is copied and committed alone, named with its CPU; an
    unfinished one is left; a second pass commits nothing more."""
    repo, work = tmp_path / "repo", tmp_path / "work"
    git = ["git", "-c", "user.name=t", "-c", "user.email=t@t"]
    subprocess.run(["git", "init", "-q", str(repo)], check=True)
    (repo / "unrelated.txt").write_text("staged, not the watcher's to commit\n")
    subprocess.run(git + ["commit", "-q", "--allow-empty", "-m", "start"], cwd=repo, check=True)
    subprocess.run(["git", "add", "unrelated.txt"], cwd=repo, check=True)
    runs = work / "results" / "which-sparsity" / "runs"
    for run, done in (("set_pebble_stored_noise__seed1", True), ("static_pebble_stored_noise__seed1", False)):
        (runs / run).mkdir(parents=True)
        (runs / run / "log.txt").write_text("log\n")
        if done:
            (runs / run / "done").write_text("exit code 0\nseconds 3600 over 1 start(s)\ncpu AMD EPYC, AVX2\n")
    launcher = subprocess.Popen(["true"])  # a launcher that has stopped: the watcher makes one pass and ends
    launcher.wait()
    (work / "launcher.pid").write_text(f"{launcher.pid}\n")
    env = dict(os.environ, GIT_AUTHOR_NAME="t", GIT_AUTHOR_EMAIL="t@t", GIT_COMMITTER_NAME="t",
               GIT_COMMITTER_EMAIL="t@t")
    script = os.path.join(STUDY, "continue.sh")
    for _ in range(2):
        subprocess.run(["bash", script, "--watch", str(work)], cwd=repo, env=env, check=True, timeout=60)
    log = subprocess.run(["git", "log", "--format=%s", "--name-only"], cwd=repo, capture_output=True, text=True,
                         check=True).stdout.split("\n")
    assert log[:5] == ["which-sparsity: set_pebble_stored_noise__seed1 (commit 0e11778, AMD EPYC, AVX2, 3600 over 1 "
                       "start(s))", "", "results/which-sparsity/runs/set_pebble_stored_noise__seed1/done",
                       "results/which-sparsity/runs/set_pebble_stored_noise__seed1/log.txt", "start"]
    assert not (repo / "results" / "which-sparsity" / "runs" / "static_pebble_stored_noise__seed1").exists()
    staged = subprocess.run(["git", "diff", "--cached", "--name-only"], cwd=repo, capture_output=True, text=True)
    assert staged.stdout.split() == ["unrelated.txt"]


def test_committed_analysis_is_what_the_committed_runs_give(tmp_path):
    """Once all 54 runs are in, `analysis/` is committed, and its tests and diagnostics are what the scripts make of
    the committed runs now (a run or a script changed without `analyze.sh` fails here). Before, it holds no test."""
    runs = os.path.join(STUDY, "runs")
    landed = sum(os.path.exists(os.path.join(runs, run, "done")) for run in os.listdir(runs))
    committed = os.path.join(STUDY, "analysis", "hypotheses.md")
    assert landed <= 54 and os.path.exists(committed) == (landed == 54), \
        f"{landed} of 54 runs are in: run `bash results/which-sparsity/analyze.sh` once all are, and commit analysis/"
    if landed < 54:
        return
    for script, name in (("hypotheses.py", "hypotheses.md"), ("diagnostics.py", "diagnostics.md")):
        subprocess.run([sys.executable, os.path.join(STUDY, script), "--out", str(tmp_path / name)], check=True,
                       capture_output=True, timeout=300)
        with open(os.path.join(STUDY, "analysis", name)) as f:
            assert (tmp_path / name).read_text() == f.read(), f"run `bash results/which-sparsity/analyze.sh`: {name}"
