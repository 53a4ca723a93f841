"""The main loop's step functions `act` and `store` compute what the loop computed inline before them, bit for bit,
and the actor's step computes the actor's gradients without the critics' weight gradients.

A later GPU capture replays these functions, so they must stay the same calls in the same order: the same random
stream, the same rows in the replay buffer and the episode store. Each script is checked with its own classes.
"""
import importlib

import numpy as np
import pytest
import torch

PBRL = ["pebble.py", "r2n_pebble.py", "set_pebble.py", "static_pebble.py", "l1_pebble.py", "dropconnect_pebble.py",
        "surf.py", "r2n_surf.py", "rune.py", "r2n_rune.py"]
ORACLES = ["sac.py", "anf_sac.py"]
OBS_DIM, ACT_DIM, HIDDEN = 5, 2, 16


@pytest.mark.parametrize("script", PBRL + ORACLES)
def test_act_is_the_inline_sampled_action_on_the_same_random_stream(script):
    module = importlib.import_module(script[:-3])
    torch.manual_seed(0)
    actor = module.Actor(OBS_DIM, ACT_DIM, HIDDEN)
    obs = torch.randn(OBS_DIM)
    torch.manual_seed(1)
    with torch.no_grad():
        expected = actor.get_action(obs.unsqueeze(0))[0][0]
    expected_next_draw = torch.rand(4)
    torch.manual_seed(1)
    action = module.act(actor, obs)
    assert torch.equal(action, expected)
    assert action.shape == (ACT_DIM,) and not action.requires_grad
    assert torch.equal(torch.rand(4), expected_next_draw), "act draws as many random numbers as the inline code"


def inline_store(script, objects, obs, action, next_obs, terminated, true_reward, physics):
    """The main loop's storing code as it was written inline before `store`."""
    if script in ORACLES:
        objects["rb"].add(obs, action, next_obs, terminated, float(true_reward), float(true_reward))
        return
    rb, episodes, reward_model = objects["rb"], objects["episodes"], objects["reward_model"]
    if script in ("rune.py", "r2n_rune.py"):
        with torch.no_grad():
            predicted_reward, predicted_std = reward_model.mean_reward(torch.cat([obs, action]).unsqueeze(0))
        rb.add(obs, action, next_obs, terminated, float(true_reward), predicted_reward[0], predicted_std[0])
    else:
        with torch.no_grad():
            predicted_reward = reward_model.mean_reward(torch.cat([obs, action]).unsqueeze(0))[0]
        rb.add(obs, action, next_obs, terminated, float(true_reward), predicted_reward)
    episodes.add(obs, action, float(true_reward), physics)


def storage(script, module):
    """A fresh replay buffer (3 rows, so it wraps), episode store (episodes of 2 steps) and reward ensemble."""
    objects = dict(rb=module.ReplayBuffer(3, OBS_DIM, ACT_DIM, torch.device("cpu")))
    if script in PBRL:
        torch.manual_seed(2)  # the same ensemble weights on both sides
        objects["reward_model"] = module.RewardEnsemble(OBS_DIM + ACT_DIM, HIDDEN, 2, 3)
        objects["episodes"] = module.EpisodeStore(2, 2, OBS_DIM, ACT_DIM, torch.device("cpu"))
    return objects


def same(a, b) -> bool:
    if isinstance(a, torch.Tensor):
        return isinstance(b, torch.Tensor) and a.dtype == b.dtype and torch.equal(a, b) and not b.requires_grad
    if isinstance(a, np.ndarray):
        return isinstance(b, np.ndarray) and a.dtype == b.dtype and np.array_equal(a, b)
    return type(a) is type(b) and a == b


@pytest.mark.parametrize("script", PBRL + ORACLES)
def test_store_writes_the_inline_rows(script):
    module = importlib.import_module(script[:-3])
    inline, stored = storage(script, module), storage(script, module)
    generator = torch.Generator().manual_seed(3)
    for step in range(5):  # wraps the buffer and completes two episodes
        obs, action, next_obs = (torch.randn(n, generator=generator) for n in (OBS_DIM, ACT_DIM, OBS_DIM))
        terminated, true_reward = step == 4, np.float64(0.25 * step - 0.3)  # the env's reward is a numpy float
        physics = np.full(3, float(step))
        inline_store(script, inline, obs, action, next_obs, terminated, true_reward, physics)
        if script in ORACLES:
            module.store(stored["rb"], obs, action, next_obs, terminated, float(true_reward))
        else:
            module.store(stored["rb"], obs, action, next_obs, terminated, float(true_reward),
                         stored["reward_model"], stored["episodes"], physics)
    for name in ("rb", "episodes"):
        if name in inline:
            expected, actual = vars(inline[name]), vars(stored[name])
            assert sorted(expected) == sorted(actual)
            different = [key for key in expected if not same(expected[key], actual[key])]
            assert not different, f"{script}: store wrote other {name}.{different} than the inline code"
    if script in PBRL:
        assert not torch.equal(stored["rb"].rewards, stored["rb"].true_rewards), "the agent's reward is predicted"


@pytest.mark.parametrize("script", PBRL + ORACLES)
def test_the_actor_step_gives_the_actor_its_gradients_and_leaves_the_critics_alone(script):
    """`actor_gradients` computes the actor's gradients only: the same as a full backward pass gives the actor, and
    the critics' `.grad` stays as the critic's step left it (a full pass would add the actor loss's gradients)."""
    module = importlib.import_module(script[:-3])
    torch.manual_seed(0)
    agent = module.make_agent(OBS_DIM, ACT_DIM, module.ene.suite_settings(module.Args(hidden_dim=HIDDEN)), torch.device("cpu"))
    unused = [torch.zeros(1)] * len(module.Batch._fields)
    data = module.Batch(*unused)._replace(obs=torch.randn(8, OBS_DIM))
    critics = list(agent.qf1.parameters()) + list(agent.qf2.parameters())
    for p in critics:
        p.grad = torch.randn_like(p)  # as the critic's step leaves them
    critic_grads = [p.grad.clone() for p in critics]
    torch.manual_seed(1)
    module.actor_gradients(agent, data)
    actor_grads = [p.grad.clone() for p in agent.actor.parameters()]
    assert all(torch.equal(p.grad, g) for p, g in zip(critics, critic_grads)), "the critics' gradients changed"

    torch.manual_seed(1)  # the full backward pass, as the actor's step was written before
    pi, log_pi, _ = agent.actor.get_action(data.obs)
    min_qf_pi = torch.min(agent.qf1(data.obs, pi), agent.qf2(data.obs, pi))
    agent.actor_optimizer.zero_grad()
    (agent.alpha * log_pi - min_qf_pi).mean().backward()
    for p, g in zip(agent.actor.parameters(), actor_grads):
        torch.testing.assert_close(p.grad, g, rtol=1e-6, atol=1e-7)
    assert not all(torch.equal(p.grad, g) for p, g in zip(critics, critic_grads)), "a full pass reaches the critics"
