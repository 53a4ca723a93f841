# docs and usage: docs/analyze.md
"""The paper's tables and plots from local TensorBoard runs.

Reads every run under `--log-dirs` (searched recursively; a run is one `events.out.tfevents.*` file, the scripts write
one per run), with all points (no TensorBoard subsampling), and groups runs by (task, noise, budget, method) read from
the logged hyperparameter table: task = `env_id`, method = `exp_name`, budget = `max_feedback` (absent for SAC oracles).
For every group it writes, as Markdown and CSV, three tables in the layout of the paper's appendix tables: the primary
metric (the mean of each run's last `--primary-last` (3) evaluation returns), the final return (last
`eval/episodic_return`) and the AUC (sum of all evaluation returns), and a fourth where the runs log a success rate
(Meta-World): the mean of each run's last `--primary-last` `eval/success_rate`; each as mean ± standard error over seeds
(SE = sample std (ddof 1) / sqrt(n)), the number of seeds and, against a baseline of the same task, noise and budget,
the one-tailed Welch's t-test p-value (`scipy.stats.ttest_ind(method, baseline, equal_var=False,
alternative="greater")`; `*` where p < 0.05), the one-tailed permutation-test p-value of the difference in means (exact
over every relabeling of the seeds up to `PERMUTATIONS` of them, else that many random ones) and the difference in means
with its percentile bootstrap 95% CI (`BOOTSTRAP_RESAMPLES` resamples of each arm; both with a fixed seed, so the tables
regenerate identically). It also writes learning curves per task (mean ± SE, one colour per method) and connectivity
plots (relevant vs noise degree over time for each sparse network, mean ± SE over seeds). Where runs log
`features/{net}/relevant_weight_frac`, it writes `features.md` (its final value per group and network, mean ± SE, with
the chance level) and one plot per task and setting (its curve per method and network, chance dotted).

Choices where the paper is silent:
- A run is used only if it is readable, has a hyperparameter table with `env_id`, `exp_name` and `seed`, has at least
  one evaluation point, and is finished: its last evaluation step is >= `total_timesteps` (the scripts evaluate at the
  last step). `--include-unfinished` also uses unfinished runs. A run that `benchmark.py` finished when a non-finite
  value stopped it (its folder's `done` file has a `stopped` line) is used with what it reached: it does not shorten
  its group's steps, its curve is empty after its stop, and its metrics are over its finite evaluations (the primary
  metric: its last `--primary-last` of them).
- Runs of one group must agree on every hyperparameter except the run-specific ones in `RUN_SPECIFIC_KEYS` (seed,
  exp_name, logging, device and thread settings that do not change the algorithm); a flag the scripts gained later
  (`ADDED_FLAG_DEFAULTS`) counts at its default for runs recorded before it existed. The configuration shared by most
  runs of the group is kept (a tie goes to the configuration of the alphabetically first run); the other runs are
  skipped as "mismatched settings", naming the differing keys. Two used runs with the same seed in a group: the one
  with the most evaluation steps is kept (then the most recent folder), the others are skipped as duplicates.
- Unequal evaluation points within a group (unfinished runs included, a missing point): the group is aligned on the
  steps present in every one of its runs (with one `eval_freq` this truncates to the shortest run) and a note says
  so. Final return and AUC are then those of the aligned curves, so every seed of a group covers the same steps.
  Nothing is interpolated. A method whose comparison settings (`COMPARED_KEYS`) differ from its baseline's is tested
  anyway, with a note.
- Skipped runs are listed (path and reason) on stdout, in the Markdown files and in `runs.csv`; they are never
  averaged.
- One run per event file, not per folder: the scripts give every run its own folder, but a folder that holds several
  event files (copied together, or written by an older version that could share a folder within one second) has
  each used separately, with a note.
"""
import contextlib
import csv
import glob
import itertools
import math
import os
import re
import sys
import warnings
from collections import Counter, defaultdict
from dataclasses import dataclass, field
from itertools import groupby
from typing import Literal

import numpy as np
import tyro


@dataclass
class Args:
    log_dirs: tuple[str, ...] = ("runs",)
    """folders searched recursively for TensorBoard runs (`events.out.tfevents.*` files, one per run)"""
    output_dir: str = "analysis"
    """where the tables (`primary.md/.csv`, `final_return.md/.csv`, `auc.md/.csv`, `runs.md/.csv`) and plots
    (`curves/`, `connectivity/`) go"""
    baseline: str = "pebble"
    """the method (exp_name) each method of the same task, noise and budget is tested against"""
    baseline_for: tuple[str, ...] = ()
    """per-method baselines overriding `--baseline`, as METHOD=BASELINE; METHOD=METHOD makes it untested (the paper's
    main table: `r2n_surf=surf r2n_rune=rune surf=surf rune=rune`)"""
    alternative: Literal["greater", "less"] = "greater"
    """H1 of the one-tailed Welch's t-test: `greater`: method > baseline; `less`: baseline > method (the paper's
    sparse-baselines tables, where the baseline R2N-PEBBLE is the one expected to be better)"""
    significance: float = 0.05
    """p-values below this get a `*`"""
    primary_last: int = 3
    """the primary metric of a run: the mean of its last this many evaluation returns (each itself a mean over
    `eval_episodes` episodes); a study fixes it in its protocol"""
    include_unfinished: bool = False
    """also use runs whose last evaluation step is below `total_timesteps` (groups are then aligned on common steps)"""
    plots: bool = True
    """write the PNG learning curves and connectivity plots (`--no-plots`: tables only)"""
    readme: str | None = None
    """also rewrite the part of this Markdown file between the lines `<!-- analyze.py results: start -->` and
    `<!-- analyze.py results: end -->` with the tables and curves, so a README's results follow the runs"""


# Hyperparameters that may differ between the seeds of one group: they name, log or place a run, or change only
# numerics (device, threads, chunking of the relabelling pass), not the algorithm. `cuda_graph` gives the numbers of
# eager on its GPU and `parallel_eval` the same returns (both tested), `state_minutes` only says when the state is written.
RUN_SPECIFIC_KEYS = frozenset({
    "seed", "exp_name", "track", "wandb_project_name", "wandb_entity", "capture_video", "save_model", "threads",
    "cuda", "torch_deterministic", "log_freq", "relabel_batch_size", "diagnostic_transitions", "diagnostic_pairs",
    "run_name", "checkpoint_freq", "keep_state", "state_minutes", "cuda_graph", "parallel_eval",
})
# Flags the scripts gained after runs were recorded, with the value those runs had in effect (only the simulated teacher
# existed before `--teacher`, and the noise was redrawn before `--noise-resample`), so that old and new runs of one
# configuration stay one group.
ADDED_FLAG_DEFAULTS = {"teacher": "simulated", "preferences": None, "compile": False, "tf32": False,
                       "noise_resample": True, "hidden_layers": 2, "weight_decay": 0.0, "cuda_graph_whole": False}
# Flags that change a run's numerics (issue 19), and the flag that makes the noise redrawn or stored (two different
# environments): runs that differ in one are never averaged together or compared.
NUMERICS_KEYS = ("compile", "tf32", "cuda_graph_whole")  # the last: not yet shown exact on a GPU
VARIANT_KEYS = ("noise_resample",)
# Settings a method should share with its baseline for a fair comparison (a difference gives a note, not a skip).
COMPARED_KEYS = ("total_timesteps", "eval_freq", "eval_episodes", "episode_length", "noise_type")
EVAL_TAG = "eval/episodic_return"
SUCCESS_TAG = "eval/success_rate"  # beside the return on a task with a success flag (Meta-World)
SPARSE_TAG = re.compile(r"^sparse/(?P<net>[^/]+)/(?P<metric>relevant_degree|noise_degree)$")
FEATURE_TAG = re.compile(r"^features/(?P<net>[^/]+)/relevant_weight_frac$")  # every script; its chance: `.../chance`
PERMUTATIONS = 200_000  # the permutation test is exact up to this many relabelings, else samples this many
BOOTSTRAP_RESAMPLES = 10_000  # per arm, for the CI of the difference in means
DIAGNOSTIC_TAGS = ("pbrl/reward_steps", "pbrl/reward_true_corr", "pbrl/heldout_accuracy")  # last value, in runs.md
README_MARKERS = ("<!-- analyze.py results: start -->", "<!-- analyze.py results: end -->")
PAPER_TASKS = ["cartpole-swingup", "walker-walk", "cheetah-run", "quadruped-walk", "humanoid-stand"]
PAPER_METHODS = [
    "sac", "anf_sac", "pebble", "r2n_pebble", "surf", "r2n_surf", "rune", "r2n_rune", "set_pebble", "static_pebble",
    "l1_pebble", "dropconnect_pebble", "r2n_pebble_reward_only", "r2n_pebble_agent_only",
]


@dataclass
class Run:
    """One run: its event file, hyperparameters and scalars (tag -> (steps, values), sorted by step)."""

    path: str
    hparams: dict = field(default_factory=dict)
    scalars: dict = field(default_factory=dict)
    status: str = "used"  # "used" or "skipped"
    reason: str = ""
    note: str = ""
    stopped: bool = False  # by a non-finite value: used with what it reached
    wall_seconds: float = float("nan")  # first to last event, summed over the starts of a resumed run

    @property
    def key(self):
        """The group: (task, noise, budget, method)."""
        return (self.hparams.get("env_id"), self.hparams.get("noise"), self.hparams.get("max_feedback"),
                self.hparams.get("exp_name"))

    @property
    def seed(self):
        return self.hparams.get("seed")

    @property
    def folder(self) -> str:
        return os.path.dirname(self.path)

    @property
    def eval_steps(self) -> np.ndarray:
        return self.scalars.get(EVAL_TAG, (np.zeros(0, dtype=np.int64), None))[0]

    def skip(self, reason: str):
        self.status, self.reason = "skipped", reason


@dataclass
class Group:
    """The used runs of one (task, noise, budget, method), aligned on their common evaluation steps."""

    key: tuple
    runs: list
    steps: np.ndarray = None
    curves: np.ndarray = None  # (seeds, steps)
    success_curves: np.ndarray = None  # (seeds, steps) of `SUCCESS_TAG`, where every run logs it
    notes: list = field(default_factory=list)

    @property
    def final(self) -> np.ndarray:
        return np.array([row[np.isfinite(row)][-1] for row in self.curves])

    @property
    def auc(self) -> np.ndarray:
        return np.where(np.isfinite(self.curves), self.curves, 0.0).sum(axis=1)

    def values(self, metric: str, last: int) -> np.ndarray:
        """Per seed: the mean of the `last` evaluations (`primary`), the final return, the AUC or the mean of the
        `last` success rates (`success`, NaN without them); a run stopped by a non-finite value, over its finite ones."""
        if metric == "success":
            if self.success_curves is None:
                return np.full(len(self.runs), np.nan)
            return np.array([row[np.isfinite(row)][-last:].mean() for row in self.success_curves])
        if metric != "primary":
            return getattr(self, metric)
        primary = self.curves[:, -last:].mean(axis=1)
        for i, row in enumerate(self.curves):
            if not np.isfinite(row).all():
                primary[i] = row[np.isfinite(row)][-last:].mean()
        return primary


# ---------------------------------------------------------------- reading


def parse_value(text: str):
    """A hyperparameter value as the scripts print it (`str()` of a Python value) back to int/float/bool/None/str."""
    if text in ("None", ""):
        return None if text == "None" else ""
    if text in ("True", "False"):
        return text == "True"
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    return text


def parse_hparams(text: str) -> dict:
    """The `|param|value|` Markdown table written by `writer.add_text("hyperparameters", ...)`, as a dict."""
    hparams = {}
    for line in text.splitlines():
        line = line.strip()
        if not (line.startswith("|") and line.endswith("|")) or len(line) < 2:
            continue
        key, sep, value = line[1:-1].partition("|")
        if not sep or (key, value) in (("param", "value"), ("-", "-")):
            continue
        hparams[key.strip()] = parse_value(value.strip())
    return hparams


def shown(path: str) -> str:
    """A path as the outputs name it: relative to the working folder when inside it, so that the committed tables of a
    results folder regenerate identically from any checkout."""
    relative = os.path.relpath(path)
    return path if relative.startswith(os.pardir) else relative


def find_event_files(log_dirs) -> list:
    """Every TensorBoard event file under `log_dirs` (recursively), sorted (by folder, then by start time)."""
    found = set()
    for root in log_dirs:
        for path in glob.glob(os.path.join(glob.escape(root), "**", "events.out.tfevents.*"), recursive=True):
            found.add(shown(os.path.abspath(path)))
    return sorted(found, key=lambda path: (natural_order(os.path.dirname(path)), natural_order(os.path.basename(path))))


def natural_order(name: str) -> list:
    """Numbers compared as numbers: a writer's 100th file (`...tfevents.T.host.PID.100`) comes after its 99th."""
    return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", name)]


def read_run(path: str, whole_folder: bool = False) -> Run:
    """All scalar points and the hyperparameter table of one event file, or with `whole_folder` of every event file in
    its folder read in order, as TensorBoard does (a resumed run: its purge hides the points logged after the saved
    state). Raises on unreadable files."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
    from tensorboard.util import tb_logging

    tb_logging.get_logger().setLevel("ERROR")  # not its warning on the purge of a resumed run: that is expected
    accumulator = EventAccumulator(os.path.dirname(path) if whole_folder else path, size_guidance={"scalars": 0, "tensors": 0})
    accumulator.Reload()
    tags = accumulator.Tags()
    run = Run(path)
    times = []
    for tag in tags.get("scalars", []):
        events = accumulator.Scalars(tag)
        times += [events[0].wall_time, events[-1].wall_time]
        by_step = {event.step: event.value for event in events}  # a repeated step: the last wins
        steps = np.array(sorted(by_step), dtype=np.int64)
        run.scalars[tag] = (steps, np.array([by_step[s] for s in steps], dtype=np.float64))
    for tag in tags.get("tensors", []):
        events = accumulator.Tensors(tag)
        times += [events[0].wall_time, events[-1].wall_time]
        if tag.split("/")[0] == "hyperparameters":
            values = events[-1].tensor_proto.string_val
            if values:
                run.hparams = parse_hparams(values[0].decode("utf-8", "replace"))
    if times:
        run.wall_seconds = max(times) - min(times)
    return run


def read_folder(paths: list) -> list:
    """The runs of the event files of one folder. A run resumed from its `state.pt` (docs/running.md: "Resuming a run") wrote
    one file per start, and only the first has the hyperparameter table: those files are read together as one run.
    Files that each have the table are runs of their own that shared the folder."""
    runs = []
    for path in paths:
        try:
            runs.append(read_run(path))
        except Exception as e:  # a truncated or corrupt event file
            runs.append(Run(path))
            runs[-1].skip(f"unreadable: {type(e).__name__}: {e}")
    if len(runs) > 1 and runs[0].hparams and all(run.status == "used" and not run.hparams for run in runs[1:]):
        run = read_run(paths[0], whole_folder=True)
        run.note = f"resumed {len(paths) - 1} time(s): {len(paths)} event files read as one run"
        run.wall_seconds = sum(start.wall_seconds for start in runs)
        return [run]
    for run in runs:
        if len(runs) > 1:
            run.note = f"shares its folder with {len(runs) - 1} other event file(s) (the folder's checkpoint is one of theirs)"
    return runs


def stopped_line(run: Run) -> str:
    """The `stopped` line of the `done` file beside the run (benchmark.py: a stop at a non-finite value), else ''."""
    path = os.path.join(run.folder, "done")
    lines = open(path).read().splitlines() if os.path.exists(path) else []
    return next((line for line in lines if line.startswith("stopped ")), "")


def load_runs(log_dirs, include_unfinished: bool = False) -> list:
    """Every run found, with `status` "used" or "skipped" and the reason: unreadable, crashed, unfinished."""
    runs = []
    for _, paths in groupby(find_event_files(log_dirs), key=os.path.dirname):
        runs += read_folder(list(paths))
    for run in runs:
        if run.status == "skipped":
            continue
        missing = [k for k in ("env_id", "exp_name", "seed") if k not in run.hparams]
        steps = run.eval_steps
        total = run.hparams.get("total_timesteps")
        if not run.hparams:
            run.skip("unreadable: no hyperparameters table")
        elif missing:
            run.skip(f"unreadable: hyperparameters table lacks {', '.join(missing)}")
        elif len(steps) == 0:
            run.skip(f"crashed: no {EVAL_TAG} point")
        elif (stopped := stopped_line(run)) and not np.isfinite(run.scalars[EVAL_TAG][1]).any():
            run.skip(f"crashed: {stopped} (its done file) before any finite {EVAL_TAG} point")
        elif stopped:
            run.stopped = True
            run.note = "; ".join(filter(None, [run.note, f"{stopped} (its done file): counted with what it reached"]))
        elif isinstance(total, int) and steps[-1] < total:
            state = f"unfinished: last evaluation at step {steps[-1]} of total_timesteps {total}"
            if include_unfinished:
                run.note = "; ".join(filter(None, [run.note, state + " (included: --include-unfinished)"]))
            else:
                run.skip(state + " (still running or died; --include-unfinished uses it)")
    return runs


def flag_of(run: Run, key: str):
    """A flag's value in a run, or the value it had in effect before the scripts gained it."""
    return run.hparams.get(key, ADDED_FLAG_DEFAULTS.get(key, False))


def config_of(run: Run) -> tuple:
    """The hyperparameters that must match within a group (a flag added after a run was recorded: its default)."""
    hparams = {**ADDED_FLAG_DEFAULTS, **run.hparams}
    return tuple(sorted((k, repr(v)) for k, v in hparams.items() if k not in RUN_SPECIFIC_KEYS))


def folder_time(run: Run) -> int:
    """The unix time at the end of the run folder's name (`{env}__{exp}__{seed}__{time}`), else 0."""
    tail = os.path.basename(run.folder).rsplit("__", 1)[-1]
    return int(tail) if tail.isdigit() else 0


def make_groups(runs) -> list:
    """Group the used runs by (task, noise, budget, method), skip mismatched settings and duplicate seeds, align."""
    by_key = defaultdict(list)
    for run in runs:
        if run.status == "used":
            by_key[run.key].append(run)
    groups = []
    for key, members in by_key.items():
        members.sort(key=lambda r: r.path)
        configs = Counter(config_of(r) for r in members)
        first_index = {}
        for i, r in enumerate(members):
            first_index.setdefault(config_of(r), i)
        chosen = max(configs, key=lambda c: (configs[c], -first_index[c]))
        chosen_dict = dict(chosen)
        for r in members:
            config = dict(config_of(r))
            if config != chosen_dict:
                keys = [k for k in sorted(set(config) | set(chosen_dict)) if config.get(k) != chosen_dict.get(k)]
                diffs = [f"{k}={config.get(k, '<absent>')} (group: {chosen_dict.get(k, '<absent>')})" for k in keys]
                numerics = " (numerics flags: never averaged together)" if set(keys) & set(NUMERICS_KEYS) else ""
                variant = " (noise redrawn and stored: never averaged together)" if set(keys) & set(VARIANT_KEYS) else ""
                r.skip("mismatched settings: " + ", ".join(diffs) + numerics + variant)
        members = [r for r in members if r.status == "used"]
        by_seed = defaultdict(list)
        for r in members:
            by_seed[r.seed].append(r)
        for seed, same in by_seed.items():
            same.sort(key=lambda r: (len(r.eval_steps), folder_time(r), r.path), reverse=True)
            for r in same[1:]:
                r.skip(f"duplicate seed {seed} in its group (kept {same[0].path})")
        members = sorted((r for r in members if r.status == "used"), key=lambda r: (r.seed, r.path))
        group = Group(key, members)
        aligned = [r for r in members if not r.stopped] or members  # a stopped run does not shorten the others
        common = aligned[0].eval_steps
        for r in aligned[1:]:
            common = np.intersect1d(common, r.eval_steps)
        if len(common) == 0:
            for r in members:
                r.skip("no evaluation step in common with the other runs of its group")
            continue
        dropped = sum(len(np.setdiff1d(r.eval_steps, common)) for r in members)
        if dropped:
            group.notes.append(
                f"aligned on the {len(common)} evaluation steps common to its {len(members)} runs "
                f"(up to step {common[-1]}; {dropped} points of longer runs left out)"
            )
        group.notes.extend(f"{os.path.relpath(r.path, os.path.dirname(r.folder))}: {r.note}" for r in members if r.note)
        group.steps = common
        group.curves = np.stack([curve_at(r, common) for r in members])
        if all(SUCCESS_TAG in r.scalars for r in members):
            group.success_curves = np.stack([curve_at(r, common, SUCCESS_TAG) for r in members])
        groups.append(group)
    return groups


def curve_at(run: Run, steps: np.ndarray, tag: str = EVAL_TAG) -> np.ndarray:
    """The run's evaluation returns (or another evaluation tag) at `steps`; NaN after a non-finite value stopped it."""
    tag_steps, values = run.scalars[tag]
    if not run.stopped and np.isin(steps, tag_steps).all():
        return values[np.searchsorted(tag_steps, steps)]
    returns = dict(zip(tag_steps.tolist(), values.tolist()))
    return np.array([returns.get(step, np.nan) for step in steps.tolist()])


# ---------------------------------------------------------------- statistics


def mean_se(values: np.ndarray):
    """Mean and standard error (sample std, ddof 1, / sqrt(n)); SE is nan for one seed."""
    values = np.asarray(values, dtype=np.float64)
    se = float(values.std(ddof=1) / math.sqrt(len(values))) if len(values) > 1 else float("nan")
    return float(values.mean()), se


def welch_p(a, b, alternative: str = "greater") -> float:
    """One-tailed Welch's t-test p-value of H1 mean(a) > mean(b) (`greater`) or < (`less`); nan if undefined."""
    from scipy import stats

    if len(a) < 2 or len(b) < 2:
        return float("nan")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return float(stats.ttest_ind(a, b, equal_var=False, alternative=alternative).pvalue)


def permutation_p(a, b, alternative: str = "greater", max_exact: int = PERMUTATIONS, seed: int = 0) -> tuple:
    """One-tailed permutation test of the difference in means, H1 as in `welch_p`: the share of the relabelings of
    the pooled values whose difference is at least the observed one. Every relabeling when there are at most
    `max_exact` (then the smallest possible p is 1 / C(n_a + n_b, n_a)), else `max_exact` random ones, counted with
    the observed labelling ((k + 1) / (N + 1)). Returns (p, exact); nan for an empty arm."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    if len(a) == 0 or len(b) == 0:
        return float("nan"), True
    pooled, n, sign = np.concatenate([a, b]), len(a), 1.0 if alternative == "greater" else -1.0
    exact = math.comb(len(pooled), n) <= max_exact
    if exact:
        chosen = np.array(list(itertools.combinations(range(len(pooled)), n)))
    else:
        chosen = np.random.default_rng(seed).random((max_exact, len(pooled))).argsort(axis=1)[:, :n]
    sums = pooled[chosen].sum(axis=1)
    differences = sign * (sums / n - (pooled.sum() - sums) / (len(pooled) - n))
    observed = sign * (a.mean() - b.mean())
    count = int((differences >= observed - 1e-9 * max(1.0, abs(observed))).sum())  # ties count: floating sums
    return (count / len(chosen) if exact else (count + 1) / (len(chosen) + 1)), exact


def bootstrap_ci(a, b, resamples: int = BOOTSTRAP_RESAMPLES, level: float = 0.95, seed: int = 0) -> tuple:
    """Percentile bootstrap CI of mean(a) - mean(b), each arm resampled on its own; nan with fewer than 2 per arm."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    if len(a) < 2 or len(b) < 2:
        return float("nan"), float("nan")
    rng = np.random.default_rng(seed)
    differences = (a[rng.integers(0, len(a), (resamples, len(a)))].mean(axis=1)
                   - b[rng.integers(0, len(b), (resamples, len(b)))].mean(axis=1))
    low, high = np.percentile(differences, [50 * (1 - level), 50 * (1 + level)])
    return float(low), float(high)


def power(effect: float, sd: float, n: int, alpha: float = 0.05) -> float:
    """Power of the one-tailed test of a difference `effect` at `n` seeds per arm and a common SD: the noncentral t
    with df = 2n - 2 (the studies' planning approximation of Welch's test)."""
    from scipy import stats

    df = 2 * n - 2
    return float(1 - stats.nct.cdf(stats.t.ppf(1 - alpha, df), df, effect / sd * math.sqrt(n / 2)))


def smallest_detectable(sd: float, n: int, target: float = 0.80, alpha: float = 0.05) -> int:
    """The smallest effect, in whole points, that `power` reaches `target` for at `n` per arm and this SD."""
    if not (math.isfinite(sd) and sd > 0 and n >= 2):  # else no effect is ever detectable: the search would not end
        raise ValueError(f"smallest_detectable needs a finite SD > 0 and n >= 2, got SD {sd} and n {n}")
    return next(effect for effect in itertools.count(1) if power(effect, sd, n, alpha) >= target)


def order_key(task, noise, budget, method, baseline):
    """Paper's task order, then noise and budget ascending; the baseline first, then the paper's method order."""
    task_rank = PAPER_TASKS.index(task) if task in PAPER_TASKS else len(PAPER_TASKS)
    method_rank = PAPER_METHODS.index(method) if method in PAPER_METHODS else len(PAPER_METHODS)
    return (task_rank, str(task), -1 if noise is None else noise, -1 if budget is None else budget,
            method != baseline, method_rank, str(method))


def parse_baselines(args: Args) -> dict:
    overrides = {}
    for item in args.baseline_for:
        method, sep, base = item.partition("=")
        if not sep or not method or not base:
            raise SystemExit(f"analyze: error: --baseline-for expects METHOD=BASELINE, got {item!r}")
        overrides[method] = base
    return overrides


def table_rows(groups, args: Args) -> list:
    """One row per group: the statistics of every table (`metrics_of`), against the group's baseline."""
    overrides = parse_baselines(args)
    by_key = {g.key: g for g in groups}
    rows = []
    for g in groups:
        task, noise, budget, method = g.key
        base_name = overrides.get(method, args.baseline)
        row = dict(task=task, noise=noise, budget=budget, method=method, seeds=len(g.runs),
                   seed_list=" ".join(str(r.seed) for r in g.runs), last_step=int(g.steps[-1]),
                   eval_points=len(g.steps), baseline="", notes=list(g.notes))
        if len(g.steps) < args.primary_last:  # unfinished runs aligned on fewer evaluations than the metric asks
            row["notes"].append(f"primary metric over its {len(g.steps)} evaluations, fewer than --primary-last "
                                f"{args.primary_last}")
        for metric in metrics_of(groups):
            row[f"{metric}_mean"], row[f"{metric}_se"] = mean_se(g.values(metric, args.primary_last))
            row[f"{metric}_p"] = row[f"{metric}_perm_p"] = row[f"{metric}_diff"] = float("nan")
            row[f"{metric}_ci"], row[f"{metric}_exact"] = (float("nan"), float("nan")), True
        base = by_key.get((task, noise, budget, base_name))
        numerics, variant = (base and [f"{k}={flag_of(g.runs[0], k)} vs {flag_of(base.runs[0], k)}"
                                        for k in keys if flag_of(g.runs[0], k) != flag_of(base.runs[0], k)]
                             for keys in (NUMERICS_KEYS, VARIANT_KEYS))
        if method != base_name:
            if base is None:
                row["notes"].append(f"no baseline {base_name} for this task, noise and budget")
            elif numerics:
                row["notes"].append(f"not compared with {base_name}: the numerics flags differ ({', '.join(numerics)}); "
                                    "runs with different numerics are never compared")
            elif variant:
                row["notes"].append(f"not compared with {base_name}: the noise is redrawn in one and stored in the other "
                                    f"({', '.join(variant)}); runs of different environments are never compared")
            else:
                row["baseline"] = base_name
                for metric in metrics_of(groups):
                    ours, theirs = g.values(metric, args.primary_last), base.values(metric, args.primary_last)
                    row[f"{metric}_p"] = welch_p(ours, theirs, args.alternative)
                    row[f"{metric}_perm_p"], row[f"{metric}_exact"] = permutation_p(ours, theirs, args.alternative)
                    row[f"{metric}_diff"], row[f"{metric}_ci"] = ours.mean() - theirs.mean(), bootstrap_ci(ours, theirs)
                differ = [k for k in COMPARED_KEYS
                          if g.runs[0].hparams.get(k) != base.runs[0].hparams.get(k)]
                if differ:
                    row["notes"].append("settings differ from the baseline's: " + ", ".join(
                        f"{k}={g.runs[0].hparams.get(k)} vs {base.runs[0].hparams.get(k)}" for k in differ))
                if (len(g.steps), g.steps[-1]) != (len(base.steps), base.steps[-1]):
                    row["notes"].append(
                        f"evaluation steps differ from the baseline's ({len(g.steps)} up to {g.steps[-1]} vs "
                        f"{len(base.steps)} up to {base.steps[-1]}): AUCs are not comparable"
                    )
        rows.append(row)
    rows.sort(key=lambda r: order_key(r["task"], r["noise"], r["budget"], r["method"], args.baseline))
    return rows


# ---------------------------------------------------------------- writing


def fmt(value: float, digits: int = 2) -> str:
    return "n/a" if value is None or not math.isfinite(value) else f"{value:.{digits}f}"


def p_text(p: float) -> str:
    """A p-value to three decimals; one below 0.001 reads as that bound, and NaN stays "nan"."""
    return "< 0.001" if p < 0.001 else f"{p:.3f}"


def fmt_p(p: float, significance: float) -> str:
    """A table's p cell: empty when there is no test, starred when significant."""
    return "" if not math.isfinite(p) else p_text(p) + ("*" if p < significance else "")


def spaced(n: int) -> str:
    """An integer with its thousands spaced: 200 000."""
    return f"{n:,}".replace(",", " ")


def setting_label(noise, budget) -> str:
    return f"{'-' if budget is None else budget} / {'-' if noise is None else noise}"


METRICS = {  # metric: (title, file name, definition); `primary` first: the studies' primary metric
    "primary": ("Primary Metric", "primary", "the mean of the last {n} evaluation returns of each run (the primary metric)"),
    "final": ("Final Return", "final_return", "the last `eval/episodic_return` of each run"),
    "auc": ("AUC", "auc", "the sum of the evaluation returns of each run"),
    "success": ("Success Rate", "success_rate", "the mean of the last {n} `eval/success_rate` of each run (the share "
                "of its evaluation episodes that succeed at some step: Meta-World's tasks)"),
}


def metrics_of(groups) -> dict:
    """The tables an analysis writes: `METRICS`, the success rate only where a group's runs all log it."""
    with_success = any(g.success_curves is not None for g in groups)
    return {metric: spec for metric, spec in METRICS.items() if metric != "success" or with_success}


def table_lines(rows, metric: str, args: Args) -> list:
    """The Markdown of one table in the paper's layout: its definition, the table and its notes."""
    title = METRICS[metric][0]
    h1 = "method > baseline" if args.alternative == "greater" else "baseline > method"
    sampled = any(not r[f"{metric}_exact"] for r in rows)
    lines = [
        f"{title} = {METRICS[metric][2].format(n=args.primary_last)}; mean ± standard error over seeds (sample std / "
        f"sqrt(n)). P Value: one-tailed Welch's t-test against the baseline (`{args.baseline}`"
        + (f"; {', '.join(args.baseline_for)}" if args.baseline_for else "")
        + f"), H1: {h1}; * p < {args.significance}. Perm. p: the same H1 by a permutation test of the difference in "
        + (f"means (every relabeling, or {spaced(PERMUTATIONS)} random ones where there are more: see the notes). "
           if sampled else "means over every relabeling of the seeds. ")
        + f"Diff.: method mean minus baseline mean, with a 95% percentile bootstrap CI ({spaced(BOOTSTRAP_RESAMPLES)} "
        + "resamples per arm).", "",
        f"| Task | Feedback / Noise | Method | {title} | P Value | Seeds | Perm. p | Diff. [95% CI] |",
        "|---|---|---|---|---|---|---|---|",
    ]
    previous = None
    for row in rows:
        setting = (row["task"], row["noise"], row["budget"])
        first = setting != previous
        previous = setting
        p, perm_p = fmt_p(row[f"{metric}_p"], args.significance), fmt_p(row[f"{metric}_perm_p"], args.significance)
        low, high = row[f"{metric}_ci"]
        diff = "" if not math.isfinite(row[f"{metric}_diff"]) else f"{fmt(row[f'{metric}_diff'])} [{fmt(low)}, {fmt(high)}]"
        lines.append(
            f"| {row['task'] if first else ''} | {setting_label(row['noise'], row['budget']) if first else ''} "
            f"| {row['method']} | {fmt(row[f'{metric}_mean'])} ± {fmt(row[f'{metric}_se'])} | {p} "
            f"| {row['seeds']} | {perm_p} | {diff} |"
        )
    sampled_note = f"permutation p from {spaced(PERMUTATIONS)} random relabelings"
    notes = [f"- {r['task']} {setting_label(r['noise'], r['budget'])} {r['method']}: {n}" for r in rows
             for n in r["notes"] + ([] if r[f"{metric}_exact"] else [sampled_note])]
    return lines + (["", "Notes:", ""] + notes if notes else [])


def skipped_lines(runs) -> list:
    skipped = [r for r in runs if r.status == "skipped"]
    return [f"Skipped runs ({len(skipped)}; never averaged):", ""] + (
        [f"- `{r.path}`: {r.reason}" for r in skipped] or ["- none"])


def last_value(run: Run, tag: str) -> float:
    return float(run.scalars[tag][1][-1]) if tag in run.scalars else float("nan")


def net_order(net: str):
    """Agent networks first, then the reward members."""
    return (not net.startswith(("actor", "qf")), net)


def connectivity(run: Run) -> list:
    """[(net, relevant_active_frac at the last step, chance)] for each sparse input layer of a run. The chance level
    (relevant columns / all columns) is not logged, but follows from the three metrics of any logged step where both
    degrees are positive: frac = R*r / (R*r + N*n) for R relevant and N noise columns of mean degrees r and n, so
    R/N = frac*n / ((1 - frac)*r)."""
    result = []
    nets = {m["net"] for tag in run.scalars if (m := SPARSE_TAG.match(tag))}
    for net in sorted(nets, key=net_order):
        tags = [f"sparse/{net}/{k}" for k in ("relevant_active_frac", "relevant_degree", "noise_degree")]
        if not all(tag in run.scalars for tag in tags):
            continue
        steps = np.intersect1d(np.intersect1d(run.scalars[tags[0]][0], run.scalars[tags[1]][0]), run.scalars[tags[2]][0])
        frac, relevant, noise = (run.scalars[t][1][np.searchsorted(run.scalars[t][0], steps)] for t in tags)
        usable = np.flatnonzero((relevant > 0) & (noise > 0) & (frac > 0) & (frac < 1))
        chance = float("nan")
        if len(usable):
            i = usable[0]
            ratio = frac[i] * noise[i] / ((1 - frac[i]) * relevant[i])
            chance = float(ratio / (1 + ratio))
        result.append((net, float(frac[-1]), chance))
    return result


def feature_nets(group: Group) -> list:
    """The networks whose `relevant_weight_frac` and chance every run of the group logs, agent networks first."""
    nets = None
    for r in group.runs:
        found = {m["net"] for tag in r.scalars if (m := FEATURE_TAG.match(tag)) and f"features/{m['net']}/chance" in r.scalars}
        nets = found if nets is None else nets & found
    return sorted(nets or (), key=net_order)


def features_lines(groups, rows) -> list:
    """The Markdown table of `features.md`: the final `relevant_weight_frac` per group and network; [] if none logs it."""
    order = {(r["task"], r["noise"], r["budget"], r["method"]): i for i, r in enumerate(rows)}
    lines = []
    for g in sorted(groups, key=lambda g: order[g.key]):
        for net in feature_nets(g):
            final = np.array([r.scalars[f"features/{net}/relevant_weight_frac"][1][-1] for r in g.runs])
            chance = float(g.runs[0].scalars[f"features/{net}/chance"][1][-1])
            mean, se = mean_se(final)
            task, noise, budget, method = g.key
            lines.append(f"| {task} | {noise} | {'-' if budget is None else budget} | {method} | {net} "
                         f"| {mean:.3f} ± {fmt(se, 3)} | {chance:.3f} | {mean / chance:.2f} | {len(final)} |")
    if not lines:
        return []
    return ["| Task | Noise | Budget | Method | Network | final `relevant_weight_frac` | chance | ratio | Seeds |",
            "|---|---|---|---|---|---|---|---|---|"] + lines


FEATURES_DEFINITION = (
    "The share of each input layer's absolute weight on relevant columns (real features and actions) at the last"
    " evaluation, mean ± standard error over seeds; chance is the relevant columns' share of all columns, and ratio"
    " is the mean over chance. A sparse layer counts its active weights only."
)


def cell(value: float, digits: int, unit: str = "") -> str:
    return "–" if not math.isfinite(value) else f"{value:.{digits}f}{unit}"


def runs_lines(groups, rows) -> list:
    """The Markdown table of every used run, in the order of the tables, then by seed."""
    order = {(r["task"], r["noise"], r["budget"], r["method"]): i for i, r in enumerate(rows)}
    lines = [
        "| run | seed | final return | AUC | wall time | reward steps | `reward_true_corr` | `heldout_accuracy` "
        "| final `relevant_active_frac` (chance) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for g in sorted(groups, key=lambda g: order[g.key]):
        for run, final, auc in zip(g.runs, g.final, g.auc):
            steps, corr, accuracy = (last_value(run, tag) for tag in DIAGNOSTIC_TAGS)
            sparse = ", ".join(f"{net} {frac:.3f} ({fmt(chance, 3)})" for net, frac, chance in connectivity(run))
            lines.append(
                f"| `{os.path.basename(run.folder)}` | {run.seed} | {final:.1f} | {auc:.0f} "
                f"| {cell(run.wall_seconds / 60, 0, ' min')} | {cell(steps, 0)} | {cell(corr, 3)} | {cell(accuracy, 3)} "
                f"| {sparse or '–'} |"
            )
    return lines


def write_tables(rows, groups, runs, args: Args):
    """`primary.md/.csv`, `final_return.md/.csv`, `auc.md/.csv` (the paper's layout), `success_rate.md/.csv` where runs
    log it, `runs.md` (every used run with its diagnostics) and `runs.csv` (every run found and its status)."""
    os.makedirs(args.output_dir, exist_ok=True)
    if "success" not in metrics_of(groups):  # an earlier analysis's, of runs that logged it
        for kind in ("md", "csv"):
            with contextlib.suppress(FileNotFoundError):
                os.remove(os.path.join(args.output_dir, f"{METRICS['success'][1]}.{kind}"))
    for metric, (title, name, _) in metrics_of(groups).items():
        lines = [f"# {title}", ""] + table_lines(rows, metric, args) + [""] + skipped_lines(runs)
        with open(os.path.join(args.output_dir, f"{name}.md"), "w") as f:
            f.write("\n".join(lines) + "\n")
        with open(os.path.join(args.output_dir, f"{name}.csv"), "w", newline="") as f:
            writer = csv.writer(f)
            writer.writerow(["task", "noise", "budget", "method", "seeds", "mean", "se", "p_value", "significant",
                             "baseline", "eval_points", "last_step", "seed_list", "notes", "perm_p", "perm_exact",
                             "diff", "ci_low", "ci_high"])
            for row in rows:
                p = row[f"{metric}_p"]
                writer.writerow([
                    row["task"], row["noise"], "" if row["budget"] is None else row["budget"], row["method"],
                    row["seeds"], repr(row[f"{metric}_mean"]), repr(row[f"{metric}_se"]),
                    "" if not math.isfinite(p) else repr(p), int(math.isfinite(p) and p < args.significance),
                    row["baseline"], row["eval_points"], row["last_step"], row["seed_list"], "; ".join(row["notes"]),
                    *("" if not math.isfinite(x) else repr(x) for x in (row[f"{metric}_perm_p"],)),
                    int(row[f"{metric}_exact"]),
                    *("" if not math.isfinite(x) else repr(float(x)) for x in (row[f"{metric}_diff"], *row[f"{metric}_ci"])),
                ])
    with open(os.path.join(args.output_dir, "runs.md"), "w") as f:
        f.write("\n".join(["# Runs", "", RUNS_DEFINITION, ""] + runs_lines(groups, rows)) + "\n")
    features, features_path = features_lines(groups, rows), os.path.join(args.output_dir, "features.md")
    if features:
        with open(features_path, "w") as f:
            f.write("\n".join(["# Weight on the relevant features", "", FEATURES_DEFINITION, ""] + features) + "\n")
    elif os.path.exists(features_path):  # an earlier analysis's, of runs that logged it
        os.remove(features_path)
    with open(os.path.join(args.output_dir, "runs.csv"), "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["path", "task", "noise", "budget", "method", "seed", "status", "reason", "eval_points",
                         "last_step", "final_return", "auc", "wall_seconds", *(t.split("/")[1] for t in DIAGNOSTIC_TAGS),
                         "connectivity"])
        for r in runs:
            steps = r.eval_steps
            values = r.scalars.get(EVAL_TAG, (None, np.zeros(0)))[1]
            task, noise, budget, method = r.key
            writer.writerow([
                r.path, task, noise, budget, method, r.seed, r.status, r.reason or r.note, len(steps),
                int(steps[-1]) if len(steps) else "", repr(float(values[-1])) if len(values) else "",
                repr(float(values.sum())) if len(values) else "", f"{r.wall_seconds:.0f}",
                *(repr(last_value(r, tag)) for tag in DIAGNOSTIC_TAGS),
                " ".join(f"{net}={frac!r}/{chance!r}" for net, frac, chance in connectivity(r)),
            ])


RUNS_DEFINITION = (
    "Every used run. Final return and AUC as in the tables (on the steps common to its group); wall time from its first"
    " to its last logged event, summed over the starts of a resumed run; the diagnostics at their last logged round:"
    " cumulative reward-optimiser steps, Pearson correlation of the reward ensemble with the true reward, held-out"
    " preference accuracy; and for each sparse input layer the share of its active weights on relevant columns, with"
    " the chance level (relevant columns / all columns) in brackets."
)


def readme_block(rows, groups, runs, args: Args, pngs: list) -> list:
    """The lines `--readme` puts between its markers: every run, the tables (the primary metric first), the skipped
    runs and the curves."""
    folder = os.path.dirname(os.path.abspath(args.readme))
    curves = [p for p in pngs if os.path.basename(os.path.dirname(p)) == "curves"]
    lines = [f"Written by `analyze.py` from {', '.join(f'`{d}`' for d in args.log_dirs)}. {RUNS_DEFINITION}", ""]
    lines += runs_lines(groups, rows)
    for metric in metrics_of(groups):
        lines += [""] + table_lines(rows, metric, args)
    lines += [""] + skipped_lines(runs)
    for png in curves:
        path = os.path.relpath(os.path.abspath(png), folder).replace(os.sep, "/")
        lines += ["", f"![learning curves: {os.path.splitext(os.path.basename(png))[0]}]({path})"]
    return lines


def check_readme(path: str) -> tuple:
    """(lines, start marker index, end marker index) of `--readme`, or exit with one line if the file is unreadable or
    lacks its markers: checked before any work."""
    try:
        with open(path) as f:
            lines = f.read().split("\n")
    except OSError as e:
        raise SystemExit(f"analyze: error: --readme {path}: {e.strerror}")
    stripped = [line.strip() for line in lines]
    if [stripped.count(marker) for marker in README_MARKERS] != [1, 1] or (
            stripped.index(README_MARKERS[0]) > stripped.index(README_MARKERS[1])):
        raise SystemExit(f"analyze: error: --readme {path} needs one line `{README_MARKERS[0]}` followed by one line "
                         f"`{README_MARKERS[1]}`")
    return lines, stripped.index(README_MARKERS[0]), stripped.index(README_MARKERS[1])


def update_readme(path: str, block: list):
    """Replace what is between the markers of `path` with `block`, written atomically."""
    lines, start, end = check_readme(path)
    with open(path + ".tmp", "w") as f:
        f.write("\n".join(lines[:start + 1] + block + lines[end:]))
    os.replace(path + ".tmp", path)


def aligned(group: Group, tag: str):
    """(steps, values (seeds, steps)) of one scalar tag over the runs of a group, on the steps common to all."""
    series = [r.scalars[tag] for r in group.runs]
    common = series[0][0]
    for steps, _ in series[1:]:
        common = np.intersect1d(common, steps)
    return common, np.stack([values[np.searchsorted(steps, common)] for steps, values in series])


def safe_name(text) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", str(text))


def curve_panels(task_groups) -> list:
    """[((noise, budget), groups)]: one panel per noise and budget of a task; the oracles (no budget) join every panel
    of their noise, and get panels of their own only at a noise without PbRL runs."""
    with_budget = {g.key[1] for g in task_groups if g.key[2] is not None}
    settings = sorted({(g.key[1], g.key[2]) for g in task_groups if g.key[2] is not None or g.key[1] not in with_budget},
                      key=lambda s: (-1 if s[0] is None else s[0], -1 if s[1] is None else s[1]))
    return [(s, [g for g in task_groups if g.key[1] == s[0] and g.key[2] in (s[1], None)]) for s in settings]


def write_plots(groups, args: Args) -> list:
    """Learning curves per task (one panel per noise/budget) and connectivity plots per sparse group; the paths."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    written = []
    methods = sorted({g.key[3] for g in groups}, key=lambda m: order_key(None, None, None, m, args.baseline)[4:])
    cmap = plt.get_cmap("tab10" if len(methods) <= 10 else "tab20")
    colour = {m: cmap(i % cmap.N) for i, m in enumerate(methods)}

    def band(ax, steps, values, label, **style):
        with warnings.catch_warnings():  # a run stopped by a non-finite value leaves the steps after its stop
            warnings.simplefilter("ignore", RuntimeWarning)
            mean = np.nanmean(values, axis=0)
            se = np.nanstd(values, axis=0, ddof=1) / np.sqrt(np.isfinite(values).sum(axis=0))
        line = ax.plot(steps, mean, label=label, **style)[0]
        if len(values) > 1:
            ax.fill_between(steps, mean - se, mean + se, color=line.get_color(), alpha=0.2, linewidth=0)

    def style_axis(ax, title, ylabel):
        ax.set_title(title)
        ax.set_xlabel("environment steps")
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)

    def save_figure(fig, axes, n_used, title, title_style, path):
        for ax in list(axes.flat)[n_used:]:
            ax.set_visible(False)
        fig.suptitle(title, **title_style)
        fig.tight_layout()
        fig.savefig(path, dpi=100)
        plt.close(fig)
        written.append(path)

    by_task = defaultdict(list)
    for g in groups:
        by_task[g.key[0]].append(g)
    os.makedirs(os.path.join(args.output_dir, "curves"), exist_ok=True)
    for task, task_groups in by_task.items():
        panels = curve_panels(task_groups)
        ncols = min(3, len(panels))
        nrows = math.ceil(len(panels) / ncols)
        fig, axes = plt.subplots(nrows, ncols, figsize=(max(6.0, 5 * ncols), 3.8 * nrows), squeeze=False)
        for ax, ((noise, budget), panel_groups) in zip(axes.flat, panels):
            for g in sorted(panel_groups, key=lambda g: methods.index(g.key[3])):
                oracle = g.key[2] is None and budget is not None
                band(ax, g.steps, g.curves, f"{g.key[3]}{' (true reward)' if oracle else ''} (n={len(g.runs)})",
                     color=colour[g.key[3]], linestyle="--" if oracle else "-")
            style_axis(ax, f"noise {noise}, " + ("no feedback" if budget is None else f"budget {budget}"), "evaluation return")
        save_figure(fig, axes, len(panels), f"{task}: mean ± standard error over seeds", {},
                    os.path.join(args.output_dir, "curves", f"{safe_name(task)}.png"))

    for g in groups:
        nets = None
        for r in g.runs:
            found = {m["net"] for tag in r.scalars if (m := SPARSE_TAG.match(tag))}
            found = {n for n in found if all(f"sparse/{n}/{k}" in r.scalars for k in ("relevant_degree", "noise_degree"))}
            nets = found if nets is None else nets & found
        if not nets:
            continue
        nets = sorted(nets, key=net_order)
        ncols = min(3, len(nets))
        nrows = math.ceil(len(nets) / ncols)
        fig, axes = plt.subplots(nrows, ncols, figsize=(max(6.0, 4.5 * ncols), 3.4 * nrows + 0.6), squeeze=False)
        for ax, net in zip(axes.flat, nets):
            for metric, style in (("relevant_degree", "-"), ("noise_degree", "--")):
                steps, values = aligned(g, f"sparse/{net}/{metric}")
                band(ax, steps, values, metric.replace("_", " "), linestyle=style)
            style_axis(ax, net, "active weights per input column")
        task, noise, budget, method = g.key
        os.makedirs(os.path.join(args.output_dir, "connectivity"), exist_ok=True)
        save_figure(fig, axes, len(nets), f"{method} on {task}, noise {noise}, budget {budget}\n"
                    f"input-layer connectivity, mean ± SE over {len(g.runs)} seeds", {"fontsize": 10},
                    os.path.join(args.output_dir, "connectivity",
                                 safe_name(f"{task}__noise{noise}__budget{budget}__{method}") + ".png"))

    for task, task_groups in by_task.items():
        for (noise, budget), panel_groups in curve_panels(task_groups):
            nets = sorted({net for g in panel_groups for net in feature_nets(g)}, key=net_order)
            if not nets:
                continue
            ncols = min(3, len(nets))
            nrows = math.ceil(len(nets) / ncols)
            fig, axes = plt.subplots(nrows, ncols, figsize=(max(6.0, 4.5 * ncols), 3.4 * nrows + 0.6), squeeze=False)
            for ax, net in zip(axes.flat, nets):
                for g in sorted(panel_groups, key=lambda g: methods.index(g.key[3])):
                    if net in feature_nets(g):
                        steps, values = aligned(g, f"features/{net}/relevant_weight_frac")
                        band(ax, steps, values, f"{g.key[3]} (n={len(g.runs)})", color=colour[g.key[3]])
                chance = next(g.runs[0].scalars[f"features/{net}/chance"][1][-1] for g in panel_groups
                              if net in feature_nets(g))
                ax.axhline(chance, color="grey", linestyle=":", label="chance")
                style_axis(ax, net, "weight share on relevant columns")
            os.makedirs(os.path.join(args.output_dir, "features"), exist_ok=True)
            save_figure(fig, axes, len(nets), f"{task}, noise {noise}, budget {budget}: `relevant_weight_frac`, "
                        "mean ± SE over seeds", {"fontsize": 10},
                        os.path.join(args.output_dir, "features", safe_name(f"{task}__noise{noise}__budget{budget}") + ".png"))
    return written


def main(args: Args) -> int:
    if args.primary_last < 1:
        raise SystemExit(f"analyze: error: --primary-last must be at least 1, got {args.primary_last}")
    if args.readme:
        check_readme(args.readme)
    missing = [d for d in args.log_dirs if not os.path.isdir(d)]
    for d in missing:
        print(f"analyze: warning: {d} is not a folder", file=sys.stderr)
    runs = load_runs(args.log_dirs, args.include_unfinished)
    if not runs:
        print(f"analyze: error: no TensorBoard run under {', '.join(args.log_dirs)}", file=sys.stderr)
        return 1
    groups = make_groups(runs)
    skipped = [r for r in runs if r.status == "skipped"]
    print(f"{len(runs)} runs found, {len(runs) - len(skipped)} used in {len(groups)} groups, {len(skipped)} skipped")
    for r in skipped:
        print(f"skipped {r.path}: {r.reason}")
    if not groups:
        print("analyze: error: no usable run", file=sys.stderr)
        return 1
    rows = table_rows(groups, args)
    write_tables(rows, groups, runs, args)
    tables = [f"{name}.{kind}" for _, name, _ in metrics_of(groups).values() for kind in ("md", "csv")]
    written = [os.path.join(args.output_dir, f) for f in tables + ["runs.md", "runs.csv"]]
    if os.path.exists(os.path.join(args.output_dir, "features.md")):
        written.append(os.path.join(args.output_dir, "features.md"))
    if args.plots:
        written += write_plots(groups, args)
    if args.readme:
        update_readme(args.readme, readme_block(rows, groups, runs, args, written))
        written.append(args.readme)
    with open(os.path.join(args.output_dir, f"{METRICS['primary'][1]}.md")) as f:  # the primary metric's table
        print(f.read().split("\n\nNotes:")[0].split("\n\nSkipped runs")[0])
    print("wrote " + ", ".join(written))
    return 0


if __name__ == "__main__":
    sys.exit(main(tyro.cli(Args)))
