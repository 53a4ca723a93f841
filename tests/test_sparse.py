"""Tests of the R2N sparse logic in r2n_pebble.py (spec: ALGORITHMS.md section 3).

Masks (`random_mask`), RigL topology updates (`rigl_update_`), the masked Adam wrapper (`SparseOptimizer`), the ANF
connectivity metric (`connectivity`), the weight share on relevant columns that every script logs
(`relevant_weight_frac`, in the harness's diagnostics), and a mechanism test: on a synthetic preference problem with 4
informative and 56 pure-noise input columns, RigL moves the reward members' input connections onto the informative
columns.
"""
import math

import pytest
import torch
import torch.nn as nn

import ene
import pebble as P
import r2n_harness.diagnostics as D
import r2n_pebble as R

CPU = torch.device("cpu")


def _flat(t: torch.Tensor) -> list:
    return t.reshape(-1).tolist()


def _positions(mask_row: torch.Tensor) -> set:
    return set(torch.nonzero(mask_row.reshape(-1)).flatten().tolist())


# ---------------------------------------------------------------- 1. random_mask


@pytest.mark.parametrize("sparsity", [0.0, 0.5, 0.8, 0.95, 0.99])
def test_random_mask_count_and_values(sparsity):
    torch.manual_seed(0)
    shape = torch.Size((7, 9))
    n = 63
    expected = n - math.floor(sparsity * n)
    mask = R.random_mask(shape, sparsity, CPU)
    assert mask.shape == shape
    assert set(_flat(mask)) <= {0.0, 1.0}
    assert int(mask.sum()) == expected


def test_random_mask_stacked_per_member():
    torch.manual_seed(1)
    shape = torch.Size((5, 7, 9))  # (E, out, in): one mask per member
    mask = R.random_mask(shape, 0.8, CPU)
    assert mask.shape == shape
    assert set(_flat(mask)) <= {0.0, 1.0}
    assert mask.sum((-2, -1)).tolist() == [63 - math.floor(0.8 * 63)] * 5  # 13 each, not 65 in total
    for a in range(5):
        for b in range(a + 1, 5):
            assert not torch.equal(mask[a], mask[b]), f"members {a} and {b} share a mask"


def test_random_mask_is_uniform_over_positions():
    torch.manual_seed(2)
    masks = R.random_mask(torch.Size((4000, 6, 5)), 0.8, CPU)  # 4000 independent (6, 5) masks, 6 active each
    frequency = masks.mean(0)
    assert torch.allclose(frequency, torch.full_like(frequency, 6 / 30), atol=0.03), frequency


# ---------------------------------------------------------------- 2. RigL on hand-built examples


def test_rigl_hand_built_with_regrowth():
    # one (3, 4) matrix, 5 active weights; drop floor(0.4 * 5) = 2
    weight = torch.tensor([
        [0.5, 0.0, -0.1, 0.0],
        [0.0, 0.3, 0.0, 0.05],
        [0.0, 0.0, -0.9, 0.0],
    ])
    mask = (weight != 0).float()
    # kept positions get the largest gradients of all (must not matter), the just-dropped (0, 2) the largest among
    # the non-kept (regrown), the inactive (2, 3) the second largest (grown); all others are smaller and distinct.
    grad = torch.tensor([
        [10.0, 0.1, -5.0, 0.2],
        [0.3, 11.0, -0.4, 0.5],
        [0.6, 0.7, 12.0, -4.0],
    ])
    exp_avg = torch.where(mask.bool(), torch.tensor(0.7), torch.tensor(0.0))
    exp_avg_sq = torch.where(mask.bool(), torch.tensor(0.2), torch.tensor(0.0))
    R.rigl_update_(weight, mask, grad, 0.4, [exp_avg, exp_avg_sq])

    expected_mask = torch.tensor([
        [1.0, 0.0, 1.0, 0.0],  # (0, 2) dropped and regrown
        [0.0, 1.0, 0.0, 0.0],  # (1, 3) dropped (smallest |w|)
        [0.0, 0.0, 1.0, 1.0],  # (2, 3) grown
    ])
    expected_weight = torch.tensor([
        [0.5, 0.0, 0.0, 0.0],  # the regrown weight restarts at 0
        [0.0, 0.3, 0.0, 0.0],
        [0.0, 0.0, -0.9, 0.0],
    ])
    assert torch.equal(mask, expected_mask)
    assert torch.equal(weight, expected_weight)
    assert int(mask.sum()) == 5
    kept = torch.tensor([[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]])
    assert torch.equal(exp_avg, 0.7 * kept)  # 0 at dropped (1, 3) and at grown (0, 2), (2, 3); unchanged when kept
    assert torch.equal(exp_avg_sq, 0.2 * kept)


def test_rigl_hand_built_without_regrowth():
    weight = torch.tensor([[0.5, 0.0, -0.1, 0.0], [0.0, 0.3, 0.0, 0.05], [0.0, 0.0, -0.9, 0.0]])
    mask = (weight != 0).float()
    grad = torch.tensor([[10.0, 3.0, 0.1, 0.2], [0.3, 11.0, -0.4, 0.5], [-2.0, 0.7, 12.0, 0.6]])
    moments = [mask * 0.7, mask * 0.2]
    R.rigl_update_(weight, mask, grad, 0.4, moments)
    expected_mask = torch.tensor([[1.0, 1.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [1.0, 0.0, 1.0, 0.0]])
    assert torch.equal(mask, expected_mask)
    assert torch.equal(weight, torch.tensor([[0.5, 0.0, 0.0, 0.0], [0.0, 0.3, 0.0, 0.0], [0.0, 0.0, -0.9, 0.0]]))
    kept = torch.tensor([[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]])
    assert torch.equal(moments[0], 0.7 * kept) and torch.equal(moments[1], 0.2 * kept)


def _rigl_reference(w: list, m: list, g: list, drop_fraction: float):
    """Plain-Python RigL on one flattened matrix with distinct |w| and |g| (unique answer)."""
    active = [i for i, v in enumerate(m) if v]
    n_drop = math.floor(drop_fraction * len(active))
    dropped = set(sorted(active, key=lambda i: abs(w[i]))[:n_drop])
    kept = set(active) - dropped
    candidates = [i for i in range(len(w)) if i not in kept]
    grown = set(sorted(candidates, key=lambda i: -abs(g[i]))[:n_drop])
    return kept, dropped, grown


def test_rigl_stacked_members_matches_reference():
    torch.manual_seed(3)
    E, out, inp = 3, 5, 6
    size = out * inp
    n_active = 12
    weight = torch.zeros(E, out, inp)
    mask = torch.zeros(E, out, inp)
    grad = torch.empty(E, out, inp)
    for e in range(E):
        active = torch.randperm(size)[:n_active]
        mask[e].view(-1)[active] = 1.0
        magnitudes = (torch.randperm(n_active).float() + 1) / 10  # distinct |w|
        signs = torch.where(torch.rand(n_active) < 0.5, -1.0, 1.0)
        weight[e].view(-1)[active] = magnitudes * signs
        grad[e].view(-1)[:] = (torch.randperm(size).float() + 1) * torch.where(torch.rand(size) < 0.5, -1.0, 1.0)
    # member 1: its smallest active weight gets the largest gradient of the matrix -> dropped, then regrown
    smallest = min(_positions(mask[1]), key=lambda i: abs(weight[1].view(-1)[i].item()))
    grad[1].view(-1)[smallest] = 1000.0
    exp_avg, exp_avg_sq = torch.rand(E, out, inp) * mask, torch.rand(E, out, inp) * mask + 0.01 * mask
    before = [t.clone() for t in (weight, mask, exp_avg, exp_avg_sq)]

    R.rigl_update_(weight, mask, grad, 0.25, [exp_avg, exp_avg_sq])  # floor(0.25 * 12) = 3 per member

    for e in range(E):
        kept, dropped, grown = _rigl_reference(_flat(before[0][e]), _flat(before[1][e]), _flat(grad[e]), 0.25)
        assert len(dropped) == len(grown) == 3
        assert _positions(mask[e]) == kept | grown, f"member {e}"
        w, w0 = weight[e].view(-1), before[0][e].view(-1)
        for i in range(size):
            if i in kept:
                assert w[i] == w0[i] and exp_avg[e].view(-1)[i] == before[2][e].view(-1)[i]
                assert exp_avg_sq[e].view(-1)[i] == before[3][e].view(-1)[i]
            else:  # dropped, grown, or inactive: weight and moments are 0
                assert w[i] == 0 and exp_avg[e].view(-1)[i] == 0 and exp_avg_sq[e].view(-1)[i] == 0
        assert int(mask[e].sum()) == n_active
    assert smallest in _positions(mask[1]) and weight[1].view(-1)[smallest] == 0  # regrown at 0
    assert not torch.equal(mask[0], before[1][0]) and not torch.equal(mask[2], before[1][2])


def test_rigl_no_drop_leaves_everything_unchanged():
    torch.manual_seed(4)
    mask = R.random_mask(torch.Size((2, 4, 5)), 0.8, CPU)  # 4 active per member: floor(0.2 * 4) = 0
    weight = torch.randn(2, 4, 5) * mask
    grad = torch.randn(2, 4, 5) * 100
    moments = [torch.rand(2, 4, 5) * mask, torch.rand(2, 4, 5) * mask]
    before = [t.clone() for t in (weight, mask, *moments)]
    R.rigl_update_(weight, mask, grad, 0.2, moments)
    for a, b in zip((weight, mask, *moments), before):
        assert torch.equal(a, b)


def test_top_k_random_ties_breaks_ties_at_random():
    torch.manual_seed(5)
    scores = torch.tensor([[3.0, 1.0, 1.0, 1.0, 1.0, 0.0]])
    picks = [tuple(sorted(R.top_k_random_ties(scores, 2)[0].tolist())) for _ in range(200)]
    assert all(p[0] == 0 and p[1] in (1, 2, 3, 4) for p in picks)  # the max always, then one of the tied
    assert {p[1] for p in picks} == {1, 2, 3, 4}


# ---------------------------------------------------------------- 3./4. SparseOptimizer invariants


def _small_model(seed: int, n_in: int = 20, hidden: int = 16):
    torch.manual_seed(seed)
    return nn.Sequential(nn.Linear(n_in, hidden), nn.ReLU(), nn.Linear(hidden, 1))


def test_density_constant_over_many_updates():
    model = _small_model(6)
    layer = model[0]
    opt = R.SparseOptimizer(torch.optim.Adam(model.parameters(), lr=1e-2), {"w": layer.weight}, 0.8, 0.2, 3)
    mask = opt.masks["w"]
    n_active = 320 - math.floor(0.8 * 320)
    assert int(mask.sum()) == n_active == 64
    assert torch.equal(layer.weight[mask == 0], torch.zeros(256))  # the initial mask is applied to the weights
    start = mask.clone()
    changed_on = []
    for step in range(1, 61):
        previous = mask.clone()
        x, y = torch.randn(32, 20), torch.randn(32, 1)
        loss = ((model(x) - y) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        assert opt.masks["w"] is mask
        assert int(mask.sum()) == n_active, f"step {step}"
        assert set(_flat(mask)) <= {0.0, 1.0}
        assert (layer.weight[mask == 0] == 0).all(), f"step {step}"
        if not torch.equal(mask, previous):
            changed_on.append(step)
    topology_steps = list(range(3, 61, 3))  # first at step == period
    assert set(changed_on) <= set(topology_steps)  # the mask only changes on topology steps
    assert len(changed_on) >= len(topology_steps) - 2, changed_on  # and (almost) every update changes it
    assert not torch.equal(mask, start)


def test_masked_weights_and_moments_stay_zero_through_adam():
    model = _small_model(7)
    layer = model[0]
    adam = torch.optim.Adam(model.parameters(), lr=1e-2)
    opt = R.SparseOptimizer(adam, {"w": layer.weight}, 0.8, 0.25, 4)
    mask = opt.masks["w"]
    checked_plain = checked_topology = 0
    for step in range(1, 41):
        x, y = torch.randn(64, 20) + 0.5, torch.randn(64, 1)  # every input non-zero: dense gradient everywhere
        old_mask, old_weight = mask.clone(), layer.weight.detach().clone()
        loss = ((model(x) - y) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        assert (layer.weight.grad != 0).float().mean() > 0.5  # the dense gradient is non-zero at masked positions
        assert (layer.weight.grad[old_mask == 0] != 0).any()
        opt.step()
        state = adam.state[layer.weight]
        inactive = mask == 0
        for tensor in (layer.weight, state["exp_avg"], state["exp_avg_sq"]):
            assert (tensor[inactive] == 0).all(), f"step {step}"
        if step % 4 == 0:
            # positions newly active, or dropped and regrown (active, was non-zero, now exactly 0): weight 0, moments 0
            grown = (mask == 1) & ((old_mask == 0) | ((layer.weight == 0) & (old_weight != 0)))
            assert grown.sum() > 0
            for tensor in (layer.weight, state["exp_avg"], state["exp_avg_sq"]):
                assert (tensor[grown] == 0).all(), f"step {step}"
            kept = (mask == 1) & ~grown
            assert (state["exp_avg_sq"][kept] > 0).all()  # the kept ones keep their moments
            checked_topology += 1
        else:
            assert torch.equal(mask, old_mask)
            assert (state["exp_avg_sq"][mask == 1] > 0).all()
            checked_plain += 1
    assert checked_plain == 30 and checked_topology == 10
    # grown weights then train: one more step moves them off zero
    grown_now = (mask == 1) & (layer.weight == 0)
    x, y = torch.randn(64, 20) + 0.5, torch.randn(64, 1)
    opt.zero_grad()
    ((model(x) - y) ** 2).mean().backward()
    opt.step()
    assert (layer.weight[grown_now] != 0).all()


# ---------------------------------------------------------------- 5. RigL uses the dense gradient of that step


def test_growth_follows_the_dense_gradient_linear():
    torch.manual_seed(8)
    layer = nn.Linear(10, 4)
    opt = R.SparseOptimizer(torch.optim.Adam(layer.parameters(), lr=1e-3), {"w": layer.weight}, 0.75, 0.2, 1)
    mask = opt.masks["w"]  # 40 - 30 = 10 active; every step is a topology step; drop floor(0.2 * 10) = 2
    chosen = torch.zeros(4, 10)
    chosen.view(-1)[torch.tensor([0, 2, 4, 6, 11, 13, 15, 22, 24, 33])] = 1.0  # columns 7 and 8 fully inactive
    mask.copy_(chosen)
    with torch.no_grad():
        layer.weight.copy_(torch.randn(4, 10) * chosen)
    # loss = sum_b sum_j c_j (W x_b)_j: dL/dW[j, i] = c_j * sum_b x[b, i]; large only on the inactive column 7
    x = torch.full((8, 10), 0.01)
    x[:, 7] = 1.0
    c = torch.tensor([1.0, 2.0, 3.0, 4.0])
    expected_grad = c[:, None] * x.sum(0)[None, :]
    opt.zero_grad()
    (layer(x) * c).sum().backward()
    assert torch.allclose(layer.weight.grad, expected_grad)
    opt.step()
    # the masked gradient is 0 on column 7; the dense one is largest at (3, 7) and (2, 7)
    grown = (mask == 1) & (chosen == 0)
    assert _positions(grown) == {3 * 10 + 7, 2 * 10 + 7}
    assert layer.weight[3, 7] == 0 and layer.weight[2, 7] == 0
    assert int(mask.sum()) == 10


def test_growth_follows_the_dense_gradient_mlp(monkeypatch):
    model = _small_model(9)
    layer = model[0]
    opt = R.SparseOptimizer(torch.optim.Adam(model.parameters(), lr=1e-2), {"w": layer.weight}, 0.8, 0.2, 5)
    mask = opt.masks["w"]
    calls = []
    real_rigl = R.rigl_update_

    def spy(weight, mask_, dense_grad, drop_fraction, moments):
        calls.append((weight.detach().clone(), mask_.clone(), dense_grad.clone(), drop_fraction))
        return real_rigl(weight, mask_, dense_grad, drop_fraction, moments)

    monkeypatch.setattr(R, "rigl_update_", spy)
    for step in range(1, 16):
        x, y = torch.randn(32, 20), torch.randn(32, 1)
        loss = ((model(x) - y) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        dense = layer.weight.grad.clone()  # this step's gradient, computed before the optimiser masks it
        old_mask = mask.clone()
        n_calls = len(calls)
        opt.step()
        if step % 5:
            assert len(calls) == n_calls and torch.equal(mask, old_mask)
            continue
        assert len(calls) == n_calls + 1
        w_after_adam, mask_before, grad_used, drop_fraction = calls[-1]
        assert torch.equal(grad_used, dense)  # the dense gradient, not the masked one
        assert (dense[old_mask == 0] != 0).sum() > 100
        assert torch.equal(mask_before, old_mask) and drop_fraction == 0.2
        # expected topology from the weights after this step's Adam update and this step's dense gradient
        n_drop = math.floor(0.2 * int(old_mask.sum()))
        magnitude = torch.where(old_mask.bool(), w_after_adam.abs(), torch.inf).view(-1)
        dropped = set(magnitude.topk(n_drop, largest=False).indices.tolist())
        kept = _positions(old_mask) - dropped
        candidates = dense.abs().view(-1).clone()
        candidates[list(kept)] = -torch.inf
        grown = set(candidates.topk(n_drop).indices.tolist())
        assert _positions(mask) == kept | grown, f"step {step}"
        assert grown - _positions(old_mask), "nothing new was grown"
        assert all(layer.weight.view(-1)[i] == 0 for i in grown)


# ---------------------------------------------------------------- 6. sparsity 0 is plain Adam


def test_sparsity_zero_is_plain_adam():
    torch.manual_seed(10)
    data = [(torch.randn(16, 20), torch.randn(16, 1)) for _ in range(25)]
    plain, wrapped = _small_model(11), _small_model(11)
    plain_opt = torch.optim.Adam(plain.parameters(), lr=1e-2)
    sparse_opt = R.SparseOptimizer(torch.optim.Adam(wrapped.parameters(), lr=1e-2), {"w": wrapped[0].weight},
                                   0.0, 0.2, 3)
    assert torch.equal(sparse_opt.masks["w"], torch.ones(16, 20))
    for x, y in data:
        for model, opt in ((plain, plain_opt), (wrapped, sparse_opt)):
            opt.zero_grad()
            ((model(x) - y) ** 2).mean().backward()
            opt.step()
    for a, b in zip(plain.parameters(), wrapped.parameters()):
        assert torch.equal(a, b)
    assert (wrapped[0].weight != 0).all()
    assert torch.equal(sparse_opt.masks["w"], torch.ones(16, 20))
    assert not torch.equal(plain[0].weight, _small_model(11)[0].weight)  # it did train


# ---------------------------------------------------------------- 7. connectivity


def test_connectivity_hand_built():
    # layout [real 0, 1 | noise 2, 3, 4 | action 5, 6]; non-zero counts per column: 3, 1 | 0, 2, 1 | 2, 0
    weight = torch.tensor([
        [0.1, 0.0, 0.0, 0.4, 0.0, -0.2, 0.0],
        [0.3, -0.5, -0.0, 0.0, 0.0, 0.6, 0.0],  # -0.0 is a zero weight
        [-0.7, 0.0, 0.0, 0.8, 0.9, 0.0, -0.0],
    ])
    metrics = R.connectivity(weight, obs_dim_real=2, obs_dim=5)
    assert float(metrics["relevant_degree"]) == pytest.approx((3 + 1 + 2 + 0) / 4)
    assert float(metrics["noise_degree"]) == pytest.approx((0 + 2 + 1) / 3)
    assert float(metrics["relevant_active_frac"]) == pytest.approx(6 / 9)
    # no action columns (actor input): relevant = real columns only
    metrics = R.connectivity(weight[:, :5], obs_dim_real=2, obs_dim=5)
    assert float(metrics["relevant_degree"]) == pytest.approx(2.0)
    assert float(metrics["noise_degree"]) == pytest.approx(1.0)
    assert float(metrics["relevant_active_frac"]) == pytest.approx(4 / 7)


def test_connectivity_without_noise_columns():
    weight = torch.tensor([[0.1, 0.0, 0.2], [0.0, 0.0, 0.3]])
    metrics = R.connectivity(weight, obs_dim_real=2, obs_dim=2)  # [real 0, 1 | action 2]
    assert "noise_degree" not in metrics
    assert float(metrics["relevant_degree"]) == pytest.approx(1.0)
    assert float(metrics["relevant_active_frac"]) == pytest.approx(1.0)


def test_relevant_weight_frac_hand_built():
    """The share of absolute weight on relevant columns (real features and actions), and its chance level."""
    # layout [real 0, 1 | noise 2, 3, 4 | action 5, 6]; |w| per column: 1.1, 0.5 | 0, 1.2, 0.9 | 0.8, 0
    weight = torch.tensor([
        [0.1, 0.0, 0.0, 0.4, 0.0, -0.2, 0.0],
        [0.3, -0.5, -0.0, 0.0, 0.0, 0.6, 0.0],
        [-0.7, 0.0, 0.0, 0.8, 0.9, 0.0, -0.0],
    ])
    frac, chance = D.relevant_weight_frac(weight, obs_dim_real=2, obs_dim=5)
    assert float(frac) == pytest.approx((1.1 + 0.5 + 0.8) / 4.5)
    assert float(chance) == pytest.approx(4 / 7)
    # the actor's input has no action columns: relevant = real columns only
    frac, chance = D.relevant_weight_frac(weight[:, :5], obs_dim_real=2, obs_dim=5)
    assert float(frac) == pytest.approx(1.6 / 3.7)
    assert float(chance) == pytest.approx(2 / 5)
    # a sparse layer counts its active weights only: masking out noise weights moves the share to the real columns
    mask = torch.ones_like(weight)
    mask[:, 3] = 0
    frac, _ = D.relevant_weight_frac(weight * mask, obs_dim_real=2, obs_dim=5)
    assert float(frac) == pytest.approx(2.4 / 3.3)
    # a dense layer with equal weight everywhere sits at chance
    frac, chance = D.relevant_weight_frac(torch.full((4, 7), -0.3), obs_dim_real=2, obs_dim=5)
    assert float(frac) == pytest.approx(float(chance))


def test_input_layers_and_their_weight_shares():
    """Every network that reads observations is logged, by name, with the chance level of its own input."""
    obs_dim_real, obs_dim, act_dim = 2, 5, 2
    args = P.ene.suite_settings(P.Args(hidden_dim=8))
    agent = P.make_agent(obs_dim, act_dim, args, CPU)
    reward_model = P.RewardEnsemble(obs_dim + act_dim, 4, 1, 3)
    layers = D.input_layers(agent)
    assert list(layers) == ["actor", "qf1", "qf2"]
    assert layers["qf1"] is agent.qf1.net[0].weight
    layers.update({f"reward{i}": weight for i, weight in enumerate(reward_model.weights[0])})  # as the main loop does

    values = D.weight_shares(layers, obs_dim_real, obs_dim)
    assert len(values) == 2 * len(layers)
    assert values["features/actor/chance"] == pytest.approx(2 / 5)
    assert values["features/reward1/chance"] == pytest.approx(4 / 7)
    frac, _ = D.relevant_weight_frac(reward_model.weights[0][1], obs_dim_real, obs_dim)
    assert values["features/reward1/relevant_weight_frac"] == pytest.approx(float(frac))
    assert all(type(value) is float for value in values.values())  # host values: the loop logs and saves them


# ---------------------------------------------------------------- 8. mechanism: RigL finds the informative columns

D_REAL, D_IN, SEGMENT, N_PAIRS = 4, 60, 10, 300
CHANCE = D_REAL / D_IN


def _train_sparse_reward(seed: int, period: int):
    """R2N's reward learning on a synthetic problem: 4 informative columns, 56 N(0, 1) noise columns redrawn on
    every read; the true per-step reward is sum_i w_i tanh(x_i) of the informative columns. Returns the
    relevant_active_frac per member and the masks (before, after)."""
    torch.manual_seed(seed)
    prefs = R.PreferenceBuffer(N_PAIRS, SEGMENT, D_IN, CPU, ene.NoiseSampler(D_REAL, D_IN - D_REAL))
    segments = torch.randn(N_PAIRS, 2, SEGMENT, D_IN)
    true_returns = (torch.tanh(segments[..., :D_REAL]) @ torch.tensor([1.0, -1.0, 0.7, -0.5])).sum(-1)
    prefs.add(segments, (true_returns[:, 1] > true_returns[:, 0]).float())
    model = R.RewardEnsemble(D_IN, 32, 2, 3)
    opt = R.SparseOptimizer(torch.optim.Adam(model.parameters(), lr=3e-3), {"reward": model.weights[0]},
                            0.8, 0.2, period)
    start = opt.masks["reward"].clone()
    # 200 epochs x 5 minibatches = 1000 optimiser steps; the last one is a topology step when period = 10
    _, accuracy, epochs = R.train_reward(model, opt, prefs, 64, 200, 1.01)
    assert epochs == 200 and opt.steps == 1000
    assert accuracy > 0.8  # it learned the reward
    fractions = [float(R.connectivity(w, D_REAL, D_IN)["relevant_active_frac"]) for w in model.weights[0]]
    return fractions, start, opt.masks["reward"]


def test_rigl_moves_reward_connections_onto_informative_columns():
    fractions, start, end = _train_sparse_reward(seed=0, period=10)
    initial = [float(m[:, :D_REAL].sum() / m.sum()) for m in start]
    # every member well above chance, and above where it started; on average more than twice chance
    assert all(f > 1.75 * CHANCE for f in fractions), (fractions, CHANCE)
    assert sum(fractions) / 3 > 2 * CHANCE, (fractions, CHANCE)
    assert all(f > i + 0.04 for f, i in zip(fractions, initial)), (fractions, initial)
    assert (end.sum((-2, -1)) == start.sum((-2, -1))).all()

    # control: no topology update ever happens, the connections stay where the random mask put them (near chance)
    control, start_c, end_c = _train_sparse_reward(seed=0, period=10**9)
    assert torch.equal(start_c, end_c)
    assert all(c < 1.5 * CHANCE for c in control), (control, CHANCE)
    assert min(fractions) > max(control) + 0.04, (fractions, control)
