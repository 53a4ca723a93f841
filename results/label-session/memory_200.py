"""The labelling app's memory over a 200-clip session at the default segment size (issue 72): a run folder of
`--rounds` rounds of `--queries` queries of `--steps`-step segments of real physics states (a seeded random-action
rollout of the task), a real `label_app.py` on it with its defaults, and every clip fetched once, in order, as a page
shows them. The app's resident memory is read from `/proc` after each clip; its peak (VmHWM) at the end. Writes
`memory.json` (the RSS after each clip, the peak, the seconds per clip) to `--out`.

    python results/label-session/memory_200.py --out results/label-session/memory-200

The defaults (10 rounds of 10 queries, 50 steps, cartpole-swingup) are 200 clips: 100 queries, two clips each.
`tests/test_label_app_session.py` runs the same probe at 20 clips in the suite and holds the per-clip growth to the
slope the bound below was stated with."""
import argparse
import json
import os
import subprocess
import sys
import time
import urllib.request

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, ROOT)
import benchmark  # noqa: E402
import ene  # noqa: E402


def write_run(run: str, env_id: str, rounds: int, queries: int, steps: int, seed: int = 0):
    """`queries/{r}.npz` as `--teacher external` writes them, each segment a stretch of one random-action rollout."""
    os.makedirs(os.path.join(run, "queries"))
    env = ene.make_env(env_id, seed, 0.9)
    rng = np.random.default_rng(seed)
    obs, _ = env.reset(seed=seed)
    for r in range(rounds):
        shape = (queries, 2, steps)
        physics, obs_rows = [], []
        for _ in range(queries * 2 * steps):
            physics.append(env.physics_state())
            obs_rows.append(obs)
            obs, _, terminated, truncated, _ = env.step(rng.uniform(-1, 1, env.action_space.shape))
            if terminated or truncated:
                obs, _ = env.reset()
        act_dim = env.action_space.shape[0]
        np.savez(os.path.join(run, "queries", f"{r}.npz"), env_id=env_id,
                 obs=np.array(obs_rows, np.float32).reshape(*shape, -1),
                 actions=np.zeros((*shape, act_dim), np.float32),
                 physics=np.array(physics).reshape(*shape, -1), true_rewards=np.zeros(shape))
    env.close()


def status(pid: int, field: str) -> float:
    """A `/proc/{pid}/status` field in MB."""
    with open(f"/proc/{pid}/status") as f:
        return int(next(line for line in f if line.startswith(field)).split()[1]) / 1024


def probe(run: str, port: int, rounds: int, queries: int, app_path: str = os.path.join(ROOT, "label_app.py")) -> dict:
    """Start the app (`app_path`) on `run`, fetch every clip once, return the memory record: the RSS after each clip
    and each clip's bytes (with the default cache, the 200 clips are all kept: their sum is the cache's size)."""
    app = subprocess.Popen([sys.executable, app_path, run, "--port", str(port)],
                           stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                           env=dict(os.environ, OMP_NUM_THREADS="1"))
    try:
        assert app.stdout.readline().startswith("labelling "), "the app did not start"
        started = status(app.pid, "VmRSS")
        rss, seconds, sizes = [], [], []
        for r in range(rounds):
            for q in range(queries):
                for side in (0, 1):
                    began = time.time()
                    with urllib.request.urlopen(f"http://127.0.0.1:{port}/clip/{r}/{q}/{side}.gif", timeout=600) as reply:
                        sizes.append(len(reply.read()))
                        assert reply.status == 200 and sizes[-1] > 0
                    seconds.append(time.time() - began)
                    rss.append(status(app.pid, "VmRSS"))
        peak = status(app.pid, "VmHWM")
    finally:
        app.terminate()
        output = app.communicate(timeout=60)[0]
    assert "Traceback" not in output, output
    return {"clips": len(rss), "rss_at_start_mb": started, "rss_after_each_clip_mb": rss, "peak_mb": peak,
            "clip_mb": [size / 2 ** 20 for size in sizes],
            "seconds_per_clip": float(np.mean(seconds))}


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", required=True)
    parser.add_argument("--env-id", default="cartpole-swingup")
    parser.add_argument("--rounds", type=int, default=10)
    parser.add_argument("--queries", type=int, default=10)
    parser.add_argument("--steps", type=int, default=50)
    parser.add_argument("--port", type=int, default=8731)
    a = parser.parse_args()
    run = os.path.join(a.out, "run")
    write_run(run, a.env_id, a.rounds, a.queries, a.steps)
    record = {"env_id": a.env_id, "rounds": a.rounds, "queries": a.queries, "steps": a.steps,
              "cpu": benchmark.cpu_of(),
              **probe(run, a.port, a.rounds, a.queries)}
    with open(os.path.join(a.out, "memory.json"), "w") as f:
        json.dump(record, f, indent=1)
    print(f"{record['clips']} clips of {a.steps} steps: RSS {record['rss_at_start_mb']:.0f} MB at the start, "
          f"{record['rss_after_each_clip_mb'][-1]:.0f} MB at the end, peak {record['peak_mb']:.0f} MB, "
          f"{record['seconds_per_clip']:.1f} s a clip, {sum(record['clip_mb']):.0f} MB of clips")


if __name__ == "__main__":
    main()
