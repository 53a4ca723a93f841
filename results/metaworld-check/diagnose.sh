#!/usr/bin/env bash
# The failed check's diagnostics (README.md here, "Looking for the bug"): metaworld's own scripted policy through
# ene.make_env, then the check's sac.py run without the noise features (noise 0), evaluated every 5 000 steps, then
# where both runs' policies get to at step 50 000 (rollout.py).
set -euo pipefail
cd "$(dirname "$0")"
export OMP_NUM_THREADS=1 PYTHONPATH=../.. MUJOCO_GL=${MUJOCO_GL:-egl}
python scripted_policy.py | tee scripted_policy.txt
python ../../sac.py --env-id drawer-open-v3 --noise 0 --total-timesteps 50000 --eval-freq 5000 --eval-episodes 10 \
    --threads 1 --no-cuda --seed 1 --run-name sac-drawer-open-v3-noise0 --resumable
for run in sac-drawer-open-v3 sac-drawer-open-v3-noise0; do
    python rollout.py "runs/$run/sac.cleanrl_model"
done | tee rollout.txt
