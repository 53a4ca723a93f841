"""Issue 44, item 4, prepared for a GPU: acting and storing as two CUDA graphs, one pinned copy each way per step.

Today a step acts (`act`), copies the action to the host (`.cpu()`, which waits for the GPU), steps the env, copies the
new observation to the device (`torch.as_tensor`) and stores the step (`store`: the reward prediction and about ten
small writes at host-side positions). Here the same work is two graphs: `act_graph` (the action, from a fixed
observation tensor) and `store_graph` (the writes at positions read from the device, the reward prediction, and the
new observation moved into the fixed one). The host packs the new observation, the true reward, `terminated` and the
three write positions into one pinned buffer and copies it in one non-blocking copy; the action comes back in one. The
positions stay counted on the host, as `ReplayBuffer.add` and `EpisodeStore.add` count them; the physics states stay
on the host.

    python results/gpu-speed/act_store_capture.py --device cuda [--script pebble] [--hidden-dim 1024] [--steps 2000]

Two arms from the same seed, fed the same observations and rewards (a stand-in env: seeded random arrays): `eager`
(the scripts' `act`, `.cpu()`, `torch.as_tensor` and `store`) and `graphs`. Checks, bit for bit, the actions, every
tensor of the replay buffer and the episode store, and the CUDA generator's state; times the host µs per step of each
(median of interleaved blocks). With `--device cpu` the `graphs` arm runs its two functions eagerly: the check that
they are today's numerics (tests/test_gpu_measure.py runs it).
"""
import argparse
import importlib
import json
import os
import statistics
import sys
import time

import numpy as np
import torch

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, ROOT)
OBS_DIM, ACT_DIM = 171, 6  # cheetah-run at --noise 0.9


class StandInEnv:
    """Observations, rewards and episode ends from a seeded generator, whatever the actions."""

    def __init__(self, seed: int, episode_length: int):
        self.rng, self.episode_length, self.t = np.random.default_rng(seed), episode_length, 0

    def reset(self) -> np.ndarray:
        self.t = 0
        return self.rng.standard_normal(OBS_DIM).astype(np.float32)

    def step(self, action: np.ndarray) -> tuple:
        self.t += 1
        obs = self.rng.standard_normal(OBS_DIM).astype(np.float32)
        return obs, float(self.rng.standard_normal()), False, self.t == self.episode_length


class Storage:
    """An arm's agent, reward model, replay buffer and episode store, built from one seed."""

    def __init__(self, module, args, device, capacity: int):
        torch.manual_seed(0)
        self.actor = module.Actor(OBS_DIM, ACT_DIM, args.hidden_dim).to(device)
        self.reward_model = module.RewardEnsemble(OBS_DIM + ACT_DIM, args.reward_hidden_dim, args.reward_layers,
                                                  args.ensemble_size).to(device)
        self.rb = module.ReplayBuffer(capacity, OBS_DIM, ACT_DIM, device)
        self.episodes = module.EpisodeStore(4, args.episode_length, OBS_DIM, ACT_DIM, device)


def eager_steps(module, s: Storage, env: StandInEnv, steps: int, device) -> list:
    """The scripts' loop body for acting and storing. Returns the host actions."""
    actions = []
    obs = torch.as_tensor(env.reset(), device=device)
    for _ in range(steps):
        action = module.act(s.actor, obs)
        env_action = action.cpu().numpy()
        actions.append(env_action.copy())
        next_obs, reward, terminated, truncated = env.step(env_action)
        next_obs = torch.as_tensor(next_obs, device=device)
        module.store(s.rb, obs, action, next_obs, terminated, float(reward), s.reward_model, s.episodes,
                     np.zeros(0))
        obs = next_obs
        if terminated or truncated:
            obs = torch.as_tensor(env.reset(), device=device)
    return actions


class Graphs:
    """Acting and storing as two graphs over fixed tensors (`capture=False`: the same functions, eagerly)."""

    def __init__(self, module, s: Storage, device, capture: bool):
        self.module, self.s, self.device, self.capture = module, s, device, capture
        pinned = device.type == "cuda"
        self.packed_host = torch.zeros(OBS_DIM + 5, pin_memory=pinned)  # next obs, reward, terminated, 3 positions
        self.packed = torch.zeros(OBS_DIM + 5, device=device)
        self.action_host = torch.zeros(ACT_DIM, pin_memory=pinned)
        self.obs = torch.zeros(OBS_DIM, device=device)
        self.action = torch.zeros(ACT_DIM, device=device)
        self.graphs = {}

    def act_step(self):
        self.action.copy_(self.module.act(self.s.actor, self.obs))

    @torch.no_grad()
    def store_step(self):
        """`store`'s writes at the packed positions; then the new observation becomes the one to act on."""
        rb, episodes = self.s.rb, self.s.episodes
        next_obs = self.packed[:OBS_DIM]
        reward = self.packed[OBS_DIM:OBS_DIM + 1]
        terminated = self.packed[OBS_DIM + 1:OBS_DIM + 2]
        pos = self.packed[OBS_DIM + 2:OBS_DIM + 3].long()
        row = self.packed[OBS_DIM + 3:OBS_DIM + 5].long()
        inputs = torch.cat([self.obs, self.action]).unsqueeze(0)  # [obs, action], as `store` forms it
        rb.obs.index_copy_(0, pos, self.obs.unsqueeze(0))
        rb.actions.index_copy_(0, pos, self.action.unsqueeze(0))
        rb.next_obs.index_copy_(0, pos, next_obs.unsqueeze(0))
        rb.dones.index_copy_(0, pos, terminated)
        rb.true_rewards.index_copy_(0, pos, reward)
        rb.rewards.index_copy_(0, pos, self.s.reward_model.mean_reward(inputs))
        flat = row[0:1] * episodes.episode_length + row[1:2]  # (slot, t) in the flattened store
        episodes.inputs.view(-1, OBS_DIM + ACT_DIM).index_copy_(0, flat, inputs)
        episodes.true_rewards.view(-1).index_copy_(0, flat, reward)
        self.obs.copy_(next_obs)

    def warm(self):
        """Capture both graphs before the first step; the warm-up's writes and draws are undone."""
        if not self.capture:
            return
        for name in ("act_step", "store_step"):
            state = torch.cuda.get_rng_state()
            snapshot = [t.clone() for t in self.tensors()]  # queued before the side stream's wait: taken first
            side = torch.cuda.Stream()
            side.wait_stream(torch.cuda.current_stream())
            with torch.cuda.stream(side):
                getattr(self, name)()
            torch.cuda.current_stream().wait_stream(side)
            graph = torch.cuda.CUDAGraph()
            with torch.cuda.graph(graph):
                getattr(self, name)()
            self.graphs[name] = graph
            for t, saved in zip(self.tensors(), snapshot):  # the warm-up wrote: put everything back
                t.copy_(saved)
            torch.cuda.set_rng_state(state)

    def tensors(self) -> list:
        rb, episodes = self.s.rb, self.s.episodes
        return [self.obs, self.action, rb.obs, rb.actions, rb.next_obs, rb.dones, rb.true_rewards, rb.rewards,
                episodes.inputs, episodes.true_rewards]

    def replay(self, name: str):
        if self.capture:
            self.graphs[name].replay()
        else:
            getattr(self, name)()

    def steps(self, env: StandInEnv, steps: int) -> list:
        rb, episodes = self.s.rb, self.s.episodes
        actions = []
        self.obs.copy_(torch.as_tensor(env.reset()))
        packed = self.packed_host.numpy()
        for _ in range(steps):
            self.replay("act_step")
            self.action_host.copy_(self.action, non_blocking=True)
            if self.device.type == "cuda":
                torch.cuda.current_stream().synchronize()  # the one wait for the GPU: the action
            env_action = self.action_host.numpy().copy()
            actions.append(env_action)
            next_obs, reward, terminated, truncated = env.step(env_action)
            packed[:OBS_DIM] = next_obs
            packed[OBS_DIM:] = (reward, float(terminated), rb.pos, episodes.n_complete % episodes.slots, episodes.t)
            self.packed.copy_(self.packed_host, non_blocking=True)
            self.replay("store_step")
            # the positions, counted on the host as `ReplayBuffer.add` and `EpisodeStore.add` count them
            rb.pos, rb.size = (rb.pos + 1) % rb.capacity, min(rb.size + 1, rb.capacity)
            episodes.t += 1
            if episodes.t == episodes.episode_length:
                episodes.n_complete, episodes.t = episodes.n_complete + 1, 0
            if terminated or truncated:
                self.obs.copy_(torch.as_tensor(env.reset()))
        return actions


def measure(script: str, device: torch.device, hidden_dim: int, episode_length: int, steps: int,
            blocks: int) -> dict:
    """Both arms over the same stand-in steps: the bit-for-bit check (the first block) and the timing (the others)."""
    module = importlib.import_module(script)
    args = module.ene.suite_settings(module.Args(hidden_dim=hidden_dim, episode_length=episode_length))
    capacity = (blocks + 1) * steps
    arms = {name: Storage(module, args, device, capacity) for name in ("eager", "graphs")}
    graphs = Graphs(module, arms["graphs"], device, capture=device.type == "cuda")
    graphs.warm()
    actions, rng_states, times = {}, {}, {name: [] for name in arms}
    for block in range(blocks + 1):
        for name, s in arms.items():
            torch.manual_seed(10 + block)
            env = StandInEnv(block, episode_length)
            if device.type == "cuda":
                torch.cuda.synchronize()
            start = time.perf_counter()
            done = eager_steps(module, s, env, steps, device) if name == "eager" else graphs.steps(env, steps)
            if device.type == "cuda":
                torch.cuda.synchronize()
            if block == 0:
                actions[name] = np.array(done)
                rng_states[name] = torch.cuda.get_rng_state() if device.type == "cuda" else torch.get_rng_state()
            else:
                times[name].append(1e6 * (time.perf_counter() - start) / steps)
    tensors = {name: [t.cpu() for t in (s.rb.obs, s.rb.actions, s.rb.next_obs, s.rb.dones, s.rb.true_rewards,
                                        s.rb.rewards, s.episodes.inputs, s.episodes.true_rewards)]
               for name, s in arms.items()}
    same = dict(actions=bool(np.array_equal(actions["eager"].view(np.int32), actions["graphs"].view(np.int32))),
                storage=[bool(torch.equal(a.view(torch.int32), b.view(torch.int32)))
                         for a, b in zip(tensors["eager"], tensors["graphs"])],
                rng=bool(torch.equal(rng_states["eager"], rng_states["graphs"])))
    return dict(device=torch.cuda.get_device_name() if device.type == "cuda" else "cpu", torch=torch.__version__,
                script=script, hidden_dim=hidden_dim, steps=steps, bitwise=same,
                host_us_per_step={name: statistics.median(t) for name, t in times.items()})


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--script", default="pebble")
    parser.add_argument("--hidden-dim", type=int, default=1024)
    parser.add_argument("--episode-length", type=int, default=1000)
    parser.add_argument("--steps", type=int, default=2000)
    parser.add_argument("--blocks", type=int, default=3, help="timing: interleaved blocks of `--steps` each")
    parser.add_argument("--out", default=None)
    cli = parser.parse_args()
    device = torch.device(cli.device)
    torch.set_num_threads(1)
    if device.type == "cuda":
        torch.cuda.set_stream(torch.cuda.Stream())
    result = measure(cli.script, device, cli.hidden_dim, cli.episode_length, cli.steps, cli.blocks)
    print(json.dumps(result), flush=True)
    if cli.out:
        with open(cli.out, "w") as f:
            json.dump(result, f, indent=1)


if __name__ == "__main__":
    main()
