#!/usr/bin/env bash
# Regenerates every table and figure of the stored-table study from the committed event files, in one command:
# analyze.py's tables, curves, connectivity and relevant_weight_frac figures of the primary runs (analysis/, once any
# is in), the pilot's decisions (pilot-decisions.md), and the table for users with the tasks' curves side by side
# (table.md, curves.png and the README's table block). Run from the repository root: bash results/stored-table/analyze.sh
set -euo pipefail
shopt -s nullglob  # a pattern that matches nothing counts 0 files
done_files=(results/stored-table/runs/*/done)
if [ "${#done_files[@]}" -gt 0 ]; then
    python analyze.py --log-dirs results/stored-table/runs --output-dir results/stored-table/analysis --primary-last 3 \
        --baseline-for r2n_pebble_stored_noise=pebble_stored_noise
else
    echo "results/stored-table/analyze.sh: no primary run is in yet: analysis/ comes with the first"
fi
python results/stored-table/power.py > results/stored-table/pilot-decisions.md.tmp
mv results/stored-table/pilot-decisions.md.tmp results/stored-table/pilot-decisions.md
python results/stored-table/table.py
