"""SURF and RUNE (`surf.py`, `rune.py`) and their R2N versions: smoke runs, the mechanisms, and the patch invariant."""
import glob
import math
import os
import shutil
import subprocess

import pytest
import torch
import torch.nn.functional as F

import rune
import surf
from test_scripts import (COMMON_TAGS, ROOT, SPARSE_TAGS, SPARSE_TINY, TINY, TOPOLOGY_TAGS, check_progress,
                          run_script, scalars)

# TINY, shortened to two feedback rounds (500, 1000) and two evaluations (600, 1200); segments of 20 are stored as
# 30 steps by SURF (crop 5), inside the 100-step episodes. SURF's tau is lowered so that pseudo-labels are kept.
SHORT = ["--total-timesteps", "1200", "--eval-freq", "600"]
SCRIPT_TAGS = {
    "rune.py": ["pbrl/beta", "losses/rune_bonus"], "r2n_rune.py": ["pbrl/beta", "losses/rune_bonus"],
    "surf.py": ["pbrl/pseudo_label_rate"], "r2n_surf.py": ["pbrl/pseudo_label_rate"],
}


@pytest.mark.parametrize("script", ["rune.py", "surf.py", "r2n_rune.py", "r2n_surf.py"])
def test_smoke_reaches_every_phase(script, tmp_path):
    sparse = script.startswith("r2n_")
    args = TINY + SHORT + (SPARSE_TINY if sparse else []) + (["--surf-tau", "0.6"] if "surf" in script else [])
    result = run_script(script, args + ["--exp-name", "smoke"], tmp_path, copied=True)  # a copy, alone
    (run_dir,) = glob.glob(str(tmp_path / "runs" / "*"))
    values = scalars(run_dir)

    expected = COMMON_TAGS + SCRIPT_TAGS[script] + (SPARSE_TAGS + TOPOLOGY_TAGS if sparse else [])
    missing = [tag for tag in expected if tag not in values]
    assert not missing, f"missing tags {missing}"
    for tag in expected:
        assert all(math.isfinite(v) for v in values[tag]), f"{tag} has non-finite values {values[tag]}"
    assert values["pbrl/total_feedback"] == [5, 10]
    assert len(values["eval/episodic_return"]) == 2 and result.stdout.count("eval_return=") == 2
    check_progress(result.stdout)
    if "rune" in script:  # logged every 100 steps from the first feedback round (500) on, with the decayed weight
        assert values["pbrl/beta"] == pytest.approx([rune.rune_beta(t, 0.05, 1e-5) for t in range(500, 1200, 100)])
        # the bonus's size, from the SAC updates after the first round on: beta x a mean population std
        assert len(values["losses/rune_bonus"]) == 6 and all(0 <= v <= 0.05 for v in values["losses/rune_bonus"])
    else:
        assert all(0 <= v <= 1 for v in values["pbrl/pseudo_label_rate"])

    checkpoint = torch.load(os.path.join(run_dir, "smoke.cleanrl_model"), weights_only=False)
    module = __import__(script[:-3])
    module.Actor(51, 1, 32).load_state_dict(checkpoint["actor"])
    module.SoftQNetwork(51, 1, 32).load_state_dict(checkpoint["qf2"])
    assert len(checkpoint["reward_models"]) == 3 and checkpoint["global_step"] == 1200
    if sparse:
        assert sorted(checkpoint["masks"]) == ["actor", "qf1", "qf2", "reward0", "reward1", "reward2"]
        assert torch.all(checkpoint["actor"]["net.0.weight"][checkpoint["masks"]["actor"] == 0] == 0)


@pytest.mark.parametrize("method", ["surf", "rune"])
def test_r2n_version_is_the_r2n_patch_applied(method, tmp_path):
    """`diff pebble.py r2n_pebble.py` applied to surf.py / rune.py (no fuzz) gives r2n_surf.py / r2n_rune.py exactly."""
    if shutil.which("patch") is None or shutil.which("diff") is None:
        pytest.skip("needs diff and patch")
    r2n_patch = subprocess.run(["diff", "-u", "pebble.py", "r2n_pebble.py"], cwd=ROOT, capture_output=True).stdout
    shutil.copy(os.path.join(ROOT, f"{method}.py"), tmp_path / "patched.py")
    result = subprocess.run(["patch", "--fuzz=0", "patched.py"], input=r2n_patch, cwd=tmp_path, capture_output=True)
    assert result.returncode == 0, result.stdout.decode() + result.stderr.decode()
    with open(tmp_path / "patched.py", "rb") as patched, open(os.path.join(ROOT, f"r2n_{method}.py"), "rb") as r2n:
        assert patched.read() == r2n.read(), f"r2n_{method}.py is not the R2N patch applied to {method}.py"


@pytest.mark.parametrize("script, flag", [("surf.py", "--surf-crop"), ("rune.py", "--rune-beta-init")])
def test_help_and_bad_input(script, flag, tmp_path):
    assert flag in run_script(script, ["--help"], tmp_path).stdout
    bad = ["--surf-crop", "45"] if script == "surf.py" else ["--rune-beta-init", "-1"]  # 20 + 2 * 45 > 100 steps
    result = run_script(script, TINY + bad, tmp_path, check=False)
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert result.returncode != 0 and len(lines) == 1 and flag in lines[0], result.stderr
    assert not os.path.exists(tmp_path / "runs")


# RUNE
def test_rune_beta_schedule():
    assert rune.rune_beta(0, 0.05, 1e-5) == 0.05
    for t, beta in [(10_000, 0.0452), (100_000, 0.0184), (200_000, 0.0068), (500_000, 3.4e-4)]:
        assert rune.rune_beta(t, 0.05, 1e-5) == pytest.approx(beta, rel=0.02)  # REFERENCE_NOTES Part A 8
    assert rune.rune_beta(123, 0.05, 1e-5) == pytest.approx(0.05 * (1 - 1e-5) ** 123)
    assert rune.rune_beta(1000, 0.05, 0.0) == 0.05


def test_rune_stores_population_std_of_members():
    torch.manual_seed(0)
    model = rune.RewardEnsemble(4 + 2, 8, 2, 3)
    rb = rune.ReplayBuffer(10, 4, 2, torch.device("cpu"))
    for _ in range(7):
        rb.add(torch.randn(4), torch.randn(2), torch.randn(4), False, 0.0, torch.tensor(9.0), torch.tensor(9.0))
    rb.relabel(model.mean_reward, chunk=3)  # chunks of 3, 3, 1
    with torch.no_grad():
        members = model(torch.cat([rb.obs[:7], rb.actions[:7]], 1))  # (3, 7)
    assert torch.allclose(rb.rewards[:7], members.mean(0), atol=1e-6)
    assert torch.allclose(rb.stds[:7], members.std(0, correction=0), atol=1e-6)
    assert torch.allclose(rb.stds[:7], torch.tensor(members.numpy().std(0)), atol=1e-6)  # numpy's ddof=0
    assert torch.all(rb.rewards[7:] == 0) and torch.all(rb.stds[7:] == 0)
    batch = rb.sample(5)
    assert torch.equal(batch.stds, rb.stds[batch.indices]) and torch.equal(batch.rewards, rb.rewards[batch.indices])


def test_rune_batch_adds_beta_sigma_to_the_rewards_for_the_critic_target():
    rewards, stds, other = torch.tensor([0.5, -0.2]), torch.tensor([0.1, 0.3]), torch.zeros(2)
    data = rune.Batch(obs=other, actions=other, rewards=rewards, next_obs=other, dones=other, indices=other, stds=stds)
    bonus = rune.rune_batch(data, 0.04)
    assert torch.allclose(bonus.rewards, torch.tensor([0.504, -0.188]))
    assert all(getattr(bonus, name) is getattr(data, name) for name in data._fields if name != "rewards")
    source = open(os.path.join(ROOT, "rune.py")).read()
    # in the updates after the critic reset and in every later one; pre-training's reward is the state entropy alone
    assert source.count("sac_update(agent, rune_batch(rb.sample(args.batch_size), beta), loop, args)") == 1
    assert source.count("sac_update(agent, rune_batch(data, beta), loop, args)") == 1  # its bonus logged too
    assert "rune_batch" not in source[source.index("if global_step < pebble_start:"):source.index("elif global_step == pebble_start:")]


# SURF
def test_surf_crop_lengths_and_windows():
    torch.manual_seed(0)
    mask = surf.temporal_crop((3, 2000), 60, 50, 5, torch.device("cpu"))  # (E, B, 2, S)
    assert mask.shape == (3, 2000, 2, 60)
    lengths = mask.sum(-1)
    assert torch.equal(lengths[..., 0], lengths[..., 1])  # one crop length per pair
    assert lengths.min() == 45 and lengths.max() == 55 and len(lengths.unique()) == 11
    steps = torch.arange(60).float()
    first = torch.where(mask.bool(), steps, 60.0).amin(-1)
    last = torch.where(mask.bool(), steps, -1.0).amax(-1)
    assert torch.equal(last - first + 1, lengths)  # a contiguous window, inside the 60 stored steps
    assert first.min() == 0 and last.max() == 59
    assert (first[..., 0] != first[..., 1]).float().mean() > 0.5  # the two segments are shifted independently


def test_surf_pseudo_labels_only_where_confident():
    returns = torch.tensor([[0.0, 5.0], [3.0, 0.0], [0.0, 0.1], [1.0, 1.0], [-2.0, 2.6]])
    labels, kept = surf.pseudo_labels(returns, tau=0.99)
    assert labels.tolist() == [1.0, 0.0, 1.0, 0.0, 1.0]
    assert kept.tolist() == [True, False, False, False, True]  # sigmoid(5) = 0.9933, sigmoid(3) = 0.953
    confidence = returns.softmax(-1).amax(-1)
    assert torch.equal(kept, confidence >= 0.99)


class CountingOptimizer:
    def __init__(self, optimizer):
        self.optimizer, self.steps = optimizer, 0

    def zero_grad(self):
        self.optimizer.zero_grad()

    def step(self):
        self.steps += 1
        self.optimizer.step()


@pytest.mark.parametrize("n_labels, epochs, batch_size, ratio", [(10, 50, 128, 10), (300, 2, 128, 0), (5, 1, 4, 3)])
def test_surf_round_trains_a_fixed_number_of_steps(n_labels, epochs, batch_size, ratio):
    torch.manual_seed(0)
    assert surf.surf_iterations(n_labels, epochs, batch_size) == math.ceil(epochs * n_labels / batch_size)
    assert surf.surf_iterations(1000, 50, 128) == 391
    device = torch.device("cpu")
    model = surf.RewardEnsemble(5, 8, 2, 3)
    optimizer = CountingOptimizer(torch.optim.Adam(model.parameters(), lr=1e-3))
    prefs = surf.PreferenceBuffer(n_labels, 6, 5, device)
    prefs.add(torch.randn(n_labels, 2, 6 + 2 * 2, 5), torch.randint(0, 2, (n_labels,)).float())
    unlabeled = surf.PreferenceBuffer(n_labels * ratio, 6, 5, device)
    unlabeled.add(torch.randn(n_labels * ratio, 2, 10, 5), torch.zeros(n_labels * ratio))
    assert prefs.segments.shape == (n_labels, 2, 10, 5)
    loss, accuracy, trained_epochs, rate = surf.train_reward(model, optimizer, prefs, unlabeled, batch_size, epochs,
                                                             crop=2, tau=0.5, lam=1.0, mu=1)
    iterations = math.ceil(epochs * n_labels / batch_size)
    assert optimizer.steps == iterations  # no early stop
    assert math.isfinite(loss) and 0 <= accuracy <= 1
    sizes = [min(batch_size, n_labels - start) for start in range(0, n_labels, batch_size)]  # one pass, then again
    assert trained_epochs == pytest.approx(sum((sizes * iterations)[:iterations]) / n_labels)
    assert rate == (1.0 if ratio else 0.0)  # tau 0.5: every pseudo-label is confident enough


def test_surf_unlabeled_loss_averages_over_the_whole_minibatch():
    returns = torch.tensor([[[0.0, 2.0], [1.0, 0.0], [0.0, 0.0], [3.0, 1.0]]])  # (E=1, B=4, 2)
    targets, kept = torch.tensor([[1.0, 0.0, 0.0, 0.0]]), torch.tensor([[True, False, False, True]])
    expected = (F.cross_entropy(returns[0, 0:1], torch.tensor([1])) + F.cross_entropy(returns[0, 3:4], torch.tensor([0])))
    assert torch.allclose(surf.pseudo_label_loss(returns, targets, kept), expected / 4)  # kept pairs / whole minibatch


class GradientRecorder:
    """An optimiser that records each step's gradient and leaves the parameters alone."""

    def __init__(self, parameters):
        self.parameters, self.gradients = list(parameters), []

    def zero_grad(self):
        for p in self.parameters:
            p.grad = None

    def step(self):
        self.gradients.append(torch.cat([p.grad.flatten() for p in self.parameters]))


def test_surf_step_is_surfs_loss():
    """A reward step's gradient is that of SURF's loss written out on its own: per member, the Bradley-Terry loss of
    its cropped labelled pairs plus lambda x the pseudo-label loss of its cropped unlabelled pairs, whose pseudo-labels
    come from their uncropped central steps and are kept where confident."""
    device, members, batch, crop, segment, lam, tau = torch.device("cpu"), 3, 8, 2, 6, 0.7, 0.6
    torch.manual_seed(0)
    prefs = surf.PreferenceBuffer(6, segment, 5, device)
    prefs.add(torch.randn(6, 2, segment + 2 * crop, 5), torch.tensor([0.0, 1.0, 1.0, 0.5, 0.0, 1.0]))
    unlabeled = surf.PreferenceBuffer(13, segment, 5, device)
    unlabeled.add(torch.randn(13, 2, segment + 2 * crop, 5) * 3, torch.zeros(13))
    model = surf.RewardEnsemble(5, 8, 2, members)
    recorder = GradientRecorder(model.parameters())
    torch.manual_seed(1)
    surf.train_reward(model, recorder, prefs, unlabeled, batch, 1, crop, tau, lam, 1)
    assert len(recorder.gradients) == 1  # ceil(1 epoch x 6 labels / 8) steps
    # the same draws, in the step's order: labelled minibatch, its crops, unlabelled minibatch, its crops
    torch.manual_seed(1)
    indices = next(surf.member_minibatches(6, members, batch, device))
    crops = surf.temporal_crop(indices.shape, segment + 2 * crop, segment, crop, device)
    indices_u = next(surf.member_minibatches(13, members, batch, device))
    crops_u = surf.temporal_crop(indices_u.shape, segment + 2 * crop, segment, crop, device)
    segments, labels = prefs.segments[indices], prefs.labels[indices]  # (E, 6, 2, S, D)
    rewards = model(segments.flatten(1, 3)).view(*segments.shape[:4])
    labelled = F.binary_cross_entropy_with_logits(
        (rewards * crops).sum(-1).diff(dim=-1).squeeze(-1), labels, reduction="none").mean(-1)
    rewards_u = model(unlabeled.segments[indices_u].flatten(1, 3)).view(members, 8, 2, -1)
    central = rewards_u[..., crop : crop + segment].detach().sum(-1)
    confident = torch.sigmoid((central[..., 1] - central[..., 0]).abs()) >= tau
    assert 0 < confident.float().mean() < 1  # both kinds of unlabelled pair are in the minibatch
    pseudo = (central[..., 1] > central[..., 0]).float()
    unlabelled = (confident * F.binary_cross_entropy_with_logits(
        (rewards_u * crops_u).sum(-1).diff(dim=-1).squeeze(-1), pseudo, reduction="none")).sum(-1) / 8
    model.zero_grad()
    (labelled + lam * unlabelled).sum().backward()
    expected = torch.cat([p.grad.flatten() for p in model.parameters()])
    assert torch.allclose(recorder.gradients[0], expected, rtol=1e-5, atol=1e-6)


def test_surf_without_confident_pseudo_labels_trains_on_labels_only():
    """With tau above 1 no pseudo-label is kept: the step equals a labelled-only step (lambda 0)."""
    device = torch.device("cpu")
    prefs = surf.PreferenceBuffer(4, 6, 5, device)
    prefs.add(torch.randn(4, 2, 10, 5), torch.tensor([0.0, 1.0, 1.0, 0.5]))
    unlabeled = surf.PreferenceBuffer(8, 6, 5, device)
    unlabeled.add(torch.randn(8, 2, 10, 5), torch.zeros(8))
    params = []
    for lam, tau in [(1.0, 1.01), (0.0, 0.5)]:
        torch.manual_seed(1)
        model = surf.RewardEnsemble(5, 8, 2, 3)
        torch.manual_seed(2)
        surf.train_reward(model, torch.optim.SGD(model.parameters(), lr=0.1), prefs, unlabeled, 4, 3, 2, tau, lam, 1)
        params.append(torch.cat([p.detach().flatten() for p in model.parameters()]))
    assert torch.allclose(params[0], params[1], atol=1e-6)


def test_surf_teacher_and_queries_use_the_central_steps():
    torch.manual_seed(0)
    device = torch.device("cpu")
    store = surf.EpisodeStore(4, 40, 3, 1, device)
    for t in range(80):
        store.add(torch.full((3,), float(t)), torch.zeros(1), float(t))
    model = surf.RewardEnsemble(4, 8, 2, 3)
    scored = []

    def scoring_model(x):
        scored.append(x)
        return model(x)

    scoring_model.ensemble_size = 3
    for sampling in ["uniform", "disagreement", "entropy"]:
        segments, true_rewards = surf.select_queries(scoring_model, store, 4, 10, sampling, 3, None, crop=5)
        assert segments.shape == (4, 2, 20, 4) and true_rewards.shape == (4, 2, 20)  # 10 + 2 * 5 stored steps
        assert torch.all(true_rewards.diff(dim=-1) == 1)  # contiguous steps of one episode
    # disagreement and entropy scored pools of 12 pairs on the central 10 steps: steps 5..14 of each stored segment
    assert [x.shape for x in scored] == [(12 * 2 * 10, 4)] * 2
    assert torch.all(scored[0].view(12, 2, 10, 4)[..., 0].diff(dim=-1) == 1)
