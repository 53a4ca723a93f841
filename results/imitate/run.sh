#!/usr/bin/env bash
# Issue 21, part 3 (results/imitate/PROTOCOL.md): the histograms from a noise-free SAC policy, then PEBBLE and R2N
# with imitating noise, 3 seeds each. Run from the repository root; what is done is skipped, the source run resumes.
set -euo pipefail
histograms=results/imitate/cartpole-swingup_histograms.npz
if [ ! -f "$histograms" ]; then
  [ -f runs/imitate-source/sac.cleanrl_model ] || python sac.py --env-id cartpole-swingup --noise 0 --seed 1 \
    --total-timesteps 80000 --hidden-dim 256 --batch-size 128 --threads 1 --run-name imitate-source
  python make_histograms.py --checkpoint runs/imitate-source/sac.cleanrl_model --output "$histograms"
  mkdir -p results/imitate/source && cp runs/imitate-source/events.out.tfevents.* results/imitate/source/
fi
python benchmark.py --preset imitate --workers "${WORKERS:-2}"
