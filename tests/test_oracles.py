"""Oracles and the imitating-noise study (spec: ALGORITHMS.md sections 1 and 5).

`sac.py` is `pebble.py` without preference learning (true reward), `anf_sac.py` is `sac.py` plus the agent half of the
R2N patch, `make_histograms.py` turns a noise-free `sac.py` checkpoint into the histograms of `--noise-type imitate`.
One pipeline, run once per module: sac.py (noise-free) and anf_sac.py (noise 0.9) at once, then the histogram command
on the SAC checkpoint, then a PEBBLE smoke run with the imitating noise those histograms define.
"""
import ast
import dataclasses
import difflib
import glob
import math
import os
import sys
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from test_scripts import (COMMON_TAGS, ROOT, TINY, check_harness_flag_stops_a_copy, check_progress,  # noqa: E402
                          run_script, scalars)

import anf_sac  # noqa: E402
import ene  # noqa: E402
import pebble  # noqa: E402
import r2n_pebble  # noqa: E402
import sac  # noqa: E402

HEADER = "# Docs: docs/NAME.md in r2n, the R2N paper's reference implementation (NAME: this file's name)"
# Tiny but complete: random steps 0-199, then one SAC update per step; evaluation and checkpoint every 500 steps;
# anf_sac: a topology update every 100 SAC steps (13 in the run).
ORACLE_TINY = [
    "--env-id", "cartpole-swingup", "--total-timesteps", "1500", "--learning-starts", "200", "--episode-length", "100",
    "--eval-freq", "500", "--eval-episodes", "2", "--hidden-dim", "32", "--batch-size", "32", "--log-freq", "100",
    "--no-cuda",
]
ORACLE_ARGS = {
    "sac.py": ORACLE_TINY + ["--noise", "0"],  # noise-free: its checkpoint feeds the histogram command
    "anf_sac.py": ORACLE_TINY + ["--noise", "0.9", "--agent-topology-period", "100"],
}
SAC_TAGS = [
    "eval/episodic_return", "charts/episodic_return", "charts/episodic_length", "charts/SPS",
    "losses/qf1_loss", "losses/qf2_loss", "losses/qf_loss", "losses/actor_loss", "losses/alpha", "losses/alpha_loss",
]
AGENT_NETS = ["actor", "qf1", "qf2"]
AGENT_SPARSE_TAGS = [f"sparse/{net}/{m}" for net in AGENT_NETS
                     for m in ("relevant_degree", "noise_degree", "relevant_active_frac", "topology_updates")]
HIST_SEED, HIST_N, HIST_EPISODE = 3, 2000, 100


def checkpoint_of(run_dir, name):
    return torch.load(os.path.join(run_dir, f"{name}.cleanrl_model"), weights_only=False)


@pytest.fixture(scope="module")
def pipeline(tmp_path_factory):
    """script -> (run dir, process result) for sac.py, anf_sac.py, make_histograms.py and pebble.py (imitate)."""
    root = tmp_path_factory.mktemp("oracles")
    out = {}
    with ThreadPoolExecutor(len(ORACLE_ARGS)) as pool:
        futures = {
            script: pool.submit(run_script, script, args + ["--exp-name", script[:-3]], root, False, True)
            for script, args in ORACLE_ARGS.items()
        }
        for script, future in futures.items():
            result = future.result()
            assert result.returncode == 0, f"{script}: {result.stderr[-3000:]}"
            (out[script],) = [(d, result) for d in glob.glob(str(root / "runs" / f"*__{script[:-3]}__*"))]
    histograms = str(root / "hist" / "cartpole.npz")
    sac_checkpoint = os.path.join(out["sac.py"][0], "sac.cleanrl_model")
    out["make_histograms.py"] = (histograms, run_script("make_histograms.py", [
        "--checkpoint", sac_checkpoint, "--output", histograms, "--num-observations", str(HIST_N),
        "--episode-length", str(HIST_EPISODE), "--seed", str(HIST_SEED),
    ], root))
    result = run_script("pebble.py", TINY + ["--noise-type", "imitate", "--noise-histograms", histograms,
                                             "--exp-name", "imitate"], root)
    (run_dir,) = glob.glob(str(root / "runs" / "*__imitate__*"))
    out["pebble.py"] = (run_dir, result)
    return out


# ---------------------------------------------------------------- oracle smoke runs


@pytest.mark.parametrize("script", list(ORACLE_ARGS))
def test_oracle_smoke_run(script, pipeline):
    run_dir, result = pipeline[script]
    values = scalars(run_dir)
    expected = SAC_TAGS + (AGENT_SPARSE_TAGS if script == "anf_sac.py" else [])
    missing = [tag for tag in expected if tag not in values]
    assert not missing, f"missing tags {missing}"
    for tag in expected:
        assert all(math.isfinite(v) for v in values[tag]), f"{tag} has non-finite values {values[tag]}"
    assert not [tag for tag in values if tag.startswith("features/")]  # --diagnostics: tests/test_harness.py
    assert not [tag for tag in values if tag.startswith("pbrl/") or tag == "losses/state_entropy_reward"]
    if script == "sac.py":
        assert not [tag for tag in values if tag.startswith("sparse/")]
    assert len(values["eval/episodic_return"]) == 3  # at 500, 1000, 1500
    assert result.stdout.count("eval_return=") == 3 and "feedback=" not in result.stdout
    check_progress(result.stdout, ("random", "SAC"))

    module = sac if script == "sac.py" else anf_sac
    checkpoint = checkpoint_of(run_dir, script[:-3])
    for key in ("args", "actor", "qf1", "qf2", "obs_dim_real", "obs_dim", "act_dim"):
        assert key in checkpoint
    assert "reward_models" not in checkpoint
    assert ("masks" in checkpoint) == (script == "anf_sac.py")
    assert checkpoint["global_step"] == 1500
    obs_dim = 5 if script == "sac.py" else 51
    assert (checkpoint["obs_dim_real"], checkpoint["obs_dim"], checkpoint["act_dim"]) == (5, obs_dim, 1)
    assert checkpoint["args"]["noise"] == (0.0 if script == "sac.py" else 0.9)
    module.Actor(obs_dim, 1, 32).load_state_dict(checkpoint["actor"])
    for q in ("qf1", "qf2"):
        module.SoftQNetwork(obs_dim, 1, 32).load_state_dict(checkpoint[q])


def test_anf_masks_active_count_and_topology_moves(pipeline):
    run_dir, _ = pipeline["anf_sac.py"]
    checkpoint = checkpoint_of(run_dir, "anf_sac")
    masks = checkpoint["masks"]
    assert sorted(masks) == AGENT_NETS
    expected_shapes = {"actor": (32, 51), "qf1": (32, 52), "qf2": (32, 52)}
    for name, mask in masks.items():
        assert tuple(mask.shape) == expected_shapes[name]
        assert set(mask.unique().tolist()) <= {0.0, 1.0}
        n = mask.numel()
        assert mask.sum().item() == n - math.floor(0.8 * n), name
        weight = checkpoint[name]["net.0.weight"]
        assert torch.all(weight[mask == 0] == 0), f"{name}: masked weights must be exactly 0"
        assert checkpoint[name]["net.2.weight"].count_nonzero() == checkpoint[name]["net.2.weight"].numel()  # dense
    assert not torch.equal(masks["qf1"], masks["qf2"]), "independent random masks"
    values = scalars(run_dir)
    assert len(set(values["sparse/actor/relevant_active_frac"])) > 1, "the actor's topology never moved"
    # the dense oracle: sac.py's input layers have no zeroed weights
    sac_checkpoint = checkpoint_of(pipeline["sac.py"][0], "sac")
    assert sac_checkpoint["actor"]["net.0.weight"].count_nonzero() == 32 * 5


# ---------------------------------------------------------------- histograms


@torch.no_grad()
def _rollouts(actor, n, seed, episode_length):
    """The test's own deterministic rollouts: the first n observations tanh(mean) acts on, noise-free env."""
    env = ene.make_env("cartpole-swingup", seed, noise=0.0, episode_length=episode_length)
    obs, _ = env.reset(seed=seed)
    observations = []
    while len(observations) < n:
        observations.append(obs)
        _, _, mean_action = actor.get_action(torch.as_tensor(obs)[None])
        obs, _, terminated, truncated, _ = env.step(mean_action[0].numpy())
        if terminated or truncated:
            obs, _ = env.reset()
    env.close()
    return np.stack(observations).astype(np.float64)


def test_histograms_match_the_policy_rollouts(pipeline):
    path, result = pipeline["make_histograms.py"]
    assert f"wrote {path}" in result.stdout
    assert _read("make_histograms.py").splitlines()[0] == HEADER
    histograms = ene.load_histograms(path)  # validates shapes, monotone edges, normalised probs
    edges, probs = histograms["bin_edges"], histograms["probs"]
    assert edges.shape == (5, 101) and probs.shape == (5, 100)

    checkpoint = checkpoint_of(pipeline["sac.py"][0], "sac")
    actor = sac.Actor(5, 1, 32)
    actor.load_state_dict(checkpoint["actor"])
    observations = _rollouts(actor, HIST_N, HIST_SEED, HIST_EPISODE)
    assert observations.shape == (HIST_N, 5)
    low, high = observations.min(0), observations.max(0)
    assert np.all(high > low), "cartpole's real features all vary"
    np.testing.assert_allclose(edges[:, 0], low, rtol=0, atol=1e-12)  # the bins span each feature's [min, max]
    np.testing.assert_allclose(edges[:, -1], high, rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.diff(edges, axis=1), ((high - low) / 100)[:, None] * np.ones((1, 100)), rtol=1e-9)
    for i in range(5):
        counts, _ = np.histogram(observations[:, i], bins=100, range=(low[i], high[i]))
        np.testing.assert_allclose(probs[i], counts / HIST_N, rtol=0, atol=1e-12)


@pytest.mark.parametrize("which", ["noisy", "missing", "not_a_checkpoint", "not_npz_output"])
def test_make_histograms_bad_input_one_line(which, pipeline, tmp_path):
    args = {
        "noisy": ["--checkpoint", os.path.join(pipeline["anf_sac.py"][0], "anf_sac.cleanrl_model")],
        "missing": ["--checkpoint", str(tmp_path / "missing.cleanrl_model")],
        "not_a_checkpoint": ["--checkpoint", pipeline["make_histograms.py"][0]],
        "not_npz_output": ["--checkpoint", os.path.join(pipeline["sac.py"][0], "sac.cleanrl_model"), "--output", "h"],
    }[which]
    result = run_script("make_histograms.py", args + ["--episode-length", "10"], tmp_path, check=False)
    assert result.returncode != 0
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("make_histograms: error: --"), result.stderr
    assert ("noise-free" in lines[0]) == (which == "noisy")
    assert os.listdir(tmp_path) == [], "nothing is written on bad input"


# ---------------------------------------------------------------- imitating noise


def _assert_follows_marginals(noise_columns, histograms, obs_dim_real, column_tol, pooled_tol):
    """Each noise column lies in its source feature's [min, max]; its bin frequencies match the source's probs
    (total variation distance, per column and pooled over the columns imitating the same feature)."""
    edges, probs = histograms["bin_edges"], histograms["probs"]
    n_noise = noise_columns.shape[1]
    pooled = {}
    for j in range(n_noise):
        source = j % obs_dim_real
        column = noise_columns[:, j].astype(np.float64)
        assert column.min() >= edges[source, 0] - 1e-6 and column.max() <= edges[source, -1] + 1e-6, j
        counts, _ = np.histogram(column, bins=edges[source])
        assert counts.sum() == len(column)
        assert 0.5 * np.abs(counts / len(column) - probs[source]).sum() < column_tol, j
        pooled[source] = pooled.get(source, 0) + counts
    for source, counts in pooled.items():
        assert 0.5 * np.abs(counts / counts.sum() - probs[source]).sum() < pooled_tol, source


def test_imitating_noise_follows_the_histograms(pipeline):
    path = pipeline["make_histograms.py"][0]
    histograms = ene.load_histograms(path)
    env = ene.make_env("cartpole-swingup", 5, noise=0.9, noise_type="imitate", noise_histograms=path, episode_length=100)
    assert (env.obs_dim_real, env.observation_space.shape[0]) == (5, 51)
    observations = [env.reset(seed=5)[0]]
    for _ in range(3999):
        obs, _, terminated, truncated, _ = env.step(env.action_space.sample())
        observations.append(env.reset()[0] if terminated or truncated else obs)
    env.close()
    observations = np.stack(observations)
    # the env's noise columns (what is observed and stored), 4000 rows, 9-10 columns per source feature
    _assert_follows_marginals(observations[:, 5:], histograms, 5, column_tol=0.2, pooled_tol=0.06)
    # the read-time redraw of --noise-resample (torch sampler): same marginals
    torch.manual_seed(0)
    refreshed = env.noise_sampler.refresh_(torch.zeros(4000, 51)).numpy()
    assert np.all(refreshed[:, :5] == 0), "refresh_ leaves the real columns alone"
    _assert_follows_marginals(refreshed[:, 5:], histograms, 5, column_tol=0.2, pooled_tol=0.06)


def test_pebble_runs_with_imitating_noise(pipeline):
    run_dir, result = pipeline["pebble.py"]
    values = scalars(run_dir)
    missing = [tag for tag in COMMON_TAGS if tag not in values]
    assert not missing, f"missing tags {missing}"
    for tag in COMMON_TAGS:
        assert all(math.isfinite(v) for v in values[tag]), f"{tag} has non-finite values {values[tag]}"
    assert values["pbrl/total_feedback"] == [5, 10, 15, 20]
    assert result.stdout.count("eval_return=") == 3
    checkpoint = checkpoint_of(run_dir, "imitate")
    assert checkpoint["args"]["noise_type"] == "imitate"
    assert checkpoint["args"]["noise_histograms"] == pipeline["make_histograms.py"][0]
    assert (checkpoint["obs_dim_real"], checkpoint["obs_dim"], checkpoint["act_dim"]) == (5, 51, 1)


# ---------------------------------------------------------------- bad input, flags


@pytest.mark.parametrize(
    "script, bad, flag",
    [
        ("sac.py", ["--noise", "1.0"], "--noise"),
        ("sac.py", ["--buffer-size", "16"], "--buffer-size"),
        ("anf_sac.py", ["--agent-sparsity", "1.0"], "--agent-sparsity"),
    ],
)
def test_oracle_bad_input_fails_fast_with_one_line(script, bad, flag, tmp_path):
    result = run_script(script, ORACLE_TINY + bad, tmp_path, check=False)
    assert result.returncode != 0
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and flag in lines[0], result.stderr
    assert not os.path.exists(tmp_path / "runs"), "nothing is written before the input is checked"


PBRL_FIELDS = {
    "reset_updates", "unsup_steps", "knn_k", "max_feedback", "queries_per_round", "feedback_freq", "segment_size",
    "segment_episodes", "query_sampling", "query_pool_multiplier", "ensemble_size", "reward_lr", "reward_hidden_dim",
    "reward_layers", "reward_batch_size", "reward_epochs", "reward_stop_accuracy", "relabel_batch_size",
    "teacher", "preferences", "teacher_beta", "teacher_gamma", "teacher_eps_mistake", "teacher_eps_skip", "teacher_eps_equal",
    "query_log",
}
AGENT_FIELDS = {"agent_sparsity", "agent_drop_fraction", "agent_topology_period"}


def _defaults(args_class) -> dict:
    return {f.name: f.default for f in dataclasses.fields(args_class) if f.name != "exp_name"}


def test_flags_are_pebbles_without_pbrl_and_anf_adds_the_agent_block():
    sac_flags, pebble_flags, anf_flags = _defaults(sac.Args), _defaults(pebble.Args), _defaults(anf_sac.Args)
    assert set(pebble_flags) - set(sac_flags) == PBRL_FIELDS
    assert all(pebble_flags[name] == default for name, default in sac_flags.items()), "same defaults as pebble.py"
    assert sac_flags["noise"] == 0.9
    assert set(anf_flags) - set(sac_flags) == AGENT_FIELDS and set(sac_flags) <= set(anf_flags)
    r2n_flags = _defaults(r2n_pebble.Args)
    assert {name: anf_flags[name] for name in AGENT_FIELDS} == {name: r2n_flags[name] for name in AGENT_FIELDS}
    assert (anf_flags["agent_sparsity"], anf_flags["agent_drop_fraction"], anf_flags["agent_topology_period"]) == (
        0.8, 0.05, 1000)


# ---------------------------------------------------------------- each oracle is a plain diff


def _read(name: str) -> str:
    with open(os.path.join(ROOT, name)) as f:
        return f.read()


def _changes(a: str, b: str) -> list:
    diff = list(difflib.unified_diff(a.splitlines(), b.splitlines(), lineterm="", n=0))[2:]
    return [line for line in diff if line[:1] in "+-"]


def _statements(source: str) -> list:
    """Each statement of a file in order, as one line of normalised source: a compound statement by its first line,
    an expression (a docstring) whole. Comments and line breaks inside a statement do not count."""
    found = []

    def visit(body):
        for node in body:
            text = ast.unparse(node)
            found.append(" ".join((text if isinstance(node, ast.Expr) else text.split("\n", 1)[0]).split()))
            for field in ("body", "orelse", "finalbody", "handlers"):
                visit([child for child in getattr(node, field, []) if isinstance(child, (ast.stmt, ast.excepthandler))])

    visit(ast.parse(source).body)
    return found


def _without_docstring(source: str) -> str:
    """The file with its module docstring cut out (its lines are each script's own words)."""
    node = ast.parse(source).body[0]
    assert isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant)
    lines = source.splitlines(keepends=True)
    return "".join(lines[: node.lineno - 1] + lines[node.end_lineno :])


def _blocks(source: str, names: list) -> dict:
    """Source text of each named function or class (module level or nested, decorators included)."""
    lines, found = source.splitlines(keepends=True), {}
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, (ast.FunctionDef, ast.ClassDef)) and node.name in names:
            first = min([node.lineno] + [d.lineno for d in node.decorator_list])
            found[node.name] = "".join(lines[first - 1 : node.end_lineno])
    assert sorted(found) == sorted(names), f"missing blocks {set(names) - set(found)}"
    return found


SAC_BLOCKS = ["read_noisy", "Batch", "mlp", "SoftQNetwork", "Actor", "evaluate", "make_critic", "sac_update"]
SPARSE_BLOCKS = ["random_mask", "top_k_random_ties", "rigl_update_", "SparseOptimizer", "connectivity"]


def test_sac_is_pebble_without_preference_learning():
    sac_source, pebble_source = _read("sac.py"), _read("pebble.py")
    assert sac_source.splitlines()[0] == HEADER
    # The bound counts statements, not physical lines (issue 42): wrapping a long line costs nothing, while any
    # statement pebble.py adds to sac.py's counts. 499 statements when the count replaced the 721 physical lines
    # (preference learning, its diagnostics, resume state, real preferences, trusting them, the labelling page, the
    # query log's files), plus 8 for the method's seam (issue 42: `simulated_teacher` in ALGO LOGIC; the plumbing's
    # `run_feedback_round`, its `ask`, and `add_preferences` out of the main block).
    statement_changes = _changes("\n".join(_statements(sac_source)), "\n".join(_statements(pebble_source)))
    assert 0 < len(statement_changes) <= 507, f"sac.py -> pebble.py: {len(statement_changes)} changed statements > 507"
    grown = pebble_source.replace("    return trained\n", "    trained = dict(trained)\n    return trained\n", 1)
    assert len(_changes("\n".join(_statements(sac_source)), "\n".join(_statements(grown)))) == len(statement_changes) + 1
    # outside the docstrings sac.py is pebble.py with lines deleted and a handful reworded
    code_changes = _changes(_without_docstring(sac_source), _without_docstring(pebble_source))
    sac_only = [line for line in code_changes if line.startswith("-")]
    # (12: among them sac.py's `log_evaluation` without the feedback counts)
    assert len(sac_only) <= 12, "lines of sac.py that pebble.py lacks:\n" + "\n".join(sac_only)
    code = _without_docstring(sac_source)
    for pbrl_name in ("RewardEnsemble", "reward_model", "teacher", "select_queries", "PreferenceBuffer", "prefs",
                      "EpisodeStore", "knn_distance", "state_entropy", "feedback_round", "relabel", "pebble_start"):
        assert pbrl_name not in code, f"{pbrl_name} is preference learning"
    sac_blocks, pebble_blocks = _blocks(sac_source, SAC_BLOCKS), _blocks(pebble_source, SAC_BLOCKS)
    for name in SAC_BLOCKS:
        assert sac_blocks[name] == pebble_blocks[name], f"{name} differs between sac.py and pebble.py"
    # the common Args fields come in pebble's order with pebble's docstrings
    sac_args, pebble_args = _blocks(sac_source, ["Args"])["Args"], _blocks(pebble_source, ["Args"])["Args"]
    remaining = iter(pebble_args.splitlines())
    assert all(line in remaining for line in sac_args.splitlines()), "sac.Args is not pebble.Args with fields deleted"


def test_anf_sac_is_sac_plus_the_agent_half_of_the_r2n_patch():
    sac_source, anf_source, r2n_source = _read("sac.py"), _read("anf_sac.py"), _read("r2n_pebble.py")
    assert anf_source.splitlines()[0] == HEADER
    changes = _changes(sac_source, anf_source)
    assert 0 < len(changes) <= 200, f"diff sac.py anf_sac.py: {len(changes)} changed lines > 200"
    assert len([line for line in changes if line.startswith("-")]) <= 2, "anf_sac.py only adds to sac.py"
    anf_blocks, sac_blocks = _blocks(anf_source, SAC_BLOCKS), _blocks(sac_source, SAC_BLOCKS)
    for name in set(SAC_BLOCKS) - {"make_critic"}:  # make_critic wraps the critic optimiser
        assert anf_blocks[name] == sac_blocks[name], f"{name} differs between sac.py and anf_sac.py"
    # the SPARSE LOGIC section is R2N's, byte for byte
    def section(source):
        return source[source.index("# SPARSE LOGIC:") : source.index("# ALGO LOGIC: the agent, and the steps of training")]
    assert section(anf_source) == section(r2n_source)
    # every added code line outside the patch comment, the flag block and its checks is a line of r2n_pebble.py
    r2n_lines = set(r2n_source.splitlines())
    added = [line[1:] for line in changes if line.startswith("+") and not line.startswith("+#")]
    own = [line for line in added if line not in r2n_lines and line.strip()]
    assert len(own) <= 12, "anf_sac.py lines that are not R2N's:\n" + "\n".join(own)
    # the reward half of the patch is not there
    for reward_part in ("reward_sparsity", "sparse_reward", "reward_optimizer", "sparse_agent"):
        assert reward_part not in anf_source


@pytest.mark.parametrize("script", list(ORACLE_ARGS))
def test_a_copied_oracle_stops_at_a_harness_flag_with_one_line(script, tmp_path):
    """`--cuda-graph` needs the run harness's package: a copy of the script without it says so in one line."""
    check_harness_flag_stops_a_copy(script, ORACLE_ARGS[script] + ["--cuda-graph"], "--cuda-graph", tmp_path)
