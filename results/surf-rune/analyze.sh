#!/usr/bin/env bash
# Regenerates the surf-rune study's analysis (PROTOCOL.md, "Analysis commands" and the addition of 2026-12-06, in
# that order): analyze.py's tables, curves and connectivity figures (each R2N arm against its method, the
# actor/critic-only arm against SURF; the stored-noise study's arms beside, untested, its R2N-PEBBLE with 8 seeds);
# the tests (hypotheses.md); the power achieved; the diagnostics. It refuses until all 48 runs of the protocol are in
# (no test is read before).
# Run from the repository root: bash results/surf-rune/analyze.sh
set -euo pipefail
shopt -s nullglob  # a pattern that matches nothing counts 0 files
study=results/surf-rune
done_files=("$study"/runs/*/done)
if [ "${#done_files[@]}" -ne 48 ]; then
    echo "$study/analyze.sh: ${#done_files[@]} of the 48 runs are in; the protocol reads no test before" >&2
    exit 1
fi
python analyze.py --log-dirs results/stored-noise/runs "$study/runs" \
    --output-dir "$study/analysis" --primary-last 3 --baseline surf_stored_noise \
    --baseline-for r2n_rune_stored_noise=rune_stored_noise rune_stored_noise=rune_stored_noise \
    pebble_stored_noise=pebble_stored_noise r2n_pebble_stored_noise=r2n_pebble_stored_noise \
    sac_stored_noise=sac_stored_noise anf_sac_stored_noise=anf_sac_stored_noise
python "$study/hypotheses.py"
# power.py --achieved prints its report: kept only if it succeeds (no half-written file)
output=$(python "$study/power.py" --achieved)
printf '%s\n' "$output" | tee "$study/analysis/power-achieved.txt"
python "$study/diagnostics.py"
