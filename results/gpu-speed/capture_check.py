"""Which way of capturing the SAC gradients works on this GPU (issue 19's first GPU session): the plain capture, and
the whole run on a non-default stream. Prints one line per variant."""
import sys

import torch

sys.path.insert(0, ".")
import pebble  # noqa: E402
from r2n_harness.cuda_graph import CudaGraph  # noqa: E402


def attempt(name, use_side_stream):
    def body():
        device = torch.device("cuda")
        args = pebble.ene.suite_settings(pebble.Args(hidden_dim=32, batch_size=16))
        torch.manual_seed(0)
        agent = pebble.make_agent(6, 2, args, device)
        steps = {n: CudaGraph(getattr(pebble, n)) for n in ("critic_gradients", "actor_gradients", "target_update")}
        saved = {n: getattr(pebble, n) for n in steps}
        for n, f in steps.items():
            setattr(pebble, n, f)
        try:
            loop = pebble.Loop()
            for step in range(6):
                batch = pebble.Batch(torch.randn(16, 6, device=device), torch.rand(16, 2, device=device),
                                     torch.randn(16, device=device), torch.randn(16, 6, device=device),
                                     torch.zeros(16, device=device), torch.arange(16, device=device))
                pebble.sac_update(agent, batch, loop, args)
            torch.cuda.synchronize()
            return {k: round(v.item(), 4) for k, v in loop.losses.items()}
        finally:
            for n, f in saved.items():
                setattr(pebble, n, f)
    try:
        if use_side_stream:
            with torch.cuda.stream(torch.cuda.Stream()):
                out = body()
        else:
            out = body()
        print(f"{name}: ok {out}", flush=True)
    except Exception as e:
        print(f"{name}: FAILED {type(e).__name__}: {str(e).splitlines()[0]}", flush=True)


attempt(sys.argv[1], sys.argv[1] == "side-stream")
