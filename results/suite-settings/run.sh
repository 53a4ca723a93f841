#!/usr/bin/env bash
# Which SAC settings gymnasium MuJoCo takes (README.md here): sac.py on HalfCheetah-v5 without noise, seed 1, one core
# each, with CleanRL's settings (the suite's defaults now) and with ANF's, then the table of both curves.
# Usage: bash run.sh [--table-only]. The two runs take about 30 minutes each on two cores.
set -euo pipefail
cd "$(dirname "$0")"
export OMP_NUM_THREADS=1 PYTHONPATH=../..
COMMON="--env-id HalfCheetah-v5 --noise 0 --total-timesteps 100000 --eval-freq 10000 --eval-episodes 10 --threads 1
        --no-cuda --seed 1"
if [ "${1:-}" != "--table-only" ]; then
    # CleanRL's (gymnasium's defaults): 2 x 256, batch 256, policy 3e-4, critics and temperature 1e-3 from 1, targets
    # every step. The flags repeat them so that the run stays this run whatever the defaults become.
    python ../../sac.py $COMMON --hidden-dim 256 --hidden-layers 2 --batch-size 256 --policy-lr 3e-4 --q-lr 1e-3 \
        --alpha-lr 1e-3 --init-temperature 1 --target-update-freq 1 --weight-decay 0 \
        --run-name halfcheetah-cleanrl > cleanrl.log 2>&1 &
    # ANF's (its utils/utils.py at 6d3bca2): 2 x 256, batch 100, one rate 1e-3, coupled L2 2e-4, temperature 0.2 fixed.
    python ../../sac.py $COMMON --hidden-dim 256 --hidden-layers 2 --batch-size 100 --policy-lr 1e-3 --q-lr 1e-3 \
        --alpha-lr 0 --init-temperature 0.2 --target-update-freq 1 --weight-decay 2e-4 \
        --run-name halfcheetah-anf > anf.log 2>&1 &
    wait
fi
python - <<'PY'
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

curves = {}
for name in ("cleanrl", "anf"):
    events = EventAccumulator(f"runs/halfcheetah-{name}", size_guidance={"scalars": 0})
    events.Reload()
    curves[name] = {e.step: e.value for e in events.Scalars("eval/episodic_return")}
steps = sorted(curves["cleanrl"])
print("| settings | " + " | ".join(f"{s:,}".replace(",", " ") for s in steps) + " |")
print("|---|" + "---|" * len(steps))
for name, label in (("cleanrl", "CleanRL's"), ("anf", "ANF's")):
    print(f"| {label} | " + " | ".join(f"{curves[name].get(s, float('nan')):.1f}" for s in steps) + " |")
PY
