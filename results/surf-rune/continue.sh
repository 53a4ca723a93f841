#!/usr/bin/env bash
# Continues the surf-rune study (PROTOCOL.md) in the background, from the protocol's fixed commit, and commits each
# run into this checkout as it finishes. Run from the repository root, with the project's venv active:
#
#   bash results/surf-rune/continue.sh [WORKTREE]     # default WORKTREE: ../surf-rune-$COMMIT
#   bash results/surf-rune/continue.sh --dry-run      # this session's runs, nothing started
#
# 1. A git worktree at the protocol's commit (made once per machine), holding a copy of the committed runs, so that
#    the launcher skips them: `benchmark.py` there with the arguments `schedule.py` gives for this session (two pairs,
#    two runs at a time at one thread; first the family whose run a session's end cut off, which resumes from its
#    `state.pt` where this machine still holds it), at the lowest priority (nice 19 on the launcher's and each run's
#    autogroup, so that the machine's other work comes first). Start it at a session's start.
# 2. A watcher: when a run's `done` file appears in the worktree and HEAD here has none, its folder is copied into
#    `runs/` here and committed alone (`git commit -- <its folder>`), its commit, CPU and seconds in the message,
#    with `members.json` (`members.py`: its reward members at the end, from the final model in the worktree). Then it
#    checks the first-seeds stop rule (`stop_rule.py`): if it fires, the watcher stops the launcher and writes `STOPPED`
#    here (a crash of `stop_rule.py` stops nothing: the log says so).
# Logs: the worktree's `logs/`, and `launcher.log` and `watcher.log` in it. Both processes outlive the shell; the
# launcher stops when its plan's runs are in, the watcher when the launcher has stopped and nothing is left to commit;
# if every run of the plan finished, the watcher then starts the next plan, so the runs go on until the session ends.
# Nothing starts while `STOPPED` is here: the protocol wants the bug search written down first. A commit that fails is
# tried again at the next pass; a stale `.git/index.lock` is removed. The tests shorten the watcher's waits with
# WATCH_TRIES (commit tries a pass, 10), WATCH_PAUSE (seconds between them, 5) and WATCH_PASS (between passes, 60).
set -euo pipefail
STUDY=results/surf-rune
main=$(git rev-parse --show-toplevel)
# the protocol's commit: the one that added PROTOCOL.md
COMMIT=$(git -C "$main" log --diff-filter=A --format=%h --abbrev=7 -- "$STUDY/PROTOCOL.md" | tail -n 1)
[ -n "$COMMIT" ] || { echo "$STUDY/PROTOCOL.md is not committed: commit the protocol first" >&2; exit 1; }
# the scripts below need the project's venv (a watcher started without it would find no stop rule)
python -c "import torch, tensorboard" 2> /dev/null || { echo "continue.sh: activate the project's venv first" >&2; exit 1; }
mode=${1:-}
[[ $mode = --dry-run || $mode = --watch ]] && shift || mode=""
work=$(realpath -m "${1:-$(dirname "$main")/surf-rune-$COMMIT}")
cd "$main"

lowest_priority() {  # the launcher and each run are sessions of their own, so `nice` alone yields only in-session
    local pid
    for pid in "$1" $(pgrep -f "$work/" || true); do
        echo 19 > "/proc/$pid/autogroup" 2> /dev/null || true
    done
}

committed() { git cat-file -e "HEAD:$STUDY/runs/$1/done" 2> /dev/null; }
lock="$(git rev-parse --absolute-git-dir)/index.lock"
unlock_if_stale() {  # a git command killed mid-commit (by a session's end) leaves its lock: every commit would fail
    local age
    age=$(($(date +%s) - $(stat -c %Y "$lock" 2> /dev/null || date +%s)))  # 0 without a lock
    if [ "$age" -ge 60 ] && ! pgrep -x git > /dev/null; then
        rm -f "$lock"
        echo "$(date -u +%FT%TZ) removed a stale $lock (no git command is running, the lock a minute old or more)"
    fi
}
watch() {  # until the launcher has stopped and every finished run is committed
    local launcher running pending id folder cpu seconds message
    launcher=$(cat "$work/launcher.pid")
    while true; do
        running="" pending=""
        kill -0 "$launcher" 2> /dev/null && running=1
        for folder in "$work/$STUDY"/runs/*/; do
            id=$(basename "$folder")
            # not yet committed: a commit that failed (the index locked) is tried again at the next pass
            [ -f "$folder/done" ] && ! committed "$id" || continue
            mkdir -p "$STUDY/runs/$id"
            cp "$folder"/* "$STUDY/runs/$id/"
            # its reward members at the end, from the final model that only this machine holds (members.py)
            nice -n 19 python "$STUDY/members.py" "$work/logs/scratch/$id/runs/$id" "$STUDY/runs/$id/members.json" ||
                echo "$(date -u +%FT%TZ) members.py failed for $id: committed without members.json"
            cpu=$(sed -n 's/^cpu //p' "$STUDY/runs/$id/done")
            seconds=$(sed -n 's/^seconds //p' "$STUDY/runs/$id/done")
            unlock_if_stale
            for _ in $(seq "${WATCH_TRIES:-10}"); do  # another git command may hold the index for a moment
                git add -- "$STUDY/runs/$id" && git commit -q -m \
                    "surf-rune: $id (commit $COMMIT, $cpu, $seconds)" -- "$STUDY/runs/$id" && break
                sleep "${WATCH_PAUSE:-5}"
            done
            # unstaged, so that no later commit of this checkout takes it in under another message
            committed "$id" || { git reset -q -- "$STUDY/runs/$id" 2> /dev/null || true; pending=1
                                 echo "$(date -u +%FT%TZ) could not commit $id: tried again in a minute"; continue; }
            echo "$(date -u +%FT%TZ) committed $id"
            # it fired when it says so; a crash of its own stops nothing, and says so
            message=$(python "$STUDY/stop_rule.py" 2>&1) || true
            if grep -q "^stop rule: " <<< "$message"; then
                kill -TERM "$launcher" 2> /dev/null || true
                printf '%s\n%s\n' "$(date -u +%FT%TZ)" "$message" > "$STUDY/STOPPED"
                echo "$(date -u +%FT%TZ) $message; launcher stopped"
            elif [ -n "$message" ]; then
                echo "$(date -u +%FT%TZ) stop_rule.py failed, the stop rule is unchecked after $id: $message"
            fi
        done
        [ -n "$running$pending" ] || return 0
        lowest_priority "$launcher"
        sleep "${WATCH_PASS:-60}"
    done
}
finished_all() {  # the launcher's last line: every run of its plan finished, none stopped, none failed
    tail -n 1 "$work/launcher.log" | grep -Eq '^[0-9]+ runs finished, [0-9]+ skipped as already finished, 0 failed$'
}
if [ "$mode" = --watch ]; then
    watch
    # the machine stays busy: the next plan starts (nothing while `STOPPED` is here, or once every run is in)
    if finished_all && [ ! -e "$STUDY/STOPPED" ]; then
        echo "$(date -u +%FT%TZ) the launcher's runs are in: the next plan"
        exec bash "$main/$STUDY/continue.sh" "$work"
    fi
    exit 0
fi
[ -e "$STUDY/STOPPED" ] && { echo "$STUDY/STOPPED: the stop rule fired; write the bug search down first" >&2; exit 1; }
[ "$mode" = --dry-run ] || unlock_if_stale
if [ ! -d "$work" ]; then  # a new machine: a run cut off on another starts over whole
    git worktree prune
    git worktree add --detach "$work" "$COMMIT" > /dev/null
    echo "new worktree: $work"
fi
[ "$(git -C "$work" rev-parse --short=7 HEAD)" = "$COMMIT" ] || { echo "$work is not at $COMMIT" >&2; exit 1; }
mkdir -p "$work/$STUDY/runs"
for run in "$STUDY"/runs/*/; do  # the committed runs, so that the launcher skips them
    [ -d "$run" ] || continue
    [ -e "$work/$STUDY/runs/$(basename "$run")/done" ] || cp -r "$run" "$work/$STUDY/runs/"
done
for state in "$work"/logs/scratch/*/runs/*/state.pt; do
    [ -f "$state" ] && echo "resumes from its state.pt: $(basename "$(dirname "$state")")"
done
plan=$(python "$STUDY/schedule.py" "$STUDY/runs" "$work/logs/scratch")
read -ra session <<< "$plan"
[ "${#session[@]}" -gt 0 ] || { echo "no run can start (schedule.py says why, if one waits); once all 48 are in: bash $STUDY/analyze.sh" >&2; exit 0; }
echo "this session: benchmark.py ${session[*]}"
if [ "$mode" = --dry-run ]; then
    (cd "$work" && python benchmark.py "${session[@]}" --dry-run | tail -n 1)
    exit 0
fi
if [ -f "$work/launcher.pid" ] && kill -0 "$(cat "$work/launcher.pid")" 2> /dev/null; then
    echo "a launcher is running already: $work/launcher.log" >&2; exit 1
fi
# `$!` is the launcher itself: a background job is no process-group leader here, so `setsid` needs no fork of its own
cd "$work"
setsid nohup nice -n 19 python benchmark.py "${session[@]}" > "$work/launcher.log" 2>&1 < /dev/null &
echo $! > "$work/launcher.pid"
cd "$main"
lowest_priority "$(cat "$work/launcher.pid")"
# one watcher: an earlier one still trying to commit gives way (a watcher keeps no state); a chained start is it
watcher=$(cat "$work/watcher.pid" 2> /dev/null || true)
[ -n "$watcher" ] && [ "$watcher" != $$ ] && grep -qs -- --watch "/proc/$watcher/cmdline" && kill "$watcher" || true
setsid nohup bash "$main/$STUDY/continue.sh" --watch "$work" >> "$work/watcher.log" 2>&1 < /dev/null &
echo $! > "$work/watcher.pid"
echo "launcher: $work/launcher.log; watcher: $work/watcher.log; the runs' logs: $work/logs/"
