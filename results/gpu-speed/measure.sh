#!/bin/bash
# Issue 32's prepared GPU measurement, in at most 9.5 minutes: `bash results/gpu-speed/measure.sh OUT [--dry-run]`.
# Every part has a time budget and writes its result file into OUT as it ends, so a call cut off still returns what
# finished. The runs live in a work folder outside OUT: their state files are about 1 GB each.
# Parts, in order (README "The prepared measurement (issue 32)"):
#   items      host and GPU microseconds of each step item of a captured run (measure.py items) -> items.csv
#   adam       one graph per SAC update, Adam inside, once its scalars settle: bit for bit against eager, and the
#              milliseconds per update of eager, today's --cuda-graph and the whole capture (adam_capture.py) -> adam.json
#   act_store  acting and storing as two graphs, one pinned copy each way: bit for bit against eager, host µs per
#              step of each (act_store_capture.py) -> act_store.json
#   lines      each line of the main loop, `sac_update` and `store`, timed (measure.py lines) -> lines.csv (not run
#              unless PARTS names it)
#   actor      the actor's step with and without the critics' weight gradients (actor_step.py) -> actor.txt (not run
#              unless PARTS names it: its question was answered with --tf32)
#   exact      eager against --cuda-graph, and against --cuda-graph --cuda-graph-whole, bit for bit, all 12 scripts
#              (tests/test_cuda_graph.py) -> exact.csv
#   window     a 20 000-step window of one captured run (the whole update replayed with
#              EXTRA_FLAGS=--cuda-graph-whole): steps/s, evaluations' and state writes' shares -> window.json
#   aggregate  steady-state steps/s of 1, 4 and 8 runs at once, without and with MPS, and 8 at 256 wide started by
#              benchmark.py with MPS -> aggregate.csv (one row per configuration, written as each ends)
#   resume     exact resume under --cuda-graph (issue 44's item 7: surf.py once differed after a SIGKILL): rounds of
#              tests/test_resume.py's kill test for surf.py, r2n_surf.py and pebble.py (the control), several copies at
#              once, until the budget -> resume.csv (one row per test and round; not run unless PARTS names it)
# Also measure.log (this console) and runs.tgz (event files and logs, archived after each part and on exit).
# --dry-run: every part on the CPU with tiny runs (32 wide, a few hundred steps), no --cuda-graph and no MPS.
# PARTS="items window": only these parts, in the order PARTS lists them (default: exact window aggregate,
# 570 s: the whole update's test and rate).
# BUDGET_AGGREGATE=130 (any part's name, upper case): that part's budget in seconds, in place of the one below.
# EXTRA_FLAGS="--tf32": flags added to every timed run (the flags line of measure.log names them); of them, the actor
# part takes --tf32.
set -u
out=${1:?usage: measure.sh OUT [--dry-run]}
dry=${2:-}
root=$(cd "$(dirname "$0")/../.." && pwd)
py=${PYTHON:-python3}
helper="$root/results/gpu-speed/measure.py"
work=${MEASURE_WORK:-/tmp/measure-work}
mkdir -p "$out"
out=$(cd "$out" && pwd)
rm -rf "$work"
mkdir -p "$work"
exec > >(tee -a "$out/measure.log") 2>&1
export OMP_NUM_THREADS=1 PYTHONUNBUFFERED=1 PYTHONWARNINGS=ignore

# Settings. Every run of a timed part has the same flags but for its length, evaluations and state writes.
# The steady-state window lies in the learned-reward phase: after the first feedback round (at learning starts +
# unsupervised steps) and the critic's re-capture, before the next round and with no evaluation inside.
if [ "$dry" = "--dry-run" ]; then
  base=(--env-id cheetah-run --noise 0.9 --learning-starts 200 --unsup-steps 100 --episode-length 100
        --hidden-dim 32 --batch-size 32 --segment-size 20 --max-feedback 40 --queries-per-round 5
        --feedback-freq 300 --reward-epochs 5 --buffer-size 20000 --eval-episodes 2 --threads 1 --log-freq 50)
  gpu=()
  items_steps=(400 600)  # the items' window; the run ends one step after it
  items_flags=(--eval-freq 200)
  window_steps=(400 1200)
  window_flags=(--total-timesteps 1250 --eval-freq 400 --checkpoint-freq 500 --resumable)
  window_rounds=(600 900 1200)
  agg_steps=(400 500)
  agg_total=501
  configs=("bench x2-benchmark 2" "no x2 2" "yes x2 2")  # MPS cannot start on the CPU: its row is skipped
  exact_workers=1
  actor_flags=(--hidden-dim 32 --batch-size 32 --repeats 5)
  adam_flags=(--device cpu --hidden-dim 32 --batch-size 32 --updates 20 --blocks 1)
  act_store_flags=(--device cpu --hidden-dim 32 --steps 200 --episode-length 100 --blocks 1)
  budget_items=120 budget_lines=120 budget_adam=60 budget_act_store=60 budget_actor=30 budget_exact=60 budget_window=150 budget_aggregate=150
  budget_resume=150
  resume_env="" resume_copies=1 resume_round=140 resume_scripts=(surf.py)  # on the CPU: one test, once
  declare -A config_budget=([x2]=70 [x2-benchmark]=80)
else
  base=(--env-id cheetah-run --noise 0.9 --learning-starts 1000 --unsup-steps 1000 --threads 1 --log-freq 100)
  gpu=(--cuda-graph)
  items_steps=(2200 2800)
  items_flags=(--eval-freq 1000 --parallel-eval)  # its evaluations time --parallel-eval; the window's the serial one
  # with EXTRA_FLAGS=--cuda-graph-whole the whole update replays once the critic's new Adam (the reset at step
  # 2 000) has settled, near step 18 630
  window_steps=(20000 40000)
  window_flags=(--total-timesteps 40100 --checkpoint-freq 10000 --resumable)  # the default evaluations: every 5000 steps
  window_rounds=(22000 27000 32000 37000)
  agg_steps=(2200 2500)
  agg_total=2501  # one evaluation, at the end, after the window
  # the most telling first: a call cut off still compares 8 runs without and with MPS, and has 8 at 256 wide
  # the issue's target first (8 runs at 256 wide with MPS, started by benchmark.py), then 8 at the paper's size with
  # and without MPS
  configs=("bench x8-256wide 8 --hidden-dim 256 --batch-size 256" "yes x8 8" "no x8 8" "no x4 4" "yes x4 4"
           "yes x1 1")
  exact_workers=16
  # from the H100's first call (h100-2026-11-26/measure.log): items took 34 s, the window 103 s, the aggregate's
  # configurations 65, 34, 23, 40, 27 and 21 s; the exactness tests 116 s on 14 workers; in the second
  # session (after the actor change, a slower host) 144 s on 16 workers, and the window its whole 115 s
  actor_flags=(--cuda --repeats 30)
  adam_flags=(--device cuda --updates 200 --blocks 4)  # the paper's size; 2 scripts x 4 arms x 5 passes of 200
  act_store_flags=(--device cuda --steps 2000 --blocks 3)  # 8 000 steps per arm at about 1 ms each
  # adam: 2 scripts x 4 arms x 5 passes of 200 updates, at most about 4 ms each (about 32 s), plus the imports
  budget_items=45 budget_lines=45 budget_adam=45 budget_act_store=35 budget_actor=20 budget_exact=160
  budget_window=240 budget_aggregate=170  # the window: 40 100 steps at 200-300 steps/s, its evaluations, start-up
  # each test runs a tiny run three times (reference, killed, resumed); 4 copies of 3 tests are 12 runs at once
  budget_resume=190
  resume_env=graph resume_copies=4 resume_round=90 resume_scripts=(surf.py r2n_surf.py pebble.py)
  declare -A config_budget=([x8]=80 [x4]=55 [x8-256wide]=45 [x1]=35)
fi
gpu+=(${EXTRA_FLAGS:-})
[[ " ${EXTRA_FLAGS:-} " == *" --tf32 "* ]] && actor_flags+=(--tf32)
parts=(${PARTS:-exact window aggregate})
total=0
plan=""
for part in "${parts[@]}"; do
  budget="budget_$part"
  [ -n "${!budget:-}" ] || {
    echo "PARTS: no part named $part (items lines adam act_store actor exact window aggregate resume)"
    exit 2; }
  override="BUDGET_${part^^}"
  [ -n "${!override:-}" ] && printf -v "$budget" %s "${!override}"
  total=$((total + ${!budget}))
  plan+="$part ${!budget} s, "
done

mps_on=0
pids=()
archive() {  # event files and logs only: checkpoints, states and preference files are too large
  tar czf "$out/runs.tgz.tmp" -C "$work" --exclude='*.pt' --exclude='*.npz' --exclude='*.cleanrl_model' . 2>/dev/null \
    && mv "$out/runs.tgz.tmp" "$out/runs.tgz"
}
mps_quit() {
  if [ "$mps_on" = 1 ]; then
    echo quit | nvidia-cuda-mps-control
    mps_on=0
    echo "$(date +%T) MPS daemon quit"
  fi
}
finish() {
  kill $(jobs -p) 2> /dev/null  # a part still running when a signal came (each job is its `timeout`)
  mps_quit
  archive
  echo "$(date +%T) done in $SECONDS s; files: $(cd "$out" && ls | tr '\n' ' ')"
}
trap finish EXIT
trap 'echo "stopped by a signal"; exit 130' INT TERM  # parts run in the background: `wait` lets the trap in at once

run() {  # folder, name, seconds, flags...: one run in the background, killed at its budget
  local dir=$1 name=$2 seconds=$3
  shift 3
  mkdir -p "$dir"
  (cd "$dir" && exec timeout -s KILL "$seconds" "$py" "$root/r2n_pebble.py" "${base[@]}" "${gpu[@]}" \
    --run-name "$name" "$@" > "$name.log" 2>&1) &
  pids+=($!)
}

wait_runs() {  # by id: a plain `wait` would also wait for the console's tee
  wait "${pids[@]}"
  pids=()
}

part_start() {
  echo "$(date +%T) [$SECONDS s] part $1 (budget $2 s)"
}

echo "$(date +%T) plan: ${plan}${total} s in all; ${dry:-GPU}"
echo "flags of every timed run: ${base[*]} ${gpu[*]}"
"$py" -c "import torch; print('torch', torch.__version__, 'cuda', torch.cuda.is_available() and \
torch.cuda.get_device_name(0))"
command -v nvidia-smi > /dev/null && nvidia-smi --query-gpu=name,memory.used,memory.total --format=csv,noheader

instrumented() {  # items or lines: one run in the helper's process, timed by item or by line -> $out/$1.csv
  local kind=$1 budget="budget_$1"
  mkdir -p "$work/$kind"
  (cd "$work/$kind" && exec timeout -s KILL "${!budget}" "$py" "$helper" "$kind" "$out/$kind.csv" \
    --from-step "${items_steps[0]}" --to-step "${items_steps[1]}" "$root/r2n_pebble.py" "${base[@]}" "${gpu[@]}" \
    "${items_flags[@]}" --total-timesteps $((items_steps[1] + 1)) --run-name "$kind" > "$kind.log" 2>&1) &
  wait $! || echo "$kind: exit $? (137: cut off at its budget); the log's end: $(tail -3 "$work/$kind/$kind.log")"
  [ -f "$out/$kind.csv" ] && cat "$out/$kind.csv"
}

part_items() {
  instrumented items
}

part_lines() {
  instrumented lines
}

part_adam() {
  (cd "$root" && exec timeout -s KILL "$budget_adam" "$py" results/gpu-speed/adam_capture.py "${adam_flags[@]}" \
    --out "$out/adam.json" > "$work/adam.log" 2>&1) &
  wait $! || echo "adam: exit $? (137: cut off at its budget)"
  cat "$work/adam.log"
}

part_act_store() {
  (cd "$root" && exec timeout -s KILL "$budget_act_store" "$py" results/gpu-speed/act_store_capture.py \
    "${act_store_flags[@]}" --out "$out/act_store.json" > "$work/act_store.log" 2>&1) &
  wait $! || echo "act_store: exit $? (137: cut off at its budget)"
  cat "$work/act_store.log"
}

part_actor() {
  timeout -s KILL "$budget_actor" "$py" "$root/results/gpu-speed/actor_step.py" "${actor_flags[@]}" \
    > "$out/actor.txt" 2>&1 &
  wait $! || echo "actor: exit $? (137: cut off at its budget)"
  cat "$out/actor.txt"
}

part_exact() {
  (cd "$root" && R2N_TEST_CUDA=1 exec timeout -s KILL "$budget_exact" "$py" -m pytest -q -p no:cacheprovider \
    tests/test_cuda_graph.py -n "$exact_workers" --junitxml="$work/exact.xml" > "$work/exact.log" 2>&1) &
  wait $!
  echo "exact: pytest exit $? (137: cut off at its budget): $(tail -1 "$work/exact.log")"
  if [ -f "$work/exact.xml" ]; then
    "$py" "$helper" exact "$work/exact.xml" "$out/exact.csv"
  else
    tail -20 "$work/exact.log" > "$out/exact.csv"
  fi
}

part_window() {
  run "$work/window" window "$budget_window" "${window_flags[@]}"
  wait_runs
  "$py" "$helper" window "$work/window/runs/window" "$work/window/window.log" "$out/window.json" \
    --from-step "${window_steps[0]}" --to-step "${window_steps[1]}" --feedback-steps "${window_rounds[@]}" \
    || echo "window: no result; the log's end: $(tail -3 "$work/window/window.log")"
  # the same flags as the aggregate's runs: its early steps are the one-run row without MPS
  "$py" "$helper" rates "$work/window" "$out/aggregate.csv" --name x1-window --mps no --from-step "${agg_steps[0]}" \
    --to-step "${agg_steps[1]}"
}

bench_config() {  # name, runs, flags...: the runs started by benchmark.py, with its own MPS daemon on the GPU
  local name=$1 n=$2
  shift 2
  mps_quit  # benchmark.py starts a daemon of its own
  local dir="$work/aggregate/$name-benchmark" seconds=${config_budget[$name]}
  mkdir -p "$dir"
  local sharing=(--workers "$n")
  [ "$dry" = "--dry-run" ] || sharing=(--gpus 0 --runs-per-gpu "$n" --mps)
  echo "$(date +%T) [$SECONDS s] $name: $n run(s) started by benchmark.py ${sharing[*]}, budget $seconds s, flags: $*"
  # the base flags but the task and noise, which benchmark.py gives each command
  (cd "$dir" && exec timeout -s TERM "$seconds" "$py" "$root/benchmark.py" --env-ids cheetah-run --noises 0.9 \
    --methods r2n_pebble --seeds $(seq 1 "$n") "${sharing[@]}" --log-dir "$dir/logs" \
    --extra="${base[*]:4} ${gpu[*]} --total-timesteps $agg_total --eval-freq 100000 $*" > "$dir/benchmark.log" 2>&1) &
  wait $! || echo "$name: benchmark.py exit $? (124: cut off at its budget); its log's end: $(tail -2 "$dir/benchmark.log")"
  "$py" "$helper" rates "$dir" "$out/aggregate.csv" --name "$name" --mps benchmark --started "$n" \
    --from-step "${agg_steps[0]}" --to-step "${agg_steps[1]}"
  archive
}

config() {  # mps (yes, no, or bench: started by benchmark.py), name, runs, flags...: runs started together, then
  # their row of aggregate.csv
  local mps=$1 name=$2 n=$3
  shift 3
  local seconds=${config_budget[$name]}
  local left=$((part_end - SECONDS))
  if [ "$left" -lt "$seconds" ]; then
    echo "$(date +%T) $name (MPS $mps): skipped, ${left} s left of the part and it needs ${seconds} s"
    return
  fi
  if [ "$mps" = bench ]; then
    bench_config "$name" "$n" "$@"
    return
  fi
  if [ "$mps" = yes ] && [ "$mps_on" = 0 ]; then
    if nvidia-cuda-mps-control -d; then
      mps_on=1
      echo "$(date +%T) MPS daemon started"
    else
      echo "$(date +%T) $name (MPS yes): skipped, MPS did not start"
      return
    fi
  fi
  [ "$mps" = no ] && mps_quit
  local dir="$work/aggregate/$name-mps-$mps"
  echo "$(date +%T) [$SECONDS s] $name (MPS $mps): $n run(s), budget $seconds s, flags: $*"
  for i in $(seq 1 "$n"); do
    run "$dir" "run$i" "$seconds" --total-timesteps "$agg_total" --eval-freq 100000 --seed "$i" "$@"
  done
  if [ "$mps" = yes ]; then  # whether the runs go through the daemon
    (sleep 20 && echo "MPS servers: $(echo get_server_list | nvidia-cuda-mps-control 2>&1 | tr '\n' ' ')") &
  fi
  wait_runs
  "$py" "$helper" rates "$dir" "$out/aggregate.csv" --name "$name" --mps "$mps" --started "$n" \
    --from-step "${agg_steps[0]}" --to-step "${agg_steps[1]}"
  archive
}

part_aggregate() {
  part_end=$((SECONDS + budget_aggregate))
  for c in "${configs[@]}"; do
    config $c
  done
  mps_quit
  [ -f "$out/aggregate.csv" ] && cat "$out/aggregate.csv"
}

part_resume() {  # rounds of the kill test, the copies of a round at once, while a whole round fits in the part
  local end=$((SECONDS + budget_resume)) round=0 ids=()
  for script in "${resume_scripts[@]}"; do
    ids+=("tests/test_resume.py::test_killed_at_a_random_moment_resumes_exactly[$script]")
  done
  mkdir -p "$work/resume"
  echo "round,copy,test,outcome,message" > "$out/resume.csv"
  while [ $((end - SECONDS)) -ge "$resume_round" ]; do
    round=$((round + 1))
    for copy in $(seq 1 "$resume_copies"); do
      local name="$work/resume/$round-$copy"
      (cd "$root" && R2N_TEST_CUDA=$resume_env exec timeout -s KILL "$resume_round" "$py" -m pytest -q \
        -p no:cacheprovider "${ids[@]}" -n "${#ids[@]}" --basetemp "$name" --junitxml="$name.xml" > "$name.log" 2>&1) &
      pids+=($!)
    done
    wait_runs
    for copy in $(seq 1 "$resume_copies"); do
      local name="$work/resume/$round-$copy"
      if [ -f "$name.xml" ]; then
        "$py" "$helper" exact "$name.xml" "$name.csv" > /dev/null
        tail -n +2 "$name.csv" | sed "s/^/$round,$copy,/" >> "$out/resume.csv"
      else
        local last
        last=$(tail -1 "$name.log" | tr ',' ';')
        echo "$round,$copy,all,cut off at the round's $resume_round s,$last" >> "$out/resume.csv"
      fi
      grep -h -m 3 -E "differs|Error" "$name.log" | sed "s/^/resume $round-$copy: /"
    done
  done
  cat "$out/resume.csv"
}

for part in "${parts[@]}"; do
  budget="budget_$part"
  part_start "$part" "${!budget}"
  "part_$part"
  archive
done
