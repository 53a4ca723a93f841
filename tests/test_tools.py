"""The tools: `analyze.py` on synthetic TensorBoard runs (numbers checked against numpy/scipy), and `benchmark.py`:
preset grids, the local back-end (parallel fake runs, GPU slots, resume, failures, one real tiny pebble.py run) and
the SLURM back-end through submitit (local executor; a fake `sbatch` for the job script)."""
import csv
import dataclasses
import glob
import importlib.util
import itertools
import json
import math
import os
import re
import shlex
import signal
import shutil
import subprocess
import sys
import time

import numpy as np
import pytest
from torch.utils.tensorboard import SummaryWriter

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from test_scripts import ROOT, TINY  # noqa: E402

import analyze  # noqa: E402
import benchmark  # noqa: E402

needs_analysis = pytest.mark.skipif(
    not all(importlib.util.find_spec(m) for m in ("scipy", "matplotlib")), reason="needs the `analysis` extra"
)
needs_submitit = pytest.mark.skipif(importlib.util.find_spec("submitit") is None, reason="needs the `slurm` extra")
STEPS = [1000, 2000, 3000, 4000, 5000]
HARNESS = ["--resumable", "--diagnostics", "--query-log"]  # what the launcher adds to a PbRL run


def welch(a, b, alternative="greater"):
    """The p-value computed here, independently of analyze.py."""
    from scipy import stats

    return stats.ttest_ind(a, b, equal_var=False, alternative=alternative).pvalue


def exact_permutation(a, b, alternative="greater"):
    """The exact permutation p-value of the difference in means, by scipy (every relabeling)."""
    from scipy import stats

    return stats.permutation_test((a, b), lambda x, y, axis: x.mean(axis=axis) - y.mean(axis=axis), vectorized=True,
                                  permutation_type="independent", alternative=alternative, n_resamples=np.inf).pvalue


BASE_HPARAMS = dict(exp_name=None, seed=None, torch_deterministic=True, cuda=True, track=False, wandb_entity=None,
                    threads=None, env_id=None, noise=None, noise_type="gaussian", noise_histograms=None,
                    total_timesteps=5000, batch_size=1024, max_feedback=None, reward_lr=0.003, eval_freq=1000)


def hparams_writer(path, env_id, noise, budget, method, seed, **overrides) -> SummaryWriter:
    """A run's event writer that has written the hyperparameter table, as the scripts do first."""
    hparams = dict(BASE_HPARAMS, exp_name=method, seed=seed, env_id=env_id, noise=noise, max_feedback=budget)
    hparams.update(overrides)
    writer = SummaryWriter(path)
    writer.add_text("hyperparameters", "|param|value|\n|-|-|\n%s" % ("\n".join(f"|{k}|{v}|" for k, v in hparams.items())))
    return writer


def write_run(root, env_id, noise, budget, method, seed, returns, steps=STEPS, stamp=100, sparse=False, labeled=(),
              seconds_per_step=None, **overrides):
    """A run folder as the scripts write it: the hyperparameter table, then eval returns (and sparse tags, and the
    labels so far after each feedback round: `labeled`, (step, labels) pairs). With `seconds_per_step`, an evaluation
    is stamped that long per step after the table, as if the run took it."""
    path = os.path.join(root, f"{env_id}__{method}__{seed}__{stamp}")
    writer = hparams_writer(path, env_id, noise, budget, method, seed, **overrides)
    start = time.time()
    writer.add_scalar("charts/episodic_return", 1.0, 100)
    for step, labels in labeled:
        writer.add_scalar("pbrl/labeled_feedback", labels, step)
    for i, (step, value) in enumerate(zip(steps, returns)):
        walltime = start + step * seconds_per_step if seconds_per_step else None
        writer.add_scalar("eval/episodic_return", value, step, walltime=walltime)
        if sparse:
            for net in ("actor", "reward0"):
                writer.add_scalar(f"sparse/{net}/relevant_degree", 10 + i + seed, step)
                writer.add_scalar(f"sparse/{net}/noise_degree", 10 - i, step)
                writer.add_scalar(f"sparse/{net}/relevant_active_frac", 0.5, step)
    writer.close()
    return path


def values(rng, n, offset):
    """Returns exactly representable in float32 (TensorBoard stores float32), so sums are exact too."""
    return (rng.integers(0, 400, size=n) + offset * 4) / 4.0


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory):
    """Two tasks x two methods, unequal seed counts, a crashed, an unfinished, a mismatched and a duplicate run."""
    root = tmp_path_factory.mktemp("tb")
    runs_a, runs_b = root / "runs_a", root / "runs_b"  # two folders, as from two machines
    rng = np.random.default_rng(0)
    data = {}
    layout = {  # task -> (noise, budget, {method: (seeds, offset)})
        "cheetah-run": (0.9, 1000, {"pebble": ([1, 2, 3], 0), "r2n_pebble": ([1, 2, 3, 4], 150)}),  # clear gap
        "walker-walk": (0.9, 4000, {"pebble": ([1, 2, 3], 150), "r2n_pebble": ([1, 2, 3], 0)}),  # worse: p near 1
    }
    for task, (noise, budget, methods) in layout.items():
        for method, (seeds, offset) in methods.items():
            for seed in seeds:
                returns = values(rng, len(STEPS), offset)
                data[(task, method, seed)] = returns
                folder = runs_a if seed % 2 else runs_b
                write_run(str(folder), task, noise, budget, method, seed, returns, sparse=method == "r2n_pebble")
    bad = {
        "crashed": write_run(str(runs_a), "cheetah-run", 0.9, 1000, "r2n_pebble", 9, [], stamp=101),
        "unfinished": write_run(str(runs_a), "cheetah-run", 0.9, 1000, "pebble", 8, [1.0, 2.0, 3.0], stamp=102),
        "mismatched": write_run(str(runs_b), "walker-walk", 0.9, 4000, "r2n_pebble", 7, [5.0] * 5, stamp=103,
                                batch_size=256),
        # seed 1 again, older folder, same length: the newer (stamp 100) is kept
        "duplicate": write_run(str(runs_b), "walker-walk", 0.9, 4000, "pebble", 1, [9.0] * 5, stamp=50),
    }
    os.makedirs(runs_b / "garbage")
    (runs_b / "garbage" / "events.out.tfevents.0.garbage").write_bytes(b"not an event file at all")
    bad["unreadable"] = str(runs_b / "garbage")
    out = root / "out"
    code = analyze.main(analyze.Args(log_dirs=(str(runs_a), str(runs_b)), output_dir=str(out)))
    assert code == 0
    return dict(root=root, dirs=(str(runs_a), str(runs_b)), data=data, bad=bad, out=out, layout=layout)


def read_csv(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def expected_stats(data, task, method, seeds, n_steps=len(STEPS)):
    finals = np.array([data[(task, method, s)][n_steps - 1] for s in seeds])
    aucs = np.array([data[(task, method, s)][:n_steps].sum() for s in seeds])
    return finals, aucs


def se(x):
    return np.std(x, ddof=1) / np.sqrt(len(x))


def test_parse_hparams_reads_the_scripts_table():
    text = "|param|value|\n|-|-|\n|exp_name|r2n_pebble|\n|seed|3|\n|noise|0.9|\n|cuda|True|\n|wandb_entity|None|\n" \
           "|reward_lr|0.003|\n|alpha_lr|1e-05|\n|noise_histograms|h.npz|"
    assert analyze.parse_hparams(text) == dict(exp_name="r2n_pebble", seed=3, noise=0.9, cuda=True, wandb_entity=None,
                                               reward_lr=0.003, alpha_lr=1e-5, noise_histograms="h.npz")


@needs_analysis
def test_tables_match_independent_statistics(synthetic):
    data, out = synthetic["data"], synthetic["out"]
    final_rows = {(r["task"], r["method"]): r for r in read_csv(out / "final_return.csv")}
    auc_rows = {(r["task"], r["method"]): r for r in read_csv(out / "auc.csv")}
    assert set(final_rows) == set(auc_rows) == {(t, m) for t in ("cheetah-run", "walker-walk")
                                                 for m in ("pebble", "r2n_pebble")}
    for task, (noise, budget, methods) in synthetic["layout"].items():
        base_final, base_auc = expected_stats(data, task, "pebble", methods["pebble"][0])
        for method, (seeds, _) in methods.items():
            finals, aucs = expected_stats(data, task, method, seeds)
            for rows, x, base in ((final_rows, finals, base_final), (auc_rows, aucs, base_auc)):
                row = rows[(task, method)]
                assert (float(row["noise"]), int(row["budget"]), int(row["seeds"])) == (noise, budget, len(seeds))
                assert row["seed_list"] == " ".join(map(str, seeds))
                assert float(row["mean"]) == pytest.approx(x.mean(), rel=1e-12)
                assert float(row["se"]) == pytest.approx(se(x), rel=1e-12)
                if method == "pebble":
                    assert row["p_value"] == "" and row["baseline"] == ""
                else:
                    p = welch(x, base)
                    assert float(row["p_value"]) == pytest.approx(p, rel=1e-9)
                    assert row["significant"] == str(int(p < 0.05)) and row["baseline"] == "pebble"
    # R2N is clearly better on cheetah-run and clearly worse on walker-walk
    assert final_rows[("cheetah-run", "r2n_pebble")]["significant"] == "1"
    assert auc_rows[("walker-walk", "r2n_pebble")]["significant"] == "0"
    assert float(auc_rows[("walker-walk", "r2n_pebble")]["p_value"]) > 0.9


@needs_analysis
def test_markdown_has_the_paper_layout(synthetic):
    data, out = synthetic["data"], synthetic["out"]
    text = (out / "final_return.md").read_text()
    assert "| Task | Feedback / Noise | Method | Final Return | P Value | Seeds |" in text
    finals, _ = expected_stats(data, "cheetah-run", "r2n_pebble", [1, 2, 3, 4])
    base, _ = expected_stats(data, "cheetah-run", "pebble", [1, 2, 3])
    p = welch(finals, base)
    lines = text.splitlines()
    perm_p, diff = exact_permutation(finals, base), finals.mean() - base.mean()
    low, high = analyze.bootstrap_ci(finals, base)
    i = lines.index(f"| cheetah-run | 1000 / 0.9 | pebble | {base.mean():.2f} ± {se(base):.2f} |  | 3 |  |  |")
    assert lines[i + 1] == (f"|  |  | r2n_pebble | {finals.mean():.2f} ± {se(finals):.2f} | {p:.3f}* | 4 "
                            f"| {perm_p:.3f}* | {diff:.2f} [{low:.2f}, {high:.2f}] |")
    assert perm_p == pytest.approx(1 / 35)  # the observed split is the most extreme of C(7, 3) = 35
    walker = [line for line in lines if line.startswith("| walker-walk | 4000 / 0.9 | pebble | ")]
    assert len(walker) == 1 and lines[lines.index(walker[0]) + 1].startswith("|  |  | r2n_pebble | ")
    assert lines.index(walker[0]) < i  # the paper's task order: walker-walk before cheetah-run
    assert "| AUC | P Value | Seeds | Perm. p | Diff. [95% CI] |" in (out / "auc.md").read_text()
    assert "| Primary Metric | P Value | Seeds | Perm. p | Diff. [95% CI] |" in (out / "primary.md").read_text()


@needs_analysis
def test_primary_metric_permutation_p_and_ci_columns(synthetic, tmp_path):
    """primary.csv: the mean of each run's last 3 evaluations (the last 1 with --primary-last 1: the final return);
    every table's perm_p is scipy's exact permutation p, diff the difference in means, ci_* the bootstrap CI."""
    data, out, pair = synthetic["data"], synthetic["out"], ("pebble", "r2n_pebble")  # (baseline, method)
    for task, (_, _, methods) in synthetic["layout"].items():
        (base_final, base_auc), (finals, aucs) = (expected_stats(data, task, m, methods[m][0]) for m in pair)
        base_last3, last3 = (np.array([data[(task, m, s)][-3:].mean() for s in methods[m][0]]) for m in pair)
        for name, base, x in (("primary", base_last3, last3), ("final_return", base_final, finals),
                              ("auc", base_auc, aucs)):
            rows = {r["method"]: r for r in read_csv(out / f"{name}.csv") if r["task"] == task}
            assert float(rows["pebble"]["mean"]) == pytest.approx(base.mean(), rel=1e-12)
            assert float(rows["r2n_pebble"]["mean"]) == pytest.approx(x.mean(), rel=1e-12)
            assert float(rows["r2n_pebble"]["se"]) == pytest.approx(se(x), rel=1e-12)
            assert rows["pebble"]["perm_p"] == rows["pebble"]["diff"] == rows["pebble"]["ci_low"] == ""
            row = rows["r2n_pebble"]
            assert float(row["p_value"]) == pytest.approx(welch(x, base), rel=1e-9)
            assert float(row["perm_p"]) == pytest.approx(exact_permutation(x, base), rel=1e-12)
            assert row["perm_exact"] == "1" and float(row["diff"]) == pytest.approx(x.mean() - base.mean(), rel=1e-12)
            low, high = float(row["ci_low"]), float(row["ci_high"])
            assert (low, high) == analyze.bootstrap_ci(x, base) and low < float(row["diff"]) < high
    assert analyze.main(analyze.Args(log_dirs=synthetic["dirs"], output_dir=str(tmp_path), primary_last=1,
                                     plots=False)) == 0
    means = [[r["mean"] for r in read_csv(folder / name)] for folder, name in ((tmp_path, "primary.csv"),
                                                                               (out, "final_return.csv"))]
    assert means[0] == means[1]
    with pytest.raises(SystemExit, match="--primary-last must be at least 1"):
        analyze.main(analyze.Args(log_dirs=synthetic["dirs"], output_dir=str(tmp_path), primary_last=0))


@needs_analysis
def test_skipped_runs_are_reported_not_averaged(synthetic):
    out, bad = synthetic["out"], synthetic["bad"]
    runs = {os.path.dirname(r["path"]): r for r in read_csv(out / "runs.csv")}  # one event file per folder here
    expected = {"crashed": "crashed: no eval/episodic_return point", "unfinished": "unfinished: last evaluation at step 3000",
                "mismatched": "mismatched settings: batch_size=256 (group: 1024)", "duplicate": "duplicate seed 1",
                "unreadable": "unreadable"}
    markdown = (out / "final_return.md").read_text()
    for kind, reason in expected.items():
        row = runs[os.path.abspath(bad[kind])]
        assert row["status"] == "skipped" and row["reason"].startswith(reason), (kind, row)
        assert f"`{row['path']}`: {reason}" in markdown
    assert sum(r["status"] == "used" for r in runs.values()) == 13
    assert "Skipped runs (5; never averaged)" in markdown


@needs_analysis
def test_runs_with_other_numerics_are_never_averaged_or_compared(tmp_path):
    """--compile and --tf32 change numerics: such a run is skipped from an eager group, and a method whose runs all
    used other numerics than its baseline's gets no test, with one note saying why."""
    root = str(tmp_path / "runs")
    for seed in (1, 2, 3):
        write_run(root, "cheetah-run", 0.9, 1000, "pebble", seed, [1.0, 2.0, 3.0, 4.0, 5.0 + seed])
        write_run(root, "cheetah-run", 0.9, 1000, "r2n_pebble", seed, [1.0, 2.0, 3.0, 4.0, 6.0 + seed], tf32=True)
    write_run(root, "cheetah-run", 0.9, 1000, "pebble", 4, [9.0] * 5, compile=True)
    assert analyze.main(analyze.Args(log_dirs=(root,), output_dir=str(tmp_path / "out"), plots=False)) == 0
    runs = {os.path.basename(os.path.dirname(r["path"])): r for r in read_csv(tmp_path / "out" / "runs.csv")}
    assert runs["cheetah-run__pebble__4__100"]["reason"] == (
        "mismatched settings: compile=True (group: False) (numerics flags: never averaged together)")
    row = {r["method"]: r for r in read_csv(tmp_path / "out" / "final_return.csv")}["r2n_pebble"]
    assert row["p_value"] in ("", "nan") and row["seeds"] == "3"
    assert ("not compared with pebble: the numerics flags differ (tf32=True vs False); runs with different numerics "
            "are never compared") in row["notes"]


@needs_analysis
def test_runs_of_the_two_noise_variants_are_never_averaged_or_compared(tmp_path):
    """Noise redrawn and noise stored are two environments: a stored run is skipped from a redrawn group with one line,
    and a stored method gets no test against a redrawn baseline. A run recorded before `--noise-resample` existed
    counts as redrawn: it pools with the redrawn runs, and a stored method is not compared with it."""
    root = str(tmp_path / "runs")
    for seed in (1, 2, 3):
        write_run(root, "cheetah-run", 0.9, 1000, "pebble", seed, [1.0, 2.0, 3.0, 4.0, 5.0 + seed],
                  **({} if seed == 1 else {"noise_resample": True}))  # seed 1: recorded before the flag
        write_run(root, "cheetah-run", 0.9, 1000, "r2n_pebble", seed, [1.0, 2.0, 3.0, 4.0, 6.0 + seed],
                  noise_resample=False)
    write_run(root, "cheetah-run", 0.9, 1000, "pebble", 4, [9.0] * 5, noise_resample=False)
    assert analyze.main(analyze.Args(log_dirs=(root,), output_dir=str(tmp_path / "out"), plots=False)) == 0
    runs = {os.path.basename(os.path.dirname(r["path"])): r for r in read_csv(tmp_path / "out" / "runs.csv")}
    assert runs["cheetah-run__pebble__4__100"]["reason"] == (
        "mismatched settings: noise_resample=False (group: True) (noise redrawn and stored: never averaged together)")
    assert runs["cheetah-run__pebble__1__100"]["status"] == "used"
    rows = {r["method"]: r for r in read_csv(tmp_path / "out" / "final_return.csv")}
    assert rows["pebble"]["seeds"] == "3"
    row = rows["r2n_pebble"]
    assert row["p_value"] in ("", "nan") and row["diff"] in ("", "nan") and row["seeds"] == "3"
    assert ("not compared with pebble: the noise is redrawn in one and stored in the other (noise_resample=False vs "
            "True); runs of different environments are never compared") in row["notes"]


@needs_analysis
def test_run_settings_that_keep_the_numbers_are_averaged_together(tmp_path):
    """--cuda-graph (the same numbers as eager), --parallel-eval (the same returns) and --state-minutes (when the state
    is written) do not change what a run learns: runs that differ in them, or were recorded before they existed, are
    one group."""
    root = str(tmp_path / "runs")
    write_run(root, "cheetah-run", 0.9, 1000, "pebble", 1, [1.0] * 5)  # recorded before the three flags existed
    write_run(root, "cheetah-run", 0.9, 1000, "pebble", 2, [2.0] * 5, cuda_graph=True, parallel_eval=False,
              state_minutes=10.0)
    write_run(root, "cheetah-run", 0.9, 1000, "pebble", 3, [3.0] * 5, cuda_graph=False, parallel_eval=True,
              state_minutes=30.0)
    assert analyze.main(analyze.Args(log_dirs=(root,), output_dir=str(tmp_path / "out"), plots=False)) == 0
    runs = read_csv(tmp_path / "out" / "runs.csv")
    assert [r["status"] for r in runs] == ["used"] * 3, runs
    row = {r["method"]: r for r in read_csv(tmp_path / "out" / "final_return.csv")}["pebble"]
    assert row["seeds"] == "3" and float(row["mean"]) == pytest.approx(2.0), row


@needs_analysis
def test_unfinished_runs_align_on_common_steps(synthetic, tmp_path):
    """--include-unfinished: the unfinished seed joins its group, which is truncated to the steps all runs have."""
    data, bad = synthetic["data"], synthetic["bad"]
    code = analyze.main(analyze.Args(log_dirs=synthetic["dirs"], output_dir=str(tmp_path), include_unfinished=True,
                                     plots=False))
    assert code == 0
    rows = {(r["task"], r["method"]): r for r in read_csv(tmp_path / "final_return.csv")}
    auc_rows = {(r["task"], r["method"]): r for r in read_csv(tmp_path / "auc.csv")}
    row = rows[("cheetah-run", "pebble")]
    assert (row["seeds"], row["eval_points"], row["last_step"], row["seed_list"]) == ("4", "3", "3000", "1 2 3 8")
    assert "aligned on the 3 evaluation steps common to its 4 runs" in row["notes"]
    finals = np.array([data[("cheetah-run", "pebble", s)][2] for s in (1, 2, 3)] + [3.0])
    aucs = np.array([data[("cheetah-run", "pebble", s)][:3].sum() for s in (1, 2, 3)] + [6.0])
    assert float(row["mean"]) == pytest.approx(finals.mean(), rel=1e-12)
    assert float(auc_rows[("cheetah-run", "pebble")]["mean"]) == pytest.approx(aucs.mean(), rel=1e-12)
    assert "AUCs are not comparable" in auc_rows[("cheetah-run", "r2n_pebble")]["notes"]  # 5 points vs 3
    runs = {os.path.dirname(r["path"]): r for r in read_csv(tmp_path / "runs.csv")}
    assert runs[os.path.abspath(bad["crashed"])]["status"] == "skipped"  # a crashed run is never used
    assert not os.path.exists(tmp_path / "curves")
    # a primary metric asked over more evaluations than the aligned group has says so
    assert "--primary-last" not in row["notes"]
    assert analyze.main(analyze.Args(log_dirs=synthetic["dirs"], output_dir=str(tmp_path / "last4"), plots=False,
                                     include_unfinished=True, primary_last=4)) == 0
    row = {(r["task"], r["method"]): r for r in read_csv(tmp_path / "last4" / "primary.csv")}[("cheetah-run", "pebble")]
    assert "primary metric over its 3 evaluations, fewer than --primary-last 4" in row["notes"], row["notes"]


@needs_analysis
def test_a_run_stopped_by_a_non_finite_value_counts_with_what_it_reached(tmp_path):
    """A run whose `done` file says a non-finite value stopped it is used without shortening its group: its primary
    metric is the mean of its last finite evaluations, its final return its last finite one, its AUC their sum. The same
    run without that line is an unfinished run, skipped."""
    rng = np.random.default_rng(1)
    full = {seed: values(rng, len(STEPS), 0) for seed in (1, 2, 3)}
    for seed, returns in full.items():
        write_run(str(tmp_path / "runs"), "cheetah-run", 0.9, 1000, "pebble", seed, returns)
    stopped = write_run(str(tmp_path / "runs"), "cheetah-run", 0.9, 1000, "pebble", 4, [10.0, 20.0, 30.0, 40.0])
    for with_line in (False, True):
        with open(os.path.join(stopped, "done"), "w") as f:
            f.write("exit code 1\n" + "stopped non-finite losses/qf1_loss (nan) at step 4210\n" * with_line)
        out = tmp_path / f"out{with_line}"
        assert analyze.main(analyze.Args(log_dirs=(str(tmp_path / "runs"),), output_dir=str(out))) == 0
        rows = {m: read_csv(out / f"{m}.csv")[0] for m in ("primary", "final_return", "auc")}
        seeds = (1, 2, 3, 4) if with_line else (1, 2, 3)
        assert rows["primary"]["seed_list"] == " ".join(map(str, seeds))
        assert rows["primary"]["eval_points"] == str(len(STEPS))
        primary = [full[s][-3:].mean() for s in (1, 2, 3)] + [30.0] * with_line
        final = [full[s][-1] for s in (1, 2, 3)] + [40.0] * with_line
        auc = [full[s].sum() for s in (1, 2, 3)] + [100.0] * with_line
        for metric, expected in (("primary", primary), ("final_return", final), ("auc", auc)):
            assert float(rows[metric]["mean"]) == pytest.approx(np.mean(expected), rel=1e-12), metric
        assert ("stopped non-finite losses/qf1_loss" in rows["primary"]["notes"]) == with_line
    assert (tmp_path / "outTrue" / "curves").exists()
    nothing = write_run(str(tmp_path / "runs"), "cheetah-run", 0.9, 1000, "pebble", 5, [float("nan")])
    shutil.copy(os.path.join(stopped, "done"), nothing)  # stopped at its first evaluation: nothing reached
    runs = analyze.load_runs((str(tmp_path / "runs"),))
    [run] = [r for r in runs if r.seed == 5]
    assert run.status == "skipped" and run.reason.startswith("crashed: stopped non-finite"), run.reason


@needs_analysis
def test_runs_sharing_a_folder_are_read_apart(tmp_path):
    """Two runs of a sweep started in the same second write into one folder: one run per event file."""
    write_run(str(tmp_path / "runs"), "cheetah-run", 0.5, 1000, "pebble", 1, [1.0] * 5, stamp=7)
    write_run(str(tmp_path / "runs"), "cheetah-run", 0.9, 1000, "pebble", 1, [3.0] * 5, stamp=7)
    assert len(os.listdir(tmp_path / "runs")) == 1
    assert analyze.main(analyze.Args(log_dirs=(str(tmp_path / "runs"),), output_dir=str(tmp_path / "out"),
                                     plots=False)) == 0
    rows = {r["noise"]: r for r in read_csv(tmp_path / "out" / "final_return.csv")}
    assert (rows["0.5"]["mean"], rows["0.9"]["mean"], rows["0.5"]["seeds"]) == ("1.0", "3.0", "1")
    assert all("shares its folder with 1 other event file" in r["notes"] for r in rows.values())


@needs_analysis
def test_pngs_written(synthetic):
    out = synthetic["out"]
    pngs = [out / "curves" / "cheetah-run.png", out / "curves" / "walker-walk.png",
            out / "connectivity" / "cheetah-run__noise0.9__budget1000__r2n_pebble.png",
            out / "connectivity" / "walker-walk__noise0.9__budget4000__r2n_pebble.png"]
    for png in pngs:
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 5000, png
    assert sorted(os.listdir(out / "connectivity")) == sorted(p.name for p in pngs[2:])  # pebble has no sparse tags


@needs_analysis
def test_baseline_overrides_and_alternative(synthetic, tmp_path):
    """--alternative less tests baseline > method; --baseline-for pairs a method with its own baseline."""
    data = synthetic["data"]
    analyze.main(analyze.Args(log_dirs=synthetic["dirs"], output_dir=str(tmp_path), baseline="r2n_pebble",
                              alternative="less", plots=False))
    row = {(r["task"], r["method"]): r for r in read_csv(tmp_path / "final_return.csv")}[("cheetah-run", "pebble")]
    finals, _ = expected_stats(data, "cheetah-run", "pebble", [1, 2, 3])
    ref, _ = expected_stats(data, "cheetah-run", "r2n_pebble", [1, 2, 3, 4])
    assert float(row["p_value"]) == pytest.approx(welch(ref, finals), rel=1e-9)
    analyze.main(analyze.Args(log_dirs=synthetic["dirs"], output_dir=str(tmp_path), baseline="nothing",
                              baseline_for=("r2n_pebble=pebble",), plots=False))
    rows = read_csv(tmp_path / "final_return.csv")
    assert all((r["baseline"] == "pebble") == (r["method"] == "r2n_pebble") for r in rows)


# ---------------------------------------------------------------- benchmark.py: grids


def grid(**kwargs):
    return benchmark.expand(benchmark.Args(**kwargs))


def test_presets_expand_to_the_paper_grids():
    main = grid(preset="main")
    assert len(main) == 5 * 6 * 14 == len({r.run_id for r in main})
    assert {(r.env_id, r.noise, r.budget) for r in main} == {
        ("cartpole-swingup", 0.9, 400), ("walker-walk", 0.9, 4000), ("cheetah-run", 0.9, 1000),
        ("quadruped-walk", 0.7, 4000), ("humanoid-stand", 0.7, 10000)}
    assert {r.method for r in main} == {"pebble", "r2n_pebble", "surf", "r2n_surf", "rune", "r2n_rune"}
    assert {r.seed for r in main} == set(range(1, 15))
    assert [r.seed for r in main[:30]] == [1] * 30  # seed-major
    first = main[0]
    assert first.run_id == "pebble__cartpole-swingup__noise0.9__budget400__seed1"
    assert list(first.command[1:]) == [os.path.join(ROOT, "pebble.py"), "--exp-name", "pebble", "--env-id",
                                       "cartpole-swingup", "--noise", "0.9", "--max-feedback", "400", "--seed", "1",
                                       "--threads", "1", "--run-name", first.run_id, *HARNESS]
    last = main[-1]
    assert last.run_id == "r2n_rune__humanoid-stand__noise0.7__budget10000__seed14"
    assert shlex.join(last.command[1:]).endswith(
        "r2n_rune.py --exp-name r2n_rune --env-id humanoid-stand --noise 0.7 --max-feedback 10000 --seed 14 --threads 1 "
        "--run-name r2n_rune__humanoid-stand__noise0.7__budget10000__seed14 --resumable --diagnostics --query-log")

    sparse = grid(preset="sparse-baselines")
    assert len(sparse) == 5 * 5 * 5
    assert {r.method for r in sparse} == {"r2n_pebble", "set_pebble", "static_pebble", "l1_pebble", "dropconnect_pebble"}
    assert {r.seed for r in sparse} == set(range(1, 6))

    noise = grid(preset="noise-sweep")
    assert len(noise) == 6 * 2 * 5
    assert {(r.env_id, r.noise, r.budget) for r in noise} == {("cheetah-run", n, 1000) for n in (0, 0.2, 0.5, 0.7, 0.9, 0.95)}
    assert "noise0__budget1000" in noise[0].run_id and noise[0].command[7] == "0"

    feedback = grid(preset="feedback-sweep")
    assert len(feedback) == 7 * 2 * 5
    assert {r.budget for r in feedback} == {100, 200, 400, 1000, 2000, 4000, 10000}
    assert {(r.env_id, r.noise) for r in feedback} == {("cheetah-run", 0.9)}

    dst = grid(preset="dst-ablation", extra="--total-timesteps 100000 --cuda")
    assert len(dst) == 3 * 5
    by_id = {r.run_id: r for r in dst}
    reward_only = by_id["r2n_pebble_reward_only__cheetah-run__noise0.9__budget1000__seed3"]
    assert reward_only.command[1] == os.path.join(ROOT, "r2n_pebble.py")
    assert list(reward_only.command[2:4]) == ["--exp-name", "r2n_pebble_reward_only"]
    assert list(reward_only.command[-4:]) == ["--no-sparse-agent", "--total-timesteps", "100000", "--cuda"]
    assert "--no-sparse-reward" in by_id["r2n_pebble_agent_only__cheetah-run__noise0.9__budget1000__seed5"].command

    study = grid(preset="cpu-study")
    assert len(study) == len({r.run_id for r in study}) == 8 * 2 + 5 * 2 + 2 * 2 * 3 + 4 * 3
    count = lambda method, noise: sorted(r.seed for r in study if r.method == method and r.noise == noise)  # noqa: E731
    assert count("pebble", 0.9) == count("r2n_pebble", 0.9) == list(range(1, 9))
    assert count("pebble", 0.95) == count("r2n_pebble", 0.95) == list(range(1, 6))
    for method in ("sac", "anf_sac"):
        assert count(method, 0.9) == count(method, 0.95) == [1, 2, 3]
    for method in ("pebble_stored_noise", "r2n_pebble_stored_noise", "pebble_no_early_stop", "r2n_pebble_no_early_stop"):
        assert count(method, 0.9) == [1, 2, 3] and count(method, 0.95) == []
    assert [r.seed for r in study] == sorted(r.seed for r in study)  # seed-major over the preset's parts
    by_id = {r.run_id: r for r in study}
    scale = ["--total-timesteps", "80000", "--hidden-dim", "256", "--batch-size", "128"]
    pebble_run = by_id["r2n_pebble_no_early_stop__cartpole-swingup__noise0.9__budget400__seed2"].command
    assert list(pebble_run[-13:]) == ["--reward-stop-accuracy", "1.1", "--noise-resample", *scale, "--feedback-freq",
                                      "2000", "--queries-per-round", "25"]
    assert list(by_id["sac__cartpole-swingup__noise0.95__budgetnone__seed3"].command[-6:]) == scale  # no feedback flags
    stored_arm = by_id["pebble_stored_noise__cartpole-swingup__noise0.9__budget400__seed1"].command
    assert "--no-noise-resample" in stored_arm and "--noise-resample" not in stored_arm

    # the stored-noise study (results/stored-noise/PROTOCOL.md): the cheetah study's runs, each storing its noise
    cheetah, stored = grid(preset="cheetah-study"), grid(preset="stored-noise")
    assert len(stored) == len({r.run_id for r in stored}) == 8 * 2 + 3 * 2
    for original in cheetah:
        method = f"{original.method}_stored_noise"
        run_id = original.run_id.replace(f"{original.method}__", f"{method}__", 1)
        (run,) = [r for r in stored if r.run_id == run_id]
        assert run.command[1] == original.command[1]  # the same script
        expected = [a for a in original.command[2:] if a != "--noise-resample"]
        expected[1] = method  # --exp-name
        expected[expected.index("--run-name") + 1] = run_id
        # after the run name and the harness's flags (PbRL runs: and --query-log)
        position = expected.index("--run-name") + 2 + len(benchmark.HARNESS) + (run.budget is not None)
        assert list(run.command[2:]) == expected[:position] + ["--no-noise-resample"] + expected[position:]
    probes = grid(preset="redrawn-probes")
    assert sorted(r.run_id for r in probes) == sorted(
        f"{m}__cheetah-run__noise0.9__budget1000__seed{s}" for s in (1, 2, 3)
        for m in ("r2n_pebble_reward_only", "r2n_pebble_agent_as_reward", "pebble_repeat"))
    by_id = {r.run_id: r for r in probes}
    assert "--no-sparse-agent" in by_id["r2n_pebble_reward_only__cheetah-run__noise0.9__budget1000__seed1"].command
    agent = list(by_id["r2n_pebble_agent_as_reward__cheetah-run__noise0.9__budget1000__seed2"].command)
    assert agent[agent.index("--agent-drop-fraction") + 1] == "0.2"
    assert agent[agent.index("--agent-topology-period") + 1] == "100"
    repeat = by_id["pebble_repeat__cheetah-run__noise0.9__budget1000__seed3"].command
    (original,) = [r for r in cheetah if r.run_id == "pebble__cheetah-run__noise0.9__budget1000__seed3"]
    assert [a for a in repeat if "pebble" not in a] == [a for a in original.command if "pebble" not in a]
    assert "--noise-resample" in repeat and "--noise-resample" in agent  # the cheetah study's environment


def test_free_grids_and_overrides():
    assert len(grid(preset="main", env_ids=("cheetah-run",), seeds=(1, 2))) == 6 * 2
    runs = grid(methods=("pebble", "r2n_pebble"), env_ids=("walker-walk",), noises=(0.5, 0.9), budgets=(100,),
                seeds=(4,))
    assert [r.run_id for r in runs] == [f"{m}__walker-walk__noise{n}__budget100__seed4"
                                        for n in (0.5, 0.9) for m in ("pebble", "r2n_pebble")]
    assert grid(methods=("pebble",), env_ids=("cheetah-run",))[0].run_id == "pebble__cheetah-run__noise0.9__budget1000__seed1"
    with pytest.raises(SystemExit, match="no script"):
        grid(methods=("no_such_method",), env_ids=("cheetah-run",))
    with pytest.raises(SystemExit, match="not a paper task"):
        grid(methods=("pebble",), env_ids=("finger-spin",))
    with pytest.raises(SystemExit, match=r"--env-ids 'drawer-opn-v3' is neither"):  # before any run starts
        grid(methods=("pebble",), env_ids=("drawer-opn-v3",), noises=(0.9,), budgets=(1000,))
    if importlib.util.find_spec("metaworld") is not None:  # the launcher takes Meta-World's tasks
        (run,) = grid(methods=("pebble",), env_ids=("drawer-open-v3",), noises=(0.9,), budgets=(1000,))
        assert run.run_id == "pebble__drawer-open-v3__noise0.9__budget1000__seed1"


def test_sac_oracles_get_no_budget(tmp_path):
    for name in ("sac", "pebble"):
        (tmp_path / f"{name}.py").write_text("")
    runs = grid(methods=("sac", "pebble"), env_ids=("cheetah-run",), budgets=(100, 200), script_dir=str(tmp_path))
    assert [r.run_id for r in runs] == ["sac__cheetah-run__noise0.9__budgetnone__seed1",
                                        "pebble__cheetah-run__noise0.9__budget100__seed1",
                                        "pebble__cheetah-run__noise0.9__budget200__seed1"]
    assert "--max-feedback" not in runs[0].command
    oracles = grid(preset="main", methods=("sac", "anf_sac"))  # the oracle rows of the main table's settings
    assert len(oracles) == 5 * 2 * 14 and all("--max-feedback" not in r.command for r in oracles)
    assert oracles[0].run_id == "sac__cartpole-swingup__noise0.9__budgetnone__seed1"


# ---------------------------------------------------------------- benchmark.py: back-ends

FAKE = """import json, os, sys, time
start = time.time()
time.sleep(float(os.environ.get("FAKE_SLEEP", "1")))
print(json.dumps(dict(cuda=os.environ.get("CUDA_VISIBLE_DEVICES"), omp=os.environ.get("OMP_NUM_THREADS"),
                      mps=os.environ.get("CUDA_MPS_PIPE_DIRECTORY"), argv=sys.argv[1:], start=start, end=time.time())))
sys.exit(3 if sys.argv[sys.argv.index("--seed") + 1] == "99" else 0)
"""


@pytest.fixture
def fake_scripts(tmp_path, monkeypatch):
    """A working folder with fake `pebble.py` / `r2n_pebble.py` that print what they see (exit 3 for seed 99)."""
    scripts = tmp_path / "scripts"
    scripts.mkdir()
    for name in ("pebble", "r2n_pebble"):
        (scripts / f"{name}.py").write_text(FAKE)
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    return str(scripts)


def child_view(run_id):
    """What the fake script printed (the JSON line of its log)."""
    import json

    with open(os.path.join("logs", f"{run_id}.log")) as f:
        return json.loads(next(line for line in f if line.startswith("{")))


def test_local_backend_parallel_gpu_slots_and_resume(fake_scripts, capsys):
    args = benchmark.Args(methods=("pebble", "r2n_pebble"), env_ids=("cheetah-run",), seeds=(1, 2), gpus="0,1",
                          runs_per_gpu=2, script_dir=fake_scripts)
    runs = benchmark.expand(args)
    assert benchmark.main(args) == 0
    views = [child_view(r.run_id) for r in runs]
    assert [v["cuda"] for v in views] == ["0", "1", "0", "1"]  # round-robin over 2 GPUs x 2 slots
    assert all(v["omp"] == "1" and v["argv"][-7:] == ["--threads", "1", "--run-name", r.run_id, *HARNESS]
               for v, r in zip(views, runs))
    assert max(v["start"] for v in views) < min(v["end"] for v in views)  # all four ran at the same time
    assert all(os.path.exists(f"logs/{r.run_id}.done") for r in runs)
    log = open(f"logs/{runs[0].run_id}.log").read()
    assert "# exit code 0" in log and "--exp-name pebble" in log

    # a second call skips the finished runs; seed 99 fails with its exit code and log, and the call exits non-zero
    capsys.readouterr()
    mtimes = [os.path.getmtime(f"logs/{r.run_id}.log") for r in runs]
    args.seeds = (1, 2, 99)
    assert benchmark.main(args) == 1
    output = capsys.readouterr().out
    assert "skipping 4 finished runs" in output
    assert [os.path.getmtime(f"logs/{r.run_id}.log") for r in runs] == mtimes
    for method in ("pebble", "r2n_pebble"):
        run_id = f"{method}__cheetah-run__noise0.9__budget1000__seed99"
        assert f"FAILED {run_id}: exit code 3, log {os.path.abspath(f'logs/{run_id}.log')}" in output
        assert os.path.exists(f"logs/{run_id}.failed") and not os.path.exists(f"logs/{run_id}.done")
    assert "0 runs finished, 4 skipped as already finished, 2 failed" in output

    # --dry-run lists what is done, what failed and what would run
    args.dry_run = True
    assert benchmark.main(args) == 0
    output = capsys.readouterr().out
    assert output.count("# done: ") == 4 and output.count("# previously failed (exit code 3") == 2
    assert "# 6 runs, 4 already finished, 2 to run" in output


def test_a_study_run_without_an_event_file_is_not_kept(tmp_path):
    """With a results folder, an exit code 0 is not enough: a run that left no event file is marked failed, and its
    results folder gets no `done` file (which would count it as finished for good)."""
    spec = dict(run_id="r", command=["python", "pebble.py"], threads=1, commit="abc", cwd=str(tmp_path / "scratch"),
                log=str(tmp_path / "r.log"), results=str(tmp_path / "results" / "r"))
    os.makedirs(os.path.join(spec["cwd"], "runs", "r"))
    open(spec["log"], "w").close()
    benchmark.finish_run(spec, 0, 1.0)
    assert open(tmp_path / "r.failed").read().startswith("exit code 0, no event file\n")
    assert not os.path.exists(tmp_path / "r.done") and not os.path.exists(tmp_path / "results" / "r" / "done")
    SummaryWriter(os.path.join(spec["cwd"], "runs", "r")).close()  # now it has one
    benchmark.finish_run(spec, 0, 1.0)
    assert os.path.exists(tmp_path / "r.done") and os.path.exists(tmp_path / "results" / "r" / "done")


def test_a_run_stopped_by_a_non_finite_value_is_kept_with_what_it_reached(tmp_path):
    """A run stopped by a non-finite value (exit code 1 and the script's one line) would stop there again if resumed:
    it is done, its `done` file names the stop, and its event file is kept. The same line in an earlier start, or an
    exit code 1 without it, is a failure."""
    spec = dict(run_id="r", command=["python", "pebble.py"], threads=1, commit="abc", cwd=str(tmp_path / "scratch"),
                log=str(tmp_path / "r.log"), results=str(tmp_path / "results" / "r"))
    os.makedirs(os.path.join(spec["cwd"], "runs", "r"))
    SummaryWriter(os.path.join(spec["cwd"], "runs", "r")).close()
    line = ("pebble: error: non-finite losses/qf1_loss (nan) at step 1210; "
            "checkpoint for debugging: runs/r/pebble.cleanrl_model")
    for log, code in (("# started 2026-11-28 01:00:00\nstep=1000\n", 1),  # stopped otherwise
                      (f"# started 2026-11-28 01:00:00\n{line}\n# exit code 1 after 9 s\n"
                       f"{benchmark.RESUMED}# started 2026-11-28 02:00:00\nstep=1000\n", 1),  # the stop was earlier
                      (f"# started 2026-11-28 01:00:00\n{line}\n", 2)):  # not the stop's exit code
        open(spec["log"], "w").write(log)
        benchmark.finish_run(spec, code, 1.0)
        assert os.path.exists(tmp_path / "r.failed") and not os.path.exists(tmp_path / "results" / "r" / "done")
        assert benchmark.outcome(code, spec["log"]) == "failed"  # the sweep's summary lists it as FAILED
        os.remove(tmp_path / "r.failed")
    open(spec["log"], "w").write(f"# started 2026-11-28 01:00:00\nstep=1000\n{line}\n")
    benchmark.finish_run(spec, 1, 1.0)
    done = open(tmp_path / "results" / "r" / "done").read().splitlines()
    assert done[:2] == ["exit code 1", "stopped non-finite losses/qf1_loss (nan) at step 1210"], done
    assert glob.glob(str(tmp_path / "results" / "r" / "events.out.tfevents.*")) and os.path.exists(tmp_path / "r.done")
    assert benchmark.outcome(1, spec["log"]) == "finished"  # not FAILED in the sweep's summary, for all its exit code


def test_a_run_stopped_with_its_state_saved_is_stopped_not_failed(tmp_path):
    """Either of the scripts' stop lines (pebble.py's `Stopped`: after a step, or while waiting for a person's labels)
    in the last start, with exit code 1, gives the `.stopped` marker, which names the stop; the line in an earlier
    start only, or another exit code, gives `.failed`. SIGTERM's default action (a run stopped as it started)
    gives `.stopped` too. Each marker replaces the earlier start's."""
    spec = dict(run_id="r", command=["python", "pebble.py"], threads=1, commit="abc", cwd=str(tmp_path / "scratch"),
                log=str(tmp_path / "r.log"), results=None)
    markers = lambda: sorted(p.name for p in tmp_path.glob("r.*") if p.name != "r.log")  # noqa: E731
    after_step = ("pebble: stopped by SIGTERM after step 5210; state saved in runs/r/state.pt: run the same command "
                  "with --run-name r to resume")
    waiting = ("pebble: stopped by SIGUSR2 while waiting for runs/r/labels/3.json; the state before this round is "
               "saved: run the same command with --run-name r to resume")
    start = "# started 2026-11-28 01:00:00\nstep=1000\n"
    for line, stop in ((after_step, "stopped by SIGTERM after step 5210"),
                       (waiting, "stopped by SIGUSR2 while waiting for runs/r/labels/3.json")):
        open(spec["log"], "w").write(f"{start}{line}\n")
        open(tmp_path / "r.failed", "w").close()  # an earlier start's
        assert benchmark.finish_run(spec, 1, 1.0) == "stopped" and markers() == ["r.stopped"]
        assert open(tmp_path / "r.stopped").read().splitlines()[1] == \
            f"{stop}, its state saved: the same command resumes it"
        assert benchmark.resumable(1, spec["log"]) and not benchmark.resumable("job 7 failed: OOM", spec["log"])
    for log, code in ((f"{start}{after_step}\n# exit code 1 after 9 s\n{benchmark.RESUMED}{start}", 1),  # earlier
                      (f"{start}{after_step}\n", 2)):  # not the stop's exit code
        open(spec["log"], "w").write(log)
        assert benchmark.finish_run(spec, code, 1.0) == "failed" and markers() == ["r.failed"]
        assert not benchmark.resumable(code, spec["log"])
    open(spec["log"], "w").write(start)
    assert benchmark.finish_run(spec, 0, 1.0) == "done" and markers() == ["r.done"]
    open(spec["log"], "w").write(f"{start}{after_step}\n")  # a `--force` rerun, stopped
    assert benchmark.finish_run(spec, 1, 1.0) == "stopped" and markers() == ["r.stopped"]
    open(spec["log"], "w").write(start)  # SIGTERM while the script imports, before its handler is set
    assert benchmark.finish_run(spec, -signal.SIGTERM, 1.0) == "stopped" and markers() == ["r.stopped"]
    assert open(tmp_path / "r.stopped").read().splitlines()[1] == \
        "stopped by SIGTERM before its script took the signal over: the same command runs it"
    assert benchmark.resumable(-signal.SIGTERM, spec["log"])
    assert benchmark.outcome(-signal.SIGTERM, spec["log"]) == "stopped"
    assert benchmark.finish_run(spec, -signal.SIGKILL, 1.0) == "failed" and markers() == ["r.failed"]
    assert not benchmark.resumable(-signal.SIGTERM, spec["log"])  # its marker is `.failed` now
    assert benchmark.outcome(-signal.SIGKILL, spec["log"]) == "failed"


def start_sweep(tmp_path, signum, handler, patch="", takes_sigterm=True):
    """benchmark.py over one fake run that saves its state on SIGTERM (unless not `takes_sigterm`: then SIGTERM's
    default action ends it, as while a script imports), in a process group of its own as a shell starts a job, with
    `signum` set to `handler` and the Python code `patch` run first; returns (the launcher, its work folder) once the
    run is going."""
    scripts, work = tmp_path / "scripts", tmp_path / "work"
    scripts.mkdir()
    work.mkdir()
    (scripts / "pebble.py").write_text(  # its stop: the scripts' line and exit code
        "import signal, sys, time\n"
        "def stop(signum, frame):\n"
        "    sys.exit(f'pebble: stopped by {signal.Signals(signum).name} after step 0; state saved in state.pt: '\n"
        "             'run the same command with --run-name x to resume')\n"
        + ("signal.signal(signal.SIGTERM, stop)\n" if takes_sigterm else "")
        + "open('ready', 'w').close()\n"
        "time.sleep(60)\n")
    launch = f"{patch}import runpy\nrunpy.run_path({os.path.join(ROOT, 'benchmark.py')!r}, run_name='__main__')\n"
    launcher = subprocess.Popen(
        [sys.executable, "-c", launch, "--methods", "pebble", "--env-ids", "cheetah-run", "--seeds",
         "1", "--script-dir", str(scripts)], cwd=work, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        start_new_session=True, preexec_fn=lambda: signal.signal(signum, handler))
    deadline = time.time() + 60
    while not (work / "ready").exists() and time.time() < deadline:
        time.sleep(0.05)
    return launcher, work


def end_of_sweep(launcher, work, signum=None):
    """(the launcher's output, its run's log) once the launcher has ended, after `signum` to its process group if one
    is given; a launcher still going after 60 s is killed, and the wait fails the test."""
    try:
        if signum is not None:
            os.killpg(launcher.pid, signum)
        output = launcher.communicate(timeout=60)[0]
    finally:
        if launcher.poll() is None:
            launcher.kill()
    return output, (work / "logs" / "pebble__cheetah-run__noise0.9__budget1000__seed1.log").read_text()


def test_ctrl_c_in_a_terminal_stops_the_runs_through_sigterm(tmp_path, monkeypatch, capsys):
    """A terminal sends Ctrl-C's SIGINT to its whole foreground process group. The runs are in sessions of their own:
    only the launcher gets it, and it stops them with SIGTERM, on which the scripts save their state. Such a run is
    stopped, not failed: its marker, the summary and `--dry-run` say that the same command resumes it."""
    launcher, work = start_sweep(tmp_path, signal.SIGINT, signal.SIG_DFL)  # as in a terminal, however pytest started
    output, log = end_of_sweep(launcher, work, signal.SIGINT)  # what the terminal does
    assert "interrupted: running runs terminated" in output, output
    assert "stopped by SIGTERM after step 0; state saved" in log and "KeyboardInterrupt" not in log, log
    assert "1 stopped or not started (the same command resumes them), 0 failed" in output and "FAILED" not in output
    assert launcher.returncode == 1
    run_id = "pebble__cheetah-run__noise0.9__budget1000__seed1"
    marker = (work / "logs" / f"{run_id}.stopped").read_text().splitlines()
    assert marker[:2] == ["exit code 1", "stopped by SIGTERM after step 0, its state saved: the same command resumes it"]
    monkeypatch.chdir(work)
    benchmark.main(benchmark.Args(methods=("pebble",), env_ids=("cheetah-run",), seeds=(1,),
                                  script_dir=str(tmp_path / "scripts"), dry_run=True))
    assert (f"# stopped by SIGTERM after step 0, its state saved: the same command resumes it (log logs/{run_id}.log)"
            in capsys.readouterr().out)


def test_a_run_stopped_before_its_script_takes_sigterm_is_stopped_not_failed(tmp_path):
    """Ctrl-C while a run's script still imports: the launcher's SIGTERM ends it by the default action (exit -15).
    Nothing was lost, so the sweep counts it as stopped, not failed, and its marker says the same command runs it."""
    launcher, work = start_sweep(tmp_path, signal.SIGINT, signal.SIG_DFL, takes_sigterm=False)
    output, log = end_of_sweep(launcher, work, signal.SIGINT)
    assert "# exit code -15 after" in log, log
    assert "1 stopped or not started (the same command resumes them), 0 failed" in output and "FAILED" not in output
    marker = (work / "logs" / "pebble__cheetah-run__noise0.9__budget1000__seed1.stopped").read_text().splitlines()
    assert marker[:2] == ["exit code -15",
                          "stopped by SIGTERM before its script took the signal over: the same command runs it"]


def test_a_stop_signal_inside_a_poll_leaves_the_cleanup_able_to_wait(tmp_path):
    """A signal's handler runs between any two bytecodes. Had it raised right after `Popen.poll` took its wait lock,
    the lock would stay held and the cleanup's `wait` block forever: the handler only notes the signal."""
    patch = ("import os, signal, subprocess\n"
             "poll = subprocess.Popen.poll\n"
             "def poll_with_a_signal_inside(self):\n"
             "    if os.path.exists('ready') and self._waitpid_lock.acquire(False):\n"
             "        os.kill(os.getpid(), signal.SIGTERM)  # handled as this call returns, before the release\n"
             "        self._waitpid_lock.release()\n"
             "    return poll(self)\n"
             "subprocess.Popen.poll = poll_with_a_signal_inside\n")
    launcher, work = start_sweep(tmp_path, signal.SIGINT, signal.SIG_DFL, patch)
    output, log = end_of_sweep(launcher, work)
    assert "interrupted: running runs terminated" in output, output
    assert "stopped by SIGTERM after step 0; state saved" in log, log


def test_one_local_launcher_per_log_folder(fake_scripts, monkeypatch):
    """A second launcher in the same log folder would start the same runs into the same folders: it stops with one
    line naming the first one's pid, and can go once the first has ended."""
    monkeypatch.setenv("FAKE_SLEEP", "0")
    os.makedirs("logs")
    first = benchmark.lock_log_dir("logs")  # as a first launcher holds it
    args = benchmark.Args(methods=("pebble",), env_ids=("cheetah-run",), seeds=(1,), script_dir=fake_scripts)
    with pytest.raises(SystemExit, match=f"another benchmark.py is running runs in logs/ \\(pid {os.getpid()}\\)"):
        benchmark.main(args)
    assert not os.path.exists("logs/pebble__cheetah-run__noise0.9__budget1000__seed1.log")  # nothing started
    first.close()  # the first launcher ends
    assert benchmark.main(args) == 0


def test_a_failing_launcher_stops_its_runs_first(tmp_path, monkeypatch):
    """If the launcher itself fails (here: writing a run's marker), it stops the other runs with SIGTERM (they save
    their state) before the error ends it: no run goes on untracked, to be started a second time by the next call."""
    scripts, work = tmp_path / "scripts", tmp_path / "work"
    scripts.mkdir()
    work.mkdir()
    monkeypatch.chdir(work)
    (scripts / "pebble.py").write_text(
        "import os, signal, sys, time\n"
        "def stop(signum, frame):\n"
        "    print('state saved on', signal.Signals(signum).name, flush=True)\n"
        "    sys.exit(1)\n"
        "signal.signal(signal.SIGTERM, stop)\n"
        "if sys.argv[sys.argv.index('--seed') + 1] == '2':\n"
        "    open('ready', 'w').close()\n"
        "    time.sleep(60)\n"
        "while not os.path.exists('ready'):  # seed 1 ends once seed 2 can save its state\n"
        "    time.sleep(0.01)\n")
    finish_run = benchmark.finish_run

    def disk_full_once(spec, returncode, seconds):
        if spec["run_id"].endswith("seed1"):
            raise OSError(28, "No space left on device")
        finish_run(spec, returncode, seconds)

    monkeypatch.setattr(benchmark, "finish_run", disk_full_once)
    args = benchmark.Args(methods=("pebble",), env_ids=("cheetah-run",), seeds=(1, 2), workers=2,
                          script_dir=str(scripts))
    with pytest.raises(OSError, match="No space left on device"):
        benchmark.main(args)
    log = open("logs/pebble__cheetah-run__noise0.9__budget1000__seed2.log").read()
    assert "state saved on SIGTERM" in log and "# exit code 1 after" in log, log
    assert os.path.exists("logs/pebble__cheetah-run__noise0.9__budget1000__seed2.failed")


@pytest.mark.skipif(sys.platform != "linux", reason="prctl(PR_SET_PDEATHSIG) is Linux's")
def test_nohup_is_kept_and_runs_stop_with_a_killed_launcher(tmp_path):
    """A launcher started under `nohup` (SIGHUP ignored) keeps ignoring it; a launcher killed with SIGKILL, which can
    stop nothing, still takes its runs along: each gets SIGTERM and saves its state, none goes on untracked."""
    launcher, work = start_sweep(tmp_path, signal.SIGHUP, signal.SIG_IGN)  # as `nohup` does
    log = work / "logs" / "pebble__cheetah-run__noise0.9__budget1000__seed1.log"
    try:
        launcher.send_signal(signal.SIGHUP)  # a closed terminal
        time.sleep(2)
        assert launcher.poll() is None and "state saved" not in log.read_text()
        launcher.kill()
        deadline = time.time() + 60
        while "stopped by SIGTERM after step 0; state saved" not in log.read_text() and time.time() < deadline:
            time.sleep(0.1)
        assert "stopped by SIGTERM after step 0; state saved" in log.read_text()
    finally:
        if launcher.poll() is None:
            launcher.kill()


def test_cli_exit_code_and_no_gpus(fake_scripts):
    """The command line: without --gpus, CUDA_VISIBLE_DEVICES is left alone; a failed run makes the exit code 1."""
    env = dict(os.environ, FAKE_SLEEP="0", CUDA_VISIBLE_DEVICES="7")
    result = subprocess.run(
        [sys.executable, os.path.join(ROOT, "benchmark.py"), "--methods", "pebble", "--env-ids", "cheetah-run",
         "--seeds", "1", "99", "--workers", "2", "--script-dir", fake_scripts, "--threads", "2"],
        capture_output=True, text=True, env=env, timeout=120,
    )
    assert result.returncode == 1, result.stdout + result.stderr
    assert "FAILED pebble__cheetah-run__noise0.9__budget1000__seed99: exit code 3" in result.stdout
    view = child_view("pebble__cheetah-run__noise0.9__budget1000__seed1")
    assert (view["cuda"], view["omp"]) == ("7", "2")


FAKE_MPS = """#!/bin/sh
# a fake nvidia-cuda-mps-control: one line per call (time, argument, standard input, pipe folder, visible devices)
if [ "$1" = "-d" ]; then input=""; else input=$(cat); fi
echo "$(python3 -c 'import time; print(time.time())') ${1:-none} ${input:-none} $CUDA_MPS_PIPE_DIRECTORY \
${CUDA_VISIBLE_DEVICES:-none}" >> "$MPS_CALLS"
exit "${FAKE_MPS_EXIT:-0}"
"""


@pytest.fixture
def fake_mps(tmp_path, monkeypatch):
    """A fake `nvidia-cuda-mps-control` first on PATH; returns the file its calls are written to."""
    bin_dir = tmp_path / "mps-bin"
    bin_dir.mkdir()
    (bin_dir / "nvidia-cuda-mps-control").write_text(FAKE_MPS)
    (bin_dir / "nvidia-cuda-mps-control").chmod(0o755)
    monkeypatch.setenv("PATH", f"{bin_dir}{os.pathsep}{os.environ['PATH']}")
    monkeypatch.setenv("MPS_CALLS", str(tmp_path / "mps-calls"))
    monkeypatch.delenv("CUDA_MPS_PIPE_DIRECTORY", raising=False)
    return tmp_path / "mps-calls"


def mps_calls(path) -> list:
    """(time, argument, input, pipe folder, visible devices) of each call of the fake daemon control."""
    return [(float(t), arg, given, folder, devices) for t, arg, given, folder, devices in
            (line.split() for line in open(path).read().splitlines())]


def test_mps_daemon_serves_the_runs_and_quits_after_the_last(fake_scripts, fake_mps, capsys, monkeypatch):
    """`--mps`: the daemon starts before the first run and sees the `--gpus`; every run finds it through
    CUDA_MPS_PIPE_DIRECTORY and gets its GPU's position among them (an MPS server numbers its devices from 0); the
    daemon is quit after the last run has ended; its private folder goes, and the launcher's environment is as
    before."""
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "4,5")
    args = benchmark.Args(methods=("pebble", "r2n_pebble"), env_ids=("cheetah-run",), seeds=(1,), gpus="4,5",
                          mps=True, script_dir=fake_scripts)
    assert benchmark.main(args) == 0
    (start, arg, _, folder, devices), (end, quit_arg, given, quit_folder, _) = mps_calls(fake_mps)
    assert (arg, quit_arg, given, devices) == ("-d", "none", "quit", "4,5") and quit_folder == folder
    views = [child_view(r.run_id) for r in benchmark.expand(args)]
    assert all(v["mps"] == folder for v in views) and [v["cuda"] for v in views] == ["0", "1"]
    assert start < min(v["start"] for v in views) and max(v["end"] for v in views) < end
    assert not os.path.exists(folder) and "CUDA_MPS_PIPE_DIRECTORY" not in os.environ
    assert os.environ["CUDA_VISIBLE_DEVICES"] == "4,5"
    output = capsys.readouterr().out
    assert "MPS daemon started" in output and "on GPU 4" in output and "on GPU 5" in output


def test_mps_daemon_that_does_not_start_stops_the_sweep_before_any_run(fake_scripts, fake_mps, monkeypatch):
    monkeypatch.setenv("FAKE_MPS_EXIT", "1")
    args = benchmark.Args(methods=("pebble",), env_ids=("cheetah-run",), seeds=(1,), mps=True, script_dir=fake_scripts)
    with pytest.raises(SystemExit, match=r"--mps: the MPS daemon did not start \(nvidia-cuda-mps-control -d: exit code 1\)"):
        benchmark.main(args)
    assert not glob.glob("logs/*.log")
    monkeypatch.setenv("PATH", str(fake_mps.parent / "nowhere"))  # no daemon control at all
    with pytest.raises(SystemExit, match="--mps: the MPS daemon did not start .*not found"):
        benchmark.main(args)


def test_a_slurm_task_with_mps_runs_its_group_through_one_daemon(fake_scripts, fake_mps, monkeypatch):
    """On SLURM the daemon is the array task's, started before its runs and quit after them. It sees the job's GPU;
    the runs see all of the daemon's (none named: a job's physical index would not count within the daemon's)."""
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "3")
    args = benchmark.Args(methods=("pebble", "r2n_pebble"), env_ids=("cheetah-run",), seeds=(1,), script_dir=fake_scripts)
    os.makedirs("logs")
    specs = [benchmark.spec_of(run, args) for run in benchmark.expand(args)]
    results = benchmark.RunGroup(mps=True)(specs)
    assert [code for _, code, _ in results] == [0, 0]
    (_, arg, _, folder, devices), (_, _, given, _, _) = mps_calls(fake_mps)
    assert (arg, given, devices) == ("-d", "quit", "3")
    assert all(child_view(spec["run_id"])["mps"] == folder for spec in specs)
    assert all(child_view(spec["run_id"])["cuda"] is None for spec in specs)
    assert os.environ["CUDA_VISIBLE_DEVICES"] == "3"



@needs_submitit
def test_a_requeued_slurm_task_keeps_its_mps_daemon():
    requeued = benchmark.RunGroup(mps=True).checkpoint([])
    assert requeued.function.mps and not benchmark.RunGroup().checkpoint([]).function.mps


@needs_submitit
def test_slurm_backend_with_submitit_local_executor(fake_scripts, capsys, monkeypatch):
    """One job array, two runs packed per job; the job results report the failures; finished runs are not resubmitted."""
    monkeypatch.setenv("FAKE_SLEEP", "0")
    args = benchmark.Args(methods=("pebble", "r2n_pebble"), env_ids=("cheetah-run",), seeds=(1, 99), runs_per_gpu=2,
                          script_dir=fake_scripts, backend="slurm", slurm_cluster="local", slurm_wait=True, slurm_time=5,
                          slurm_folder="submitit")
    assert benchmark.main(args) == 1
    output = capsys.readouterr().out
    assert "submitted 4 runs as 2 array tasks (2 per GPU job)" in output
    for method in ("pebble", "r2n_pebble"):
        assert os.path.exists(f"logs/{method}__cheetah-run__noise0.9__budget1000__seed1.done")
        assert f"FAILED {method}__cheetah-run__noise0.9__budget1000__seed99: exit code 3" in output
    assert child_view("r2n_pebble__cheetah-run__noise0.9__budget1000__seed1")["argv"][:2] == ["--exp-name", "r2n_pebble"]
    assert benchmark.main(args) == 1  # resubmits only the two failed runs
    output = capsys.readouterr().out
    assert "skipping 2 finished runs" in output and "submitted 2 runs as 1 array tasks" in output


@needs_submitit
def test_slurm_job_script(fake_scripts, tmp_path, monkeypatch, capsys):
    """On a cluster: a fake `sbatch` receives one array script with the user's settings."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    (bin_dir / "sbatch").write_text(f'#!/bin/sh\ncp "$1" {bin_dir}/job.sbatch\necho "Submitted batch job 4242"\n')
    (bin_dir / "srun").write_text("#!/bin/sh\nexit 0\n")
    for f in bin_dir.iterdir():
        f.chmod(0o755)
    monkeypatch.setenv("PATH", f"{bin_dir}{os.pathsep}{os.environ['PATH']}")
    args = benchmark.Args(methods=("pebble", "r2n_pebble"), env_ids=("cheetah-run",), seeds=(1, 2, 3), runs_per_gpu=2,
                          script_dir=fake_scripts, backend="slurm", slurm_partition="gpu", slurm_time=1440,
                          slurm_mem_gb=40, slurm_account="rl", slurm_extra=("constraint=a100",), slurm_folder="sub")
    assert benchmark.main(args) == 0
    assert "submitted 6 runs as 3 array tasks" in capsys.readouterr().out
    script = (bin_dir / "job.sbatch").read_text()
    for line in ("#SBATCH --array=0-2%", "#SBATCH --partition=gpu", "#SBATCH --time=1440", "#SBATCH --mem=80GB",
                 "#SBATCH --gpus-per-node=1", "#SBATCH --cpus-per-task=2", "#SBATCH --account=rl",
                 "#SBATCH --constraint=a100"):
        assert line in script, line


def test_a_study_run_is_finished_only_when_its_results_folder_holds_it(tmp_path, monkeypatch):
    """Run ids leave out a preset's scale flags (cpu-study and imitate share 6): with a results folder, a run is
    finished when that folder holds its copy, whatever the log folder's markers say; without one, by its marker."""
    monkeypatch.chdir(tmp_path)
    imitate = benchmark.Args(preset="imitate")
    run = next(r for r in benchmark.expand(imitate) if r.run_id == "pebble__cartpole-swingup__noise0.9__budget400__seed1")
    assert any(r.run_id == run.run_id for r in benchmark.expand(benchmark.Args(preset="cpu-study")))
    os.makedirs("logs")
    open(f"logs/{run.run_id}.done", "w").close()  # the cpu-study's run, in the same log folder
    args = dataclasses.replace(imitate, results_dir=str(tmp_path / "results"))
    assert not benchmark.is_done(run, args)
    os.makedirs(tmp_path / "results" / run.run_id)
    open(tmp_path / "results" / run.run_id / "done", "w").close()
    assert benchmark.is_done(run, args)
    assert benchmark.is_done(run, benchmark.Args(methods=("pebble",)))  # no results folder: the marker


def test_a_slurm_task_records_each_run_when_it_ends_and_reports_earlier_starts(tmp_path):
    """`RunGroup` records each run as it ends, not in order (a short run's `done` file has its own seconds, not those
    of a longer one started before it), and its results start with those of the task's earlier starts."""
    specs = [dict(run_id=name, command=[sys.executable, "-c", f"import time; time.sleep({sleep})"], threads=1,
                  commit="abc", cwd=str(tmp_path), log=str(tmp_path / f"{name}.log"), results=None)
             for name, sleep in (("long", 6), ("short", 0))]
    earlier = [("before", 1, "before.log")]  # a run that failed in the task's first start
    results = benchmark.RunGroup(earlier)(specs)
    assert results == earlier + [("short", 0, specs[1]["log"]), ("long", 0, specs[0]["log"])]
    seconds = lambda name: int(re.search(r"seconds (\d+) ", open(tmp_path / f"{name}.done").read()).group(1))  # noqa: E731
    assert seconds("short") < 4 <= seconds("long")


def test_a_start_cut_off_without_an_exit_line_is_counted_in_the_done_file(tmp_path):
    """A start whose launcher was killed (its log has `# started` and no exit line) still counts as a start in the
    `done` file, which says its seconds are unknown; the starts that ended, a SLURM requeue among them, add up their
    seconds."""
    log = tmp_path / "run.log"
    log.write_text("# started 2026-11-26 04:00:00\nstep=5000\n"
                   "# exit code 1 after 40 s: stopped at the job's time limit, requeued to resume\n"
                   f"{benchmark.RESUMED}# started 2026-11-26 06:40:49\nstep=10000\n"  # killed here: no exit line
                   f"{benchmark.RESUMED}# started 2026-11-26 08:09:59\nstep=20000\n")
    spec = dict(run_id="run", command=["python", "pebble.py"], commit="abc", cwd=str(tmp_path), log=str(log),
                results=None)
    benchmark.finish_run(spec, 0, 553.0)
    assert open(tmp_path / "run.done").read().splitlines()[:2] == [
        "exit code 0", "seconds 593 over 2 start(s); 1 more start(s) ended without an exit line, their seconds unknown"]
    log.write_text("# started 2026-11-26 08:09:59\nstep=20000\n")
    benchmark.finish_run(spec, 0, 553.0)
    assert open(tmp_path / "run.done").read().splitlines()[1] == "seconds 553 over 1 start(s)"


@needs_submitit
def test_a_slurm_requeue_records_finished_runs_and_resumes_only_the_others(tmp_path):
    """At the time limit, `RunGroup.checkpoint` stops the running runs (SIGUSR2) and requeues only them; a run that
    had already finished, though the job had not yet seen it, gets its `.done`, is not trained again, and is in the
    requeued task's results. A run the signal kills before its script takes SIGUSR2 over is requeued, its exit code
    written as Popen writes it (minus the signal's number)."""
    python = sys.executable
    stops = ("import signal, sys, time; signal.signal(signal.SIGUSR2, lambda *a: sys.exit(1)); "
             "open('ready', 'w').close(); time.sleep(60)")
    unhandled = "import time; open('ready', 'w').close(); time.sleep(60)"
    specs = [dict(run_id=name, command=[python, "-c", code], threads=1, commit="abc", cwd=str(tmp_path / name),
                  log=str(tmp_path / f"{name}.log"), results=None)
             for name, code in (("running", stops), ("finished", "open('ready', 'w').close()"), ("starting", unhandled))]
    for spec in specs:
        os.makedirs(spec["cwd"])
    group = benchmark.RunGroup()
    group.finished, group.results = set(), []  # as `__call__` starts
    group.processes = [(spec, benchmark.launch(spec)) for spec in specs]
    deadline = time.time() + 60
    for spec in (specs[0], specs[2]):
        while not os.path.exists(os.path.join(spec["cwd"], "ready")) and time.time() < deadline:
            time.sleep(0.05)
    os.waitid(os.P_PID, group.processes[1][1].pid, os.WEXITED | os.WNOWAIT)  # ended, not yet seen by `__call__`'s poll
    delayed = group.checkpoint(specs)
    assert [spec["run_id"] for spec in delayed.args[0]] == ["running", "starting"]
    assert f"\n# exit code -{int(signal.SIGUSR2)} after " in open(tmp_path / "starting.log").read()
    assert delayed.function.earlier == [("finished", 0, specs[1]["log"])]  # the requeued task reports it too
    assert open(tmp_path / "finished.done").read().startswith("exit code 0\nseconds ")
    assert not os.path.exists(tmp_path / "running.done")
    assert "stopped at the job's time limit, requeued to resume" in open(tmp_path / "running.log").read()
    group.processes[0][1].wait(timeout=30)
    benchmark.finish_run(specs[0], 0, 7.0)  # the requeued start ends: the seconds of both starts add up
    first = float(re.search(r"exit code 1 after (\d+) s", open(tmp_path / "running.log").read()).group(1))
    assert open(tmp_path / "running.done").read().splitlines()[1] == f"seconds {first + 7:.0f} over 2 start(s)"


@needs_analysis
def test_real_pebble_run_through_the_launcher_then_analyze(tmp_path, monkeypatch, capsys):
    """One tiny real pebble.py run (TINY from test_scripts) launched by benchmark.py, then read by analyze.py."""
    monkeypatch.chdir(tmp_path)
    tiny, skip = [], {"--env-id", "--noise", "--max-feedback"}
    for i in range(0, len(TINY), 2):
        if TINY[i] not in skip:
            tiny += TINY[i:i + 2]
    started = time.time()
    args = benchmark.Args(methods=("pebble",), env_ids=("cartpole-swingup",), noises=(0.9,), budgets=(20,), seeds=(5,),
                          extra=shlex.join(tiny), results_dir="results")
    code = benchmark.main(args)
    run_id = "pebble__cartpole-swingup__noise0.9__budget20__seed5"
    log = open(f"logs/{run_id}.log").read()
    assert code == 0, log
    assert "step=3000 eval_return=" in log and time.time() - started < 300
    # the results folder keeps the event file, the log and a `done` file naming the commit; no checkpoint
    kept = sorted(os.listdir(f"results/{run_id}"))
    assert len(kept) == 3 and kept[0] == "done" and kept[1].startswith("events.out.tfevents.") and kept[2] == "log.txt"
    done = open(f"results/{run_id}/done").read()
    assert "git commit " in done and "# git commit " in log
    assert f"\ndevice cpu\ncpu {benchmark.cpu_of()}\nnumerics default (eager, FP32)\n" in done, done  # TINY says --no-cuda
    # the command as a user types it in the repository, not with this machine's interpreter and paths
    assert "\ncommand python pebble.py --exp-name pebble --env-id cartpole-swingup " in done, done
    assert sys.executable not in done and ROOT not in done, done
    assert not os.path.exists("runs")  # the run worked in its own scratch folder under logs/
    os.remove(f"logs/{run_id}.done")  # only the kept results say it is finished now
    assert benchmark.main(args) == 0 and "nothing to run" in capsys.readouterr().out
    assert analyze.main(analyze.Args(log_dirs=("results",), output_dir="analysis")) == 0
    (row,) = read_csv("analysis/final_return.csv")
    assert (row["task"], row["noise"], row["budget"], row["method"], row["seeds"], row["last_step"]) == (
        "cartpole-swingup", "0.9", "20", "pebble", "1", "3000")
    last_eval = float(log.split("step=3000 eval_return=")[1].split()[0])
    assert float(row["mean"]) == pytest.approx(last_eval, abs=0.006) and row["se"] == "nan"
    assert os.path.getsize("analysis/curves/cartpole-swingup.png") > 0


def test_oracles_share_the_axes_of_the_pbrl_methods_of_their_noise():
    group = lambda noise, budget, method: analyze.Group(("cartpole-swingup", noise, budget, method), [])  # noqa: E731
    sac9, sac95, sac5 = group(0.9, None, "sac"), group(0.95, None, "sac"), group(0.5, None, "sac")
    pebble9, r2n9, pebble9_1000, r2n95 = (group(0.9, 400, "pebble"), group(0.9, 400, "r2n_pebble"),
                                          group(0.9, 1000, "pebble"), group(0.95, 400, "r2n_pebble"))
    panels = analyze.curve_panels([sac9, pebble9, r2n9, pebble9_1000, sac95, r2n95, sac5])
    assert [setting for setting, _ in panels] == [(0.5, None), (0.9, 400), (0.9, 1000), (0.95, 400)]
    assert [[g.key[3] for g in groups] for _, groups in panels] == [
        ["sac"], ["sac", "pebble", "r2n_pebble"], ["sac", "pebble"], ["sac", "r2n_pebble"]]


ORACLE_TINY_RESUMABLE = (  # test_resume's ORACLE: evaluations at 400, 800, 1200, a state every 150 steps
    "--total-timesteps 1200 --learning-starts 200 --episode-length 100 --eval-freq 400 --eval-episodes 2 "
    "--hidden-dim 32 --batch-size 32 --log-freq 100 --no-cuda --checkpoint-freq 150"
)


def interrupt_job_of(run_id, state):
    """What SLURM does at the time limit: SIGUSR2 to the job (the submitit process that launched the run)."""
    while not os.path.exists(state):
        time.sleep(0.05)
    for pid in filter(str.isdigit, os.listdir("/proc")):
        try:
            cmdline = open(f"/proc/{pid}/cmdline", "rb").read().split(b"\0")
            parent = int(open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()[1])
        except OSError:
            continue
        if run_id.encode() in cmdline and b"--run-name" in cmdline:
            os.kill(parent, signal.SIGUSR2)
            return
    raise AssertionError(f"no process of {run_id}")


@needs_submitit
@needs_analysis
def test_slurm_job_at_its_time_limit_requeues_and_resumes_exactly(tmp_path, monkeypatch, capsys):
    """A real sac.py run in a submitit (local executor) job gets the time-limit signal after its first state: the job
    has it save its state, requeues itself, and the run resumes; its points equal those of an uninterrupted run."""
    import threading

    monkeypatch.chdir(tmp_path)
    run_id = "sac__cartpole-swingup__noise0.9__budgetnone__seed3"
    common = dict(methods=("sac",), env_ids=("cartpole-swingup",), noises=(0.9,), seeds=(3,), extra=ORACLE_TINY_RESUMABLE)
    assert benchmark.main(benchmark.Args(**common, log_dir="logs-local", results_dir="uninterrupted")) == 0
    state = f"logs-slurm/scratch/{run_id}/runs/{run_id}/state.pt"
    interrupter = threading.Thread(target=interrupt_job_of, args=(run_id, state), daemon=True)
    interrupter.start()
    args = benchmark.Args(**common, log_dir="logs-slurm", results_dir="requeued", backend="slurm", slurm_cluster="local",
                          slurm_wait=True, slurm_time=10, slurm_folder="submitit")
    assert benchmark.main(args) == 0, open(f"logs-slurm/{run_id}.log").read()
    interrupter.join(1)
    log = open(f"logs-slurm/{run_id}.log").read()
    assert "stopped at the job's time limit, requeued to resume" in log and "# resumed from its state.pt" in log
    assert "resuming runs/" in log and "# exit code 0" in log
    assert len(glob.glob(f"requeued/{run_id}/events.out.tfevents.*")) == 2
    (reference,), (resumed,) = [analyze.load_runs([f"{folder}/{run_id}"]) for folder in ("uninterrupted", "requeued")]
    assert resumed.status == "used" and "resumed 1 time(s)" in resumed.note
    for tag, (steps, values) in reference.scalars.items():
        assert np.array_equal(resumed.scalars[tag][0], steps), tag
        assert tag == "charts/SPS" or np.array_equal(resumed.scalars[tag][1], values), tag


@needs_analysis
def test_local_sweep_interrupted_and_rerun_resumes_exactly(tmp_path, monkeypatch):
    """A stopped launcher (Ctrl-C or `kill`): its runs get SIGTERM, save their state and stop; the same command again
    resumes them, and the sweep ends with the points of an uninterrupted one."""
    monkeypatch.chdir(tmp_path)
    run_id = "sac__cartpole-swingup__noise0.9__budgetnone__seed4"
    flags = ["--methods", "sac", "--env-ids", "cartpole-swingup", "--noises", "0.9", "--seeds", "4",
             f"--extra={ORACLE_TINY_RESUMABLE}"]
    launcher = [sys.executable, os.path.join(ROOT, "benchmark.py"), *flags]
    subprocess.run(launcher + ["--log-dir", "logs-a", "--results-dir", "uninterrupted"], check=True, timeout=300,
                   capture_output=True)
    sweep = launcher + ["--log-dir", "logs-b", "--results-dir", "resumed"]
    process = subprocess.Popen(sweep, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    while not os.path.exists(f"logs-b/scratch/{run_id}/runs/{run_id}/state.pt"):
        assert process.poll() is None, process.communicate()[0]
        time.sleep(0.05)
    process.send_signal(signal.SIGTERM)  # not SIGINT: a shell's background job ignores it, as may a CI runner
    output = process.communicate(timeout=300)[0]
    assert "interrupted: running runs terminated" in output and os.path.exists(f"logs-b/{run_id}.stopped")
    assert "stopped by SIGTERM" in open(f"logs-b/{run_id}.log").read()
    result = subprocess.run(sweep, timeout=300, capture_output=True, text=True)
    assert result.returncode == 0 and "1 runs finished" in result.stdout, result.stdout + result.stderr
    assert os.path.exists(f"logs-b/{run_id}.done") and not os.path.exists(f"logs-b/{run_id}.stopped")
    log = open(f"logs-b/{run_id}.log").read()
    assert "# resumed from its state.pt" in log
    starts = [int(s) for s in re.findall(r"^# exit code -?\d+ after (\d+) s$", log, re.M)]
    assert len(starts) == 2
    assert open(f"resumed/{run_id}/done").read().splitlines()[1] == f"seconds {sum(starts)} over 2 start(s)"
    (reference,), (resumed,) = [analyze.load_runs([f"{folder}/{run_id}"]) for folder in ("uninterrupted", "resumed")]
    assert resumed.status == "used" and "resumed 1 time(s)" in resumed.note
    for tag, (steps, values) in reference.scalars.items():
        assert np.array_equal(resumed.scalars[tag][0], steps), tag
        assert tag == "charts/SPS" or np.array_equal(resumed.scalars[tag][1], values), tag


def test_flags_added_later_take_their_default_for_older_runs(tmp_path):
    """Runs recorded before `--teacher` existed group with new simulated-teacher runs; an external-teacher run does not."""
    root = str(tmp_path / "runs")
    write_run(root, "cheetah-run", 0.9, 1000, "pebble", 1, [1.0] * 5)  # an older run: no teacher, no preferences
    write_run(root, "cheetah-run", 0.9, 1000, "pebble", 2, [3.0] * 5, teacher="simulated", preferences=None)
    write_run(root, "cheetah-run", 0.9, 1000, "pebble", 3, [5.0] * 5, teacher="external", preferences=None)
    assert analyze.main(analyze.Args(log_dirs=(root,), output_dir=str(tmp_path / "out"), plots=False)) == 0
    (row,) = read_csv(tmp_path / "out" / "final_return.csv")
    assert (row["mean"], row["seeds"]) == ("2.0", "2")
    assert "teacher='external'" in open(tmp_path / "out" / "final_return.md").read()  # skipped, with the reason


def write_diagnosed_run(folder, seed, starts):
    """A PbRL run with the study's diagnostics and one sparse net whose input layer has 5 relevant and 46 noise
    columns, written in `starts` (a resumed run: one event file per start, the table only in the first). Each start is
    a list of (step, walltime); the eval return is step / 100."""
    for i, points in enumerate(starts):
        writer = SummaryWriter(folder)
        if i == 0:
            hparams = dict(BASE_HPARAMS, exp_name="r2n_pebble", seed=seed, env_id="cartpole-swingup", noise=0.9,
                           max_feedback=400, total_timesteps=starts[-1][-1][0])
            table = "\n".join(f"|{k}|{v}|" for k, v in hparams.items())
            writer.add_text("hyperparameters", f"|param|value|\n|-|-|\n{table}", walltime=points[0][1])
        for step, walltime in points:
            writer.add_scalar("eval/episodic_return", step / 100, step, walltime=walltime)
            writer.add_scalar("pbrl/reward_steps", step // 10, step, walltime=walltime)
            writer.add_scalar("pbrl/reward_true_corr", 0.5 + step / 1e5, step, walltime=walltime)
            writer.add_scalar("pbrl/heldout_accuracy", 0.75, step, walltime=walltime)
            relevant, noise = 1.0 + step / 1000, 1.0  # mean active weights per relevant / noise column
            writer.add_scalar("sparse/actor/relevant_degree", relevant, step, walltime=walltime)
            writer.add_scalar("sparse/actor/noise_degree", noise, step, walltime=walltime)
            writer.add_scalar("sparse/actor/relevant_active_frac", 5 * relevant / (5 * relevant + 46 * noise), step,
                              walltime=walltime)
        writer.close()
        (path,) = [p for p in glob.glob(f"{folder}/events.out.tfevents.*") if not p.endswith(".start")]
        os.rename(path, f"{folder}/events.out.tfevents.0{i}.start")  # named in the order of the starts, whatever the clock


@needs_analysis
def test_runs_table_diagnostics_wall_time_and_readme(tmp_path, monkeypatch):
    """runs.md/runs.csv: per-run final return, AUC, wall time (summed over the starts of a resumed run), the last
    diagnostics and each sparse layer's connectivity with its chance level (5/51, derived from the logged degrees);
    paths relative to the working folder; `--readme` rewrites only its marked block, the same way every time."""
    monkeypatch.chdir(tmp_path)
    write_diagnosed_run("results/run1", 1, [[(1000, 100.0), (2000, 400.0), (3000, 700.0)]])
    write_diagnosed_run("results/run2", 2, [[(1000, 100.0), (2000, 160.0)], [(2000, 5000.0), (3000, 5120.0)]])
    readme = tmp_path / "README.md"
    text = "# Title\n\nbefore\n<!-- analyze.py results: start -->\nold\n<!-- analyze.py results: end -->\nafter\n"
    readme.write_text(text)
    args = analyze.Args(log_dirs=("results",), output_dir="out", readme=str(readme))
    assert analyze.main(args) == 0
    rows = {r["seed"]: r for r in read_csv("out/runs.csv")}
    assert rows["1"]["path"].startswith("results/run1/") and rows["2"]["reason"].startswith("resumed 1 time(s)")
    assert (rows["1"]["wall_seconds"], rows["2"]["wall_seconds"]) == ("600", "180")  # 60 + 120 s over two starts
    assert float(rows["1"]["reward_steps"]) == 300 and float(rows["1"]["reward_true_corr"]) == pytest.approx(0.53)
    net, value = rows["1"]["connectivity"].split("=")
    frac, chance = map(float, value.split("/"))
    assert net == "actor" and frac == pytest.approx(20 / 66, rel=1e-6) and chance == pytest.approx(5 / 51, rel=1e-6)
    table = open("out/runs.md").read()
    assert "| `run1` | 1 | 30.0 | 60 | 10 min | 300 | 0.530 | 0.750 | actor 0.303 (0.098) |" in table
    assert "| `run2` | 2 | 30.0 | 60 | 3 min | 300 | 0.530 | 0.750 | actor 0.303 (0.098) |" in table
    written = readme.read_text()
    before, block = written.split("<!-- analyze.py results: start -->\n")
    block, after = block.split("<!-- analyze.py results: end -->")
    assert before == "# Title\n\nbefore\n" and after == "\nafter\n" and "old" not in block
    assert "| `run1` | 1 |" in block and "| cartpole-swingup | 400 / 0.9 | r2n_pebble | 30.00 ± 0.00 |" in block
    titles = [block.index(f"| {title} | P Value |") for title in ("Primary Metric", "Final Return", "AUC")]
    assert titles == sorted(titles) and "(the primary metric)" in block  # the primary metric first
    assert "![learning curves: cartpole-swingup](out/curves/cartpole-swingup.png)" in block
    assert analyze.main(args) == 0 and readme.read_text() == written  # regenerates identically
    readme.write_text("no markers\n")
    with pytest.raises(SystemExit, match="--readme .* needs one line `<!-- analyze.py results: start -->`"):
        analyze.main(args)


def test_permutation_test_and_bootstrap_ci_of_the_difference():
    p, exact = analyze.permutation_p([4, 5, 6], [1, 2, 3])
    assert exact and p == pytest.approx(1 / 20)  # the observed split is the most extreme of C(6, 3) = 20
    assert analyze.permutation_p([1, 2, 3], [4, 5, 6])[0] == 1.0
    assert analyze.permutation_p([1, 2, 3], [4, 5, 6], "less")[0] == pytest.approx(1 / 20)
    assert analyze.permutation_p([1, 2, 3], [1, 2, 3])[0] == pytest.approx(14 / 20)  # 14 splits differ by >= 0
    assert analyze.permutation_p([0.1, 0.1, 0.1], [0.1, 0.1, 0.1])[0] == 1.0  # floating ties count as extreme
    for n_a, n_b, relabelings in ((3, 3, 20), (4, 3, 35), (2, 5, 21)):
        rng = np.random.default_rng(n_a * 10 + n_b)
        x, y = rng.normal(size=n_a), rng.normal(size=n_b)
        p, exact = analyze.permutation_p(x, y)
        assert exact and p * relabelings == pytest.approx(round(p * relabelings))
        assert p == pytest.approx(exact_permutation(x, y)) and p + analyze.permutation_p(y, x)[0] == pytest.approx(
            1 + 1 / relabelings)  # the two tails share only the observed split (no ties in normal draws)
    a, b = np.arange(8.0) + 2.5, np.arange(8.0)  # C(16, 8) = 12 870 relabelings
    exact_p, exact = analyze.permutation_p(a, b)
    sampled_p, sampled_exact = analyze.permutation_p(a, b, max_exact=2000)
    assert exact and not sampled_exact and 0 < exact_p < 0.2
    assert sampled_p == pytest.approx(exact_p, abs=0.03) and sampled_p == analyze.permutation_p(a, b, max_exact=2000)[0]
    rng = np.random.default_rng(1)
    x, y = rng.normal(5.0, 1.0, 40), rng.normal(3.0, 1.0, 40)
    low, high = analyze.bootstrap_ci(x, y)
    assert low < x.mean() - y.mean() < high and low < 2.0 < high and high - low < 1.5
    # near normal here: the 2.5 and 97.5 percentiles of the bootstrap differences lie 1.96 bootstrap SDs either side
    bootstrap_sd = math.sqrt(x.var() / len(x) + y.var() / len(y))
    assert [(x.mean() - y.mean() - low) / bootstrap_sd, (high - x.mean() + y.mean()) / bootstrap_sd] == pytest.approx(
        [1.96, 1.96], abs=0.08)
    assert analyze.bootstrap_ci(x, y) == (low, high)  # a fixed seed: the same CI every time
    assert all(math.isnan(v) for v in analyze.bootstrap_ci([1.0], [2.0, 3.0]))


def test_primary_metric_is_the_mean_of_the_last_evaluations():
    curves = np.array([[1.0, 2.0, 3.0, 4.0, 8.0], [0.0, 0.0, 1.0, 1.0, 1.0]])
    group = analyze.Group(("cheetah-run", 0.9, 1000, "pebble"), runs=[], steps=np.arange(1, 6) * 1000, curves=curves)
    assert np.array_equal(group.values("primary", 3), np.array([5.0, 1.0]))
    assert np.array_equal(group.values("primary", 1), group.final) and np.array_equal(group.values("auc", 3), group.auc)


def test_gpu_speed_windows_from_event_wall_times_and_logs(tmp_path):
    """results/gpu-speed/speed.py: a run's rate over its window is the steps between two evaluations over their
    wall-clock gap; runs of one configuration add up; evaluations' and state writes' shares come from the log."""
    for config, n in (("one", 1), ("two", 2)):
        for i in range(1, n + 1):
            writer = SummaryWriter(str(tmp_path / config / "runs" / f"run{i}"))
            for step, wall in ((2000, 100.0), (4000, 110.0), (8000, 130.0)):  # 4000 steps in 20 s from step 4000
                writer.add_scalar("eval/episodic_return", 1.0, step, walltime=wall)
            writer.close()
            (tmp_path / config / f"run{i}.log").write_text(
                "step=4000 eval_return=1.00 SPS=9 eval_seconds=9.00 feedback=0/10 labels=0\n"
                "state saved after step 6000: 0.92 GB in 1.0 s\n"
                "step=8000 eval_return=1.00 SPS=9 eval_seconds=2.00 feedback=0/10 labels=0\n")
    result = subprocess.run([sys.executable, os.path.join(ROOT, "results", "gpu-speed", "speed.py"), str(tmp_path),
                             "--from-step", "4000"], capture_output=True, text=True, check=True)
    assert "| one | 1 | 4000-8000 | 200.0 | 200.0 | 10.0% | 5.0% |" in result.stdout, result.stdout
    assert "| two | 2 | 4000-8000 | 200.0 | 400.0 | 10.0% | 5.0% |" in result.stdout, result.stdout
    assert json.load(open(tmp_path / "speed.json"))[1]["aggregate"] == 400.0


@needs_analysis
def test_cheetah_power_achieved_is_read_only_when_the_study_is_complete(tmp_path):
    """results/cheetah-study/power.py --achieved: refused while a PbRL run of the protocol is missing; then the
    power for the planned +79.4 at the pooled SD of the primary metric (mean of the last 3 evaluations), as scipy's
    noncentral t gives it independently here."""
    from scipy import stats

    study = tmp_path / "results" / "cheetah-study"
    study.mkdir(parents=True)
    script = study / "power.py"
    script.write_text(open(os.path.join(ROOT, "results", "cheetah-study", "power.py")).read())
    primary = {"pebble": [100.0, 140.0, 180.0, 220.0, 260.0, 300.0, 340.0, 380.0],
               "r2n_pebble": [150.0, 170.0, 190.0, 210.0, 230.0, 250.0, 270.0, 290.0]}
    for method, values in primary.items():
        for seed, value in enumerate(values, 1):
            folder = study / f"{method}__cheetah-run__noise0.9__budget1000__seed{seed}"
            writer = SummaryWriter(str(folder))
            for step, value_at_step in ((220_000, 0.0), (230_000, value - 3), (240_000, value), (250_000, value + 3)):
                writer.add_scalar("eval/episodic_return", value_at_step, step)  # the last 3 average to `value`
            writer.close()
            if not (method == "r2n_pebble" and seed == 8):
                (folder / "done").write_text("exit code 0\n")
    command = [sys.executable, str(script), "--achieved"]
    env = dict(os.environ, PYTHONPATH=ROOT)  # the repository's analyze.py, which the copy imports
    refused = subprocess.run(command, capture_output=True, text=True, env=env)
    assert refused.returncode != 0 and "7 of 8 r2n_pebble runs are in" in refused.stderr, refused.stderr
    (study / "r2n_pebble__cheetah-run__noise0.9__budget1000__seed8" / "done").write_text("exit code 0\n")
    result = subprocess.run(command, capture_output=True, text=True, check=True, env=env).stdout
    pooled = math.sqrt((np.var(primary["pebble"], ddof=1) + np.var(primary["r2n_pebble"], ddof=1)) / 2)
    power = lambda effect: 1 - stats.nct.cdf(stats.t.ppf(0.95, 14), 14, effect / pooled * 2)  # d * sqrt(n / 2)
    smallest = next(effect for effect in range(1, 1000) if power(effect) >= 0.8)
    assert f"pooled {pooled:.1f}" in result, result
    assert f"power for the planned effect +79.4 at 8 per arm: {power(79.4):.2f}" in result, result
    assert f"smallest effect with 80% power: {smallest} points" in result, result


def test_power_and_smallest_detectable_effect_against_scipy():
    """`analyze.power`: the noncentral t of a one-tailed test at n per arm, df = 2n - 2, computed here from scipy's
    distributions; `smallest_detectable`: the first whole effect with at least 80% power."""
    from scipy import stats

    for effect, sd, n in ((79.4, 60.6, 8), (212.5, 180.9, 8), (10.0, 50.0, 3)):
        ncp, df = effect / sd * math.sqrt(n / 2), 2 * n - 2
        assert analyze.power(effect, sd, n) == pytest.approx(1 - stats.nct.cdf(stats.t.ppf(0.95, df), df, ncp), rel=1e-9)
    smallest = analyze.smallest_detectable(60.6, 8)
    assert analyze.power(smallest, 60.6, 8) >= 0.8 > analyze.power(smallest - 1, 60.6, 8)
    assert smallest == 80  # the cheetah study's PROTOCOL.md
    for sd, n in ((float("nan"), 8), (0.0, 8), (60.6, 1)):  # no effect is ever detectable: refused, not searched forever
        with pytest.raises(ValueError, match="smallest_detectable needs a finite SD > 0 and n >= 2"):
            analyze.smallest_detectable(sd, n)


def test_fmt_p_stars_significance_and_bounds_tiny_p():
    """A p below 0.001 reads as that bound, not as 0.000; the star follows the threshold, not the rounding."""
    assert (analyze.p_text(0.0123), analyze.p_text(0.001), analyze.p_text(0.00077)) == ("0.012", "0.001", "< 0.001")
    assert analyze.p_text(float("nan")) == "nan"  # no test is not a tiny p
    cells = [analyze.fmt_p(p, 0.05) for p in (0.0123, 0.001, 0.00077, 0.05, 0.5, float("nan"))]
    assert cells == ["0.012*", "0.001*", "< 0.001*", "0.050", "0.500", ""]
    assert analyze.fmt_p(0.0004, 0.0001) == "< 0.001"


@needs_analysis
def test_early_stop_power_reproduces_its_protocol_and_reads_the_study_only_when_complete(tmp_path):
    """results/early-stop/power.py prints PROTOCOL.md's numbers from the committed cpu-study runs; `--achieved`
    refuses until all 16 runs are in, then gives each test's power at its observed pooled SD."""
    script = os.path.join(ROOT, "results", "early-stop", "power.py")
    plain = subprocess.run([sys.executable, script], capture_output=True, text=True, check=True).stdout
    for quoted in ("planning SD (pooled, main arms) 180.9; lead +212.5, d = 1.17, power 0.72 at 8 per arm",
                   "power 0.30; 80% power needs 37 per arm", "at 8 per arm: 237 points", "96.9: 127 points"):
        assert quoted in plain, plain
    # a copy beside synthetic runs: the cpu-study's arms, then the study's seeds 9-16, the last one missing at first
    study, cpu = tmp_path / "results" / "early-stop", tmp_path / "results" / "cpu-study"
    study.mkdir(parents=True)
    (study / "power.py").write_text(open(script).read())
    rng = np.random.default_rng(0)
    for method, seeds in (("pebble", range(1, 9)), ("r2n_pebble", range(1, 9)), ("pebble_no_early_stop", range(1, 4)),
                          ("r2n_pebble_no_early_stop", range(1, 4))):
        for seed in seeds:
            write_run(str(cpu), "cartpole-swingup", 0.9, 400, method, seed, values(rng, 5, 100))
    primary = {}
    for method in ("pebble_no_early_stop", "r2n_pebble_no_early_stop"):
        for seed in range(9, 17 if method == "pebble_no_early_stop" else 16):
            returns = values(rng, 5, 150)
            primary.setdefault(method, []).append(returns[-3:].mean())
            write_run(str(study), "cartpole-swingup", 0.9, 400, method, seed, returns)
    command, env = [sys.executable, str(study / "power.py"), "--achieved"], dict(os.environ, PYTHONPATH=ROOT)
    refused = subprocess.run(command, capture_output=True, text=True, env=env)
    assert refused.returncode != 0 and "'r2n_pebble_no_early_stop': 7} runs of 8 per arm are in" in refused.stderr
    returns = values(rng, 5, 150)
    primary["r2n_pebble_no_early_stop"].append(returns[-3:].mean())
    write_run(str(study), "cartpole-swingup", 0.9, 400, "r2n_pebble_no_early_stop", 16, returns)
    result = subprocess.run(command, capture_output=True, text=True, check=True, env=env).stdout
    sd = math.sqrt((np.var(primary["pebble_no_early_stop"], ddof=1) + np.var(primary["r2n_pebble_no_early_stop"], ddof=1)) / 2)
    assert f"H1: observed pooled SD {sd:.1f}; " in result and "H2: observed pooled SD" in result, result


@needs_analysis
def test_event_files_of_a_folder_are_read_in_the_order_written(tmp_path):
    """A writer numbers its files; the 100th sorts after the 99th, so a resumed run's first file (the one with the
    hyperparameter table) is read first, whatever the counter's digits."""
    names = ["events.out.tfevents.1795669934.vm.21712.100", "events.out.tfevents.1795669934.vm.21712.99"]
    for folder in ("run9", "run10"):
        for name in names:
            (tmp_path / folder).mkdir(exist_ok=True)
            (tmp_path / folder / name).write_bytes(b"")
    found = [os.path.relpath(path, tmp_path) for path in analyze.find_event_files([str(tmp_path)])]
    assert found == [os.path.join(folder, name) for folder in ("run9", "run10") for name in reversed(names)]


@needs_analysis
def test_analyze_reports_relevant_weight_frac_where_runs_log_it(tmp_path):
    """`features.md` holds each group's final `relevant_weight_frac` per network (mean ± SE over seeds, chance, their
    ratio), and a plot per setting shows it; runs without the tags (older studies) get neither."""
    log_dir = tmp_path / "runs"
    finals = {"pebble": [0.10, 0.20], "r2n_pebble": [0.30, 0.40]}
    for method, per_seed in finals.items():
        for seed, final in enumerate(per_seed, 1):
            path = write_run(str(log_dir), "cheetah-run", 0.9, 1000, method, seed, [1.0, 2.0, 3.0, 4.0, 5.0])
            writer = SummaryWriter(path)
            for step in STEPS:
                for net, chance in (("actor", 0.1), ("reward0", 0.13)):
                    writer.add_scalar(f"features/{net}/relevant_weight_frac", final if step == STEPS[-1] else 0.5, step)
                    writer.add_scalar(f"features/{net}/chance", chance, step)
            writer.close()
    out = tmp_path / "analysis"
    assert analyze.main(analyze.Args(log_dirs=(str(log_dir),), output_dir=str(out), baseline="pebble")) == 0
    table = (out / "features.md").read_text()
    se = np.std([0.3, 0.4], ddof=1) / math.sqrt(2)
    assert f"| cheetah-run | 0.9 | 1000 | r2n_pebble | actor | 0.350 ± {se:.3f} | 0.100 | 3.50 | 2 |" in table, table
    assert f"| cheetah-run | 0.9 | 1000 | pebble | reward0 | 0.150 ± {se:.3f} | 0.130 | 1.15 | 2 |" in table, table
    assert (out / "features" / "cheetah-run__noise0.9__budget1000.png").stat().st_size > 0
    older = tmp_path / "older"
    write_run(str(older), "cheetah-run", 0.9, 1000, "pebble", 1, [1.0, 2.0, 3.0, 4.0, 5.0])
    assert analyze.main(analyze.Args(log_dirs=(str(older),), output_dir=str(out), baseline="pebble")) == 0
    assert not (out / "features.md").exists()



def test_analyze_tables_the_success_rate_where_runs_log_it(tmp_path):
    """`success_rate.md/.csv`: the mean of each run's last `--primary-last` success rates, mean ± SE over seeds, tested
    against the baseline; written only where a group's runs log `eval/success_rate`, and gone when no run does. A run
    recorded before `--hidden-layers` and `--weight-decay` existed groups with one that records their defaults."""
    log_dir = tmp_path / "runs"
    rates = {("pebble", 1): [0.0, 0.1, 0.2, 0.3, 0.4], ("pebble", 2): [0.0, 0.0, 0.1, 0.1, 0.2],
             ("r2n_pebble", 1): [0.0, 0.3, 0.6, 0.8, 1.0], ("r2n_pebble", 2): [0.1, 0.4, 0.5, 0.7, 0.9]}
    for (method, seed), per_step in rates.items():
        new_flags = dict(hidden_layers=2, weight_decay=0.0) if seed == 2 else {}
        path = write_run(str(log_dir), "drawer-open-v3", 0.9, 1000, method, seed, [1.0, 2.0, 3.0, 4.0, 5.0],
                         **new_flags)
        writer = SummaryWriter(path)
        for step, rate in zip(STEPS, per_step):
            writer.add_scalar("eval/success_rate", rate, step)
        writer.close()
    out = tmp_path / "analysis"
    assert analyze.main(analyze.Args(log_dirs=(str(log_dir),), output_dir=str(out), baseline="pebble")) == 0
    with open(out / "success_rate.csv") as f:
        rows = {row["method"]: row for row in csv.DictReader(f)}
    assert rows["r2n_pebble"]["seeds"] == rows["pebble"]["seeds"] == "2"
    last3 = {key: np.mean(np.float32(per_step[-3:])) for key, per_step in rates.items()}  # TensorBoard's float32
    for method in ("pebble", "r2n_pebble"):
        mean, se = analyze.mean_se([last3[(method, 1)], last3[(method, 2)]])
        assert float(rows[method]["mean"]) == pytest.approx(mean) and float(rows[method]["se"]) == pytest.approx(se)
    assert rows["r2n_pebble"]["baseline"] == "pebble" and 0 < float(rows["r2n_pebble"]["p_value"]) < 0.05
    assert "# Success Rate" in (out / "success_rate.md").read_text()
    older = tmp_path / "older"
    write_run(str(older), "cheetah-run", 0.9, 1000, "pebble", 1, [1.0, 2.0, 3.0, 4.0, 5.0])
    assert analyze.main(analyze.Args(log_dirs=(str(older),), output_dir=str(out), baseline="pebble")) == 0
    assert not (out / "success_rate.md").exists() and not (out / "success_rate.csv").exists()

def stored_noise_module(name):
    """results/stored-noise/{name}.py, imported."""
    spec = importlib.util.spec_from_file_location(f"stored_noise_{name}",
                                                  os.path.join(ROOT, "results", "stored-noise", f"{name}.py"))
    module = importlib.util.module_from_spec(spec)
    sys.path.insert(0, os.path.join(ROOT, "results", "stored-noise"))
    spec.loader.exec_module(module)
    return module


@needs_analysis
def test_interaction_test_of_the_stored_noise_study_by_brute_force():
    """H2's statistic D and its exact permutation p (relabelling within each environment), against every relabeling
    enumerated here, ties included; its Welch-type t and power against the formulas, computed with scipy."""
    from scipy import stats

    interaction = stored_noise_module("interaction")
    arms = [np.array(a) for a in ([5.0, 7.0, 9.0], [1.0, 2.0, 2.0], [3.0, 4.0, 4.0], [2.0, 4.0, 6.0])]
    observed = (arms[0].mean() - arms[1].mean()) - (arms[2].mean() - arms[3].mean())

    def differences(a, b):
        pooled = np.concatenate([a, b])
        out = []
        for first in itertools.combinations(range(6), 3):
            rest = [i for i in range(6) if i not in first]
            out.append(pooled[list(first)].mean() - pooled[rest].mean())
        return out

    brute = np.mean([s - r >= observed - 1e-12 for s in differences(*arms[:2]) for r in differences(*arms[2:])])
    assert interaction.interaction_p(*arms) == pytest.approx(brute, abs=1e-12)
    assert 0 < brute < 0.2  # a clear interaction, yet not the smallest p that 3 per arm allows
    reversed_p = interaction.interaction_p(arms[2], arms[3], arms[0], arms[1])
    assert reversed_p > 0.8  # the other direction
    low, high = interaction.interaction_ci(arms)
    assert low < observed < high
    assert interaction.interaction_ci([np.full(4, v) for v in (3.0, 1.0, 2.0, 2.0)]) == (2.0, 2.0)
    same = [np.array([1.0, 2.0, 4.0]) + shift for shift in (3, 0, 1, 0)]  # equal variances: df = 4n - 4
    t, df, p = interaction.interaction_welch(same)
    assert df == pytest.approx(8)
    assert t == pytest.approx(2 / math.sqrt(4 * np.var(same[0], ddof=1) / 3))
    assert p == pytest.approx(stats.t.sf(t, 8))
    expected = 1 - stats.nct.cdf(stats.t.ppf(0.95, 28), 28, 79.4 / (50.1 * math.sqrt(4 / 8)))
    assert interaction.interaction_power(79.4, 50.1, 8) == pytest.approx(expected, rel=1e-9)


@needs_analysis
def test_stored_noise_scripts_reproduce_the_protocol_and_wait_for_every_run(tmp_path):
    """power.py prints PROTOCOL.md's table from the cheetah study's committed runs; interaction.py and
    `power.py --achieved` refuse until all 8 runs of the four arms are in, then read them."""
    script = os.path.join(ROOT, "results", "stored-noise", "power.py")
    plain = subprocess.run([sys.executable, script], capture_output=True, text=True, check=True).stdout
    with open(os.path.join(ROOT, "results", "stored-noise", "PROTOCOL.md")) as f:
        protocol = f.read()
    for sd, h1, smallest_h1, h2, smallest_h2 in (("50.1", "0.91", 66, "0.71", 91), ("75.2", "0.64", 99, "0.43", 136),
                                                  ("100.2", "0.45", 132, "0.29", 181)):
        assert (f"SD {sd}. H1 power for +79.4 at 8 per arm: {h1}; smallest effect with 80% power {smallest_h1}. "
                f"H2 power for D = +79.4: {h2}; smallest D with 80% power {smallest_h2}") in plain, plain
        assert f"| {h1} | {smallest_h1} | {h2} | {smallest_h2} |" in protocol
    # copies beside synthetic runs: this study's two arms and the cheetah study's, the last run not yet done
    study, cheetah = tmp_path / "results" / "stored-noise", tmp_path / "results" / "cheetah-study"
    study.mkdir(parents=True)
    for name in ("interaction.py", "power.py"):
        (study / name).write_text(open(os.path.join(ROOT, "results", "stored-noise", name)).read())
    rng = np.random.default_rng(1)
    primary = {}
    for folder, method in ((study / "runs", "r2n_pebble_stored_noise"), (study / "runs", "pebble_stored_noise"),
                           (cheetah, "r2n_pebble"), (cheetah, "pebble")):
        for seed in range(1, 9):
            returns = values(rng, 5, 100)
            primary.setdefault(method, []).append(returns[-3:].mean())
            run = folder / f"{method}__cheetah-run__noise0.9__budget1000__seed{seed}"
            writer = SummaryWriter(str(run))  # a committed run: its event file directly in the run's folder
            for step, value in zip(STEPS, returns):
                writer.add_scalar("eval/episodic_return", value, step)
            writer.close()
            if not (method == "pebble_stored_noise" and seed == 8):
                (run / "done").write_text("exit code 0\n")
    env = dict(os.environ, PYTHONPATH=ROOT)
    for command in ([str(study / "interaction.py")], [str(study / "power.py"), "--achieved"]):
        refused = subprocess.run([sys.executable, *command], capture_output=True, text=True, env=env)
        assert refused.returncode != 0 and "7 of 8 pebble_stored_noise runs are in" in refused.stderr, refused.stderr
    (study / "runs" / "pebble_stored_noise__cheetah-run__noise0.9__budget1000__seed8" / "done").write_text("0\n")
    result = subprocess.run([sys.executable, str(study / "interaction.py")], capture_output=True, text=True,
                            check=True, env=env).stdout
    arms = [np.array(primary[m]) for m in ("r2n_pebble_stored_noise", "pebble_stored_noise", "r2n_pebble", "pebble")]
    d = (arms[0].mean() - arms[1].mean()) - (arms[2].mean() - arms[3].mean())
    assert f"H2: D = {d:+.1f}, bootstrap 95% CI" in result, result
    interaction = stored_noise_module("interaction")
    assert f"exact permutation p {interaction.interaction_p(*arms):.4f}" in result, result
    achieved = subprocess.run([sys.executable, str(study / "power.py"), "--achieved"], capture_output=True, text=True,
                              check=True, env=env).stdout
    pooled = math.sqrt((np.var(arms[0], ddof=1) + np.var(arms[1], ddof=1)) / 2)
    assert f"achieved, H1 (the stored arms' pooled SD): SD {pooled:.1f}." in achieved, achieved


def test_noise_sensitivity_is_zero_for_a_policy_blind_to_the_noise(tmp_path):
    """noise_sensitivity.py: the redraws' share of the variance is 0 for values that differ only between states and 1
    for values that differ only between redraws; from a checkpoint, 0 for an actor whose noise weights are zero and
    more than 0 for the same actor with them."""
    study = stored_noise_module("noise_sensitivity")
    states = np.arange(6.0)[:, None, None] * np.ones((6, 4, 2))
    assert study.noise_share(states) == 0.0
    assert study.noise_share(np.random.default_rng(0).normal(size=(1, 4, 2)).repeat(6, 0)) == pytest.approx(1.0)
    import sac
    import torch

    args = sac.ene.suite_settings(sac.Args(env_id="cheetah-run", noise=0.9, hidden_dim=16))
    obs_dim, act_dim = 171, 6
    torch.manual_seed(0)
    agent = sac.make_agent(obs_dim, act_dim, args, torch.device("cpu"))
    shares = []
    for blind in (False, True):  # the zeroing stays: the blind actor second
        if blind:
            with torch.no_grad():
                agent.actor.net[0].weight[:, 17:] = 0  # cheetah-run has 17 real features
        path = str(tmp_path / f"blind{blind}.cleanrl_model")
        sac.save_checkpoint(path, args, 0, {"agent": agent}, (17, obs_dim, act_dim))
        shares.append(study.sensitivity(path, "sac", episodes=1, redraws=3, seed=1)["action"])
    assert shares[0] > 0.01 and shares[1] < 1e-9  # 0 up to the batched matmul's rounding


STORED_NOISE_TABLE = os.path.join(ROOT, "results", "stored-noise", "analysis", "primary.csv")


@needs_analysis
def test_stored_noise_analysis_runs_end_to_end_on_22_synthetic_runs(tmp_path):
    """`analyze.sh` in a copy of the repository whose stored-noise runs and probes are synthetic (the cheetah study's
    are the committed ones): it writes the tables, H2's test and the power achieved into analysis/, and H2 reads R2N's
    gain with the noise stored from these runs. The probes' table sets them beside the cheetah study's arms, and a
    pebble_repeat run that logs PEBBLE's evaluations again is reported equal to it."""
    study = tmp_path / "results" / "stored-noise"
    study.mkdir(parents=True)
    for name in ("analyze.sh", "interaction.py", "power.py", "repeat_check.py", "diagnostics.py"):
        shutil.copy(os.path.join(ROOT, "results", "stored-noise", name), study / name)
    os.symlink(os.path.join(ROOT, "results", "cheetah-study"), tmp_path / "results" / "cheetah-study")
    os.symlink(os.path.join(ROOT, "analyze.py"), tmp_path / "analyze.py")
    rng = np.random.default_rng(0)
    arms = {"pebble_stored_noise": (1000, 8, 100), "r2n_pebble_stored_noise": (1000, 8, 150),
            "sac_stored_noise": (None, 3, 90), "anf_sac_stored_noise": (None, 3, 380)}
    primary = {}
    for method, (budget, seeds, offset) in arms.items():
        primary[method] = values(rng, seeds, offset)
        for seed, value in enumerate(primary[method], 1):
            folder = study / "runs" / f"{method}__cheetah-run__noise0.9__budget{budget or 'none'}__seed{seed}"
            writer = hparams_writer(str(folder), "cheetah-run", 0.9, budget, method, seed, noise_resample=False)
            for step, at_step in ((220_000, 0.0), (230_000, value - 1), (240_000, value), (250_000, value + 1)):
                writer.add_scalar("eval/episodic_return", at_step, step)  # the last 3 average to `value`
            writer.close()
            (folder / "done").write_text("exit code 0\n")
    probes = {method: values(rng, 3, 200) for method in ("r2n_pebble_reward_only", "r2n_pebble_agent_as_reward")}
    for method, returns in probes.items():
        for seed, value in enumerate(returns, 1):
            folder = study / "probes" / f"{method}__cheetah-run__noise0.9__budget1000__seed{seed}"
            writer = hparams_writer(str(folder), "cheetah-run", 0.9, 1000, method, seed, total_timesteps=250_000)
            writer.add_scalar("eval/episodic_return", value, 250_000)
            writer.close()
            (folder / "done").write_text("exit code 0\n")
    # pebble_repeat seed 1 logs the cheetah study's PEBBLE seed 1 evaluations again
    pebble_seed1 = os.path.join(ROOT, "results", "cheetah-study", "pebble__cheetah-run__noise0.9__budget1000__seed1")
    [original] = analyze.read_folder(sorted(glob.glob(os.path.join(pebble_seed1, "events.out.tfevents.*"))))
    folder = study / "probes" / "pebble_repeat__cheetah-run__noise0.9__budget1000__seed1"
    writer = hparams_writer(str(folder), "cheetah-run", 0.9, 1000, "pebble_repeat", 1, total_timesteps=250_000)
    for step, value in zip(*original.scalars["eval/episodic_return"]):
        writer.add_scalar("eval/episodic_return", value, step)
    writer.close()
    (folder / "done").write_text("exit code 0\n")
    env = dict(os.environ, PATH=os.path.dirname(sys.executable) + os.pathsep + os.environ["PATH"], MPLBACKEND="Agg")
    result = subprocess.run(["bash", str(study / "analyze.sh")], cwd=tmp_path, capture_output=True, text=True, env=env)
    assert result.returncode == 0, result.stderr[-2000:]
    assert "the probes: pebble_repeat has 1 of 3 runs in" in result.stdout
    with open(study / "analysis-probes" / "primary.csv") as f:
        methods = {row["method"] for row in csv.DictReader(f)}
    assert methods == {"pebble", "r2n_pebble", "sac", "anf_sac", "pebble_repeat", *probes}
    evaluations = len(original.eval_steps)
    assert (study / "analysis-probes" / "repeat.txt").read_text() == (
        f"pebble_repeat seed 1 against the cheetah study's pebble seed 1: {evaluations} of {evaluations} shared "
        "scalars equal, to the evaluation at step 250000\n")
    diagnostics = (study / "analysis-probes" / "diagnostics.md").read_text().splitlines()
    mean, se = analyze.mean_se(probes["r2n_pebble_reward_only"])
    assert f"| `r2n_pebble_reward_only` | redrawn | dense | sparse | 3 | {mean:.1f} ± {se:.1f} | - |" in diagnostics[5]
    assert [line.split(" | ")[0] for line in diagnostics[2:9]] == [f"| `{method}`" for method in (
        "pebble", "r2n_pebble", "pebble_repeat", "r2n_pebble_reward_only", "r2n_pebble_agent_as_reward",
        "pebble_stored_noise", "r2n_pebble_stored_noise")]
    with open(study / "analysis" / "primary.csv") as f:
        assert {row["method"] for row in csv.DictReader(f)} == set(arms)
    gain = primary["r2n_pebble_stored_noise"].mean() - primary["pebble_stored_noise"].mean()
    interaction_txt = (study / "analysis" / "interaction.txt").read_text()
    assert f"R2N's gain: stored {gain:+.1f}," in interaction_txt, interaction_txt
    assert "H2: D = " in interaction_txt and "exact permutation p " in interaction_txt
    power_txt = (study / "analysis" / "power-achieved.txt").read_text()
    assert "achieved, H1 (the stored arms' pooled SD)" in power_txt and "achieved, H2" in power_txt, power_txt


@needs_analysis
def test_repeat_check_names_the_first_scalar_that_differs_and_a_run_under_way(tmp_path, capsys):
    """`repeat_check.py` compares the scalars a pebble_repeat run shares with the PEBBLE run of its seed: all equal,
    or the first that differs (by step, then tag: an earlier loss before a later return); the SPS chart, wall time,
    is left out; a run under way says so."""
    repeat_check = stored_noise_module("repeat_check")
    for method, folder, seeds in (("pebble", "cheetah", (1, 2)), ("pebble_repeat", "probes", (1, 2))):
        for seed in seeds:
            writer = hparams_writer(str(tmp_path / folder / f"{method}{seed}"), "cheetah-run", 0.9, 1000, method, seed,
                                    total_timesteps=30_000)
            last = 30_000 if method == "pebble" or seed == 1 else 20_000
            for step in range(10_000, last + 1, 10_000):
                changed = method == "pebble_repeat" and seed == 1  # eval at step 20 000, the loss at 10 000 and 20 000
                writer.add_scalar("eval/episodic_return", step / 100 + 0.5 * (changed and step == 20_000), step)
                writer.add_scalar("losses/qf_loss", 0.25 + 0.5 * (changed and step <= 20_000), step)
                writer.add_scalar("charts/SPS", 80 if method == "pebble" else 90, step)
            writer.close()
    assert repeat_check.main([str(tmp_path / "probes")], cheetah=str(tmp_path / "cheetah")) == 0
    assert capsys.readouterr().out.splitlines() == [
        "pebble_repeat seed 1 against the cheetah study's pebble seed 1: 3 of 6 shared scalars equal, to the "
        "evaluation at step 30000; the first that differs: losses/qf_loss at step 10000",
        "pebble_repeat seed 2 against the cheetah study's pebble seed 2: 4 of 4 shared scalars equal, to the "
        "evaluation at step 20000 of 30000 (under way)",
    ]


def test_stored_noise_tables_are_committed_once_every_primary_run_is_in():
    """Once the 22 primary runs of the stored-noise study are committed, so is its analysis (`analyze.sh`): the
    table check below then runs on it. Before, the analysis must not exist, since the protocol reads no test."""
    landed = len(glob.glob(os.path.join(ROOT, "results", "stored-noise", "runs", "*", "done")))
    assert landed <= 22
    assert os.path.exists(STORED_NOISE_TABLE) == (landed == 22), \
        f"{landed} of 22 runs are in: run `bash results/stored-noise/analyze.sh` once all are, and commit analysis/"


PROBES_TABLE = os.path.join(ROOT, "results", "stored-noise", "analysis-probes", "primary.csv")
STORED_TABLE_ANALYSIS = os.path.join(ROOT, "results", "stored-table", "analysis", "primary.csv")


def test_probe_table_is_committed_once_the_issue_probes_are_in():
    """The probes' table (`analyze.sh`) is committed once the 6 runs of the issue's two probe arms are, and not
    before; its pebble_repeat report then names every committed pebble_repeat run, and only those, and its
    diagnostics table is what `diagnostics.py` makes of the committed runs."""
    probes = os.path.join(ROOT, "results", "stored-noise", "probes")
    landed = len(glob.glob(os.path.join(probes, "r2n_pebble_reward_only__*", "done"))
                 + glob.glob(os.path.join(probes, "r2n_pebble_agent_as_reward__*", "done")))
    assert landed <= 6
    assert os.path.exists(PROBES_TABLE) == (landed == 6), (
        f"{landed} of 6 probes are in: run `bash results/stored-noise/analyze.sh` once all are, and commit "
        "analysis-probes/")
    if landed == 6:
        repeats = sorted(int(path.split("__seed")[1].split(os.sep)[0])
                         for path in glob.glob(os.path.join(probes, "pebble_repeat__*", "done")))
        with open(os.path.join(os.path.dirname(PROBES_TABLE), "repeat.txt")) as f:
            reported = [int(line.split()[2]) for line in f if line.startswith("pebble_repeat seed ")]
        assert reported == repeats, "run `bash results/stored-noise/analyze.sh` again and commit analysis-probes/"
        script = os.path.join(ROOT, "results", "stored-noise", "diagnostics.py")  # its table, from the committed runs
        regenerated = subprocess.run([sys.executable, script], capture_output=True, text=True, check=True).stdout
        with open(os.path.join(os.path.dirname(PROBES_TABLE), "diagnostics.md")) as f:
            assert f.read() == regenerated


def test_stored_noise_analysis_refuses_until_every_primary_run_is_in(tmp_path):
    """`bash results/stored-noise/analyze.sh` reads no test before the 22 primary runs are in: with 21 it stops with
    one line saying how many are in, and writes nothing."""
    for seed in range(21):
        (tmp_path / "results" / "stored-noise" / "runs" / f"run{seed}").mkdir(parents=True)
        (tmp_path / "results" / "stored-noise" / "runs" / f"run{seed}" / "done").write_text("exit code 0\n")
    result = subprocess.run(["bash", os.path.join(ROOT, "results", "stored-noise", "analyze.sh")], cwd=tmp_path,
                            capture_output=True, text=True)
    assert result.returncode == 1
    assert result.stderr.strip().splitlines() == [
        "results/stored-noise/analyze.sh: 21 of the 22 primary runs are in; the protocol reads no test before"]
    assert not (tmp_path / "results" / "stored-noise" / "analysis").exists()


def run_stored_noise_analysis(tmp_path, runs):
    """`analyze.sh` run in `tmp_path` after a `done` file is written in each of `runs` (folders under
    results/stored-noise); `analyze.py` is an empty stub, so its tables steps succeed and write nothing."""
    study = tmp_path / "results" / "stored-noise"
    for run in runs:
        (study / run).mkdir(parents=True)
        (study / run / "done").write_text("exit code 0\n")
    (tmp_path / "analyze.py").write_text("")
    (study / "analysis").mkdir(exist_ok=True)
    env = dict(os.environ, PATH=os.path.dirname(sys.executable) + os.pathsep + os.environ["PATH"])
    return subprocess.run(["bash", os.path.join(ROOT, "results", "stored-noise", "analyze.sh")], cwd=tmp_path,
                          capture_output=True, text=True, env=env)


def test_stored_noise_analysis_keeps_the_old_report_when_a_step_fails(tmp_path):
    """A step of `analyze.sh` that fails after printing leaves the report it would write as it was, and the script
    stops there: no half-written interaction.txt."""
    study = tmp_path / "results" / "stored-noise"
    (study / "analysis").mkdir(parents=True)
    (study / "interaction.py").write_text("print('H2: D = half of it')\nraise SystemExit(1)\n")
    (study / "analysis" / "interaction.txt").write_text("the old report\n")
    result = run_stored_noise_analysis(tmp_path, [f"runs/run{seed}" for seed in range(22)])
    assert result.returncode == 1
    assert (study / "analysis" / "interaction.txt").read_text() == "the old report\n"
    assert not (study / "analysis" / "power-achieved.txt").exists()


def test_stored_noise_probe_table_waits_for_the_issue_probes(tmp_path):
    """With 5 of the issue's 6 probe runs in, and a pebble_repeat run beside them, `analyze.sh` writes the primary
    analysis and says how many probes are in, but no probes' table."""
    study = tmp_path / "results" / "stored-noise"
    study.mkdir(parents=True)
    for name in ("interaction.py", "power.py"):
        (study / name).write_text(f"print('{name} ran')\n")
    probes = [("r2n_pebble_reward_only", 1), ("r2n_pebble_reward_only", 2), ("r2n_pebble_reward_only", 3),
              ("r2n_pebble_agent_as_reward", 1), ("r2n_pebble_agent_as_reward", 2), ("pebble_repeat", 1)]
    result = run_stored_noise_analysis(tmp_path, [f"runs/run{seed}" for seed in range(22)] + [
        f"probes/{method}__cheetah-run__noise0.9__budget1000__seed{seed}" for method, seed in probes])
    assert result.returncode == 0, result.stderr
    assert result.stdout.splitlines() == ["interaction.py ran", "power.py ran", "the probes: 5 of the 6 runs of "
                                          "r2n_pebble_reward_only and r2n_pebble_agent_as_reward are in; their table "
                                          "comes when all are"]
    assert not (study / "analysis-probes").exists()


@pytest.mark.parametrize("log_dirs, output_dir, baseline, baseline_for", [
    (("results/cheetah-study",), "results/cheetah-study/analysis", "pebble",
     ("r2n_pebble=pebble", "sac=sac", "anf_sac=sac")),
    (("results/early-stop",), "results/early-stop/analysis", "pebble_no_early_stop", ()),
    (("results/early-stop", "results/cpu-study/r2n_pebble__cartpole-swingup__noise0.9__budget400__seed*"),
     "results/early-stop/analysis-h2", "r2n_pebble", ("pebble_no_early_stop=pebble_no_early_stop",)),
    pytest.param(("results/stored-noise/runs",), "results/stored-noise/analysis", "pebble",
                 ("r2n_pebble_stored_noise=pebble_stored_noise", "sac_stored_noise=sac_stored_noise",
                  "anf_sac_stored_noise=sac_stored_noise"),
                 marks=pytest.mark.skipif(not os.path.exists(STORED_NOISE_TABLE),
                                          reason="the stored-noise study's runs are under way")),
    pytest.param(("results/cheetah-study", "results/stored-noise/probes"), "results/stored-noise/analysis-probes",
                 "pebble", (), marks=pytest.mark.skipif(not os.path.exists(PROBES_TABLE),
                                                        reason="the stored-noise study's probes are under way")),
    pytest.param(("results/stored-table/runs",), "results/stored-table/analysis", "pebble",
                 ("r2n_pebble_stored_noise=pebble_stored_noise",),
                 marks=pytest.mark.skipif(not os.path.exists(STORED_TABLE_ANALYSIS),
                                          reason="no stored-table primary run is in yet")),
])
def test_committed_study_tables_regenerate_from_the_committed_runs(tmp_path, log_dirs, output_dir, baseline,
                                                                   baseline_for):
    """The studies' analyze.py commands (README, PROTOCOL.md), rerun on the committed event files, give the committed
    primary table: every number the README's readings quote (means, SEs, p-values, the bootstrap CI) comes from the
    runs in the repo."""
    dirs = tuple(path for pattern in log_dirs for path in sorted(glob.glob(os.path.join(ROOT, pattern))))
    assert analyze.main(analyze.Args(log_dirs=dirs, output_dir=str(tmp_path), baseline=baseline,
                                     baseline_for=baseline_for, primary_last=3, plots=False)) == 0
    with open(os.path.join(ROOT, output_dir, "primary.csv")) as f:
        committed = list(csv.DictReader(f))
    with open(tmp_path / "primary.csv") as f:
        regenerated = list(csv.DictReader(f))
    assert [row["method"] for row in regenerated] == [row["method"] for row in committed]
    for new, old in zip(regenerated, committed):
        assert new["seeds"] == old["seeds"] and new["seed_list"] == old["seed_list"], new["method"]
        for column in ("mean", "se", "p_value", "perm_p", "diff", "ci_low", "ci_high"):
            if old[column] == "":
                assert new[column] == "", (new["method"], column)
            elif math.isnan(float(old[column])):  # a statistic undefined at so few seeds (one seed's SE)
                assert math.isnan(float(new[column])), (new["method"], column, new[column])
            else:
                assert math.isclose(float(new[column]), float(old[column]), rel_tol=1e-9, abs_tol=1e-9), \
                    (new["method"], column, new[column], old[column])


# Fields of a run's hyperparameter table that say where and when it ran, not what it computed: the script's own
# folder (`noise_histograms` is compared by file name), and the flags that only say when `state.pt` is written.
WHERE_AND_WHEN = ("state_minutes", "checkpoint_freq")


def recorded_hparams(folder: str) -> dict:
    """The hyperparameter table of a committed run: its first event file's, read up to it (the scripts write it
    first; a resumed run's later files have none)."""
    from tensorboard.backend.event_processing.event_file_loader import EventFileLoader

    paths = sorted(glob.glob(os.path.join(folder, "events.out.tfevents.*")), key=analyze.natural_order)
    for event in EventFileLoader(paths[0]).Load():
        for value in event.summary.value:
            if value.tag.startswith("hyperparameters"):
                return analyze.parse_hparams(value.tensor.string_val[0].decode())
    raise AssertionError(f"{paths[0]}: no hyperparameter table")


def preset_differences(preset: str, folder: str) -> list:
    """Where the command that `preset` gives at HEAD for the committed run in `folder`, parsed by its script, differs
    from the hyperparameters the run recorded. A flag the scripts gained after the run counts at its value then
    (`analyze.ADDED_FLAG_DEFAULTS`: before `--noise-resample`, the noise was redrawn)."""
    import tyro

    (run,) = [r for r in benchmark.expand(benchmark.Args(preset=preset)) if r.run_id == os.path.basename(folder)]
    module = importlib.import_module(os.path.basename(run.command[1])[:-3])
    args = module.ene.suite_settings(tyro.cli(module.Args, args=list(run.command[2:])))
    module.validate_args(args)
    recorded = {**{k: v for k, v in analyze.ADDED_FLAG_DEFAULTS.items() if k in vars(args)},
                **recorded_hparams(folder)}
    differ = []
    for key, value in vars(args).items():
        if key in WHERE_AND_WHEN or key not in recorded:
            continue
        now, then = analyze.parse_value(str(value)), recorded[key]
        if key == "noise_histograms" and now is not None and then is not None:
            now, then = os.path.basename(now), os.path.basename(then)
        if now != then:
            differ.append(f"{key}: {now!r} at HEAD, {then!r} recorded")
    return differ


def committed_runs() -> list:
    """(preset, folder) of every committed run that has a `done` file, by the preset whose results folder holds it."""
    return [(preset, os.path.dirname(done)) for preset, results in sorted(benchmark.RESULTS.items())
            for done in sorted(glob.glob(os.path.join(ROOT, results, "*", "done")))]


@needs_analysis
def test_every_committed_run_is_its_preset_at_head():
    """Every committed study run, rerun from its preset at HEAD (`--dry-run`'s command), is the run it was: its
    command, parsed by its script, gives every hyperparameter the run recorded, the noise variant included. So a
    change of a default that a preset does not pin fails here, and every `done` file under `results/` belongs to a
    preset's results folder."""
    sys.path.insert(0, ROOT)
    runs = committed_runs()
    every_done = {os.path.dirname(p) for p in glob.glob(os.path.join(ROOT, "results", "**", "done"), recursive=True)}
    assert every_done == {folder for _, folder in runs}, "a committed run that no preset's results folder holds"
    failures = {os.path.relpath(folder, ROOT): d for preset, folder in runs if (d := preset_differences(preset, folder))}
    assert not failures, failures


@needs_analysis
def test_a_preset_that_loses_its_variant_flag_no_longer_reproduces_its_runs(monkeypatch):
    """The check above can fail: without its `--noise-resample`, the cheetah study's preset gives the stored
    environment, which its committed runs never saw."""
    sys.path.insert(0, ROOT)
    folder = os.path.join(ROOT, "results", "cheetah-study", "pebble__cheetah-run__noise0.9__budget1000__seed1")
    assert preset_differences("cheetah-study", folder) == []
    unpinned = tuple(part._replace(flags=tuple(f for f in part.flags if f != "--noise-resample"))
                     for part in benchmark.PRESETS["cheetah-study"])
    monkeypatch.setitem(benchmark.PRESETS, "cheetah-study", unpinned)
    assert preset_differences("cheetah-study", folder) == ["noise_resample: False at HEAD, True recorded"]


@needs_analysis
def test_stored_table_pilot_decisions_follow_the_protocol_rules(tmp_path, monkeypatch):
    """results/stored-table/power.py on synthetic pilot runs: rule 1 (learns: twice the first evaluation and 50 above
    it), rule 3 (the larger CV), rule 5 (seeds and powered or exploratory), rule 6 (cartpole's length), and a task whose
    runs are not all in is named, not decided."""
    spec = importlib.util.spec_from_file_location("stored_table_power",
                                                  os.path.join(ROOT, "results", "stored-table", "power.py"))
    power = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(power)
    monkeypatch.setattr(power, "PILOT", str(tmp_path))
    steps = list(range(10_000, 250_001, 10_000))
    flat = lambda first, end: [first] + [end] * (len(steps) - 1)  # noqa: E731 (reached by step 20 000)
    runs = {("pebble_stored_noise", 901): flat(100.0, 300.0), ("pebble_stored_noise", 902): flat(100.0, 500.0),
            ("r2n_pebble_stored_noise", 901): flat(100.0, 600.0), ("sac_stored_noise", 901): flat(100.0, 180.0),
            ("anf_sac_stored_noise", 901): flat(300.0, 700.0)}
    rounds = [10_000 + 1_200 * i for i in range(100)]  # the last at 128 800
    labeled = {key: [(step, 4.0 * (i + 1)) for i, step in enumerate(rounds)] for key in runs if "pebble" in key[0]}
    for (method, seed), returns in runs.items():
        folder = power.run_folder("cartpole-swingup", method, seed)
        write_run(os.path.dirname(folder), "cartpole-swingup", 0.9, 400, method, seed, returns, steps=steps,
                  labeled=labeled.get((method, seed), ()))
        os.replace(os.path.join(os.path.dirname(folder), f"cartpole-swingup__{method}__{seed}__100"), folder)
        open(os.path.join(folder, "done"), "w").close()
    lines = power.report("cartpole-swingup", 0.315)
    assert "| sac_stored_noise seed 901 | 100.0 | 180.0 | no |" in lines  # 180 < 2 x 100
    assert "| anf_sac_stored_noise seed 901 | 300.0 | 700.0 | yes |" in lines
    assert "- Stop rule (2): anf_sac_stored_noise learns." in lines
    cv = np.std([300.0, 500.0], ddof=1) / 400.0  # 0.354 > 0.315: the pilot's
    assert f"- Spread (3): pilot CV {cv:.3f} (PEBBLE 300.0 and 500.0), stored-noise study CV 0.315: CV = {cv:.3f}." in lines
    d = (716.89 / 660.48 - 1) / (2 * cv)
    assert analyze.power(d, 1.0, 10) < 0.5  # cartpole's +8.5%: exploratory, 8 seeds
    assert f"- Seeds (5): 8 per arm, power {analyze.power(d, 1.0, 8):.2f}: exploratory." in lines
    assert "- Length (6): 150000 steps" in lines
    assert "- Feedback (7): pebble_stored_noise seed 902: 400 of 400 labels in 100 rounds (0 short), the last at step " \
        "128800." in lines and lines[-1] == "- Feedback (7): unchanged."
    one_short = [(step, labels - 1 if step >= 50_000 else labels) for step, labels in labeled[("pebble_stored_noise", 901)]]
    folder = power.run_folder("cartpole-swingup", "pebble_stored_noise", 901)
    assert power.feedback_used(folder, 400) == (400, 100, 0, 128_800)
    for file in glob.glob(os.path.join(folder, "events.out.tfevents.*")):
        os.remove(file)
    write_run(folder, "cartpole-swingup", 0.9, 400, "pebble_stored_noise", 901, runs[("pebble_stored_noise", 901)],
              steps=steps, labeled=one_short)  # a round that labels 3 of its 4 queries: 399 labels
    for file in glob.glob(os.path.join(folder, "*", "events.out.tfevents.*")):
        os.replace(file, os.path.join(folder, os.path.basename(file)))
    assert power.feedback_used(folder, 400) == (399, 100, 1, 128_800)
    assert power.report("cartpole-swingup", 0.315)[-1] == "- Feedback (7): a run could not use it: part 2 says what changes."
    assert power.seeds_for(1.4) == (8, analyze.power(1.4, 1.0, 8), "powered")  # 8 already reach 0.8
    assert power.seeds_for(1.25)[::2] == (9, "powered")
    assert power.seeds_for(0.9)[::2] == (10, "powered")  # 0.8 out of reach, 10 above 0.5
    os.remove(os.path.join(power.run_folder("cartpole-swingup", "sac_stored_noise", 901), "done"))
    assert power.report("cartpole-swingup", 0.315) == [
        "## cartpole-swingup: 4 of 5 pilot runs are in (missing: sac_stored_noise__cartpole-swingup__noise0.9__budgetnone"
        "__seed901)"]


def stored_table_module(name):
    """results/stored-table/{name}.py, imported (table.py imports power.py beside it)."""
    sys.path.insert(0, os.path.join(ROOT, "results", "stored-table"))
    spec = importlib.util.spec_from_file_location(f"stored_table_{name}",
                                                  os.path.join(ROOT, "results", "stored-table", f"{name}.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@needs_analysis
def test_stored_table_rows_from_synthetic_pilot_and_primary_runs(tmp_path, monkeypatch):
    """table.py: a task's row waits for its pilot, then for all its primary runs, then gives analyze.py's statistics
    and the power for the pilot's effect of interest; once every pilot is in, Holm's correction runs over this study's
    powered tasks only (not cheetah-run's, its own study's test, nor an exploratory task)."""
    table = stored_table_module("table")
    power = table.power
    monkeypatch.setattr(power, "PILOT", str(tmp_path / "pilot"))
    monkeypatch.setattr(table, "RUNS", str(tmp_path / "runs"))
    monkeypatch.setattr(power, "stored_noise_cv", lambda: 0.315)
    steps = list(range(10_000, 250_001, 10_000))
    flat = lambda first, end: [first] + [end] * (len(steps) - 1)  # noqa: E731

    def run(folder, task, method, seed, end):
        noise, budget = table.TASKS[task][:2]
        budget_id = "none" if method.startswith(("sac", "anf_sac")) else budget
        name = f"{method}__{task}__noise{noise:g}__budget{budget_id}__seed{seed}"
        os.makedirs(folder, exist_ok=True)
        written = write_run(folder, task, noise, budget, method, seed, flat(100.0, end), steps=steps,
                            seconds_per_step=0.02 if method.startswith("r2n") else 0.01)  # 2 500 s or 5 000 s
        os.replace(written, os.path.join(folder, name))
        open(os.path.join(folder, name, "done"), "w").close()

    task = "quadruped-walk"  # d = 0.668 / (2 x 0.315) = 1.06: powered
    assert next(r for r in table.rows() if r["task"] == task)["plan"] is None  # the pilot is not in
    pilot = (("pebble_stored_noise", 901, 300.0), ("pebble_stored_noise", 902, 340.0),
             ("r2n_pebble_stored_noise", 901, 400.0), ("sac_stored_noise", 901, 200.0),
             ("anf_sac_stored_noise", 901, 500.0))
    for method, seed, end in pilot:
        run(str(tmp_path / "pilot"), task, method, seed, end)
    plan = power.plan(task, 0.315)
    assert plan["kind"] == "powered" and plan["effect"] == pytest.approx((309.33 / 185.41 - 1) / 2 * 320.0)
    pebble = [250.0 + 10 * s for s in range(1, plan["n"] + 1)]
    r2n = [300.0 + 12 * s for s in range(1, plan["n"] + 1)]
    for seed, (p, r) in enumerate(zip(pebble, r2n), start=1):
        run(str(tmp_path / "runs"), task, "pebble_stored_noise", seed, p)
        if seed > 1:
            run(str(tmp_path / "runs"), task, "r2n_pebble_stored_noise", seed, r)
    row = next(r for r in table.rows() if r["task"] == task)
    assert "arms" not in row and row["runs_in"] == 2 * plan["n"] - 1
    assert f"| {2 * plan['n'] - 1} of {2 * plan['n']} runs in |" in "\n".join(table.table_lines([row]))
    run(str(tmp_path / "runs"), task, "r2n_pebble_stored_noise", 1, r2n[0])
    row = next(r for r in table.rows() if r["task"] == task)
    assert row["welch"] == analyze.welch_p(np.array(r2n), np.array(pebble))
    assert row["ci"] == analyze.bootstrap_ci(np.array(r2n), np.array(pebble))
    sd = np.sqrt((np.var(r2n, ddof=1) + np.var(pebble, ddof=1)) / 2)
    assert row["power"] == pytest.approx(analyze.power(plan["effect"], sd, plan["n"]))
    assert "holm" not in row  # the other tasks' pilots are not in: Holm's family is not known yet
    line = table.table_lines([row])[-1]
    pebble_cell = f"| {np.mean(pebble):.1f} ± {np.std(pebble, ddof=1) / np.sqrt(plan['n']):.1f} ({plan['n']}) |"
    assert pebble_cell in line
    assert row["hours"] == pytest.approx({"pebble_stored_noise": 2500 / 3600, "r2n_pebble_stored_noise": 5000 / 3600},
                                         rel=1e-3)
    short = table.table_lines([row], table.SHORT)
    assert len(short[-1].split("|")) == len(table.SHORT) + 2 and pebble_cell in short[-1]
    assert short[0] == "| " + " | ".join(table.SHORT) + " |" and "permutation p" not in short[0]
    assert table.holm({"a": 0.01, "b": 0.04, "c": 0.03}) == pytest.approx({"a": 0.03, "b": 0.06, "c": 0.06})
    for other in ("cartpole-swingup", "walker-walk"):  # every pilot in: cartpole-swingup's decides it exploratory
        for method, seed, end in pilot:
            run(str(tmp_path / "pilot"), other, method, seed, end)
    decided = power.plan  # walker-walk decided powered at 3 seeds: a family of two powered tasks
    monkeypatch.setattr(power, "plan", lambda t, cv: dict(decided(t, cv), kind="powered", n=3)
                        if t == "walker-walk" else decided(t, cv))
    for seed, (p, r) in enumerate(((200.0, 260.0), (220.0, 250.0), (240.0, 300.0)), start=1):
        run(str(tmp_path / "runs"), "walker-walk", "pebble_stored_noise", seed, p)
        run(str(tmp_path / "runs"), "walker-walk", "r2n_pebble_stored_noise", seed, r)
    out = {r["task"]: r for r in table.rows()}
    assert out["cheetah-run"]["welch"] < 0.05 and out["cartpole-swingup"]["plan"]["kind"] == "exploratory"
    family = table.holm({t: out[t]["welch"] for t in ("quadruped-walk", "walker-walk")})
    assert {t: r["holm"] for t, r in out.items() if "holm" in r} == family
    assert family["quadruped-walk"] == pytest.approx(2 * out["quadruped-walk"]["welch"])  # the smaller of two p
    quadruped = table.table_lines([out["quadruped-walk"]])[-1]
    assert f"| {analyze.p_text(out['quadruped-walk']['welch'])} ({analyze.p_text(family['quadruped-walk'])}) |" in quadruped
    for name, path in (("README", "study.md"), ("ROOT_README", "root.md")):  # the blocks, written then checked
        markers = table.MARKERS if name == "README" else table.ROOT_MARKERS
        (tmp_path / path).write_text(f"# A page\n\n{markers[0]}\nold\n{markers[1]}\n\nAfter.\n")
        monkeypatch.setattr(table, name, str(tmp_path / path))
    monkeypatch.setattr(table, "STUDY", str(tmp_path))
    monkeypatch.setattr(sys, "argv", ["table.py"])
    table.main()
    root = (tmp_path / "root.md").read_text()
    assert "\n".join(table.table_lines(table.rows(), table.SHORT)) in root and root.endswith("\n\nAfter.\n")
    monkeypatch.setattr(sys, "argv", ["table.py", "--check"])
    table.main()
    (tmp_path / "root.md").write_text(root.replace(" | powered |", " | exploratory |"))
    with pytest.raises(SystemExit, match="not what the runs give: .*root.md"):
        table.main()


def test_stored_table_curves_keep_every_step_a_run_reached():
    """An arm's curve in curves.png: a run stopped by a non-finite value counts until its stop and does not shorten
    the others; its non-finite evaluation is left out."""
    table = stored_table_module("table")
    steps = np.array([10, 20, 30])
    curves = [(steps, np.array([1.0, 2.0, 3.0])), (steps, np.array([3.0, 4.0, 7.0])), (steps[:2], np.array([5.0, np.inf]))]
    at, mean, se = table.arm_curve(curves)
    assert list(at) == [10, 20, 30]
    assert mean == pytest.approx([3.0, 3.0, 5.0])
    assert se == pytest.approx([np.std([1, 3, 5], ddof=1) / np.sqrt(3), np.std([2, 4], ddof=1) / np.sqrt(2),
                                np.std([3, 7], ddof=1) / np.sqrt(2)])


def test_stored_table_table_is_what_the_committed_runs_give():
    """The committed table.md, the study README's table block, the root README's short form and the pilot's decisions
    (pilot-decisions.md) regenerate from the committed event files."""
    study = os.path.join(ROOT, "results", "stored-table")
    subprocess.run([sys.executable, os.path.join(study, "table.py"), "--check"], check=True, cwd=ROOT,
                   capture_output=True, text=True)
    decisions = subprocess.run([sys.executable, os.path.join(study, "power.py")], check=True, cwd=ROOT,
                               capture_output=True, text=True).stdout
    assert decisions == open(os.path.join(study, "pilot-decisions.md")).read()


def test_stored_table_analysis_is_committed_with_the_first_primary_run():
    """Once a primary run of the stored-table study is committed, so is `analyze.sh`'s analysis/ (the regeneration
    test above then checks it against every committed run)."""
    landed = glob.glob(os.path.join(ROOT, "results", "stored-table", "runs", "*", "done"))
    assert not landed or os.path.exists(STORED_TABLE_ANALYSIS), \
        f"{len(landed)} primary runs are in: run `bash results/stored-table/analyze.sh` and commit analysis/"


@needs_analysis
def test_stored_table_preset_runs_what_the_pilot_decided():
    """The primary preset holds, per task part 2 has decided, seeds 1 to the n of the task's pilot (power.py) of both
    PbRL arms, in the stored ENE at the pilot's scale and feedback schedule, into the folder table.py reads."""
    sys.path.insert(0, ROOT)
    power = stored_table_module("power")
    study_cv = power.stored_noise_cv()
    assert list(benchmark.STORED_TABLE_SEEDS) == [t for t in power.TASKS if t in benchmark.STORED_TABLE_SEEDS]
    pilot = benchmark.STORED_TABLE_PILOT[0]
    for part in benchmark.PRESETS["stored-table"]:
        [(task, noise, budget)] = part.settings
        assert not power.missing_runs(task), f"{task} is in the preset before its pilot is in"
        assert (noise, budget) == power.TASKS[task][:2]
        assert part.seeds == tuple(range(1, power.plan(task, study_cv)["n"] + 1))
        assert part.methods == ("pebble_stored_noise", "r2n_pebble_stored_noise")
        assert (part.flags, part.feedback_flags) == (pilot.flags, pilot.feedback_flags)
    assert [p.settings[0][0] for p in benchmark.PRESETS["stored-table"]] == list(benchmark.STORED_TABLE_SEEDS)
    assert os.path.join(ROOT, benchmark.RESULTS["stored-table"]) == stored_table_module("table").RUNS


def test_typed_command_makes_the_repository_paths_relative():
    """A `done` file's command runs anywhere: `python`, the script and any path under the repository relative to it;
    a path outside the repository stays as it is."""
    command = ("/opt/venv/bin/python", "/repo/r2n_pebble.py", "--seed", "3", "--noise-histograms",
               "/repo/results/imitate/h.npz", "--preferences", "/elsewhere/prefs", "--exp-name", "a b")
    assert benchmark.typed_command(command, root="/repo") == (
        "python r2n_pebble.py --seed 3 --noise-histograms results/imitate/h.npz --preferences /elsewhere/prefs "
        "--exp-name 'a b'")
    assert benchmark.typed_command(("/usr/bin/python3", "/repository/x.py"), root="/repo") == "python /repository/x.py"


def test_cpu_of_names_a_model():
    """The CPU model every `done` file records: a non-empty line."""
    model = benchmark.cpu_of()
    assert model and "\n" not in model


WHICH_SPARSITY = os.path.join(ROOT, "results", "which-sparsity")


def load_study_module(name: str):
    spec = importlib.util.spec_from_file_location(f"which_sparsity_{name}", os.path.join(WHICH_SPARSITY, f"{name}.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_which_sparsity_preset_is_the_protocols_runs_in_its_order():
    """Issue 69's preset: 54 runs, the DST ablation's arms (with R2N-PEBBLE's seeds 9-10) first, then L1 and
    DropConnect, then SET and Static; every arm stores the noise at the stored-noise study's scale."""
    runs = benchmark.expand(benchmark.Args(preset="which-sparsity"))
    assert len(runs) == 54
    stages = [{r.method for r in runs[:22]}, {r.method for r in runs[22:38]}, {r.method for r in runs[38:]}]
    assert stages == [
        {"r2n_pebble_agent_only_stored_noise", "r2n_pebble_reward_only_stored_noise", "r2n_pebble_stored_noise"},
        {"l1_pebble_stored_noise", "dropconnect_pebble_stored_noise"},
        {"set_pebble_stored_noise", "static_pebble_stored_noise"}]
    assert sorted(r.seed for r in runs if r.method == "r2n_pebble_stored_noise") == [9, 10]
    assert [r.seed for r in runs[:22]] == sorted(r.seed for r in runs[:22])  # seed-major within a stage
    (reference,) = [r for r in benchmark.expand(benchmark.Args(preset="stored-noise"))
                    if r.run_id == "r2n_pebble_stored_noise__cheetah-run__noise0.9__budget1000__seed8"]
    (new,) = [r for r in runs if r.run_id == reference.run_id.replace("seed8", "seed9")]
    same = lambda command, seed: [w for w in command if "seed" not in w and w != seed]  # noqa: E731
    assert same(new.command, "9") == same(reference.command, "8")
    for run in runs:
        assert "--no-noise-resample" in run.command and run.command[run.command.index("--total-timesteps") + 1] == "250000"
    flags = {r.method: r.command for r in runs}
    assert "--no-sparse-reward" in flags["r2n_pebble_agent_only_stored_noise"]
    assert "--no-sparse-agent" in flags["r2n_pebble_reward_only_stored_noise"]


@needs_analysis
def test_which_sparsity_like_with_like_check(tmp_path):
    """The committed check says today's code computes what e6130f6 computed; a changed query round or scalar fails it."""
    module = load_study_module("like_with_like")
    assert all(same for _, same in (module.compare(arm) for arm in module.ARMS))
    shutil.copytree(module.FOLDER, tmp_path / "copy")
    module.FOLDER = str(tmp_path / "copy")
    digests = tmp_path / "copy" / "today" / "pebble_stored_noise" / "queries.json"
    changed = json.loads(digests.read_text())
    changed["3"]["labels"] = "0" * 64
    digests.write_text(json.dumps(changed))
    text, same = module.compare("pebble_stored_noise")
    assert not same and "1 differ" in text, text
    [events] = glob.glob(str(tmp_path / "copy" / "today" / "r2n_pebble_stored_noise" / "events.*"))
    os.remove(events)
    writer = SummaryWriter(str(tmp_path / "copy" / "today" / "r2n_pebble_stored_noise"))
    for tag in ("losses/qf1_loss", analyze.EVAL_TAG):
        writer.add_scalar(tag, 1.0, 10_000)
    writer.close()
    text, same = module.compare("r2n_pebble_stored_noise")
    assert not same and "losses/qf1_loss" in text, text


@needs_analysis
def test_which_sparsity_power_is_what_the_protocol_quotes():
    """PROTOCOL.md's power table comes from power.py on the committed reference arms."""
    module = load_study_module("power")
    r2n = module.arm_values(module.REFERENCE, "r2n_pebble_stored_noise")
    pebble = module.arm_values(module.REFERENCE, "pebble_stored_noise")
    sd = module.pooled_sd([r2n, pebble])
    assert (len(r2n), len(pebble), round(sd, 1), round(r2n.mean(), 1)) == (8, 8, 57.0, 258.7)
    protocol = open(os.path.join(WHICH_SPARSITY, "PROTOCOL.md")).read()
    effect = lambda arm: (1 - module.ARMS[arm][0] / module.PAPER_R2N) * r2n.mean()
    planned = {arm: spec[3] for arm, spec in module.ARMS.items()}
    holm = module.holm_power(r2n.mean(), sd, 10, planned)
    for arm, row in (("r2n_pebble_reward_only_stored_noise", "H1 reward-only"),
                     ("dropconnect_pebble_stored_noise", "H2 DropConnect"), ("l1_pebble_stored_noise", "H3 L1")):
        bound = module.power(effect(arm), sd, planned[arm], 10, 0.05 / 3)
        assert f"| {row} | -{effect(arm):.1f} | {planned[arm]} vs 10 | {bound:.2f}, {holm[arm]:.2f} |" in protocol, row
    reward_only, agent_only = effect("r2n_pebble_reward_only_stored_noise"), effect("r2n_pebble_agent_only_stored_noise")
    assert holm["r2n_pebble_reward_only_stored_noise"] >= module.power(reward_only, sd, 10, 10, 0.05 / 3)
    agent = module.power(agent_only, sd, 10, 10)
    assert f"| E1 agent-only (alpha 0.05) | -{agent_only:.1f} | 10 vs 10 | {agent:.2f} |" in protocol
