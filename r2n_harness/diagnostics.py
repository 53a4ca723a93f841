"""`--diagnostics`: what a run logs to explain its numbers, computed apart from training so that
a run's numbers are the same with or without it (docs/running.md, "Watching a run").

- `pbrl/reward_true_corr`, `pbrl/heldout_accuracy`: how well the reward ensemble tracks the true
  reward, after each feedback round;
- `pbrl/reward_steps`: the reward optimiser's steps so far;
- `features/{net}/relevant_weight_frac` and `features/{net}/chance`: the share of each input
  layer's absolute weight on the real features and actions, at each evaluation."""
import torch

TRANSITIONS = 10_000  # stored transitions behind `pbrl/reward_true_corr`, at fixed relative positions
PAIRS = 256  # new pairs per round for `pbrl/heldout_accuracy`: oracle labels, not trained on or counted


def read_noisy(x: torch.Tensor, noise) -> torch.Tensor:
    """Stored rows as the networks read them: with `--noise-resample`, fresh noise columns."""
    return x if noise is None else noise.refresh_(x.clone())


def optimizer_steps(optimizer) -> int:
    """Optimiser steps so far (`pbrl/reward_steps`): Adam's count, via a wrapper's `optimizer`."""
    states = getattr(optimizer, "optimizer", optimizer).state.values()
    return max((int(state["step"]) for state in states), default=0)


@torch.no_grad()
def log_reward_diagnostics(writer, global_step: int, seed: int, model, rb,
                           store, positions: torch.Tensor, n_pairs: int, segment_size: int):
    """How well the ensemble mean tracks the true reward (logs only): Pearson correlation on stored
    transitions at fixed relative buffer `positions`; preference accuracy against the oracle on
    `n_pairs` fresh segment pairs, never in the dataset or budget, ties left out. A generator of
    their own makes the pairs fresh each round, the same in a rerun, training's draws unchanged."""
    device, noise = rb.obs.device, rb.noise
    with torch.random.fork_rng(devices=[device] if device.type == "cuda" else []):
        torch.manual_seed(seed + global_step)
        idx = (positions * rb.size).long()
        predicted = model(torch.cat([read_noisy(rb.obs[idx], noise), rb.actions[idx]], 1)).mean(0)
        correlation = torch.corrcoef(torch.stack([predicted, rb.true_rewards[idx]]))[0, 1]
        segments, true_rewards = store.sample_segments(n_pairs, segment_size)
        returns = (model(read_noisy(segments, noise).flatten(0, 2)).mean(0)
                   .view(*segments.shape[:3]).sum(-1))
        # the oracle: B-Pref's teacher without noise, margin or discount
        labels = (true_rewards[:, 1].sum(-1) > true_rewards[:, 0].sum(-1)).float()
    strict = true_rewards[:, 0].sum(-1) != true_rewards[:, 1].sum(-1)
    accuracy = (((returns[:, 1] > returns[:, 0]).float() == labels) & strict).sum() / strict.sum()
    correlation, accuracy = torch.stack([correlation, accuracy]).tolist()
    writer.add_scalar("pbrl/reward_true_corr", correlation, global_step)
    writer.add_scalar("pbrl/heldout_accuracy", accuracy, global_step)


def input_layers(agent) -> dict:
    """The input layers of the actor and of both critics, by the names the logs use."""
    return {name: getattr(agent, name).net[0].weight for name in ("actor", "qf1", "qf2")}


@torch.no_grad()
def relevant_weight_frac(weight: torch.Tensor, obs_dim_real: int, obs_dim: int) -> tuple:
    """The share of an input layer's absolute weight on relevant columns, and its chance level.

    The layer is (out, in) on [real obs | noise | action]. Relevant columns are the real features
    and the actions, as in `relevant_active_frac`. Chance is the relevant columns' share of all
    columns. A zero weight adds nothing, so a sparse layer counts its active weights only."""
    column = torch.arange(weight.shape[-1], device=weight.device)
    relevant = (column < obs_dim_real) | (column >= obs_dim)
    magnitude = weight.abs().sum(0)
    return magnitude[relevant].sum() / magnitude.sum(), relevant.float().mean()


def weight_shares(layers: dict, obs_dim_real: int, obs_dim: int) -> dict:
    """The tags `features/{net}/relevant_weight_frac` and
    `features/{net}/chance` of each layer, as floats.

    It reads the weights only, so a run's numbers are the same with or without it.
    One host sync per call."""
    values = {}
    for name, weight in layers.items():
        frac, chance = relevant_weight_frac(weight, obs_dim_real, obs_dim)
        values[f"features/{name}/relevant_weight_frac"] = frac
        values[f"features/{name}/chance"] = chance
    return dict(zip(values, torch.stack(list(values.values())).tolist()))
