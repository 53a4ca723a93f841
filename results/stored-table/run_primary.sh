#!/usr/bin/env bash
# The primary runs of PROTOCOL.md part 2, task by task in its order (the tasks part 2 has decided, `benchmark.py`'s
# `STORED_TABLE_SEEDS`). Committed runs are skipped and interrupted ones resume from their state.pt. Run it from the
# repository root of a checkout fixed at the primary runs' commit: `bash results/stored-table/run_primary.sh`.
set -euo pipefail
cd "$(dirname "$0")/../.."
PYTHON=${PYTHON:-python}
for task in cartpole-swingup walker-walk quadruped-walk; do
    if "$PYTHON" -c "import sys, benchmark; sys.exit('$task' not in benchmark.STORED_TABLE_SEEDS)"; then
        "$PYTHON" benchmark.py --preset stored-table --env-ids "$task" --workers 2
    fi
done
