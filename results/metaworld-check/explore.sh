#!/usr/bin/env bash
# Issue 70's exploratory runs (README.md here): pebble.py or r2n_pebble.py on drawer-open-v3 at noise 0.9, seed 1.
# Usage: bash explore.sh pebble|r2n_pebble [total steps, default 50000]
set -euo pipefail
cd "$(dirname "$0")"
export OMP_NUM_THREADS=1 PYTHONPATH=../.. MUJOCO_GL=${MUJOCO_GL:-egl}
python "../../$1.py" --env-id drawer-open-v3 --noise 0.9 --total-timesteps "${2:-50000}" --eval-freq 10000 \
    --eval-episodes 10 --threads 1 --no-cuda --seed 1 --run-name "$1-drawer-open-v3" --resumable
