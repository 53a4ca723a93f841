"""The actor's step with and without the critics' weight gradients, timed in one run, interleaved:
`python results/gpu-speed/actor_step.py [--hidden-dim 1024] [--batch-size 1024] [--repeats 15] [--cuda] [--tf32]`.

`actor_gradients` (r2n_pebble.py) asks autograd for the actor's gradients alone. The full backward pass it replaced
also computed the critics' weight gradients, which nothing reads. Prints the median seconds of each and their ratio.
Observations have cheetah-run's 171 features at noise 0.9."""
import argparse
import os
import statistics
import sys
import time

import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
import r2n_pebble  # noqa: E402

OBS_DIM, ACT_DIM = 171, 6


def full_backward(agent, data):
    """The actor's step with a full backward pass, as it was written before."""
    pi, log_pi, _ = agent.actor.get_action(data.obs)
    min_qf_pi = torch.min(agent.qf1(data.obs, pi), agent.qf2(data.obs, pi))
    agent.actor_optimizer.zero_grad()
    (agent.alpha * log_pi - min_qf_pi).mean().backward()


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--hidden-dim", type=int, default=1024)
    parser.add_argument("--batch-size", type=int, default=1024)
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--cuda", action="store_true")
    parser.add_argument("--tf32", action="store_true", help="TF32 matmuls, as the scripts' --tf32")
    args = parser.parse_args()
    torch.set_num_threads(1)
    torch.backends.cuda.matmul.allow_tf32 = args.tf32
    device = torch.device("cuda" if args.cuda else "cpu")
    torch.manual_seed(0)
    settings = r2n_pebble.ene.suite_settings(r2n_pebble.Args(hidden_dim=args.hidden_dim))
    agent = r2n_pebble.make_agent(OBS_DIM, ACT_DIM, settings, device)
    unused = [torch.zeros(1, device=device)] * len(r2n_pebble.Batch._fields)
    data = r2n_pebble.Batch(*unused)._replace(obs=torch.randn(args.batch_size, OBS_DIM, device=device))
    steps = {"full backward": full_backward, "actor only": r2n_pebble.actor_gradients}
    seconds = {name: [] for name in steps}
    for i in range(3 + args.repeats):  # 3 warm-up rounds
        for name, step in steps.items():
            if args.cuda:
                torch.cuda.synchronize()
            start = time.perf_counter()
            step(agent, data)
            if args.cuda:
                torch.cuda.synchronize()
            if i >= 3:
                seconds[name].append(time.perf_counter() - start)
    full, actor = (statistics.median(seconds[name]) for name in steps)
    print(f"{args.hidden_dim} wide, batch {args.batch_size}, {device}{', TF32' if args.tf32 else ''}: "
          f"full backward {1e3 * full:.2f} ms, "
          f"actor only {1e3 * actor:.2f} ms, ratio {full / actor:.3f}")


if __name__ == "__main__":
    main()
