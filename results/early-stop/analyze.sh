#!/usr/bin/env bash
# Regenerates every committed table, curve and connectivity figure of the early-stop confirmation, and prints the
# power each test achieved: the protocol's two analyze.py commands (PROTOCOL.md, "Analysis commands"), then power.py.
# Run from the repository root: bash results/early-stop/analyze.sh
set -euo pipefail
python analyze.py --log-dirs results/early-stop --output-dir results/early-stop/analysis --primary-last 3 \
    --baseline pebble_no_early_stop
python analyze.py --log-dirs results/early-stop results/cpu-study/r2n_pebble__cartpole-swingup__noise0.9__budget400__seed* \
    --output-dir results/early-stop/analysis-h2 --primary-last 3 --baseline r2n_pebble \
    --baseline-for pebble_no_early_stop=pebble_no_early_stop
python results/early-stop/power.py --achieved
