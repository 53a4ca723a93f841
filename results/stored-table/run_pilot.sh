#!/usr/bin/env bash
# The pilot of PROTOCOL.md, task by task: the two PEBBLE seeds together, then the task's other runs.
# Committed runs are skipped and interrupted ones resume from their state.pt. Run it from the repository root
# of a checkout fixed at the pilot's commit: `bash results/stored-table/run_pilot.sh`.
set -euo pipefail
cd "$(dirname "$0")/../.."
PYTHON=${PYTHON:-python}
for task in cartpole-swingup walker-walk quadruped-walk; do
    "$PYTHON" benchmark.py --preset stored-table-pilot --env-ids "$task" --methods pebble_stored_noise --workers 2
    "$PYTHON" benchmark.py --preset stored-table-pilot --env-ids "$task" --workers 2
done
