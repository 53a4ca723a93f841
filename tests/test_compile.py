"""Issue 19's numerics flags on the CPU: `--compile` (torch.compile of the three SAC steps) matches eager within a
float tolerance in all 12 scripts and compiles each step once; a run records the flags and a resume that flips one
is refused; `--tf32` and `--cuda-graph` without a GPU fail with one line. (Capture: tests/test_cuda_graph.py, on a GPU.)"""
import copy
import dataclasses
import importlib
import os
import shutil
import sys
import sysconfig

import pytest
import torch

from test_layout import ORACLES, PBRL
from test_scripts import ROOT, TINY, run_script, scalars

sys.path.insert(0, ROOT)

needs_compiler = pytest.mark.skipif(
    shutil.which("cc") is None and shutil.which("gcc") is None
    or not os.path.exists(os.path.join(sysconfig.get_paths()["include"], "Python.h")),
    reason="torch.compile's CPU backend needs a C compiler and Python's headers",
)
STEPS = ("critic_gradients", "actor_gradients", "target_update")


def tiny_batch(module, step: int, obs_dim: int, act_dim: int, batch_size: int = 16):
    g = torch.Generator().manual_seed(step)
    columns = dict(
        obs=torch.randn(batch_size, obs_dim, generator=g), actions=torch.rand(batch_size, act_dim, generator=g) * 2 - 1,
        rewards=torch.randn(batch_size, generator=g), next_obs=torch.randn(batch_size, obs_dim, generator=g),
        dones=(torch.rand(batch_size, generator=g) < 0.1).float(), indices=torch.arange(batch_size),
        stds=torch.rand(batch_size, generator=g),  # RUNE: the reward ensemble's spread
    )
    return module.Batch(**{name: columns[name] for name in module.Batch._fields})


def updates(module, agent, loop, steps: range, obs_dim: int, act_dim: int, args) -> list:
    """The script's `sac_update` on the batches of `steps` (RUNE: a new bonus weight each time); the losses of each."""
    losses = []
    for step in steps:
        extra = (0.05 * 0.9**step,) if "beta" in module.sac_update.__code__.co_varnames else ()
        module.sac_update(agent, tiny_batch(module, step, obs_dim, act_dim), loop, args, *extra)
        losses.append({name: value.item() for name, value in loop.losses.items()})
    return losses


@needs_compiler
@pytest.mark.parametrize("script", PBRL + ORACLES)
def test_compiled_steps_match_eager_within_tolerance(script, monkeypatch):
    """The script's three steps, compiled as `--compile` does, against eager from the same agent: the same losses
    and parameters within float tolerance after 6 updates (topology updates included in the sparse scripts), with
    inductor's random numbers drawn as eager's, and no recompilation after the first calls."""
    torch.set_num_threads(1)
    module = importlib.import_module(script[:-3])
    obs_dim, act_dim = 6, 2
    overrides = dict(hidden_dim=32, batch_size=16)
    names = {field.name for field in dataclasses.fields(module.Args)}
    overrides.update({name: 2 for name in ("agent_topology_period", "topology_period") if name in names})
    args = module.ene.suite_settings(module.Args(**overrides))
    torch.manual_seed(0)
    eager_agent = module.make_agent(obs_dim, act_dim, args, torch.device("cpu"))
    compiled_agent = copy.deepcopy(eager_agent)
    torch.manual_seed(1)
    eager = updates(module, eager_agent, module.Loop(), range(6), obs_dim, act_dim, args)
    torch._dynamo.reset()
    for name in STEPS:
        monkeypatch.setattr(module, name, torch.compile(getattr(module, name)))
    torch.manual_seed(1)
    loop = module.Loop()
    with torch._inductor.config.patch(fallback_random=True):
        compiled = updates(module, compiled_agent, loop, range(2), obs_dim, act_dim, args)
        with torch._dynamo.config.patch(error_on_recompile=True):
            compiled += updates(module, compiled_agent, loop, range(2, 6), obs_dim, act_dim, args)
    for step, (a, b) in enumerate(zip(eager, compiled)):
        assert a.keys() == b.keys()
        for name in a:
            assert b[name] == pytest.approx(a[name], rel=1e-4, abs=1e-5), f"{script}: {name} at update {step}"
    networks = ("actor", "qf1", "qf2", "qf1_target", "qf2_target")
    for net in networks:
        for (key, p), q in zip(getattr(eager_agent, net).state_dict().items(),
                               getattr(compiled_agent, net).state_dict().values()):
            torch.testing.assert_close(q, p, rtol=1e-4, atol=1e-5, msg=f"{script}: {net}.{key}")
    torch.testing.assert_close(compiled_agent.log_alpha, eager_agent.log_alpha, rtol=1e-4, atol=1e-5)


# Every phase, shortest: 10 compiled pre-training updates from step 200, a feedback round at 210, compiled SAC updates
# on the learned reward, and an evaluation at 260.
COMPILED_RUN = ["--unsup-steps", "10", "--total-timesteps", "260", "--eval-freq", "260"]


@needs_compiler
def test_a_compiled_run_records_its_flag_and_a_resume_may_not_flip_it(tmp_path):
    result = run_script("pebble.py", TINY + COMPILED_RUN + ["--compile", "--run-name", "c", "--resumable", "--keep-state"], tmp_path)
    assert result.returncode == 0
    values = scalars(str(tmp_path / "runs" / "c"))
    assert all(torch.isfinite(torch.tensor(values["eval/episodic_return"])))
    assert values["pbrl/total_feedback"] == [5] and len(values["losses/qf1_loss"]) > 0
    refused = run_script("pebble.py", TINY + COMPILED_RUN + ["--run-name", "c", "--resumable"], tmp_path, check=False)
    assert refused.returncode == 1 and "the saved run differs in --compile True (now False)" in refused.stderr


@pytest.mark.parametrize("flag, line", [
    ("--tf32", "--tf32: TF32 matmuls need a CUDA GPU, and this run is on the CPU"),
    ("--cuda-graph", "--cuda-graph: CUDA graphs need a CUDA GPU, and this run is on the CPU"),
])
def test_gpu_flags_without_a_gpu_fail_with_one_line(flag, line, tmp_path):
    if torch.cuda.is_available():
        pytest.skip("a GPU is here")
    result = run_script("sac.py", [flag, "--total-timesteps", "10"], tmp_path, check=False)
    assert result.returncode == 1
    assert result.stderr.strip() == f"sac: error: {line}"
    assert not os.path.exists(tmp_path / "runs")
