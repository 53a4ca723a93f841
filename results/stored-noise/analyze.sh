#!/usr/bin/env bash
# Regenerates every table, curve and connectivity figure of the stored-noise study, H2's test and the power achieved
# (analysis/interaction.txt, analysis/power-achieved.txt): the commands of PROTOCOL.md ("Analysis commands"), in its
# order. It refuses until all 22 primary runs are in (the protocol reads no test before). The probes' descriptive
# table (analysis-probes/) comes once the 6 runs of the two probe arms are in, with pebble_repeat's runs that
# are in; repeat.txt says whether they repeat the cheetah study's PEBBLE (PROTOCOL.md, "Addition"), and
# diagnostics.md sets the PbRL arms of both environments side by side.
# Run from the repository root: bash results/stored-noise/analyze.sh
set -euo pipefail
shopt -s nullglob  # a pattern that matches nothing counts 0 files
done_files=(results/stored-noise/runs/*/done)
if [ "${#done_files[@]}" -ne 22 ]; then
    echo "results/stored-noise/analyze.sh: ${#done_files[@]} of the 22 primary runs are in; the protocol reads no test before" >&2
    exit 1
fi
python analyze.py --log-dirs results/stored-noise/runs --output-dir results/stored-noise/analysis --primary-last 3 \
    --baseline-for r2n_pebble_stored_noise=pebble_stored_noise sac_stored_noise=sac_stored_noise \
    anf_sac_stored_noise=sac_stored_noise
# keep FILE: runs the command after it and writes its output to FILE, only if it succeeds (no half-written report)
keep() {
    local file=$1 output
    shift
    output=$("$@")
    printf '%s\n' "$output" | tee "$file"
}
# H2's test and the power achieved are kept beside the tables
keep results/stored-noise/analysis/interaction.txt python results/stored-noise/interaction.py
keep results/stored-noise/analysis/power-achieved.txt python results/stored-noise/power.py --achieved
probe_done_files=(results/stored-noise/probes/r2n_pebble_{reward_only,agent_as_reward}__*/done)
repeat_done_files=(results/stored-noise/probes/pebble_repeat__*/done)
if [ "${#probe_done_files[@]}" -eq 6 ]; then
    python analyze.py --log-dirs results/cheetah-study results/stored-noise/probes \
        --output-dir results/stored-noise/analysis-probes --primary-last 3
    echo "the probes: pebble_repeat has ${#repeat_done_files[@]} of 3 runs in"
    keep results/stored-noise/analysis-probes/repeat.txt python results/stored-noise/repeat_check.py
    keep results/stored-noise/analysis-probes/diagnostics.md python results/stored-noise/diagnostics.py
else
    echo "the probes: ${#probe_done_files[@]} of the 6 runs of r2n_pebble_reward_only and" \
        "r2n_pebble_agent_as_reward are in; their table comes when all are"
fi
