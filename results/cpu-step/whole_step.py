"""Issue 44 (CPU part): a whole training step's speed before and after the lighter CPU step, as a ratio in one run.

The two versions run side by side: each pair starts a run of the code before (`--before`) and one of the code after
(`--after`) at the same moment, the same command, the same seed, one thread each. Load on the machine slows both alike,
so each pair gives a ratio even on a busy machine. The order in which a pair starts alternates. Each run's steps/s is
read over a window of learned-reward steps from the wall times of its `losses/qf_loss` points (every 100 steps, after
the losses' host read), so start-up, the random phase and pre-training do not count.

    .venv/bin/python results/cpu-step/whole_step.py --before 45006c8^ --after HEAD --pairs 3

Each version is a detached git worktree in a temporary folder. The runs are the stored-noise study's config
(cheetah-run 0.9, 256 wide, batch 128, budget 1000, a round every 1 200 steps, the noise stored, named by its flag),
with pre-training cut to 1 000 steps so that the window's learned-reward steps come early. Both versions' numerics are
bitwise the same (tests/test_numerics.py), so both runs of a pair do the same work: the script checks that their last
losses agree bit for bit. Writes `whole_step.json` and `whole_step.log` beside itself, and the runs' event files
under `whole-step/`.
"""
import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(os.path.dirname(HERE))
sys.path.insert(0, os.path.join(ROOT, "results", "gpu-speed"))
from measure import points, wall_at  # noqa: E402

FLAGS = ("--env-id", "cheetah-run", "--noise", "0.9", "--no-noise-resample", "--max-feedback", "1000",
         "--feedback-freq", "1200", "--hidden-dim", "256", "--batch-size", "128", "--threads", "1",
         "--learning-starts", "1000", "--unsup-steps", "1000", "--eval-freq", "100000", "--log-freq", "100",
         "--no-cuda", "--seed", "1")


def worktree(commit: str, folder: str) -> str:
    """A detached worktree of `commit`; returns its full commit hash."""
    subprocess.run(["git", "-C", ROOT, "worktree", "add", "--detach", folder, commit], check=True,
                   capture_output=True)
    return subprocess.run(["git", "-C", folder, "rev-parse", "HEAD"], check=True, capture_output=True,
                          text=True).stdout.strip()


def start(code: str, script: str, work: str, last: int, log) -> subprocess.Popen:
    os.makedirs(work, exist_ok=True)
    command = [sys.executable, os.path.join(code, script), *FLAGS, "--total-timesteps", str(last + 1),
               "--run-name", "run"]
    env = os.environ | {"OMP_NUM_THREADS": "1"}
    return subprocess.Popen(command, cwd=work, stdout=log, stderr=subprocess.STDOUT, env=env)


def rate(work: str, first: int, last: int) -> tuple:
    """(steps/s over the window, the last point's qf_loss value) of the run in `work`."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    run_dir = os.path.join(work, "runs", "run")
    pts = points(run_dir)
    seconds = wall_at(pts, last) - wall_at(pts, first)
    events = EventAccumulator(run_dir, size_guidance={"scalars": 0})
    events.Reload()
    return (last - first) / seconds, events.Scalars("losses/qf_loss")[-1].value


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--before", required=True, help="the commit before the change")
    parser.add_argument("--after", default="HEAD", help="the commit after it")
    parser.add_argument("--scripts", nargs="+", default=["r2n_pebble.py", "pebble.py"])
    parser.add_argument("--pairs", type=int, default=3, help="pairs per script")
    parser.add_argument("--from-step", type=int, default=2100)
    parser.add_argument("--to-step", type=int, default=4100)
    args = parser.parse_args()
    scratch = tempfile.mkdtemp(prefix="whole-step-")
    out = os.path.join(HERE, "whole-step")
    shutil.rmtree(out, ignore_errors=True)
    code = {name: os.path.join(scratch, name) for name in ("before", "after")}
    commits = {name: worktree(getattr(args, name), folder) for name, folder in code.items()}
    result = dict(commits=commits, flags=" ".join(FLAGS), window=[args.from_step, args.to_step],
                  torch=__import__("torch").__version__, cores=os.cpu_count(), pairs={})
    with open(os.path.join(HERE, "whole_step.log"), "w") as log:
        log.write(f"# {time.strftime('%Y-%m-%d %H:%M:%S')} before {commits['before']} after {commits['after']}\n")
        for script in args.scripts:
            for pair in range(args.pairs):
                order = ("before", "after") if pair % 2 == 0 else ("after", "before")
                works = {name: os.path.join(out, script[:-3], f"pair{pair}", name) for name in order}
                logs = {name: open(os.path.join(scratch, f"{script}-{pair}-{name}.log"), "w") for name in order}
                runs = {name: start(code[name], script, works[name], args.to_step, logs[name]) for name in order}
                for name, run in runs.items():
                    if run.wait():
                        raise SystemExit(f"{script} pair {pair} {name} failed: see {logs[name].name}")
                rates = {name: rate(works[name], args.from_step, args.to_step) for name in order}
                if rates["before"][1] != rates["after"][1]:
                    raise SystemExit(f"{script} pair {pair}: the two versions' losses differ")
                row = dict(order=list(order), before=rates["before"][0], after=rates["after"][0],
                           ratio=rates["after"][0] / rates["before"][0])
                result["pairs"].setdefault(script, []).append(row)
                log.write(f"{script} pair {pair} ({' first, '.join(order)} second): before {row['before']:.1f} "
                          f"after {row['after']:.1f} steps/s, ratio {row['ratio']:.3f}\n")
                log.flush()
                for work in works.values():  # the event files stay; states, checkpoints and query logs go
                    for name in os.listdir(os.path.join(work, "runs", "run")):
                        path = os.path.join(work, "runs", "run", name)
                        if os.path.isdir(path):
                            shutil.rmtree(path)
                        elif not name.startswith("events."):
                            os.remove(path)
                    shutil.rmtree(os.path.join(work, "videos"), ignore_errors=True)
            ratios = [row["ratio"] for row in result["pairs"][script]]
            result.setdefault("median_ratio", {})[script] = statistics.median(ratios)
            log.write(f"{script}: median ratio after/before {statistics.median(ratios):.3f} "
                      f"(range {min(ratios):.3f}-{max(ratios):.3f})\n")
    with open(os.path.join(HERE, "whole_step.json"), "w") as f:
        json.dump(result, f, indent=1)
    for folder in code.values():
        subprocess.run(["git", "-C", ROOT, "worktree", "remove", "--force", folder], check=False)
    print(json.dumps(result["median_ratio"]))


if __name__ == "__main__":
    main()
