#!/usr/bin/env bash
# Continues the which-sparsity study (PROTOCOL.md) in the background, from the protocol's fixed commit, and commits
# each run into this checkout as it finishes. Run from the repository root, with the project's venv active:
#
#   bash results/which-sparsity/continue.sh [WORKTREE]     # default WORKTREE: ../which-sparsity-0e11778
#   bash results/which-sparsity/continue.sh --dry-run      # how many runs are left, nothing started
#
# 1. A git worktree at the protocol's commit (made once), holding a copy of the committed runs, so that the launcher
#    skips them: `benchmark.py --preset which-sparsity --workers 2` there, one torch thread a run.
# 2. A watcher: when a run's `done` file appears in the worktree, its folder is copied into `runs/` here and
#    committed alone (`git commit -- <its folder>`), its commit, CPU and seconds in the message.
# Logs: the worktree's `logs/`, and `launcher.log` and `watcher.log` in it. Both processes outlive the shell; the
# launcher stops when every run is in, the watcher when the launcher has stopped and nothing is left to commit.
set -euo pipefail
COMMIT=0e11778
STUDY=results/which-sparsity
main=$(git rev-parse --show-toplevel)
mode=${1:-}
[[ $mode = --dry-run || $mode = --watch ]] && shift || mode=""
work=$(realpath -m "${1:-$(dirname "$main")/which-sparsity-$COMMIT}")
cd "$main"

watch() {  # until the launcher has stopped and every finished run is committed
    local launcher running id folder cpu seconds
    launcher=$(cat "$work/launcher.pid")
    while true; do
        running=""
        kill -0 "$launcher" 2> /dev/null && running=1
        for folder in "$work/$STUDY"/runs/*/; do
            id=$(basename "$folder")
            [ -f "$folder/done" ] && [ ! -f "$STUDY/runs/$id/done" ] || continue
            mkdir -p "$STUDY/runs/$id"
            cp "$folder"/* "$STUDY/runs/$id/"
            cpu=$(sed -n 's/^cpu //p' "$STUDY/runs/$id/done")
            seconds=$(sed -n 's/^seconds //p' "$STUDY/runs/$id/done")
            for _ in 1 2 3 4 5 6 7 8 9 10; do  # another git command may hold the index for a moment
                git add -- "$STUDY/runs/$id" && git commit -q -m \
                    "which-sparsity: $id (commit $COMMIT, $cpu, $seconds)" -- "$STUDY/runs/$id" && break
                sleep 5
            done
            echo "$(date -u +%FT%TZ) committed $id"
        done
        [ -n "$running" ] || return 0
        sleep 60
    done
}
[ "$mode" = --watch ] && { watch; exit 0; }
if [ ! -d "$work" ]; then
    git worktree add --detach "$work" "$COMMIT" > /dev/null
fi
[ "$(git -C "$work" rev-parse --short=7 HEAD)" = "$COMMIT" ] || { echo "$work is not at $COMMIT" >&2; exit 1; }
mkdir -p "$work/$STUDY/runs"
for run in "$STUDY"/runs/*/; do  # the committed runs, so that the launcher skips them
    [ -e "$work/$STUDY/runs/$(basename "$run")/done" ] || cp -r "$run" "$work/$STUDY/runs/"
done
export OMP_NUM_THREADS=1 MKL_NUM_THREADS=1
if [ "$mode" = --dry-run ]; then
    (cd "$work" && python benchmark.py --preset which-sparsity --workers 2 --dry-run | tail -n 1)
    exit 0
fi
(cd "$work" && setsid nohup python benchmark.py --preset which-sparsity --workers 2 \
    > "$work/launcher.log" 2>&1 < /dev/null & echo $! > "$work/launcher.pid")
setsid nohup bash "$main/$STUDY/continue.sh" --watch "$work" >> "$work/watcher.log" 2>&1 < /dev/null &
echo "launcher: $work/launcher.log; watcher: $work/watcher.log; the runs' logs: $work/logs/"
