#!/bin/bash
# The GPU speed runs of issue 19 (README "What a run costs"): `bash results/gpu-speed/run.sh PART OUT [ARCHIVE]`, then
# `python results/gpu-speed/speed.py OUT --from-step S`. Every configuration runs r2n_pebble.py on cheetah-run at
# noise 0.9 with the paper's networks (1024 wide, batch 1024) and default evaluations (10 episodes every 5000 steps);
# pre-training is cut to 1000 steps (`--unsup-steps 1000`) so that the device time goes to the learned-reward phase,
# whose feedback rounds (every 5000 steps) fall inside the windows. Runs of one configuration start together.
# With ARCHIVE (the device's $OUT), each configuration's event files and logs are archived as soon as it ends, so that
# a call cut off at its time limit still brings back the configurations it finished (one file each: at most 8).
set -u
part=$1
out=$2
archive=${3:-}
root=$(cd "$(dirname "$0")/../.." && pwd)
# one torch thread per run: several runs at once would otherwise each start a thread per core and fight over them
base=(--env-id cheetah-run --noise 0.9 --learning-starts 1000 --unsup-steps 1000 --log-freq 1000 --threads 1)

config() {  # name, runs at once, total steps, flags...
  local name=$1 n=$2 steps=$3
  shift 3
  mkdir -p "$out/$name"
  echo "$(date +%T) $name: $n run(s) of $steps steps, flags: $*"
  for i in $(seq 1 "$n"); do
    (cd "$out/$name" && python "$root/r2n_pebble.py" "${base[@]}" --total-timesteps "$steps" --seed "$i" \
      --run-name "run$i" "$@" > "run$i.log" 2>&1 || echo "$name run$i failed: $(tail -2 run$i.log)") &
  done
  wait
  echo "$(date +%T) $name: done"
  if [ -n "$archive" ]; then  # event files and logs only: the checkpoints and preferences.npz are too large
    tar czf "$archive/$name.tgz" -C "$out" --exclude='*.pt' --exclude='*.npz' --exclude='*.cleanrl_model' "$name"
  fi
}

case $part in
  probe)  # a first look: 4000-step windows (4000 to 8000)
    config eager 1 8000 --eval-freq 2000
    config graph 1 8000 --eval-freq 2000 --cuda-graph
    config graph-tf32 1 8000 --eval-freq 2000 --cuda-graph --tf32
    config graph-tf32-compile 1 8000 --eval-freq 2000 --cuda-graph --tf32 --compile
    ;;
  window)  # the issue's window: 20 000 steps of the learned-reward phase (5000 to 25 000), with state writes
    config window-graph 1 25000 --cuda-graph --checkpoint-freq 10000 --resumable
    config window-graph-parallel-eval 1 25000 --cuda-graph --parallel-eval --checkpoint-freq 10000 --resumable
    ;;
  aggregate)  # several runs at once on the GPU, with TF32 (4000-step windows, 4000 to 8000); about 7 minutes
    for n in 2 4 8; do
      config "x$n-graph-tf32" "$n" 8000 --eval-freq 2000 --cuda-graph --tf32
    done
    ;;
  mps)  # the same under CUDA MPS (one GPU context for all runs), then 8 runs at 256 wide
    nvidia-cuda-mps-control -d || { echo "MPS did not start"; exit 1; }
    # the daemon outlives this script: quit it however the script ends (a timeout, an error, the end)
    trap 'echo quit | nvidia-cuda-mps-control' EXIT
    trap 'exit 130' INT TERM
    for n in 4 8; do
      config "x$n-graph-tf32-mps" "$n" 8000 --eval-freq 2000 --cuda-graph --tf32
    done
    config x8-256wide-graph-tf32-mps 8 8000 --eval-freq 2000 --cuda-graph --tf32 --hidden-dim 256 --batch-size 256
    ;;
  profile)  # where a captured step's host time goes: cProfile of 2000 learned-reward steps, the top 40 by own time
    mkdir -p "$out/profile"
    (cd "$out/profile" && python -m cProfile -o profile.prof "$root/r2n_pebble.py" "${base[@]}" --total-timesteps 4000 \
      --eval-freq 100000 --cuda-graph --run-name profile > run.log 2>&1)
    python -c "import pstats; pstats.Stats('$out/profile/profile.prof').sort_stats('tottime').print_stats(40)" \
      > "$out/profile/top.txt"
    [ -n "$archive" ] && cp "$out/profile/top.txt" "$archive/profile-top.txt"
    ;;
  *)
    echo "unknown part $part" >&2
    exit 2
    ;;
esac
