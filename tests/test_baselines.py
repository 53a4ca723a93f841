"""The R2N paper's baselines (spec: ALGORITHMS.md section 3, "Baselines"; REFERENCE_NOTES.md Part B section 6).

`set_pebble.py` and `static_pebble.py` are `r2n_pebble.py` with random regrowth / no topology update;
`l1_pebble.py` and `dropconnect_pebble.py` are `pebble.py` with an L1 penalty / DropConnect on the reward models'
input layers. Smoke runs of every phase (the four run at once), each method's mechanism, and the size of each diff.
"""
import difflib
import glob
import math
import os
import sys
from concurrent.futures import ThreadPoolExecutor

import pytest
import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from test_scripts import (COMMON_TAGS, ROOT, SPARSE_NETS, SPARSE_TAGS, SPARSE_TINY, TINY,  # noqa: E402
                          TOPOLOGY_TAGS, check_progress, run_script, scalars)

import dropconnect_pebble  # noqa: E402
import l1_pebble  # noqa: E402
import r2n_pebble  # noqa: E402
import set_pebble  # noqa: E402
import static_pebble  # noqa: E402

MODULES = {"set_pebble.py": set_pebble, "static_pebble.py": static_pebble, "l1_pebble.py": l1_pebble,
           "dropconnect_pebble.py": dropconnect_pebble}
SMOKE_ARGS = {  # Static has no topology flags
    "set_pebble.py": TINY + SPARSE_TINY,
    "static_pebble.py": TINY,
    "l1_pebble.py": TINY,
    "dropconnect_pebble.py": TINY,
}
REWARD_TAGS = [f"sparse/reward{e}/{m}" for e in range(3) for m in ("relevant_degree", "noise_degree", "relevant_active_frac")]


# ---------------------------------------------------------------- smoke runs


@pytest.fixture(scope="module")
def smoke_runs(tmp_path_factory):
    """The four smoke runs, concurrently (independent one-thread processes): script -> (run dir, process result)."""
    cwds = {script: tmp_path_factory.mktemp(script[:-3]) for script in SMOKE_ARGS}
    with ThreadPoolExecutor(len(SMOKE_ARGS)) as pool:
        futures = {
            script: pool.submit(run_script, script, args + ["--exp-name", "smoke"], cwds[script], False, True)
            for script, args in SMOKE_ARGS.items()
        }
        results = {script: future.result() for script, future in futures.items()}
    return {script: (glob.glob(str(cwds[script] / "runs" / "*")), result) for script, result in results.items()}


@pytest.mark.parametrize("script", list(SMOKE_ARGS))
def test_smoke_reaches_every_phase(script, smoke_runs):
    run_dirs, result = smoke_runs[script]
    assert result.returncode == 0, result.stderr[-3000:]
    (run_dir,) = run_dirs
    values = scalars(run_dir)

    sparse = script in ("set_pebble.py", "static_pebble.py")
    expected = COMMON_TAGS + (SPARSE_TAGS if sparse else REWARD_TAGS) + (TOPOLOGY_TAGS if sparse else [])
    missing = [tag for tag in expected if tag not in values]
    assert not missing, f"missing tags {missing}"
    for tag in expected:
        assert all(math.isfinite(v) for v in values[tag]), f"{tag} has non-finite values {values[tag]}"
    if not sparse:  # dense agent: no actor/critic connectivity
        assert not [tag for tag in values if tag.startswith(("sparse/actor", "sparse/qf"))]
        for e in range(3):  # a dense 16-unit input layer: at most 16 connections per column
            assert all(0 < v <= 16 for v in values[f"sparse/reward{e}/relevant_degree"])

    assert values["pbrl/total_feedback"] == [5, 10, 15, 20]
    assert values["pbrl/labeled_feedback"][-1] == 20
    assert len(values["eval/episodic_return"]) == 3
    assert result.stdout.count("eval_return=") == 3
    check_progress(result.stdout)

    checkpoint = torch.load(os.path.join(run_dir, "smoke.cleanrl_model"), weights_only=False)
    for key in ("args", "actor", "qf1", "qf2", "reward_models", "obs_dim_real", "obs_dim", "act_dim"):
        assert key in checkpoint
    assert (checkpoint["obs_dim_real"], checkpoint["obs_dim"], checkpoint["act_dim"]) == (5, 51, 1)
    assert checkpoint["global_step"] == 3000
    module = MODULES[script]
    module.Actor(51, 1, 32).load_state_dict(checkpoint["actor"])
    module.SoftQNetwork(51, 1, 32).load_state_dict(checkpoint["qf1"])
    members = checkpoint["reward_models"]
    ensemble = module.RewardEnsemble(52, 16, 2, 3)
    ensemble.load_state_dict({name: torch.stack([member[name] for member in members]) for name in members[0]})

    if sparse:
        masks = checkpoint["masks"]
        assert sorted(masks) == sorted(SPARSE_NETS)
        for name, mask in masks.items():
            n = mask.numel()
            assert mask.sum().item() == n - math.floor(0.8 * n), name
        assert torch.all(checkpoint["actor"]["net.0.weight"][masks["actor"] == 0] == 0)
        assert torch.all(checkpoint["qf2"]["net.0.weight"][masks["qf2"] == 0] == 0)
        for e in range(3):
            assert torch.all(members[e]["weights.0"][masks[f"reward{e}"] == 0] == 0)
    else:
        assert "masks" not in checkpoint
        flag, default = ("l1_lambda", 0.01) if script == "l1_pebble.py" else ("dropconnect_p", 0.2)
        assert checkpoint["args"][flag] == default

    if script == "set_pebble.py":  # topology updates moved the reward members' connections between evaluations
        assert len(set(values["sparse/reward0/relevant_active_frac"])) > 1
    if script == "static_pebble.py":  # every mask is fixed (the critic reset at step 500 precedes the first eval)
        for tag in SPARSE_TAGS:
            assert len(set(values[tag])) == 1, (tag, values[tag])
        assert {v for tag in TOPOLOGY_TAGS for v in values[tag]} == {0}


# ---------------------------------------------------------------- SET: random regrowth


def _one_update(module, hot_columns, seed):
    """One topology update (period 1) of a 64x64 layer at sparsity 0.8, drop 0.2, with a gradient that is huge on
    `hot_columns`. Returns (mask before, mask after, weight, optimizer)."""
    torch.manual_seed(seed)
    weight = torch.nn.Parameter(torch.randn(64, 64))
    optimizer = module.SparseOptimizer(torch.optim.Adam([weight], lr=1e-3), {"w": weight}, 0.8, 0.2, 1)
    before = optimizer.masks["w"].clone()
    weight.grad = 1e-3 * torch.randn(64, 64)
    weight.grad[:, hot_columns] = 100.0
    optimizer.step()
    return before, optimizer.masks["w"].clone(), weight, optimizer


def test_set_grows_at_random_where_rigl_grows_on_the_gradient():
    hot = [3, 17, 40, 41]  # 256 positions, about 205 inactive: enough for RigL's 164 grown weights
    n_active = 64 * 64 - math.floor(0.8 * 64 * 64)
    n_drop = math.floor(0.2 * n_active)

    before, after, _, _ = _one_update(r2n_pebble, hot, seed=0)
    grown = (after == 1) & (before == 0)  # new positions (a just-dropped one that regrows is not counted)
    assert grown.sum() > 0.8 * n_drop and grown[:, hot].sum() == grown.sum()  # RigL: all on the hot columns

    shares = []
    for seed in range(3):
        before, after, weight, optimizer = _one_update(set_pebble, hot, seed)
        grown = (after == 1) & (before == 0)
        assert after.sum() == before.sum() == n_active  # density constant
        assert 0.8 * n_drop < grown.sum() <= n_drop  # floor(0.2 * n_active) regrown, a few at just-dropped positions
        shares.append(grown[:, hot].sum().item() / grown.sum().item())
        assert len(grown.any(0).nonzero()) > 40  # spread over the matrix, not concentrated on a few columns
        assert torch.all(weight[grown] == 0)  # grown weights start at zero, with zero Adam moments
        state = optimizer.optimizer.state[weight]
        assert torch.all(state["exp_avg"][grown] == 0) and torch.all(state["exp_avg_sq"][grown] == 0)
        assert torch.all(weight[after == 0] == 0)
    # uniform among the ~3440 non-kept positions: ~7.4% land on the 256 hot ones
    assert max(shares) < 0.2, shares


def test_set_regrowth_is_uniform_over_columns():
    """set_update_ on fresh random layers with a gradient concentrated on column 0: grown positions per column stay
    uniform (RigL would put nearly all of them on column 0)."""
    torch.manual_seed(1)
    counts = torch.zeros(16)
    for _ in range(300):
        mask = set_pebble.random_mask(torch.Size([32, 16]), 0.8, torch.device("cpu"))
        weight = torch.randn(32, 16) * mask
        before = mask.clone()
        grad = torch.zeros(32, 16)
        grad[:, 0] = 1e3
        set_pebble.set_update_(weight, mask, grad, 0.5, [])
        assert mask.sum() == before.sum()
        counts += ((mask == 1) & (before == 0)).sum(0)
    share = counts / counts.sum()
    assert share.min() > 0.75 / 16 and share.max() < 1.25 / 16, share


def test_set_drops_the_smallest_active_weights_of_each_member():
    """set_update_ on a stacked (reward-ensemble) layer drops, in each member, exactly the floor(d * n_active) active
    weights of smallest |w|, whatever the gradient; the rest stay active with their values. When the weights on some
    columns are smaller, SET therefore moves connections off them (the which-sparsity study's SET reward members)."""
    torch.manual_seed(2)
    mask = set_pebble.random_mask(torch.Size([3, 32, 40]), 0.8, torch.device("cpu"))
    weight = (torch.rand(3, 32, 40) + 0.01) * torch.where(torch.rand(3, 32, 40) < 0.5, -1.0, 1.0) * mask
    weight[:, :, :8] *= 0.1  # small weights on the first 8 columns
    before, values = mask.clone(), weight.clone()
    set_pebble.set_update_(weight, mask, torch.randn(3, 32, 40), 0.2, [])
    n_active = int(before[0].sum())
    n_drop = math.floor(0.2 * n_active)
    for member in range(3):
        active = before[member].bool()
        smallest = values[member].abs()[active].sort().values
        kept = active & (mask[member] == 1)
        assert int(active.sum()) - int(kept.sum()) <= n_drop  # a just-dropped position may regrow
        dropped = active & ~kept
        threshold = smallest[n_drop - 1]
        assert torch.all(values[member].abs()[dropped] <= threshold)
        assert torch.all(values[member].abs()[active & (values[member].abs() > threshold)] == weight[member].abs()[
            active & (values[member].abs() > threshold)])  # larger ones kept, unchanged
        assert int(mask[member].sum()) == n_active
    small = lambda m: m[:, :, :8].sum() / m.sum()  # noqa: E731
    assert small(mask) < small(before)  # connections move off the small-weight columns


# ---------------------------------------------------------------- Static: the initial mask never changes


def test_static_same_initial_masks_as_r2n_never_updated():
    def make(module, *topology):
        torch.manual_seed(5)
        weight = torch.nn.Parameter(torch.randn(3, 16, 24))  # stacked like the reward ensemble's input layer
        return weight, module.SparseOptimizer(torch.optim.Adam([weight], lr=1e-2), {"reward": weight}, 0.8, *topology)

    weight, optimizer = make(static_pebble)
    r2n_weight, r2n_optimizer = make(r2n_pebble, 0.2, 10)
    start = optimizer.masks["reward"].clone()
    assert torch.equal(start, r2n_optimizer.masks["reward"])  # same random initial mask for the same seed
    initial = weight.detach().clone()
    torch.manual_seed(6)
    for _ in range(300):
        grad = torch.randn(3, 16, 24)
        weight.grad, r2n_weight.grad = grad.clone(), grad.clone()
        optimizer.step()
        r2n_optimizer.step()
    assert torch.equal(optimizer.masks["reward"], start)
    assert not torch.equal(r2n_optimizer.masks["reward"], start)  # R2N would have moved it
    assert torch.all(weight[start == 0] == 0)  # masked weights stay exactly zero
    assert torch.all(weight[start == 1] != initial[start == 1])  # the active ones trained
    assert start.sum((1, 2)).tolist() == [16 * 24 - math.floor(0.8 * 16 * 24)] * 3


def test_static_has_no_topology_flags():
    fields = static_pebble.Args.__dataclass_fields__
    for flag in ("reward_drop_fraction", "reward_topology_period", "agent_drop_fraction", "agent_topology_period"):
        assert flag not in fields and flag in r2n_pebble.Args.__dataclass_fields__
    assert not hasattr(static_pebble, "rigl_update_")
    for flag in ("sparse_reward", "sparse_agent", "reward_sparsity", "agent_sparsity"):
        assert flag in fields


# ---------------------------------------------------------------- L1 on the reward input layers


def _preferences(module, n=12, input_dim=7, segment_size=4):
    torch.manual_seed(11)
    prefs = module.PreferenceBuffer(n, segment_size, input_dim, torch.device("cpu"))
    prefs.add(torch.randn(n, 2, segment_size, input_dim), (torch.rand(n) < 0.5).float())
    return prefs


def test_l1_penalty_is_lambda_sum_abs_input_weights():
    torch.manual_seed(0)
    model = l1_pebble.RewardEnsemble(7, 8, 2, 3)
    penalty = l1_pebble.l1_penalty(model, 0.01)
    assert penalty.shape == (3,)
    for e in range(3):
        assert torch.allclose(penalty[e], 0.01 * model.weights[0][e].abs().sum())
    assert torch.all(l1_pebble.l1_penalty(model, 0.0) == 0)


def test_l1_gradient_adds_lambda_sign_w_on_input_layer_only():
    """One SGD step (lr 1) of train_reward with and without the penalty: the input weights differ by lambda * sign(w),
    every other parameter is the same; the returned loss is the Bradley-Terry loss in both cases."""
    prefs = _preferences(l1_pebble)
    torch.manual_seed(0)
    initial = l1_pebble.RewardEnsemble(7, 8, 2, 3).state_dict()
    models, losses = {}, {}
    for lam in (0.0, 0.01):
        model = l1_pebble.RewardEnsemble(7, 8, 2, 3)
        model.load_state_dict(initial)
        torch.manual_seed(1)  # the same shuffle
        losses[lam] = l1_pebble.train_reward(model, torch.optim.SGD(model.parameters(), lr=1.0), prefs, 64, 1, 1.0, lam)
        models[lam] = model.state_dict()
    w0 = initial["weights.0"]
    assert torch.allclose(models[0.0]["weights.0"] - models[0.01]["weights.0"], 0.01 * w0.sign(), atol=1e-6)
    for name in initial:
        if name != "weights.0":
            assert torch.equal(models[0.0][name], models[0.01][name]), name
    assert losses[0.0] == losses[0.01]  # (loss, accuracy, epochs): the penalty is not in the reported loss


def test_l1_pebble_keeps_agent_dense_and_default_lambda():
    assert l1_pebble.Args.l1_lambda == 0.01
    assert not hasattr(l1_pebble, "SparseOptimizer")
    with pytest.raises(ValueError, match="--l1-lambda"):
        l1_pebble.validate_args(l1_pebble.ene.suite_settings(l1_pebble.Args(l1_lambda=-1.0)))


# ---------------------------------------------------------------- DropConnect on the reward input layers


def _full_weight_forward(model, x):
    """The reward ensemble written out by hand, full weights (independent of the script's forward)."""
    h = x.expand(model.ensemble_size, *x.shape)
    for i, (weight, bias) in enumerate(zip(model.weights, model.biases)):
        h = h @ weight.transpose(1, 2) + bias
        h = torch.nn.functional.leaky_relu(h) if i < len(model.weights) - 1 else torch.tanh(h)
    return h.squeeze(-1)


def test_dropconnect_evaluation_forwards_are_deterministic_full_weights():
    torch.manual_seed(0)
    model = dropconnect_pebble.RewardEnsemble(6, 8, 2, 3)
    x = torch.randn(20, 6)
    with torch.no_grad():
        full = _full_weight_forward(model, x)
        assert torch.equal(model(x), model(x))
        assert torch.allclose(model(x), full, atol=1e-6)
        assert torch.allclose(model.mean_reward(x), full.mean(0), atol=1e-6)
        assert torch.equal(model(x, 0.0), model(x))


def test_dropconnect_training_forwards_random_per_member_shared_across_batch():
    torch.manual_seed(0)
    model = dropconnect_pebble.RewardEnsemble(6, 8, 2, 3)
    with torch.no_grad():
        for e in range(1, 3):  # identical members: any difference between them comes from their own masks
            for weights in (model.weights, model.biases):
                for p in weights:
                    p[e] = p[0]
        x = torch.randn(1, 6).expand(10, 6)  # ten identical rows
        a, b = model(x, 0.2), model(x, 0.2)
    # Rows of one batched matmul may differ in their last bits (the BLAS kernel, hence the rounding, depends on the
    # CPU), so "equal" is up to float32 rounding; a different mask moves an output by ~1e-3, far beyond it.
    tol = dict(rtol=1e-5, atol=1e-6)
    assert not torch.equal(a, b)  # a fresh mask per call
    assert (a - b).abs().max() > 100 * tol["atol"]  # ... which changes the output far beyond the tolerance below
    torch.testing.assert_close(a, a[:, :1].expand_as(a), **tol)  # one mask per member, shared by the whole batch
    assert not (torch.allclose(a[0], a[1], **tol) and torch.allclose(a[0], a[2], **tol))  # members draw their own masks


def test_dropconnect_masks_and_inverted_scaling(monkeypatch):
    """With the nonlinearities replaced by the identity, a one-layer ensemble on a one-hot input returns b + w * m / (1-p)
    with m ~ Bernoulli(1 - p), per member; and a deeper one averages to the full-weight output."""
    monkeypatch.setattr(torch, "tanh", lambda h: h)
    monkeypatch.setattr(torch.nn.functional, "leaky_relu", lambda h: h)
    p = 0.2
    torch.manual_seed(0)
    model = dropconnect_pebble.RewardEnsemble(5, 1, 0, 3)  # a single Linear(5, 1) per member
    x = torch.zeros(1, 5)
    x[0, 2] = 1.0
    with torch.no_grad():
        w, b = model.weights[0][:, 0, 2], model.biases[0][:, 0, 0]
        samples = torch.stack([model(x, p)[:, 0] for _ in range(4000)])  # (4000, E)
    kept = torch.isclose(samples, b + w / (1 - p), atol=1e-6)
    dropped = torch.isclose(samples, b.expand_as(samples), atol=1e-6)
    assert torch.all(kept | dropped)
    assert abs(dropped.float().mean().item() - p) < 5 * math.sqrt(p * (1 - p) / dropped.numel())

    torch.manual_seed(1)
    model = dropconnect_pebble.RewardEnsemble(6, 8, 2, 3)  # linear now: E[output] = full-weight output
    x = torch.randn(4, 6)
    with torch.no_grad():
        full = model(x)
        samples = torch.stack([model(x, p) for _ in range(4000)])
    mean, stderr = samples.mean(0), samples.std(0) / math.sqrt(len(samples))
    assert torch.all((mean - full).abs() < 5 * stderr + 1e-4), (mean - full) / stderr


def test_dropconnect_only_in_reward_training(monkeypatch):
    """train_reward forwards with p; query scoring, relabelling and the per-step reward use the full weights."""
    prefs = _preferences(dropconnect_pebble)
    torch.manual_seed(0)
    model = dropconnect_pebble.RewardEnsemble(7, 8, 2, 3)
    seen = []
    forward = model.forward
    monkeypatch.setattr(model, "forward", lambda x, dropconnect_p=0.0: seen.append(dropconnect_p) or forward(x, dropconnect_p))
    dropconnect_pebble.train_reward(model, torch.optim.Adam(model.parameters(), lr=1e-3), prefs, 4, 2, 1.0, 0.2)
    assert seen == [0.2] * 6  # 12 pairs in minibatches of 4, two epochs
    seen.clear()
    store = dropconnect_pebble.EpisodeStore(3, 10, 5, 2, torch.device("cpu"))
    for _ in range(30):
        store.add(torch.randn(5), torch.randn(2), 0.0)
    dropconnect_pebble.select_queries(model, store, 2, 4, "disagreement", 3)
    rb = dropconnect_pebble.ReplayBuffer(8, 5, 2, torch.device("cpu"))
    for _ in range(8):
        rb.add(torch.randn(5), torch.randn(2), torch.randn(5), False, 0.0, 0.0)
    rb.relabel(model.mean_reward, 4)
    model.mean_reward(torch.randn(1, 7))
    assert seen and all(p == 0.0 for p in seen)
    assert dropconnect_pebble.Args.dropconnect_p == 0.2
    assert not hasattr(dropconnect_pebble, "SparseOptimizer")


def test_connectivity_counts_weights_above_threshold():
    weight = torch.zeros(4, 6)  # columns: 2 real, 3 noise, 1 action (obs_dim_real 2, obs_dim 5)
    weight[:, 0] = 0.5
    weight[:2, 3] = -0.01
    weight[:, 4] = 5e-4  # below 1e-3: not a connection
    weight[:3, 5] = 0.2
    for module in (l1_pebble, dropconnect_pebble):
        metrics = {k: v.item() for k, v in module.connectivity(weight, 2, 5).items()}
        assert metrics["relevant_degree"] == pytest.approx((4 + 0 + 3) / 3)
        assert metrics["noise_degree"] == pytest.approx((0 + 2 + 0) / 3)
        assert metrics["relevant_active_frac"] == pytest.approx(7 / 9)


# ---------------------------------------------------------------- each baseline is a small diff of its parent


@pytest.mark.parametrize(
    "parent, variant, budget",
    [
        ("r2n_pebble.py", "set_pebble.py", 30),
        # Static deletes RigL outright (rigl_update_, top_k_random_ties, the topology step and its four flags: about
        # 60 removed lines) instead of keeping it as dead code, hence a larger budget than the other sparse variant.
        ("r2n_pebble.py", "static_pebble.py", 80),
        ("pebble.py", "l1_pebble.py", 60),
        ("pebble.py", "dropconnect_pebble.py", 80),
    ],
)
def test_diff_against_parent_is_small(parent, variant, budget):
    with open(os.path.join(ROOT, parent)) as f:
        a = f.read().splitlines()
    with open(os.path.join(ROOT, variant)) as f:
        b = f.read().splitlines()
    changes = [line for line in list(difflib.unified_diff(a, b, lineterm="", n=0))[2:] if line[:1] in "+-"]
    assert 0 < len(changes) <= budget, f"diff {parent} {variant}: {len(changes)} changed lines > {budget}"
    assert b[0] == a[0] == "# Docs: docs/NAME.md in r2n, the R2N paper's reference implementation (NAME: this file's name)"
