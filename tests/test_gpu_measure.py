"""results/gpu-speed/measure.py, the helper of issue 32's prepared GPU measurement: steady-state rates from the wall
times of event-file points (synthetic runs with known rates), a window's shares from a run's log, the exactness
table from a JUnit report, and the step items of one tiny real run on the CPU."""
import csv
import json
import os
import subprocess
import sys

import pytest
from torch.utils.tensorboard import SummaryWriter

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from test_scripts import ROOT  # noqa: E402

HELPER = os.path.join(ROOT, "results", "gpu-speed", "measure.py")
sys.path.insert(0, os.path.dirname(HELPER))
import measure  # noqa: E402


# a tiny cartpole run: learned-reward steps from step 200, no evaluation before the end
TINY_RUN = ("--env-id", "cartpole-swingup", "--noise", "0.9", "--learning-starts", "100", "--unsup-steps", "100",
            "--episode-length", "100", "--eval-freq", "10000", "--eval-episodes", "1", "--hidden-dim", "32",
            "--batch-size", "32", "--reward-hidden-dim", "16", "--reward-epochs", "2", "--segment-size", "20",
            "--max-feedback", "10", "--queries-per-round", "5", "--no-cuda")


def instrumented(kind, out, first, last, script, args):
    """The helper's `items` or `lines` run of `script`, in `out`'s folder."""
    subprocess.run([sys.executable, HELPER, kind, str(out), "--from-step", str(first), "--to-step", str(last),
                    os.path.join(ROOT, script), *args], cwd=os.path.dirname(out), capture_output=True, text=True,
                   check=True, env=dict(os.environ, OMP_NUM_THREADS="1", PYTHONWARNINGS="ignore"), timeout=120)


def write_run(folder, points, tag="losses/qf_loss"):
    writer = SummaryWriter(str(folder))
    for step, wall in points:
        writer.add_scalar(tag, 1.0, step, walltime=wall)
    writer.close()


def helper(*args):
    return subprocess.run([sys.executable, HELPER, *map(str, args)], capture_output=True, text=True, check=True)


def test_rates_of_runs_at_once_are_summed_and_timed_over_their_overlap(tmp_path):
    # run1: 100 steps/s from t=100; run2: 50 steps/s from t=100.5; each logs every 100 steps from step 2100
    write_run(tmp_path / "x2" / "runs" / "run1", [(s, 100 + (s - 2200) / 100) for s in range(2100, 2600, 100)])
    write_run(tmp_path / "x2" / "runs" / "run2", [(s, 100.5 + (s - 2200) / 50) for s in range(2100, 2600, 100)])
    helper("rates", tmp_path / "x2", tmp_path / "aggregate.csv", "--name", "x2", "--mps", "yes",
           "--from-step", 2200, "--to-step", 2500)
    (row,) = csv.DictReader(open(tmp_path / "aggregate.csv"))
    assert row["window"] == "2200-2500" and row["runs_in_window"] == "2" and row["mps"] == "yes"
    assert float(row["sum_steps_per_s"]) == 150.0
    # both in the window from t=100.5 (run2's start) to t=103 (run1's end): 250 + 125 steps in 2.5 s
    assert float(row["overlap_seconds"]) == 2.5
    assert float(row["overlap_steps_per_s"]) == 150.0
    # both logging from t=99 (run1's first point) to t=103 (run1's last): run1 400 steps, run2 200 (2125 to 2325)
    assert float(row["alive_seconds"]) == 4.0
    assert float(row["alive_steps_per_s"]) == 150.0
    assert row["per_run"] == "run1:100.0 run2:50.0"


def test_a_run_cut_off_inside_the_window_shortens_it_for_all():
    runs = {"a": [(s, s / 100) for s in range(2200, 2600, 100)], "b": [(s, s / 25) for s in range(2200, 2500, 100)]}
    result = measure.window_rates(runs, 2200, 2500)
    assert result["last"] == 2400
    assert result["per_run"] == {"a": pytest.approx(100.0), "b": pytest.approx(25.0)}
    # windows that never overlap in wall time: summed, but no rate of the runs together
    result = measure.window_rates({"a": [(1, 0.0), (2, 1.0)], "b": [(1, 5.0), (2, 6.0)]}, 1, 2)
    assert result["sum"] == 2.0 and result["overlap_rate"] is None and result["alive_rate"] is None


def test_window_shares_of_evaluations_state_writes_and_feedback_rounds(tmp_path):
    # 100 steps a second, except a 3 s evaluation before step 5000, a 2 s state write after step 6000 and a 4 s
    # feedback round at step 7000: each adds its seconds to the interval that holds it
    points, wall = [], 0.0
    for step in range(3000, 9001, 500):
        if step > 3000:
            wall += 5.0 + {5000: 3.0, 6000: 2.0, 7000: 4.0}.get(step, 0.0)
        points.append((step, wall))
    write_run(tmp_path / "runs" / "window", points)
    log = ("step=3000 eval_return=1.00 SPS=9 eval_seconds=7.00 feedback=0/10 labels=0\n"
           "step=5000 eval_return=1.00 SPS=9 eval_seconds=3.00 feedback=0/10 labels=0\n"
           "state saved after step 6000: 0.92 GB in 2.0 s\n")
    (tmp_path / "window.log").write_text(log)
    helper("window", tmp_path / "runs" / "window", tmp_path / "window.log", tmp_path / "window.json",
           "--from-step", 3000, "--to-step", 9000, "--feedback-steps", 7000, 12000)
    result = json.load(open(tmp_path / "window.json"))
    assert result["seconds"] == 69.0
    assert result["evaluations"] == 1 and result["eval_seconds"] == 3.0  # the one at 3000 is not inside
    assert result["eval_share"] == round(3 / 69, 4) and result["state_share"] == round(2 / 69, 4)
    assert result["feedback_rounds_seconds_estimate"] == 4.0
    assert result["steps_per_s_without_evals_states"] == round(6000 / 64, 4)


def test_exact_table_from_a_junit_report(tmp_path):
    (tmp_path / "r.xml").write_text(
        '<testsuites><testsuite name="pytest">'
        '<testcase classname="t" name="test_captured_run_equals_eager[pebble.py]"/>'
        '<testcase classname="t" name="test_captured_run_equals_eager[surf.py]">'
        '<failure message="AssertionError: surf.py: losses/qf_loss&#10;more">trace</failure></testcase>'
        '<testcase classname="t" name="test_x"><skipped message="no GPU"/></testcase>'
        "</testsuite></testsuites>")
    result = helper("exact", tmp_path / "r.xml", tmp_path / "exact.csv")
    assert "1 passed, 1 failure, 0 error, 1 skipped" in result.stdout
    rows = list(csv.reader(open(tmp_path / "exact.csv")))
    assert rows[2] == ["test_captured_run_equals_eager[surf.py]", "failure", "AssertionError: surf.py: losses/qf_loss"]


def test_items_of_a_tiny_run_on_the_cpu(tmp_path):
    """Steps 250 to 300 of a tiny run: no evaluation or feedback round inside, so every step counts; each item is
    timed once a step (the target update every second step), and the items and the rest add up to the step."""
    args = [*TINY_RUN, "--total-timesteps", "301"]
    out = tmp_path / "items.csv"
    instrumented("items", out, 250, 300, "r2n_pebble.py", args)
    text = out.read_text()
    rows = {r["item"]: r for r in csv.DictReader(line for line in text.splitlines() if not line.startswith("#"))}
    assert "# 50 plain steps from 250 to 300 (0 left out" in text
    once = ("act", "env_step", "physics_state", "reward_prediction", "buffer_write", "episode_write", "sample",
            "critic_gradients", "actor_gradients", "optimizer_step/critic", "optimizer_step/actor",
            "optimizer_step/adam (alpha)", "sac_update (all)", "store (all)", "progress", "check_finite",
            "state_due", "feedback_due", "action to host (.cpu)")
    for item in once:
        assert rows[item]["calls"] == "50", item
    assert rows["target_update"]["calls"] == "25"
    assert rows["act"]["gpu_us_mean"] == "nan"  # no GPU: host times only
    # the episode that ends at step 300: its return's tags, the reset and the new observation's copy
    assert rows["env_reset"]["calls"] == "1" and rows["writer.add_scalar"]["calls"] == "2"
    assert rows["as_tensor (obs to the device)"]["calls"] == "51"
    # the items that hold others are not summed with them
    parts = [r for name, r in rows.items() if name not in ("sac_update (all)", "store (all)", "step (whole)")]
    leaves = sum(float(r["share_of_step"]) for r in parts)
    assert leaves == pytest.approx(1.0, abs=0.002)  # each share is written to 4 places
    assert "# evaluate: 1 calls" in text  # the one at the end, after the window


def test_adam_capture_settle_step_is_where_torchs_adam_scalars_stop_changing():
    """From the settle step on, a foreach Adam step is the same whatever the step count (its float32 scalars are
    their limits), so a graph captured there replays exactly; one step earlier it is not."""
    import adam_capture
    import torch

    lr, betas = 1e-4, (0.9, 0.999)  # the scripts' agent Adams
    settle = adam_capture.settle_step(lr, *betas)
    assert 10_000 < settle < 20_000

    def step_at(t):
        """The parameters after one step at step count t, from the same state and gradient."""
        generator = torch.Generator().manual_seed(0)
        param = torch.nn.Parameter(torch.randn(1000, generator=generator))
        adam = torch.optim.Adam([param], lr=lr, betas=betas, foreach=True)
        param.grad = torch.randn(1000, generator=generator)
        adam.step()
        adam.state[param]["step"].fill_(t - 1)
        param.grad = torch.randn(1000, generator=generator)
        adam.step()
        return param.detach().clone()

    later = step_at(settle + 50_000)
    assert torch.equal(step_at(settle), later)
    assert not torch.equal(step_at(settle - 1), later)


def test_adam_capture_host_counts_move_by_one_update(tmp_path):
    """The counts an update keeps on the host: one `sac_update` moves each by one (the sparse optimisers' too), and
    writing the old values back undoes it, as after a capture."""
    import adam_capture

    sys.path.insert(0, ROOT)
    import r2n_pebble

    args = r2n_pebble.ene.suite_settings(r2n_pebble.Args(hidden_dim=16, batch_size=8))
    agent, loop = r2n_pebble.make_agent(5, 2, args, r2n_pebble.torch.device("cpu")), r2n_pebble.Loop()
    torch = r2n_pebble.torch
    batch = r2n_pebble.Batch(torch.randn(8, 5), torch.rand(8, 2), torch.randn(8), torch.randn(8, 5), torch.zeros(8),
                             torch.arange(8))
    r2n_pebble.sac_update(agent, batch, loop, args)  # Adam's state exists from here
    counts = adam_capture.HostCounts(agent, loop)
    assert len(counts.sparse) == 2 and len(counts.steps) == 12 + 6 + 1  # two critics, actor, temperature
    before = counts.read()
    r2n_pebble.sac_update(agent, batch, loop, args)
    after = counts.read()
    assert [a - b for a, b in zip(after, before)] == [1] * len(before)
    counts.write(before)
    assert counts.read() == before


def test_lines_of_a_tiny_run_on_the_cpu(tmp_path):
    """The line profile: each line of the main loop and of `sac_update` and `store` is a row, named by its text; the
    main lines and the rest add up to the step, the functions' lines being inside them."""
    args = [*TINY_RUN, "--total-timesteps", "241"]
    out = tmp_path / "lines.csv"
    instrumented("lines", out, 210, 240, "pebble.py", args)
    rows = list(csv.DictReader(line for line in out.read_text().splitlines() if not line.startswith("#")))
    names = [r["item"] for r in rows]
    assert any(n.startswith("main:") and "env.step(" in n for n in names)
    assert any(n.startswith("sac_update:") and "agent.q_optimizer.step()" in n for n in names)
    assert any(n.startswith("store:") and "episodes.add(" in n for n in names)  # under its torch.no_grad
    (step,) = [r for r in rows if r["item"] == "step (whole)"]
    assert step["calls"] == "30"
    main = [r for r in rows if r["item"].startswith("main:") or r["item"] == "other (loop body)"]
    assert sum(float(r["share_of_step"]) for r in main) == pytest.approx(1.0, abs=0.003)


def test_act_store_capture_functions_are_todays_numerics_on_the_cpu(monkeypatch):
    """The two functions the act and store graphs replay, run eagerly on the CPU, give the scripts' actions, buffers,
    episode store and generator state bit for bit; a store that skips one write is caught."""
    import act_store_capture
    import torch

    sys.path.insert(0, ROOT)
    run = lambda: act_store_capture.measure("pebble", torch.device("cpu"), 16, 50, 120, 1)  # noqa: E731
    same = run()["bitwise"]
    assert same == {"actions": True, "storage": [True] * 8, "rng": True}
    store_step = act_store_capture.Graphs.store_step

    def without_true_reward(self):
        saved = self.s.rb.true_rewards.clone()
        store_step(self)
        self.s.rb.true_rewards.copy_(saved)
    monkeypatch.setattr(act_store_capture.Graphs, "store_step", without_true_reward)
    assert run()["bitwise"]["storage"] == [True] * 4 + [False] + [True] * 3


def test_adam_capture_gathers_are_the_samples_batch():
    """The gathers that the whole-update graph holds give `ReplayBuffer.sample`'s batch, bit for bit, when the indices
    are drawn as `sample` draws them."""
    import adam_capture
    import torch

    sys.path.insert(0, ROOT)
    import pebble

    rb = pebble.ReplayBuffer(50, 5, 2, torch.device("cpu"))
    for _ in range(40):
        rb.add(torch.randn(5), torch.rand(2), torch.randn(5), False, 0.5, torch.randn(()))
    torch.manual_seed(3)
    sampled = rb.sample(8)
    torch.manual_seed(3)
    batch = adam_capture.gathered(pebble, rb, torch.randint(0, rb.size, (8,)))
    assert all(torch.equal(a, b) for a, b in zip(sampled, batch))
