"""The helper of `measure.sh` (issue 32): one instrumented run, and the tables read from the runs' event files and logs.

- `items`: runs a training script in this process with a timer around each step item (acting, the env step, the
  reward prediction, buffer writes, sampling, the three SAC steps, the optimiser steps) and around the loop body's own
  calls (the progress line, the NaN check, the observation's copy to the device, the action's to the host, which on a
  GPU waits for the work queued before it, the state and feedback clocks, the env's reset, the episode's tags). Host
  microseconds come from `time.perf_counter`; GPU microseconds from CUDA events on the run's stream, that is the
  stream time between an item's start and end marks (a GPU waiting for the host counts in it). The timers' own time
  is an item of its own. "other (loop body)" is what is left: the loop's own lines, and the lines of `sac_update` and
  `store` outside the items they call; its median is over the steps. Only steps of the window count, and none
  holding an evaluation, a feedback round or a state write.
- `lines`: the same run with Python's line tracer instead of the timers: each line of the main loop, of `sac_update`
  and of `store`, timed from its start to the next line's start in its frame.
- `rates`: the steady-state steps/s of the runs of one configuration (runs that ran at once), each over the same step
  window, from the wall times of its `losses/qf_loss` points; their sum, the rate over the wall-clock span in
  which every run was inside the window, and the rate over the span in which every run was logging (any phase).
- `window`: one run's steps/s over a step window, and the evaluations' and state writes' shares of its seconds.
- `exact`: the pass/fail table of a JUnit XML report (the eager-against-captured tests).
"""
import argparse
import csv
import functools
import glob
import json
import os
import re
import statistics
import sys
import time
import types
import xml.etree.ElementTree as ET

OVERHEAD = "(the timers' own overhead)"
TAG = "losses/qf_loss"  # logged every --log-freq steps after a host sync: the wall time of a step's end


# Reading event files and logs
def points(run_dir: str, tag: str = TAG) -> list:
    """(step, wall time) of every point of `tag` in a run folder, in step order."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = EventAccumulator(run_dir, size_guidance={"scalars": 0})
    events.Reload()
    if tag not in events.Tags()["scalars"]:
        return []
    return sorted((e.step, e.wall_time) for e in events.Scalars(tag))


def wall_at(pts: list, step: int) -> float:
    """The wall time of the point at `step`; KeyError if the run logged none there."""
    for s, t in pts:
        if s == step:
            return t
    raise KeyError(step)


def steps_at(pts: list, wall: float) -> float:
    """The step reached at wall time `wall`, linear between the points around it."""
    for (s0, t0), (s1, t1) in zip(pts, pts[1:]):
        if t0 <= wall <= t1:
            return s0 + (s1 - s0) * (wall - t0) / (t1 - t0) if t1 > t0 else s1
    raise ValueError(f"wall time {wall} outside the points")


def together(point_lists: list, spans: list) -> tuple:
    """(seconds, steps/s) of runs together over the span in which each was inside its own (start, end) span:
    (0.0, None) when the spans do not overlap."""
    if not point_lists:
        return 0.0, None
    start, end = max(a for a, _ in spans), min(b for _, b in spans)
    if end <= start:
        return 0.0, None
    steps = sum(steps_at(pts, end) - steps_at(pts, start) for pts in point_lists)
    return end - start, steps / (end - start)


def window_rates(runs: dict, first: int, last: int) -> dict:
    """Steady-state rates of runs that ran at once, each from step `first` to `last`. `runs`: name -> points.
    Returns each run's rate, their sum, and the rate of all runs together over the span where each was in the
    window (None when the windows do not overlap: the sum then overstates what ran at once), and the rate of all runs
    together over the span in which every run was logging, whatever its phase (`alive_rate`)."""
    reached = [max(s for s, _ in pts) for pts in runs.values() if pts]
    if reached and first < min(reached) < last:  # a run cut off inside the window: the window all runs finished
        last = min(reached)  # the runs log at the same steps: each has a point there
    per_run, spans = {}, {}
    for name, pts in runs.items():
        try:
            spans[name] = wall_at(pts, first), wall_at(pts, last)
        except KeyError:
            continue  # cut off before the window's end, or never started
        per_run[name] = (last - first) / (spans[name][1] - spans[name][0])
    overlap_seconds, overlap_rate = together([runs[n] for n in per_run], [spans[n] for n in per_run])
    logging = [pts for pts in runs.values() if len(pts) > 1]
    alive_seconds, alive_rate = together(logging, [(pts[0][1], pts[-1][1]) for pts in logging])
    return dict(last=last, per_run=per_run, runs_in_window=len(per_run), runs=len(runs), sum=sum(per_run.values()),
                overlap_seconds=overlap_seconds, overlap_rate=overlap_rate, alive_seconds=alive_seconds,
                alive_rate=alive_rate)


def log_seconds(text: str, first: int, last: int) -> tuple:
    """Evaluation seconds and state-write seconds that a run's log reports after step `first` up to `last`."""
    evals = [float(s) for step, s in re.findall(r"step=(\d+) eval_return=\S+ SPS=\d+ eval_seconds=(\S+)", text)
             if first < int(step) <= last]
    states = [float(s) for step, s in re.findall(r"state saved after step (\d+): \S+ GB in (\S+) s", text)
              if first < int(step) <= last]
    return evals, states


def window_shares(pts: list, log_text: str, first: int, last: int, feedback_steps: list) -> dict:
    """Steps/s of one run from `first` to `last`, and what its evaluations, state writes and feedback rounds took
    of those seconds. A round's seconds are not logged: they are estimated as the excess of the log interval that
    holds it over the median interval."""
    seconds = wall_at(pts, last) - wall_at(pts, first)
    evals, states = log_seconds(log_text, first, last)
    inside = [(s, t) for s, t in pts if first <= s <= last]
    gaps = [(s0, s1, t1 - t0) for (s0, t0), (s1, t1) in zip(inside, inside[1:])]
    typical = statistics.median(dt for _, _, dt in gaps)
    rounds = sum(max(0.0, dt - typical) for s0, s1, dt in gaps if any(s0 < f <= s1 for f in feedback_steps))
    return dict(first=first, last=last, seconds=seconds, steps_per_s=(last - first) / seconds,
                evaluations=len(evals), eval_seconds=sum(evals), eval_share=sum(evals) / seconds,
                state_writes=len(states), state_seconds=sum(states), state_share=sum(states) / seconds,
                feedback_rounds_seconds_estimate=rounds, feedback_share_estimate=rounds / seconds,
                steps_per_s_without_evals_states=(last - first) / (seconds - sum(evals) - sum(states)))


def junit_table(path: str) -> list:
    """(test, outcome, message) of each test case of a JUnit XML report."""
    rows = []
    for case in ET.parse(path).getroot().iter("testcase"):
        name = case.get("name")
        outcome, message = "passed", ""
        for kind in ("failure", "error", "skipped"):
            found = case.find(kind)
            if found is not None:
                outcome, message = kind, (found.get("message") or "").split("\n")[0][:200]
                break
        rows.append((name, outcome, message))
    return rows


# The instrumented run
class Timers:
    """Host and GPU times of the step items, for the steps from `first` to `last` (exclusive)."""

    def __init__(self, first: int, last: int, cuda: bool):
        self.first, self.last, self.cuda = first, last, cuda
        self.step, self.step_start, self.busy = None, None, False  # busy: the step held an eval, round or state
        self.leaf, self.blocked = 0, 0  # depth inside an item (no double counts) and inside an excluded part
        self.calls, self.step_seconds, self.skipped_steps = [], [], 0
        self.step_other = []  # per plain step: its seconds outside every leaf item
        self.current = []  # this step's calls, kept only if the step turns out plain
        self.excluded = {}  # seconds of the excluded parts (evaluations, rounds, state writes), each call
        self.on_window_end = None
        self.wrappers = set()  # the items that hold other items (not leaves): not summed with them

    def in_window(self) -> bool:
        return self.step is not None and self.first <= self.step < self.last

    def new_step(self, step: int):
        now = time.perf_counter()
        if self.in_window():
            if self.busy:
                self.skipped_steps += 1
            else:
                self.step_seconds.append(now - self.step_start)
                self.calls.extend(self.current)
                leaves = sum(c[1] for c in self.current if c[0] not in self.wrappers)
                self.step_other.append(now - self.step_start - leaves)
        self.step, self.step_start, self.busy, self.current = step, now, False, []
        if step >= self.last and self.on_window_end is not None:  # written now: the run may be cut off later
            self.on_window_end(self)
            self.on_window_end = None

    def item(self, name, fn, leaf: bool = True):
        """`fn` timed as item `name` (a callable that takes the item's name from its first argument when `name`
        is callable). Items inside another leaf item, or inside an excluded part, are not counted."""
        import torch

        timers = self
        if not leaf:
            self.wrappers.add(name)

        def timed(*args, **kwargs):
            entered = time.perf_counter()
            label = name(*args) if callable(name) else name
            if timers.blocked or (leaf and timers.leaf) or not timers.in_window():
                return fn(*args, **kwargs)
            marks = None
            if timers.cuda:
                marks = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
                marks[0].record()
            timers.leaf += leaf
            start = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                host = time.perf_counter() - start
                timers.leaf -= leaf
                if marks:
                    marks[1].record()
                timers.current.append((label, host, marks))
                # This wrapper's own time (the events, the clock, the label) would otherwise count as loop body.
                timers.current.append((OVERHEAD, time.perf_counter() - entered - host, None))
        return functools.wraps(fn)(timed)

    def excluding(self, name, fn):
        """`fn` as a part excluded from the items (an evaluation, a feedback round, a state write): its seconds are
        kept, and its step is left out of the step times."""
        timers = self

        def timed(*args, **kwargs):
            timers.blocked += 1
            start = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                timers.blocked -= 1
                timers.excluded.setdefault(name, []).append(time.perf_counter() - start)
                timers.busy = True
        return timed

    def table(self) -> list:
        import torch

        if self.cuda:
            torch.cuda.synchronize()
        steps = len(self.step_seconds)
        step_us = 1e6 * statistics.fmean(self.step_seconds) if steps else float("nan")
        names = sorted({c[0] for c in self.calls}, key=lambda n: min(i for i, c in enumerate(self.calls) if c[0] == n))
        rows = []
        for name in names:
            host = [1e6 * c[1] for c in self.calls if c[0] == name]
            gpu = [c[2][0].elapsed_time(c[2][1]) * 1e3 for c in self.calls if c[0] == name and c[2]]
            per_step = sum(host) / steps if steps else float("nan")
            rows.append(dict(item=name, calls=len(host), calls_per_step=len(host) / steps if steps else float("nan"),
                             host_us_mean=statistics.fmean(host), host_us_median=statistics.median(host),
                             gpu_us_mean=statistics.fmean(gpu) if gpu else float("nan"),
                             gpu_us_median=statistics.median(gpu) if gpu else float("nan"),
                             host_us_per_step=per_step, share_of_step=per_step / step_us))
        leaves = sum(r["host_us_per_step"] for r in rows if r["item"] not in self.wrappers)
        rows.append(dict(item="other (loop body)", calls=steps, calls_per_step=1.0, host_us_mean=step_us - leaves,
                         host_us_median=1e6 * statistics.median(self.step_other) if steps else float("nan"), gpu_us_mean=float("nan"), gpu_us_median=float("nan"),
                         host_us_per_step=step_us - leaves, share_of_step=(step_us - leaves) / step_us))
        rows.append(dict(item="step (whole)", calls=steps, calls_per_step=1.0, host_us_mean=step_us,
                         host_us_median=1e6 * statistics.median(self.step_seconds) if steps else float("nan"),
                         gpu_us_mean=float("nan"), gpu_us_median=float("nan"), host_us_per_step=step_us,
                         share_of_step=1.0))
        return rows


def instrument(namespace: dict, timers: Timers):
    """Wrap the step items of a script's definitions (`namespace`) and of the modules it uses, before its main
    block runs. The main block then calls the wrapped versions by their names."""
    import torch

    import ene

    from r2n_harness import cuda_graph, resume

    g = namespace
    update = g["Progress"].update

    timed_update = timers.item("progress", update)

    def step_start(self, step, *args, **kwargs):  # the loop calls it early in every step (the progress line)
        timers.new_step(step)
        return timed_update(self, step, *args, **kwargs)
    g["Progress"].update = step_start
    # The loop body's own calls, so that "other (loop body)" is only its Python lines.
    for name in ("check_finite", "log_losses", "feedback_due"):
        if name in g:
            g[name] = timers.item(name, g[name])
    resume.state_due = timers.item("state_due", resume.state_due)
    g["store"] = timers.item("store (all)", g["store"], leaf=False)
    torch.as_tensor = timers.item("as_tensor (obs to the device)", torch.as_tensor)
    # The action's copy to the host: on a GPU it waits for the work queued before it.
    torch.Tensor.cpu = timers.item("action to host (.cpu)", torch.Tensor.cpu)
    g["SummaryWriter"].add_scalar = timers.item("writer.add_scalar", g["SummaryWriter"].add_scalar)
    g["act"] = timers.item("act", g["act"])
    g["RewardEnsemble"].mean_reward = timers.item("reward_prediction", g["RewardEnsemble"].mean_reward)
    g["ReplayBuffer"].add = timers.item("buffer_write", g["ReplayBuffer"].add)
    g["ReplayBuffer"].sample = timers.item("sample", g["ReplayBuffer"].sample)
    if "EpisodeStore" in g:
        g["EpisodeStore"].add = timers.item("episode_write", g["EpisodeStore"].add)
    for name in ("critic_gradients", "actor_gradients", "target_update"):
        g[name] = timers.item(name, g[name])
    # captured: the replay is the item (the step inside it is not timed: it is being captured)
    label = lambda self, *inputs: self.step.__name__ + " (replay)"  # noqa: E731
    cuda_graph.CudaGraph.__call__ = timers.item(label, cuda_graph.CudaGraph.__call__)
    g["sac_update"] = timers.item("sac_update (all)", g["sac_update"], leaf=False)

    def optimiser_name(self, *a):
        return "optimizer_step/" + ("critic" if "qf1" in self.layers else next(iter(self.layers)))
    g["SparseOptimizer"].step = timers.item(optimiser_name, g["SparseOptimizer"].step)
    torch.optim.Adam.step = timers.item("optimizer_step/adam (alpha)", torch.optim.Adam.step)
    for name in ("evaluate", "feedback_round"):
        if name in g:
            g[name] = timers.excluding(name, g[name])
    resume.save_state = timers.excluding("save_state", resume.save_state)
    make_env = ene.make_env

    def timed_env(*args, **kwargs):
        env = make_env(*args, **kwargs)
        env.step = timers.item("env_step", env.step)
        env.physics_state = timers.item("physics_state", env.physics_state)
        env.reset = timers.item("env_reset", env.reset)
        return env
    ene.make_env = timed_env


def trace_lines(namespace: dict, timers: Timers, body, functions=("sac_update", "store")):
    """Time each line of the main block (`body`) and of `functions`: from its start to the next line's start in the
    same frame, its calls included. Each line is an item named by its function, number and text; the functions'
    lines are inside their main line's time, so only the main lines add up to the step. Python's tracer adds time to
    every line and every Python call (an env step makes hundreds), so lines read high: the ranking is the point."""
    import inspect
    import linecache

    from r2n_harness import resume

    g = namespace
    update = g["Progress"].update

    def step_start(self, step, *args, **kwargs):
        timers.new_step(step)
        return update(self, step, *args, **kwargs)
    g["Progress"].update = step_start
    for name in ("evaluate", "feedback_round"):
        if name in g:
            g[name] = timers.excluding(name, g[name])
    resume.save_state = timers.excluding("save_state", resume.save_state)
    # the functions' own code, under their decorators (`torch.no_grad`)
    codes = {body: "main", **{inspect.unwrap(g[f]).__code__: f for f in functions if f in g}}
    started = {}  # frame -> (its current line, when it started)

    def local(frame, event, arg):
        now = time.perf_counter()
        if frame in started and timers.in_window() and not timers.blocked:
            line, start = started[frame]
            text = linecache.getline(frame.f_code.co_filename, line).strip()[:60]
            label = f"{codes[frame.f_code]}:{line} {text}"
            if frame.f_code is not body:  # inside a main line's time: not summed with the main lines
                timers.wrappers.add(label)
            timers.current.append((label, now - start, None))
        if event == "return":
            started.pop(frame, None)
        else:
            started[frame] = frame.f_lineno, time.perf_counter()
        return local

    def global_trace(frame, event, arg):
        return local if frame.f_code in codes else None
    sys.settrace(global_trace)


def run_items(script: str, argv: list, first: int, last: int, out: str, lines: bool = False):
    """Run `script` with `argv` in this process, its items (`lines`: its lines) timed, and write the table to `out`
    (CSV)."""
    import torch

    source = open(script).read()
    head, main = source.split('\nif __name__ == "__main__":\n', 1)
    module = types.ModuleType("timed_script")  # a module of its own: pickle finds the script's classes there
    module.__file__ = os.path.abspath(script)
    sys.modules[module.__name__] = module
    namespace = module.__dict__
    # the step as the studies run it: with the harness's hooks (the progress line marks each step's start)
    argv = argv if "--resumable" in argv else [*argv, "--resumable"]
    sys.argv = [script, *argv]
    sys.path.insert(0, os.path.dirname(os.path.abspath(script)))
    exec(compile(head, script, "exec"), namespace)
    cuda = torch.cuda.is_available() and "--no-cuda" not in argv
    timers = Timers(first, last, cuda)
    timers.on_window_end = lambda t: write_items(t, out)
    offset = head.count("\n") + 1  # the main block keeps its line numbers in tracebacks
    body = compile("\n" * offset + "if True:\n" + main, script, "exec")
    if lines:
        trace_lines(namespace, timers, body)
    else:
        instrument(namespace, timers)
    try:
        exec(body, namespace)
    except SystemExit as e:
        if e.code not in (None, 0):
            raise
    finally:
        sys.settrace(None)
    if timers.on_window_end is not None:
        raise SystemExit(f"items: the run ended before step {last}")
    with open(out, "a") as f:  # the evaluations after the window too
        for name, seconds in timers.excluded.items():
            f.write(f"# {name}: {len(seconds)} calls, seconds each: {' '.join(f'{s:.2f}' for s in seconds)}\n")


def write_items(timers: Timers, out: str):
    rows = timers.table()
    with open(out, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        for r in rows:
            # Shares to 4 places: a dozen rounded to 2 can sum to 1.02.
            writer.writerow({k: round(v, 4 if k == "share_of_step" else 2) if isinstance(v, float) else v
                             for k, v in r.items()})
        f.write(f"# {len(timers.step_seconds)} plain steps from {timers.first} to {timers.last} "
                f"({timers.skipped_steps} left out: an evaluation, feedback round or state write); "
                f"GPU timing: {timers.cuda}\n")
    print_table(rows)
    sys.stdout.flush()


def print_table(rows: list):
    print(f"{'item':34s} {'calls/step':>10s} {'host us':>9s} {'median':>9s} {'gpu us':>9s} {'host us/step':>12s} "
          f"{'share':>6s}")
    for r in rows:
        print(f"{r['item']:34s} {r['calls_per_step']:10.2f} {r['host_us_mean']:9.1f} {r['host_us_median']:9.1f} "
              f"{r['gpu_us_mean']:9.1f} "
              f"{r['host_us_per_step']:12.1f} {100 * r['share_of_step']:5.1f}%")


def append_csv(path: str, row: dict):
    new = not os.path.exists(path)
    with open(path, "a", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(row))
        if new:
            writer.writeheader()
        writer.writerow(row)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="part", required=True)
    for part, help in (("items", "one instrumented run: items.csv"),
                       ("lines", "one run, each line of its main loop, `sac_update` and `store` timed: lines.csv")):
        p = sub.add_parser(part, help=help)
        p.add_argument("out")
        p.add_argument("--from-step", type=int, required=True)
        p.add_argument("--to-step", type=int, required=True)
        p.add_argument("script")
        p.add_argument("args", nargs=argparse.REMAINDER)
    p = sub.add_parser("rates", help="the steady-state rates of one configuration: a row of aggregate.csv")
    p.add_argument("config_dir")
    p.add_argument("out")
    p.add_argument("--from-step", type=int, required=True)
    p.add_argument("--to-step", type=int, required=True)
    p.add_argument("--name", required=True)
    p.add_argument("--mps", default="no")
    p.add_argument("--started", type=int, default=0, help="runs started (missing ones count as cut off)")
    p = sub.add_parser("window", help="one run's window: window.json")
    p.add_argument("run_dir")
    p.add_argument("log")
    p.add_argument("out")
    p.add_argument("--from-step", type=int, required=True)
    p.add_argument("--to-step", type=int, required=True)
    p.add_argument("--feedback-steps", type=int, nargs="*", default=[])
    p = sub.add_parser("exact", help="a JUnit report as exact.csv")
    p.add_argument("junit")
    p.add_argument("out")
    args = parser.parse_args()
    if args.part in ("items", "lines"):
        run_items(args.script, args.args, args.from_step, args.to_step, args.out, lines=args.part == "lines")
    elif args.part == "rates":
        runs = {os.path.basename(r): points(r) for r in sorted(glob.glob(os.path.join(args.config_dir, "runs", "*")))}
        result = window_rates(runs, args.from_step, args.to_step)
        row = dict(config=args.name, mps=args.mps, runs_started=args.started or len(runs),
                   runs_in_window=result["runs_in_window"], window=f"{args.from_step}-{result['last']}",
                   sum_steps_per_s=round(result["sum"], 1),
                   overlap_steps_per_s=None if result["overlap_rate"] is None else round(result["overlap_rate"], 1),
                   overlap_seconds=round(result["overlap_seconds"], 1),
                   alive_steps_per_s=None if result["alive_rate"] is None else round(result["alive_rate"], 1),
                   alive_seconds=round(result["alive_seconds"], 1),
                   per_run=" ".join(f"{n}:{r:.1f}" for n, r in result["per_run"].items()))
        append_csv(args.out, row)
        print(", ".join(f"{k}={v}" for k, v in row.items()))
    elif args.part == "window":
        result = window_shares(points(args.run_dir), open(args.log).read(), args.from_step, args.to_step,
                               args.feedback_steps)
        result = {k: round(v, 4) if isinstance(v, float) else v for k, v in result.items()}
        with open(args.out, "w") as f:
            json.dump(result, f, indent=1)
        print(json.dumps(result))
    elif args.part == "exact":
        rows = junit_table(args.junit)
        with open(args.out, "w", newline="") as f:
            writer = csv.writer(f)
            writer.writerow(["test", "outcome", "message"])
            writer.writerows(rows)
        counts = {o: sum(r[1] == o for r in rows) for o in ("passed", "failure", "error", "skipped")}
        print("exact: " + ", ".join(f"{n} {o}" for o, n in counts.items()))


if __name__ == "__main__":
    main()
