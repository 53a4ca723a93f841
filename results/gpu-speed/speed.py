"""Steps/s of the GPU speed runs (issue 19), from their event files and logs: `python results/gpu-speed/speed.py DIR`.

DIR holds one folder per configuration (`run.sh` names them), each with the run folders of the runs that ran at
once (`runs/*`) and their logs (`*.log`). For each run, the window is from the evaluation at `--from-step` to its
last one, timed by the wall clock of those two `eval/episodic_return` points: it includes the evaluations, feedback
rounds and state writes in between. A configuration's aggregate is the sum of its runs' window rates (they ran at
once). The evaluations' and state writes' shares are the seconds the logs report over the window's seconds."""
import argparse
import glob
import json
import os
import re

from tensorboard.backend.event_processing.event_accumulator import EventAccumulator


def window(run_dir: str, from_step: int) -> tuple:
    events = EventAccumulator(run_dir, size_guidance={"scalars": 0})
    events.Reload()
    points = [e for e in events.Scalars("eval/episodic_return") if e.step >= from_step]
    if len(points) < 2:
        raise SystemExit(f"{run_dir}: fewer than two evaluations from step {from_step}")
    return points[0].step, points[-1].step, points[-1].wall_time - points[0].wall_time


def seconds_in_log(log: str, first: int, last: int) -> tuple:
    """Seconds of the evaluations after step `first` up to `last`, and of the state writes between them."""
    text = open(log).read()
    evals = sum(float(s) for step, s in re.findall(r"step=(\d+) eval_return=\S+ SPS=\d+ eval_seconds=(\S+)", text)
                if first < int(step) <= last)
    states = sum(float(s) for step, s in re.findall(r"state saved after step (\d+): \S+ GB in (\S+) s", text)
                 if first < int(step) <= last)
    return evals, states


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dir")
    parser.add_argument("--from-step", type=int, default=4000)
    args = parser.parse_args()
    rows = []
    for config in sorted(os.listdir(args.dir)):
        runs = sorted(glob.glob(os.path.join(args.dir, config, "runs", "*")))
        if not runs:
            continue
        rates, shares = [], []
        for run in runs:
            first, last, seconds = window(run, args.from_step)
            log = os.path.join(args.dir, config, os.path.basename(run) + ".log")
            evals, states = seconds_in_log(log, first, last) if os.path.exists(log) else (float("nan"),) * 2
            rates.append((last - first) / seconds)
            shares.append((evals / seconds, states / seconds))
        rows.append(dict(config=config, runs=len(runs), window=f"{first}-{last}", steps_per_s=round(rates[0], 1),
                         aggregate=round(sum(rates), 1), eval_share=round(shares[0][0], 4),
                         state_share=round(shares[0][1], 4)))
    print("| configuration | runs at once | window (steps) | steps/s of one run | aggregate steps/s | evaluations | "
          "state writes |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['config']} | {r['runs']} | {r['window']} | {r['steps_per_s']} | {r['aggregate']} | "
              f"{100 * r['eval_share']:.1f}% | {100 * r['state_share']:.1f}% |")
    with open(os.path.join(args.dir, "speed.json"), "w") as f:
        json.dump(rows, f, indent=1)


if __name__ == "__main__":
    main()
