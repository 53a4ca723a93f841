# docs and usage: docs/benchmark.md
"""Launch the paper's experiments: a grid of (method, task, noise, budget, seed) runs, locally or on SLURM.

Presets (`--preset`) are the paper's experiments and this project's studies (docs/benchmark.md); `--methods`,
`--env-ids`, `--noises`, `--budgets` and `--seeds` replace a preset's values or, without a preset, define the grid.
Each run has a deterministic id `{method}__{env_id}__noise{noise}__budget{budget}__seed{seed}` and runs
`python {script} --exp-name {method} --env-id ... --noise ... --max-feedback ... --seed ... --threads ...
--resumable --diagnostics --query-log` plus `--extra`, so `analyze.py` groups its TensorBoard run by the method name.
The run harness's three flags (docs/running.md) make every run resumable, log its diagnostics and its queries; none
changes a number.

Choices where the issue is silent:
- Order: seed-major (all configurations of seed 1, then seed 2, ...), so an interrupted sweep has whole seeds.
- A run is finished when its marker `{log_dir}/{run_id}.done` exists; the launcher writes it when the script exits
  with code 0, or stops at a non-finite value, which a resume would meet again (its line is in the marker: the run
  counts with what it reached); a run stopped by SIGTERM or SIGUSR2 after saving its state, or by SIGTERM before its
  script takes the signal over, writes `{run_id}.stopped` (the same command resumes it); a failure writes
  `{run_id}.failed` with the exit code instead. Finished runs are skipped by the next call (`--force` reruns them);
  deleting a marker reruns that run. TensorBoard folders are not inspected: the marker is cheap, exact, and works for
  runs whose folder name carries only env, method, seed and time. With a results folder (`--results-dir`,
  `cpu-study`), a run counts as finished only when `{results_dir}/{run_id}/done` exists: the event file, the log and
  that file, which names the git commit, are what a study commits; the run itself works in
  `{log_dir}/scratch/{run_id}` (its checkpoint stays there). The run id does not include `--extra` nor a preset's
  scale flags: a results folder is for one configuration, and its `done` files, not the log folder's markers, which
  the presets at other scales share (`cpu-study` and `imitate` have 6 run ids in common), say what it holds.
- Local back-end: up to `--workers` runs at once; with `--gpus 0,1`, `--runs-per-gpu K` makes K slots per GPU, handed
  out round-robin (0, 1, 0, 1, ...) and reused as runs end, through `CUDA_VISIBLE_DEVICES`. Every child gets
  `OMP_NUM_THREADS=MKL_NUM_THREADS=--threads` and `--threads`; stdout and stderr go to `{log_dir}/{run_id}.log`.
  One local launcher per log folder (a lock on `{log_dir}/.launcher.lock`): a second would run the same runs again.
  `--mps`: one CUDA MPS daemon for the sweep (one per array task on SLURM), in a private temporary folder; it sees
  the `--gpus`, and each run's CUDA_VISIBLE_DEVICES is its GPU's position among them, as MPS clients count.
  Local runs are in sessions of their own: Ctrl-C, SIGTERM or SIGHUP reach the launcher only, which stops them with
  SIGTERM (they save their state), and on Linux they get SIGTERM when the launcher dies, however it dies.
- SLURM back-end (submitit, extra `slurm`): one job array; each array task runs `--runs-per-gpu` runs at once on one
  GPU (SLURM sets `CUDA_VISIBLE_DEVICES`), with `--slurm-mem-gb` per run. It returns after submission unless
  `--slurm-wait`. A job at its time limit has its runs save their state and requeues itself with the runs still
  going (`--slurm-max-requeues`); a run without a `.done` marker is resubmitted by the next call and resumes from its
  `state.pt` if it has one.
- Methods: a method is a script `{method}.py` in `--script-dir`, or a variant in `VARIANTS` (script + flags). Methods
  in `NO_FEEDBACK` (SAC oracles) get no `--max-feedback`; their id says `budgetnone`.
- Run folders: every run gets `--run-name {run_id}`, so its folder is `runs/{run_id}` and re-running the sweep
  resumes an interrupted run from its `state.pt` (docs/running.md: "Resuming a run"). A folder without a state (a run that
  stopped before its first state, or one rerun with `--force`) is renamed `runs/{run_id}.old-{time}`, never deleted.
"""
import contextlib
import ctypes
import fcntl
import glob
import os
import platform
import re
import shlex
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections import deque
from dataclasses import dataclass
from typing import Literal, NamedTuple, Optional

import tyro

ROOT = os.path.dirname(os.path.abspath(__file__))

# The paper's main table: task -> (noise, feedback budget).
PAPER_SETTINGS = {
    "cartpole-swingup": (0.9, 400),
    "walker-walk": (0.9, 4000),
    "cheetah-run": (0.9, 1000),
    "quadruped-walk": (0.7, 4000),
    "humanoid-stand": (0.7, 10000),
}
# Method names that are a script with extra flags (the DST ablation); any other method runs `{method}.py`.
VARIANTS = {
    "r2n_pebble_reward_only": ("r2n_pebble.py", ("--no-sparse-agent",)),
    "r2n_pebble_agent_only": ("r2n_pebble.py", ("--no-sparse-reward",)),
    # the CPU study's sensitivity arms: the stored (memorisable) noise, and reward training without early stopping
    **{f"{m}_stored_noise": (f"{m}.py", ("--no-noise-resample",)) for m in ("pebble", "r2n_pebble", "sac", "anf_sac")},
    **{f"{m}_no_early_stop": (f"{m}.py", ("--reward-stop-accuracy", "1.1")) for m in ("pebble", "r2n_pebble")},
    # the stored-noise study's probe: the agent's RigL at the reward models' settings (the paper's section 4)
    "r2n_pebble_agent_as_reward": ("r2n_pebble.py", ("--agent-drop-fraction", "0.2", "--agent-topology-period", "100")),
    # and a repeat of the cheetah study's PEBBLE runs, under a name of its own so that the two are never pooled
    "pebble_repeat": ("pebble.py", ()),
    # issue 69's study of which sparsity carries R2N's gain: the DST ablation and the sparse-training baselines
    "r2n_pebble_reward_only_stored_noise": ("r2n_pebble.py", ("--no-sparse-agent", "--no-noise-resample")),
    "r2n_pebble_agent_only_stored_noise": ("r2n_pebble.py", ("--no-sparse-reward", "--no-noise-resample")),
    **{f"{m}_stored_noise": (f"{m}.py", ("--no-noise-resample",))
       for m in ("set_pebble", "static_pebble", "l1_pebble", "dropconnect_pebble")},
    # issue 91's study of R2N on SURF and RUNE, and of R2N's sparse reward where its topology moves (SURF's schedule)
    **{f"{m}_stored_noise": (f"{m}.py", ("--no-noise-resample",)) for m in ("surf", "r2n_surf", "rune", "r2n_rune")},
    "r2n_surf_agent_only_stored_noise": ("r2n_surf.py", ("--no-sparse-reward", "--no-noise-resample")),
}
# SAC oracles: trained on the true reward, no feedback budget.
NO_FEEDBACK = frozenset({"sac", "anf_sac", "sac_stored_noise", "anf_sac_stored_noise"})


class Preset(NamedTuple):
    settings: tuple  # (env_id, noise, budget) triples
    methods: tuple
    seeds: tuple
    flags: tuple = ()  # appended to every command of the preset (scale)
    feedback_flags: tuple = ()  # appended to the commands of the PbRL methods (feedback schedule)
    stage: int = 0  # a preset's parts run stage by stage (each seed-major): a protocol's order of arms


# The studies that ran with the noise redrawn name it, so that their commands stay theirs whatever the default.
REDRAWN = ("--noise-resample",)
# The CPU study (results/cpu-study/README.md): the paper's claim at a scale that runs in <= 20 minutes on one CPU core.
# Fixed before any of its runs was looked at; its README says why each value.
CPU_STUDY_FLAGS = ("--total-timesteps", "80000", "--hidden-dim", "256", "--batch-size", "128")
CPU_STUDY_FEEDBACK = ("--feedback-freq", "2000", "--queries-per-round", "25")  # 16 rounds: 400 labels by step 40 000
CPU_STUDY_MAIN, CPU_STUDY_HARDER = (("cartpole-swingup", 0.9, 400),), (("cartpole-swingup", 0.95, 400),)
CPU_STUDY = tuple(
    Preset(settings, methods, seeds, variant + CPU_STUDY_FLAGS, CPU_STUDY_FEEDBACK)
    for settings, methods, seeds, variant in (
        (CPU_STUDY_MAIN, ("pebble", "r2n_pebble"), tuple(range(1, 9)), REDRAWN),
        (CPU_STUDY_HARDER, ("pebble", "r2n_pebble"), tuple(range(1, 6)), REDRAWN),
        (CPU_STUDY_MAIN + CPU_STUDY_HARDER, ("sac", "anf_sac"), (1, 2, 3), REDRAWN),
        (CPU_STUDY_MAIN, ("pebble_stored_noise", "r2n_pebble_stored_noise"), (1, 2, 3), ()),  # the variant names it
        (CPU_STUDY_MAIN, ("pebble_no_early_stop", "r2n_pebble_no_early_stop"), (1, 2, 3), REDRAWN),
    )
)
# Issue 21's confirmation of the cpu-study's one lead (R2N beats PEBBLE when the reward's early stop is off): the
# cpu-study's main setting with 8 new seeds per arm (results/early-stop/PROTOCOL.md, fixed before its first run).
EARLY_STOP = (Preset(CPU_STUDY_MAIN, ("pebble_no_early_stop", "r2n_pebble_no_early_stop"), tuple(range(9, 17)),
                     REDRAWN + CPU_STUDY_FLAGS, CPU_STUDY_FEEDBACK),)
# Issue 21's powered study (results/cheetah-study/PROTOCOL.md, fixed after its pilot): cheetah-run 0.9/1000 at a CPU
# scale, 8 seeds per PbRL arm (80% power for half the paper's gain), 3 per oracle.
CHEETAH_FLAGS = ("--total-timesteps", "250000", "--hidden-dim", "256", "--batch-size", "128", "--eval-freq", "10000")
CHEETAH_STUDY = tuple(
    Preset((("cheetah-run", 0.9, 1000),), methods, seeds, REDRAWN + CHEETAH_FLAGS, ("--feedback-freq", "1200"))
    for methods, seeds in ((("pebble", "r2n_pebble"), tuple(range(1, 9))), (("sac", "anf_sac"), (1, 2, 3)))
)
# Its pilot (protocol results/cheetah-study/PILOT.md, runs results/cheetah-pilot): SAC seed 901, PEBBLE seeds 901
# and 902, at the study's scale.
CHEETAH_PILOT = tuple(
    Preset((("cheetah-run", 0.9, 1000),), methods, seeds, REDRAWN + CHEETAH_FLAGS, ("--feedback-freq", "1200"))
    for methods, seeds in ((("sac",), (901,)), (("pebble",), (901, 902)))
)
# Issue 29's study of the stored noise (results/stored-noise/PROTOCOL.md, fixed before its first run): the cheetah
# study's design with every arm storing the noise it saw (`--no-noise-resample`), as B-Pref's buffers would.
STORED_NOISE = tuple(
    Preset((("cheetah-run", 0.9, 1000),), methods, seeds, CHEETAH_FLAGS, ("--feedback-freq", "1200"))
    for methods, seeds in ((("pebble_stored_noise", "r2n_pebble_stored_noise"), tuple(range(1, 9))),
                           (("sac_stored_noise", "anf_sac_stored_noise"), (1, 2, 3)))
)
# Its exploratory probes, run after it, in the cheetah study's environment (redrawn noise), 3 seeds each, no test.
REDRAWN_PROBES = (Preset((("cheetah-run", 0.9, 1000),),
                         ("r2n_pebble_reward_only", "r2n_pebble_agent_as_reward", "pebble_repeat"), (1, 2, 3),
                         REDRAWN + CHEETAH_FLAGS, ("--feedback-freq", "1200")),)
# Issue 41's table in the stored ENE (results/stored-table/PROTOCOL.md): its pilot, one seed of each arm per task and a
# second PEBBLE seed for the spread, at the stored-noise study's scale; every arm names its variant (`*_stored_noise`).
STORED_TABLE_SETTINGS = (("cartpole-swingup", 0.9, 400), ("walker-walk", 0.9, 4000), ("quadruped-walk", 0.7, 4000))
STORED_TABLE_PILOT = tuple(
    Preset(STORED_TABLE_SETTINGS, tuple(f"{m}_stored_noise" for m in methods), seeds, CHEETAH_FLAGS,
           ("--feedback-freq", "1200"))
    for methods, seeds in ((("pebble", "r2n_pebble", "sac", "anf_sac"), (901,)), (("pebble",), (902,)))
)
# Its primary runs (PROTOCOL.md part 2): per task, seeds 1 to n, n from its pilot (`results/stored-table/power.py`).
# A task enters once part 2 has decided it; the order is the protocol's.
STORED_TABLE_SEEDS = {"cartpole-swingup": 8, "walker-walk": 8, "quadruped-walk": 10}
STORED_TABLE = tuple(
    Preset((setting,), ("pebble_stored_noise", "r2n_pebble_stored_noise"), tuple(range(1, STORED_TABLE_SEEDS[task] + 1)),
           CHEETAH_FLAGS, ("--feedback-freq", "1200"))
    for setting in STORED_TABLE_SETTINGS if (task := setting[0]) in STORED_TABLE_SEEDS
)
# Issue 21's imitating noise (results/imitate/PROTOCOL.md, exploratory): the cpu-study's main setting with noise features
# drawn from the histograms of a noise-free SAC policy's observations (made by results/imitate/run.sh first).
IMITATE = (Preset(CPU_STUDY_MAIN, ("pebble", "r2n_pebble"), (1, 2, 3), REDRAWN + CPU_STUDY_FLAGS + (
    "--noise-type", "imitate", "--noise-histograms", os.path.join(ROOT, "results/imitate/cartpole-swingup_histograms.npz"),
), CPU_STUDY_FEEDBACK),)  # an absolute path: each run works in its own scratch folder
# Issue 69's study (results/which-sparsity/PROTOCOL.md, fixed before its first run): which sparsity carries R2N's gain,
# at the stored-noise study's scale and environment, against its committed PEBBLE and R2N-PEBBLE (seeds 1-8). In the
# protocol's order: the DST ablation's two arms with R2N-PEBBLE's seeds 9-10, then L1 and DropConnect, then SET and Static.
WHICH_SPARSITY = tuple(
    Preset((("cheetah-run", 0.9, 1000),), methods, seeds, CHEETAH_FLAGS, ("--feedback-freq", "1200"), stage)
    for methods, seeds, stage in (
        (("r2n_pebble_agent_only_stored_noise", "r2n_pebble_reward_only_stored_noise"), tuple(range(1, 11)), 0),
        (("r2n_pebble_stored_noise",), (9, 10), 0),
        (("l1_pebble_stored_noise", "dropconnect_pebble_stored_noise"), tuple(range(1, 9)), 1),
        (("set_pebble_stored_noise", "static_pebble_stored_noise"), tuple(range(1, 9)), 2),
    )
)
# Issue 91's study (results/surf-rune/PROTOCOL.md, fixed before its first run): R2N on SURF and RUNE, and SURF's
# actor/critic-only arm, at the stored-noise study's scale and environment. In the protocol's order: RUNE's and SURF's
# two arms seed-major (RUNE and R2N-RUNE 10 seeds, SURF 8, R2N-SURF 10), then the actor/critic-only arm (10 seeds).
SURF_RUNE = tuple(
    Preset((("cheetah-run", 0.9, 1000),), methods, seeds, CHEETAH_FLAGS, ("--feedback-freq", "1200"), stage)
    for methods, seeds, stage in (
        (("rune_stored_noise", "r2n_rune_stored_noise", "surf_stored_noise", "r2n_surf_stored_noise"),
         tuple(range(1, 9)), 0),
        (("rune_stored_noise", "r2n_rune_stored_noise", "r2n_surf_stored_noise"), (9, 10), 0),
        (("r2n_surf_agent_only_stored_noise",), tuple(range(1, 11)), 1),
    )
)
# A preset's results folder: the event file, log and `done` file of each finished run, committed
RESULTS = {"cpu-study": "results/cpu-study", "cheetah-pilot": "results/cheetah-pilot", "early-stop": "results/early-stop",
           "cheetah-study": "results/cheetah-study", "imitate": "results/imitate",
           "stored-noise": "results/stored-noise/runs", "redrawn-probes": "results/stored-noise/probes",
           "stored-table-pilot": "results/stored-table/pilot", "stored-table": "results/stored-table/runs",
           "which-sparsity": "results/which-sparsity/runs", "surf-rune": "results/surf-rune/runs"}


MAIN_SETTINGS = tuple((env, noise, budget) for env, (noise, budget) in PAPER_SETTINGS.items())
PRESETS = {
    # the main table: 5 tasks x 6 methods x 14 seeds = 420 runs
    "main": (Preset(MAIN_SETTINGS, ("pebble", "r2n_pebble", "surf", "r2n_surf", "rune", "r2n_rune"), tuple(range(1, 15))),),
    # R2N against the sparse-training baselines: 5 tasks x 5 methods x 5 seeds = 125 runs
    "sparse-baselines": (Preset(
        MAIN_SETTINGS, ("r2n_pebble", "set_pebble", "static_pebble", "l1_pebble", "dropconnect_pebble"), tuple(range(1, 6))
    ),),
    # cheetah-run, noise sweep at budget 1000: 6 x 2 x 5 = 60 runs
    "noise-sweep": (Preset(
        tuple(("cheetah-run", noise, 1000) for noise in (0.0, 0.2, 0.5, 0.7, 0.9, 0.95)), ("pebble", "r2n_pebble"),
        tuple(range(1, 6)),
    ),),
    # cheetah-run, budget sweep at noise 0.9: 7 x 2 x 5 = 70 runs
    "feedback-sweep": (Preset(
        tuple(("cheetah-run", 0.9, budget) for budget in (100, 200, 400, 1000, 2000, 4000, 10000)),
        ("pebble", "r2n_pebble"), tuple(range(1, 6)),
    ),),
    # cheetah-run 0.9/1000: full R2N, sparse reward models only, sparse actor/critics only: 3 x 5 = 15 runs
    "dst-ablation": (Preset(
        (("cheetah-run", 0.9, 1000),), ("r2n_pebble", "r2n_pebble_reward_only", "r2n_pebble_agent_only"),
        tuple(range(1, 6)),
    ),),
    # the CPU study: cartpole-swingup at noise 0.9 and 0.95, budget 400, 80k steps, 256-wide SAC: 8+8, 5+5, 12, 12 runs
    "cpu-study": CPU_STUDY,
    # the confirmation of the early-stop lead: cartpole-swingup 0.9/400 at the cpu-study's scale, reward early stop off
    "early-stop": EARLY_STOP,
    # its pilot: SAC seed 901 and PEBBLE seeds 901 and 902 at the study's scale
    "cheetah-pilot": CHEETAH_PILOT,
    # the powered study: cheetah-run 0.9/1000, 250k steps, 256-wide; 8 + 8 PbRL runs and 3 + 3 oracle runs
    "cheetah-study": CHEETAH_STUDY,
    # imitating noise, exploratory: cartpole-swingup 0.9/400 at the cpu-study's scale, 3 + 3 runs
    "imitate": IMITATE,
    # the cheetah study with the noise stored: 8 + 8 PbRL runs and 3 + 3 oracle runs
    "stored-noise": STORED_NOISE,
    # after it, redrawn noise: R2N's reward half alone, the agent's RigL at the reward's settings, PEBBLE again; 3 x 3
    "redrawn-probes": REDRAWN_PROBES,
    # the main table's pilot in the stored ENE: 3 tasks x (pebble, r2n_pebble, sac, anf_sac, seed 901; pebble, seed 902)
    "stored-table-pilot": STORED_TABLE_PILOT,
    # its primary runs: per task decided by part 2, pebble_stored_noise and r2n_pebble_stored_noise, seeds 1 to n
    "stored-table": STORED_TABLE,
    # which sparsity carries R2N's gain: 2 DST-ablation arms x 10 seeds, R2N-PEBBLE seeds 9-10, 4 baselines x 8 seeds
    "which-sparsity": WHICH_SPARSITY,
    # R2N on SURF and RUNE: RUNE, R2N-RUNE x 10 seeds, SURF x 8, R2N-SURF x 10, then R2N-SURF's actor/critic-only x 10
    "surf-rune": SURF_RUNE,
}


@dataclass
class Args:
    preset: Optional[Literal["main", "sparse-baselines", "noise-sweep", "feedback-sweep", "dst-ablation", "cpu-study",
                             "early-stop", "cheetah-pilot", "cheetah-study", "imitate", "stored-noise",
                             "redrawn-probes", "stored-table-pilot", "stored-table", "which-sparsity",
                             "surf-rune"]] = None
    """a paper experiment: `main` (5 tasks, pebble/surf/rune and their R2N versions, 14 seeds), `sparse-baselines`
    (r2n/set/static/l1/dropconnect pebble, 5 tasks, 5 seeds), `noise-sweep`, `feedback-sweep` (cheetah-run, pebble and
    r2n_pebble, 5 seeds), `dst-ablation` (r2n_pebble, r2n_pebble_reward_only, r2n_pebble_agent_only, 5 seeds); or
    `cpu-study`, the CPU-scale study (its results go to `results/cpu-study`); `early-stop`, its lead's
    confirmation (`results/early-stop`); `cheetah-pilot`, its pilot (`results/cheetah-pilot`); `cheetah-study`,
    the powered study (`results/cheetah-study`); `imitate`,
    imitating noise (`results/imitate`; run `results/imitate/run.sh`, which first makes its histograms);
    `stored-noise`, the cheetah study with the noise stored (`results/stored-noise/runs`), then `redrawn-probes`,
    its three exploratory arms with the noise redrawn (`results/stored-noise/probes`); `stored-table-pilot`, the
    pilot of the main table in the stored ENE (`results/stored-table/pilot`), then `stored-table`, its primary runs
    (`results/stored-table/runs`); `which-sparsity`, which sparsity carries R2N's gain (`results/which-sparsity/runs`);
    `surf-rune`, R2N on SURF and RUNE and SURF's actor/critic-only arm (`results/surf-rune/runs`)"""
    methods: Optional[tuple[str, ...]] = None
    """methods (= `--exp-name`): a script name without `.py`, or a variant of `VARIANTS` (`r2n_pebble_reward_only`,
    `pebble_stored_noise`, ...); replaces the preset's"""
    env_ids: Optional[tuple[str, ...]] = None
    """tasks; with a preset, keeps only these (a paper task outside it gets the main table's noise and budget)"""
    noises: Optional[tuple[float, ...]] = None
    """noise fractions; replace the preset's (default for a paper task without preset: its main-table noise)"""
    budgets: Optional[tuple[int, ...]] = None
    """feedback budgets (`--max-feedback`); replace the preset's (default: the main-table budget of the task)"""
    seeds: Optional[tuple[int, ...]] = None
    """seeds; replace the preset's (default without a preset: 1)"""
    extra: str = ""
    """flags appended to every command, e.g. `--extra "--total-timesteps 500000 --cuda"`"""
    dry_run: bool = False
    """print the commands (and which runs are already finished) and exit"""
    force: bool = False
    """also rerun runs whose `.done` marker exists"""
    backend: Literal["local", "slurm"] = "local"
    """`local`: a process pool on this machine; `slurm`: one submitit job array"""
    workers: Optional[int] = None
    """local: runs at the same time (default and maximum with `--gpus`: the number of GPU slots; else default 1)"""
    gpus: Optional[str] = None
    """local: GPUs to use, e.g. `0,1,2,3` (CUDA_VISIBLE_DEVICES of each run, round-robin); unset: left alone"""
    runs_per_gpu: int = 1
    """runs sharing one GPU (local: slots per GPU; slurm: runs packed into one GPU job)"""
    mps: bool = False
    """runs that share a GPU go through a CUDA MPS daemon, started before the first run and quit after the last
    (local: one for the sweep; slurm: one per array task). 8 runs on one H100 went 2.2x as fast with it
    (results/gpu-speed). Needs `nvidia-cuda-mps-control`, which comes with NVIDIA's driver"""
    threads: int = 1
    """CPU threads per run (`OMP_NUM_THREADS`, `MKL_NUM_THREADS` and the scripts' `--threads`)"""
    log_dir: str = "logs"
    """per-run logs `{run_id}.log` and markers `{run_id}.done` / `.stopped` / `.failed` (and, with a results folder, each
    run's working folder `scratch/{run_id}`, which keeps its checkpoint)"""
    results_dir: Optional[str] = None
    """keep each finished run's TensorBoard event file and log (no checkpoint) in `{results_dir}/{run_id}/`, with a
    `done` file naming the git commit, the device and the numerics flags; a run with that file is finished (default
    with the study presets: `RESULTS[preset]`, so that committed results are skipped by the next session)"""
    script_dir: str = ROOT
    """folder holding the scripts"""
    python: str = sys.executable
    """the Python interpreter that runs the scripts"""
    slurm_partition: Optional[str] = None
    """slurm: partition (`--partition`)"""
    slurm_account: Optional[str] = None
    """slurm: account (`--account`)"""
    slurm_time: int = 2880
    """slurm: time limit per job in minutes (the paper reports 20-24 GPU-hours per R2N seed)"""
    slurm_mem_gb: int = 50
    """slurm: memory per run in GB; a job asks `--runs-per-gpu` times this (the paper reports 25-50 GB per seed)"""
    slurm_gpus: int = 1
    """slurm: GPUs per job"""
    slurm_cpus_per_task: Optional[int] = None
    """slurm: CPUs per job (default: `--runs-per-gpu` x `--threads`)"""
    slurm_array_parallelism: int = 256
    """slurm: at most this many array tasks at once"""
    slurm_extra: tuple[str, ...] = ()
    """slurm: further `#SBATCH` settings as KEY=VALUE (e.g. `constraint=a100 qos=normal`)"""
    slurm_folder: str = "slurm"
    """slurm: submitit's folder (job scripts, pickles, SLURM stdout/stderr)"""
    slurm_cluster: Literal["slurm", "local", "debug"] = "slurm"
    """slurm: submitit executor; `local` and `debug` run the same job functions on this machine (for tests)"""
    slurm_wait: bool = False
    """slurm: wait for the jobs and report every failed run (default: return after submission)"""
    slurm_max_requeues: int = 100
    """slurm: times a job may be requeued after its time limit (each resumes its runs from their `state.pt`)"""


@dataclass(frozen=True)
class Run:
    """One run of the grid: its id, what it is, and its command."""

    run_id: str
    method: str
    env_id: str
    noise: float
    budget: Optional[int]
    seed: int
    command: tuple


def fail(message: str):
    raise SystemExit(f"benchmark: error: {message}")


def check_task(env_id: str):
    """Fail with ene's one line if no script can make `env_id` here (Meta-World's without metaworld installed)."""
    import ene

    try:
        ene.check_env_args(env_id, 0.0)
    except ValueError as error:
        fail(str(error).replace("--env-id", "--env-ids", 1))


def grid(args: Args, preset: Optional[Preset]) -> tuple:
    """(settings, methods, seeds) of one part of the preset (or of the flags alone) with the flags' replacements."""
    methods = tuple(args.methods or (preset.methods if preset else ()))
    seeds = tuple(args.seeds or (preset.seeds if preset else (1,)))
    if not methods:
        fail("give --preset or --methods")
    if preset and not args.env_ids:
        settings = list(preset.settings)
    elif not args.env_ids:
        fail("give --preset or --env-ids")
    else:
        settings = [s for s in preset.settings if s[0] in args.env_ids] if preset else []
        for env in args.env_ids:
            if any(s[0] == env for s in settings):
                continue
            noise, budget = PAPER_SETTINGS.get(env, (None, None))
            if (noise is None and not args.noises) or (budget is None and not args.budgets):
                fail(f"{env} is not a paper task: give --noises and --budgets")
            settings.append((env, noise, budget))
    for env in dict.fromkeys(s[0] for s in settings):  # a misspelt task fails here, not in each of its runs
        check_task(env)
    if args.noises:
        settings = [(env, noise, budget) for env, _, budget in settings for noise in args.noises]
    if args.budgets:
        settings = [(env, noise, budget) for env, noise, _ in settings for budget in args.budgets]
    return list(dict.fromkeys(settings)), methods, seeds


def script_of(method: str, script_dir: str) -> tuple:
    """(script path, extra flags) of a method."""
    script, flags = VARIANTS.get(method, (f"{method}.py", ()))
    path = os.path.abspath(os.path.join(script_dir, script))
    if not os.path.isfile(path):
        fail(f"method {method}: no script {path}")
    return path, flags


# every run: resumable (preemption, time limits), with its diagnostics; a PbRL run also keeps its query log
HARNESS = ("--resumable", "--diagnostics")


def expand(args: Args) -> list:
    """The runs of the grid (the union of the preset's parts), seed-major, deduplicated by run id."""
    extra = tuple(shlex.split(args.extra))
    runs = {}
    for part in PRESETS[args.preset] if args.preset else (None,):
        settings, methods, seeds = grid(args, part)
        scripts = {m: script_of(m, args.script_dir) for m in methods}
        for seed in seeds:
            for env, noise, budget in settings:
                for method in methods:
                    budget_m = None if method in NO_FEEDBACK else budget
                    run_id = f"{method}__{env}__noise{noise:g}__budget{'none' if budget_m is None else budget_m}__seed{seed}"
                    script, flags = scripts[method]
                    command = (args.python, script, "--exp-name", method, "--env-id", env, "--noise", f"{noise:g}")
                    if budget_m is not None:
                        command += ("--max-feedback", str(budget_m))
                    command += ("--seed", str(seed), "--threads", str(args.threads), "--run-name", run_id) + HARNESS
                    command += (() if budget_m is None else ("--query-log",)) + tuple(flags)
                    if part is not None:
                        command += part.flags + (() if budget_m is None else part.feedback_flags)
                    runs.setdefault(run_id, (0 if part is None else part.stage,
                                             Run(run_id, method, env, noise, budget_m, seed, command + extra)))
    # stable: stage by stage, seed-major, within a seed the preset's order
    return [run for _, run in sorted(runs.values(), key=lambda staged: (staged[0], staged[1].seed))]


def marker(log_dir: str, run_id: str, kind: str) -> str:
    return os.path.join(log_dir, f"{run_id}.{kind}")


def results_dir_of(args: Args) -> Optional[str]:
    return args.results_dir or RESULTS.get(args.preset)


def is_done(run: Run, args: Args) -> bool:
    """With a results folder, its copy of the run; else a `.done` marker in the log folder."""
    results = results_dir_of(args)
    if results is not None:
        return os.path.exists(os.path.join(results, run.run_id, "done"))
    return os.path.exists(marker(args.log_dir, run.run_id, "done"))


def git_commit() -> str:
    """The commit of the scripts, `+dirty` when they have uncommitted changes (recorded with every run)."""
    try:
        commit = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True, check=True)
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no", "--", "*.py", "pyproject.toml"],
                               cwd=ROOT, capture_output=True, text=True, check=True)
        return commit.stdout.strip() + ("+dirty" if dirty.stdout.strip() else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown (not a git checkout)"


# ---------------------------------------------------------------- running one run (shared by both back-ends)


RESUMED = "\n# resumed from its state.pt\n"


def launch(spec: dict, gpu: Optional[str] = None, own_session: bool = False) -> subprocess.Popen:
    """Start one run, or resume it when its folder `runs/{run_id}` holds a `state.pt`: clear its markers, open its log
    (header: command, GPU, start time; appended to on a resume), return the process. With `own_session` the run is
    out of the launcher's process group, so a terminal's Ctrl-C reaches the launcher only, which stops the run with
    SIGTERM: the run saves its state (on SIGINT it would stop without)."""
    for kind in ("done", "failed"):
        if os.path.exists(spec["log"][:-4] + "." + kind):
            os.remove(spec["log"][:-4] + "." + kind)
    folder = os.path.join(spec["cwd"], "runs", spec["run_id"])
    resume = os.path.exists(os.path.join(folder, "state.pt"))
    if spec["results"] and not resume:  # a fresh scratch folder: the run's only `runs/*` is this run's
        shutil.rmtree(spec["cwd"], ignore_errors=True)
        os.makedirs(spec["cwd"])
    elif not resume and os.path.exists(folder):  # a run that stopped before its first state, or a rerun: kept aside
        os.replace(folder, f"{folder}.old-{time.strftime('%Y%m%d-%H%M%S')}")
    env = dict(os.environ, OMP_NUM_THREADS=str(spec["threads"]), MKL_NUM_THREADS=str(spec["threads"]),
               PYTHONUNBUFFERED="1")
    if gpu is not None:
        env["CUDA_VISIBLE_DEVICES"] = str(gpu)
    with open(spec["log"], "a" if resume else "w") as log:
        log.write(f"{RESUMED if resume else ''}# run {spec['run_id']}\n# command: {shlex.join(spec['command'])}\n"
                  f"# cwd: {spec['cwd']}\n# CUDA_VISIBLE_DEVICES={env.get('CUDA_VISIBLE_DEVICES', '(unset)')} "
                  f"OMP_NUM_THREADS={spec['threads']}\n# git commit {spec['commit']}\n"
                  f"# started {time.strftime('%Y-%m-%d %H:%M:%S')}\n")
        log.flush()
        process = subprocess.Popen(spec["command"], cwd=spec["cwd"], env=env, stdout=log, stderr=subprocess.STDOUT,
                                   stdin=subprocess.DEVNULL, start_new_session=own_session,
                                   preexec_fn=stop_with_launcher if own_session and sys.platform == "linux" else None)
    process.started = time.time()
    return process


@contextlib.contextmanager
def mps_daemon(enabled: bool, devices: Optional[str] = None):
    """A CUDA MPS control daemon for the runs started inside, quit when the block ends by return or exception
    (a launcher killed outright leaves it running). Its pipe and log folder is a private one on this node, so it
    neither meets another user's daemon nor needs a shared file system. The runs find it through
    `CUDA_MPS_PIPE_DIRECTORY`, set in this process's environment while inside.

    The daemon sees `devices` (a CUDA_VISIBLE_DEVICES list; default: this process's). An MPS server numbers the devices
    it sees from 0, and a client's CUDA_VISIBLE_DEVICES counts within them: so while inside, the runs inherit none,
    and a run given a GPU slot is given its position in `devices` (`run_local`)."""
    if not enabled:
        yield
        return
    folder = tempfile.mkdtemp(prefix="r2n-mps-")
    daemon_env = dict.fromkeys(("CUDA_MPS_PIPE_DIRECTORY", "CUDA_MPS_LOG_DIRECTORY"), folder)
    seen = {"CUDA_VISIBLE_DEVICES": devices} if devices else {}
    try:
        code = subprocess.run(["nvidia-cuda-mps-control", "-d"], env=os.environ | daemon_env | seen).returncode
        failure = f"exit code {code}" if code else None
    except OSError:
        failure = "not found"
    if failure:
        shutil.rmtree(folder, ignore_errors=True)
        fail(f"--mps: the MPS daemon did not start (nvidia-cuda-mps-control -d: {failure})")
    before = {name: os.environ.get(name) for name in (*daemon_env, "CUDA_VISIBLE_DEVICES")}
    os.environ.update(daemon_env)
    os.environ.pop("CUDA_VISIBLE_DEVICES", None)
    print(f"MPS daemon started ({folder}; devices {devices or before['CUDA_VISIBLE_DEVICES'] or 'all'})", flush=True)
    try:
        yield
    finally:
        subprocess.run(["nvidia-cuda-mps-control"], input="quit\n", text=True)
        print("MPS daemon quit", flush=True)
        for name, value in before.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value
        shutil.rmtree(folder, ignore_errors=True)


def stop_with_launcher():
    """In a run's process before its script starts: SIGTERM (a state, then exit) when the launcher dies, however it
    dies (SIGKILL too), so that no run out of the launcher's process group goes on untracked. Linux's prctl."""
    ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGTERM))  # 1: PR_SET_PDEATHSIG


# the scripts' numerics flags, named in each `done` file: `--compile` and `--tf32` change floating-point results (analyze.py
# never compares runs that differ in them); `--cuda-graph` gives eager's numbers on its GPU
NUMERICS_FLAGS = ("--compile", "--tf32", "--cuda-graph", "--cuda-graph-whole")


def device_of(command: tuple) -> str:
    """The device a run's script picks: the GPU torch sees (its model), unless the command says `--no-cuda`."""
    if "--no-cuda" in command:
        return "cpu"
    try:
        import torch
    except ImportError:
        return "unknown (torch not importable by the launcher)"
    return f"cuda ({torch.cuda.get_device_name(0)})" if torch.cuda.is_available() else "cpu"


def cpu_of() -> str:
    """The CPU's model, as Linux names it, and the instruction set torch's kernels dispatch on: a run's trajectory
    depends on both (a virtual machine's model name can be as vague as "Intel(R) Xeon(R) Processor")."""
    try:
        with open("/proc/cpuinfo") as f:
            models = [line.split(":", 1)[1].strip() for line in f if line.startswith("model name")]
    except OSError:
        models = []
    model = models[0] if models else (platform.processor() or platform.machine() or "unknown")
    try:
        import torch

        return f"{model}, torch CPU capability {torch.backends.cpu.get_cpu_capability()}"
    except (ImportError, AttributeError):
        return model


def typed_command(command: tuple, root: str = ROOT) -> str:
    """A run's command as a user types it in the repository: `python`, and the paths under `root` relative to it, so
    that the line in a `done` file runs on any machine."""
    words = ["python"] + [os.path.relpath(word, root) if os.path.isabs(word) and word.startswith(root + os.sep)
                          else word for word in command[1:]]
    return shlex.join(words)


def numerics_of(command: tuple) -> str:
    flags = [flag for flag in NUMERICS_FLAGS if flag in command]
    return " ".join(flags) if flags else "default (eager, FP32)"


# the one line a script prints when a non-finite value stops it (docs/running.md), its exit code 1
NON_FINITE = re.compile(r"^\S+: error: (non-finite .* at step \d+);", re.M)
NOT_STARTED = "not started (interrupted)"
# the one line a script prints when SIGTERM or SIGUSR2 stops it once its state is saved, its exit code 1
SAVED = re.compile(r"^\S+: (stopped by SIG\w+ [^;\n]*); (?:the )?state [^\n]*saved", re.M)


def finish_run(spec: dict, returncode: int, seconds: float) -> str:
    """Append the exit code to the log and write the `.done` (code 0, or a stop at a non-finite value: its `stopped`
    line names it), `.stopped` (a stop signal with the state saved, or SIGTERM before the script took it over: the
    same command resumes it) or `.failed` marker, in place of an earlier start's, and return its kind. Its `seconds`
    add up the starts of a resumed run (each ended start's time is in its log; a start cut off without an exit line is
    counted, its seconds unknown). With a results folder, copy the run there; a run that left no event file has
    nothing to keep and counts as failed."""
    with open(spec["log"], "a") as log:
        log.write(f"\n# exit code {returncode} after {seconds:.0f} s\n")
    with open(spec["log"]) as log:
        text = log.read()
    starts = [float(s) for s in re.findall(r"^# exit code -?\d+ after (\d+) s", text, re.M)]
    # a start whose launcher was killed (a session cut off) wrote no exit line: it is counted, its seconds are not
    started = re.split(r"^# started ", text, flags=re.M)
    unended = sum("\n# exit code " not in start for start in started[1:])
    events = glob.glob(os.path.join(spec["cwd"], "runs", spec["run_id"], "events.out.tfevents.*"))
    kept = events or not spec["results"]  # a study's run is what its event files hold
    # a run stopped by a non-finite value would stop there again if resumed: it is finished with what it reached
    stopped = NON_FINITE.findall(started[-1]) if returncode == 1 else []  # in the last start only
    saved = SAVED.findall(started[-1]) if returncode == 1 else []
    # SIGTERM's default action: the run was stopped before its script took the signal over (while it started)
    starting = returncode == -signal.SIGTERM
    kind = "done" if (returncode == 0 or stopped) and kept else "stopped" if saved or starting else "failed"
    summary = f"exit code {returncode}{'' if kept else ', no event file'}\n"
    if stopped:
        summary += f"stopped {stopped[-1]}\n"
    if saved:
        summary += f"{saved[-1]}, its state saved: the same command resumes it\n"
    elif starting:
        summary += "stopped by SIGTERM before its script took the signal over: the same command runs it\n"
    summary += f"seconds {sum(starts):.0f} over {len(starts)} start(s)"
    if unended > 0:
        summary += f"; {unended} more start(s) ended without an exit line, their seconds unknown"
    command = tuple(spec["command"])
    summary += f"\ncommand {typed_command(command)}\n"
    summary += f"git commit {spec['commit']}\ndevice {device_of(command)}\ncpu {cpu_of()}\nnumerics {numerics_of(command)}\n"
    if spec["results"] and kind == "done":  # keep the event files and the log; the `done` files come last
        shutil.rmtree(spec["results"], ignore_errors=True)  # what an interrupted copy may have left
        os.makedirs(spec["results"])
        for path in events:
            shutil.copy2(path, spec["results"])
        shutil.copy2(spec["log"], os.path.join(spec["results"], "log.txt"))
        with open(os.path.join(spec["results"], "done"), "w") as f:
            f.write(summary)
    for stale in ("done", "stopped", "failed"):  # an earlier start's (a `--force` rerun's `.done` too)
        if stale != kind and os.path.exists(spec["log"][:-4] + "." + stale):
            os.remove(spec["log"][:-4] + "." + stale)
    with open(spec["log"][:-4] + "." + kind, "w") as f:
        f.write(summary)
    return kind


def resumable(code, log: str) -> bool:
    """A sweep's result that the same command resumes: a run not started, or one stopped with its state saved or
    before its script took SIGTERM over (its marker, written as it ended, says so). A SLURM job that died gives a
    message, not an exit code: a failure."""
    return code == NOT_STARTED or (code in (1, -signal.SIGTERM) and bool(log) and os.path.exists(log[:-4] + ".stopped"))


def outcome(code, log: str) -> str:
    """A sweep's result as its marker says: "stopped" (`resumable`), "finished" (`.done`: exit code 0 with what a
    study keeps, or a stop at a non-finite value) or "failed" (the rest, a SLURM job that died too)."""
    if resumable(code, log):
        return "stopped"
    if isinstance(code, int) and bool(log) and os.path.exists(log[:-4] + ".done"):
        return "finished"
    return "failed"


class RunGroup:
    """A SLURM array task: run its specs at once (they share the job's GPU), return [(run_id, exit code, log)], those
    of earlier starts of the task included. Checkpointable: at the time limit submitit calls `checkpoint`, which has
    the runs save their `state.pt` (SIGUSR2) and requeues the task with the runs still going, which then resume
    (preempted jobs that SLURM requeues resume the same way). A run that ended before the signal is recorded as it
    ended (each is recorded when it ends, not in order), not started again."""

    def __init__(self, earlier: tuple = (), mps: bool = False):
        self.earlier = list(earlier)  # the results of the runs that ended in earlier starts of this task
        self.mps = mps

    def __call__(self, specs: list) -> list:
        self.finished, self.results = set(), list(self.earlier)
        with mps_daemon(self.mps):
            self.processes = [(spec, launch(spec)) for spec in specs]
            while len(self.finished) < len(self.processes):
                time.sleep(1)
                for spec, process in self.processes:
                    if spec["run_id"] not in self.finished and process.poll() is not None:
                        self.record(spec, process.returncode, time.time() - process.started)
        return self.results

    def record(self, spec: dict, returncode: int, seconds: float):
        self.finished.add(spec["run_id"])
        finish_run(spec, returncode, seconds)
        self.results.append((spec["run_id"], returncode, spec["log"]))

    def checkpoint(self, specs: list):
        import submitit

        processes = getattr(self, "processes", [])
        going = [(spec, process) for spec, process in processes if spec["run_id"] not in self.finished]
        for _, process in going:
            if process.poll() is None:
                process.send_signal(signal.SIGUSR2)
        started = {spec["run_id"] for spec, _ in processes}
        requeued = [spec for spec in specs if spec["run_id"] not in started]  # the signal came before they started
        for spec, process in going:
            try:  # the run ends its step, saves its state and exits; not `process.wait()`: this signal handler may
                # have interrupted `__call__` inside `poll`, holding its lock. WNOWAIT leaves the exit status there.
                ended = os.waitid(os.P_PID, process.pid, os.WEXITED | os.WNOWAIT)
                # a run the signal killed (before its script took SIGUSR2 over) as Popen writes it: minus the signal
                code = ended.si_status if ended.si_code == os.CLD_EXITED else -ended.si_status
            except ChildProcessError:  # already reaped
                code = process.returncode
            if code == 0:  # it finished as the signal came: its results are complete
                self.record(spec, code, time.time() - process.started)
                continue
            with open(spec["log"], "a") as log:  # its seconds count in the `done` file's sum
                log.write(f"\n# exit code {code} after {time.time() - process.started:.0f} s: stopped at the job's time "
                          "limit, requeued to resume\n")
            requeued.append(spec)
        # a fresh group (processes do not pickle) that reports the runs recorded so far too; an empty one when all
        # have ended (returning None would fail the job)
        return submitit.helpers.DelayedSubmission(RunGroup(getattr(self, "results", self.earlier), self.mps), requeued)


def spec_of(run: Run, args: Args) -> dict:
    """What a job needs to know about a run (plain data: it travels to SLURM jobs)."""
    results = results_dir_of(args)
    return dict(run_id=run.run_id, command=list(run.command), threads=args.threads, commit=git_commit(),
                log=os.path.abspath(marker(args.log_dir, run.run_id, "log")),
                cwd=os.path.abspath(os.path.join(args.log_dir, "scratch", run.run_id)) if results else os.getcwd(),
                results=os.path.abspath(os.path.join(results, run.run_id)) if results else None)


def describe(returncode: int) -> str:
    if returncode < 0:
        try:
            return f"exit code {returncode} (killed by {signal.Signals(-returncode).name})"
        except ValueError:
            return f"exit code {returncode}"
    return f"exit code {returncode}"


# ---------------------------------------------------------------- back-ends


def lock_log_dir(log_dir: str):
    """One local launcher per log folder: a second would start the same runs again, into the same folders. The lock
    is the kernel's, held until this process ends (a killed launcher leaves none behind). Returns the locked file."""
    lock = open(os.path.join(log_dir, ".launcher.lock"), "a+")
    try:
        fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        lock.seek(0)
        fail(f"another benchmark.py is running runs in {log_dir}/ ({lock.read().strip() or 'pid unknown'}); wait for "
             "it to end, stop it, or give this one another --log-dir")
    lock.truncate(0)
    lock.write(f"pid {os.getpid()}\n")
    lock.flush()
    return lock


def run_local(runs: list, args: Args) -> list:
    """A pool of at most `workers` processes; GPU slots round-robin. Returns [(run_id, exit code, log)]."""
    lock = lock_log_dir(args.log_dir)  # noqa: F841 (held while the runs run)
    gpus = [g.strip() for g in args.gpus.split(",") if g.strip()] if args.gpus else []
    slots = deque(g for _ in range(args.runs_per_gpu) for g in gpus) if gpus else None
    workers = args.workers or (len(slots) if slots else 1)
    if slots is not None:
        workers = min(workers, len(slots))
    pending, active, results = deque(runs), {}, []
    print(f"running {len(runs)} runs, {workers} at a time" + (f" on GPUs {','.join(gpus)} "
          f"({args.runs_per_gpu} per GPU)" if gpus else ""), flush=True)
    # `kill` and a closed terminal stop the sweep as Ctrl-C does (the runs, in sessions of their own, get neither);
    # a signal the launcher was started ignoring (`nohup`) stays ignored
    stops = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
    previous = {signum: signal.getsignal(signum) for signum in stops}
    # The handler only notes the signal, and the loop stops at its next turn. An exception raised between any two
    # bytecodes could leave a `Popen` half made, or its wait lock held, and then the cleanup's `wait` blocks forever.
    asked = []
    for signum in stops:
        if previous[signum] is not signal.SIG_IGN:
            signal.signal(signum, lambda signum, frame: asked.append(signum))
    try:
        while pending or active:
            if asked:
                raise KeyboardInterrupt
            while pending and len(active) < workers:
                run, gpu = pending.popleft(), slots.popleft() if slots is not None else None
                spec = spec_of(run, args)
                visible = str(gpus.index(gpu)) if args.mps and gpu is not None else gpu  # counted within the daemon's
                active[run.run_id] = (spec, launch(spec, visible, own_session=True), gpu)
                print(f"started {run.run_id}" + ("" if gpu is None else f" on GPU {gpu}") + f" -> {spec['log']}",
                      flush=True)
            time.sleep(0.05)
            for run_id, (spec, process, gpu) in list(active.items()):
                returncode = process.poll()
                if returncode is None:
                    continue
                seconds = time.time() - process.started
                del active[run_id]  # first: if recording it fails, the cleanup below does not record it again
                kind = finish_run(spec, returncode, seconds)
                results.append((run_id, returncode, spec["log"]))
                if slots is not None:
                    slots.append(gpu)
                said = {"done": "finished", "stopped": "stopped", "failed": "FAILED"}[kind]
                print(f"{said} {run_id} ({describe(returncode)}, {seconds:.0f} s)", flush=True)
    except BaseException as error:  # Ctrl-C, `kill`, or the launcher's own failure: no run is left running untracked
        for signum in stops:  # a second Ctrl-C would cut the cleanup short while the runs write their states
            signal.signal(signum, signal.SIG_IGN)
        if active:
            print(f"stopping {len(active)} runs: they save their state (further Ctrl-C ignored)", flush=True)
        for _, process, _ in active.values():
            process.terminate()
        for run_id, (spec, process, _) in active.items():
            returncode = process.wait()
            try:  # each run's marker, even if another's cannot be written (the error that ended the sweep, again)
                finish_run(spec, returncode, time.time() - process.started)
            except OSError as e:
                print(f"{run_id}: {describe(returncode)}, its marker not written ({e})", flush=True)
            results.append((run_id, returncode, spec["log"]))
        if not isinstance(error, KeyboardInterrupt):
            raise
        results += [(run.run_id, NOT_STARTED, "") for run in pending]
        print("interrupted: running runs terminated (they save their state: the same command resumes them)", flush=True)
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
    return results


def make_executor(args: Args):
    """The submitit executor of one job: `--slurm-*` settings, memory and CPUs for `--runs-per-gpu` runs."""
    import submitit

    extra = {}
    for item in args.slurm_extra:
        key, sep, value = item.partition("=")
        if not sep:
            fail(f"--slurm-extra expects KEY=VALUE, got {item!r}")
        extra[key] = value
    if args.slurm_account:
        extra["account"] = args.slurm_account
    executor = submitit.AutoExecutor(folder=args.slurm_folder, cluster=args.slurm_cluster,
                                     slurm_max_num_timeout=args.slurm_max_requeues)
    k = args.runs_per_gpu
    executor.update_parameters(
        name="r2n", timeout_min=args.slurm_time, gpus_per_node=args.slurm_gpus, mem_gb=args.slurm_mem_gb * k,
        cpus_per_task=args.slurm_cpus_per_task or k * args.threads, nodes=1, tasks_per_node=1,
        slurm_partition=args.slurm_partition, slurm_array_parallelism=args.slurm_array_parallelism,
        slurm_additional_parameters=extra or None,
    )
    return executor


def run_slurm(runs: list, args: Args) -> Optional[list]:
    """One submitit job array, `runs_per_gpu` runs per task. Returns the results with `--slurm-wait`, else None."""
    try:
        import submitit  # noqa: F401  (checked here, used in make_executor)
    except ImportError:
        fail("the SLURM back-end needs submitit: pip install -e '.[slurm]'")
    if __name__ != "__main__":  # imported (tests): ship this module's functions by value, jobs need not import it
        import cloudpickle

        cloudpickle.register_pickle_by_value(sys.modules[__name__])
    k = args.runs_per_gpu
    specs = [spec_of(run, args) for run in runs]
    chunks = [specs[i:i + k] for i in range(0, len(specs), k)]
    executor = make_executor(args)
    jobs = executor.map_array(RunGroup(mps=args.mps), chunks)
    print(f"submitted {len(runs)} runs as {len(jobs)} array tasks ({k} per GPU job): job ids "
          f"{jobs[0].job_id} .. {jobs[-1].job_id}; submitit files in {args.slurm_folder}/", flush=True)
    for job, chunk in zip(jobs, chunks):
        print(f"  {job.job_id}: {', '.join(spec['run_id'] for spec in chunk)}")
    if not args.slurm_wait:
        print(f"logs in {args.log_dir}/; rerun the same command when the jobs have ended to submit what did not "
              f"finish (see `--dry-run`)")
        return None
    results = []
    for job, chunk in zip(jobs, chunks):
        try:
            results += job.result()
        except Exception as e:  # the job itself died (time limit, node failure, out of memory)
            first_line = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
            results += [(spec["run_id"], f"job {job.job_id} failed: {first_line}", spec["log"]) for spec in chunk]
    return results


def main(args: Args) -> int:
    if args.runs_per_gpu < 1 or args.threads < 1 or (args.workers is not None and args.workers < 1):
        fail("--runs-per-gpu, --threads and --workers must be >= 1")
    runs = expand(args)
    done = [] if args.force else [r for r in runs if is_done(r, args)]
    done_ids = {r.run_id for r in done}
    todo = [r for r in runs if r.run_id not in done_ids]
    if args.dry_run:
        for run in runs:
            if run.run_id in done_ids:
                print(f"# done: {run.run_id}")
                continue
            log = marker(args.log_dir, run.run_id, "log")
            for kind in ("stopped", "failed"):
                path = marker(args.log_dir, run.run_id, kind)
                if os.path.exists(path):
                    with open(path) as f:
                        lines = f.read().splitlines() or ["?"]
                    stop = next((line for line in lines if line.startswith("stopped by ")), "stopped")
                    print(f"# {stop} (log {log})" if kind == "stopped" else
                          f"# previously failed ({lines[0]}, log {log})")
            print(shlex.join(run.command))
        print(f"# {len(runs)} runs, {len(done)} already finished, {len(todo)} to run")
        return 0
    os.makedirs(args.log_dir, exist_ok=True)
    if done:
        print(f"skipping {len(done)} finished runs ({results_dir_of(args) or args.log_dir}/ says so; --force reruns them)")
    if not todo:
        print("nothing to run")
        return 0
    if args.backend == "local":
        with mps_daemon(args.mps, args.gpus):
            results = run_local(todo, args)
    else:
        results = run_slurm(todo, args)
    if results is None:
        return 0
    stopped, failures = [], []
    for run_id, code, log in results:
        kind = outcome(code, log)
        if kind == "stopped":
            stopped.append(run_id)
        elif kind == "failed":
            failures.append((run_id, code, log))
    print(f"{len(results) - len(failures) - len(stopped)} runs finished, {len(done)} skipped as already finished, "
          + (f"{len(stopped)} stopped or not started (the same command resumes them), " if stopped else "")
          + f"{len(failures)} failed")
    for run_id, code, log in failures:
        print(f"FAILED {run_id}: {describe(code) if isinstance(code, int) else code}, log {log or '-'}")
    return 1 if failures or stopped else 0


if __name__ == "__main__":
    sys.exit(main(tyro.cli(Args)))
