#!/usr/bin/env bash
# Regenerates the which-sparsity study's analysis (PROTOCOL.md, "Analysis commands", in its order): analyze.py's
# tables, curves and connectivity figures, every arm against R2N-PEBBLE; the tests (hypotheses.md); the power
# achieved; the diagnostics. It refuses until all 54 runs of the protocol are in (no test is read before).
# Run from the repository root: bash results/which-sparsity/analyze.sh
set -euo pipefail
shopt -s nullglob  # a pattern that matches nothing counts 0 files
study=results/which-sparsity
done_files=("$study"/runs/*/done)
if [ "${#done_files[@]}" -ne 54 ]; then
    echo "$study/analyze.sh: ${#done_files[@]} of the 54 runs are in; the protocol reads no test before" >&2
    exit 1
fi
python analyze.py --log-dirs results/stored-noise/runs "$study/runs" --output-dir "$study/analysis" --primary-last 3 \
    --baseline r2n_pebble_stored_noise --alternative less \
    --baseline-for sac_stored_noise=sac_stored_noise anf_sac_stored_noise=sac_stored_noise
python "$study/hypotheses.py"
# power.py --achieved prints its report: kept only if it succeeds (no half-written file)
output=$(python "$study/power.py" --achieved)
printf '%s\n' "$output" | tee "$study/analysis/power-achieved.txt"
python "$study/diagnostics.py"
