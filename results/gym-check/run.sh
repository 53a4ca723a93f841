#!/usr/bin/env bash
# Issue 33's learning check (README.md here): sac.py on HalfCheetah-v5 without noise, against a random policy.
# About 100 000 SAC updates on one core: 20 to 30 minutes on a laptop-class CPU.
set -euo pipefail
cd "$(dirname "$0")"
export OMP_NUM_THREADS=1 PYTHONPATH=../..

# The random policy: uniform actions in sac.py's 10 evaluation envs (seeds 1001 ... 10001 at --seed 1).
python - <<'PY'
import numpy as np
import ene

returns = []
for i in range(10):
    seed = 1 + 1000 * (i + 1)
    env = ene.make_env("HalfCheetah-v5", seed, 0.0, episode_length=1000)
    env.reset(seed=seed)
    returns.append(sum(env.step(env.action_space.sample())[1] for _ in range(1000)))
print(f"random policy: mean {np.mean(returns):.1f}, SD {np.std(returns, ddof=1):.1f} over 10 episodes")
PY

# The SAC settings the run had (dm_control's, then every suite's): gymnasium's defaults are CleanRL's now.
python ../../sac.py --env-id HalfCheetah-v5 --noise 0 --total-timesteps 100000 --hidden-dim 256 --batch-size 128 \
    --hidden-layers 2 --policy-lr 1e-4 --q-lr 1e-4 --alpha-lr 1e-4 --init-temperature 0.1 --target-update-freq 2 \
    --weight-decay 0 --eval-freq 10000 --eval-episodes 10 --threads 1 --no-cuda --seed 1 --run-name sac-halfcheetah-v5

# The verdict: the mean of the last 3 evaluations (80 000, 90 000 and 100 000 steps) against the threshold of 1000.
python - <<'PY'
import numpy as np
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

events = EventAccumulator("runs/sac-halfcheetah-v5", size_guidance={"scalars": 0})
events.Reload()
points = [(e.step, e.value) for e in events.Scalars("eval/episodic_return")]
print("evaluations (step, mean return of 10 episodes):", [(step, round(value, 1)) for step, value in points])
last = np.mean([value for _, value in points[-3:]])
print(f"mean of the last 3: {last:.1f}; threshold 1000: {'PASS' if last >= 1000 else 'FAIL'}")
PY
