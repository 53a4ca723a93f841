#!/usr/bin/env bash
# Issue 70's learning check (README.md here): sac.py with the true reward on drawer-open-v3 in the ENE at noise 0.9,
# against a random policy. 50 000 SAC updates on one core: about 80 minutes (--resumable: run it again to resume).
set -euo pipefail
cd "$(dirname "$0")"
export OMP_NUM_THREADS=1 PYTHONPATH=../.. MUJOCO_GL=${MUJOCO_GL:-egl}

# The random policy: uniform actions in sac.py's 10 evaluation envs (seeds 1001 ... 10001 at --seed 1).
python - <<'PY'
import numpy as np
import ene

returns, successes = [], []
for i in range(10):
    seed = 1 + 1000 * (i + 1)
    env = ene.make_env("drawer-open-v3", seed, 0.9, episode_length=500)
    env.reset(seed=seed)
    total, success = 0.0, 0.0
    for _ in range(500):
        _, reward, _, _, info = env.step(env.action_space.sample())
        total, success = total + reward, max(success, info["success"])
    returns.append(total)
    successes.append(success)
print(f"random policy: success rate {np.mean(successes):.2f}, mean return {np.mean(returns):.1f} over 10 episodes")
PY

python ../../sac.py --env-id drawer-open-v3 --noise 0.9 --total-timesteps 50000 --eval-freq 10000 --eval-episodes 10 \
    --threads 1 --no-cuda --seed 1 --run-name sac-drawer-open-v3 --resumable

# The verdict: the mean success rate of the last 3 evaluations (30 000, 40 000 and 50 000 steps) against 0.5.
python - <<'PY'
import numpy as np
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

events = EventAccumulator("runs/sac-drawer-open-v3", size_guidance={"scalars": 0})
events.Reload()
for tag in ("eval/success_rate", "eval/episodic_return"):
    print(tag, [(e.step, round(e.value, 2)) for e in events.Scalars(tag)])
last = np.mean([e.value for e in events.Scalars("eval/success_rate")[-3:]])
print(f"mean success rate of the last 3: {last:.2f}; threshold 0.5: {'PASS' if last >= 0.5 else 'FAIL'}")
PY
