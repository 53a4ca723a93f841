"""The stored-table pilot's decisions, by PROTOCOL.md's rules, from the committed event files.

    python results/stored-table/power.py        # one block per task whose pilot runs are in

For each task: does each arm learn (rule 1), the stop rule (2), the spread CV (3), the effect d (4), the seeds per
arm and whether the task is powered or exploratory (5), cartpole's length (6), and whether each PbRL run could use its
feedback (7: `pbrl/labeled_feedback`, one point per round). A task whose 5 pilot runs are not
all in is named and skipped. Primary metric: the mean of a run's last 3 evaluations.
"""
import glob
import math
import os
import sys

import numpy as np

STUDY = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(os.path.dirname(STUDY))
sys.path.insert(0, ROOT)
import analyze  # noqa: E402

PILOT = os.path.join(STUDY, "pilot")
STORED_NOISE = os.path.join(ROOT, "results", "stored-noise", "runs")
LAST, ALPHA, SEEDS, FLOOR = 3, 0.05, (8, 9, 10), 0.5
# task -> (noise, budget, the paper's PEBBLE and R2N-PEBBLE means)
TASKS = {
    "cartpole-swingup": (0.9, 400, 660.48, 716.89),
    "walker-walk": (0.9, 4000, 340.72, 455.22),
    "quadruped-walk": (0.7, 4000, 185.41, 309.33),
}
ARMS = ("pebble_stored_noise", "r2n_pebble_stored_noise", "sac_stored_noise", "anf_sac_stored_noise")
SHORT_LENGTH, SHORT_WINDOW = 150_000, (130_000, 140_000, 150_000)  # rule 6: cartpole's shorter length
SPENT_BY, ROUNDS = 129_000, 100  # rule 7: every budget spent by this step, in this many rounds


def read(folder: str) -> "analyze.Run":
    """A run's event files, a resumed run's read as one."""
    [run] = analyze.read_folder(sorted(glob.glob(os.path.join(folder, "events.out.tfevents.*")),
                                       key=analyze.natural_order))
    return run


def curve(folder: str) -> tuple:
    """(steps, returns) of a run's evaluations."""
    return read(folder).scalars[analyze.EVAL_TAG]


def primary(returns: np.ndarray) -> float:
    return float(np.mean(returns[-LAST:]))


def learns(steps: np.ndarray, returns: np.ndarray) -> bool:
    """Rule 1: the primary metric is at least twice the first evaluation and at least 50 above it."""
    first, final = float(returns[0]), primary(returns)
    return final >= 2 * first and final >= first + 50


def feedback_used(folder: str, budget: int) -> tuple:
    """Rule 7 for one PbRL run: (labels, rounds, rounds that labelled fewer than budget/100, the step of the last
    round). A run uses its feedback when it labels its whole budget in full rounds by step 129 000."""
    steps, labeled = read(folder).scalars["pbrl/labeled_feedback"]
    short = int(np.sum(np.diff(labeled, prepend=0.0) < budget / ROUNDS))
    return int(labeled[-1]), len(steps), short, int(steps[-1])


def stored_noise_cv() -> float:
    """The stored-noise study's pooled SD of its two PbRL arms over its PEBBLE's mean."""
    arms = {}
    for method in ("pebble_stored_noise", "r2n_pebble_stored_noise"):
        folders = sorted(glob.glob(os.path.join(STORED_NOISE, f"{method}__*")))
        arms[method] = np.array([primary(curve(f)[1]) for f in folders])
    pooled = math.sqrt(np.mean([np.var(a, ddof=1) for a in arms.values()]))
    return pooled / arms["pebble_stored_noise"].mean()


def seeds_for(d: float) -> tuple:
    """Rule 5: (seeds per arm, power at them, powered or exploratory)."""
    powers = {n: analyze.power(d, 1.0, n, ALPHA) for n in SEEDS}
    if powers[SEEDS[-1]] < FLOOR:
        return SEEDS[0], powers[SEEDS[0]], "exploratory"
    n = next((n for n in SEEDS if powers[n] >= 0.8), SEEDS[-1])
    return n, powers[n], "powered"


def is_pbrl(method: str) -> bool:
    """A method that learns from preferences (the oracles learn from the true reward, with no budget)."""
    return not method.startswith(("sac", "anf_sac"))


def run_folder(task: str, method: str, seed: int) -> str:
    noise, budget = TASKS[task][:2]
    budget_id = budget if is_pbrl(method) else "none"
    return os.path.join(PILOT, f"{method}__{task}__noise{noise:g}__budget{budget_id}__seed{seed}")


def pilot_runs(task: str) -> dict:
    """(method, seed) -> run folder, for the task's 5 pilot runs."""
    runs = {(m, 901): run_folder(task, m, 901) for m in ARMS}
    runs[("pebble_stored_noise", 902)] = run_folder(task, "pebble_stored_noise", 902)
    return runs


def missing_runs(task: str) -> list:
    return [os.path.basename(f) for f in pilot_runs(task).values() if not os.path.exists(os.path.join(f, "done"))]


def plan(task: str, study_cv: float) -> dict:
    """Rules 3 to 5 from the task's two pilot PEBBLE runs: the spread, the effect (in points too) and the seeds."""
    paper_pebble, paper_r2n = TASKS[task][2:]
    runs = pilot_runs(task)
    pebble = np.array([primary(curve(runs[("pebble_stored_noise", s)])[1]) for s in (901, 902)])
    pilot_cv = float(np.std(pebble, ddof=1) / pebble.mean())
    cv = max(pilot_cv, study_cv)
    gain = paper_r2n / paper_pebble - 1
    d = gain / (2 * cv)
    n, achieved, kind = seeds_for(d)
    return dict(pebble=pebble, pilot_cv=pilot_cv, cv=cv, gain=gain, d=d, effect=gain / 2 * pebble.mean(), n=n,
                power=achieved, kind=kind)


def report(task: str, study_cv: float) -> list:
    """The task's lines, or one line naming the pilot runs still missing."""
    noise, budget = TASKS[task][:2]
    runs = pilot_runs(task)
    missing = missing_runs(task)
    if missing:
        return [f"## {task}: {len(runs) - len(missing)} of {len(runs)} pilot runs are in (missing: {', '.join(missing)})"]
    curves = {key: curve(folder) for key, folder in runs.items()}
    lines = [f"## {task} {noise:g}/{budget}", "", "| run | first evaluation | primary metric | learns (rule 1) |",
             "|---|---|---|---|"]
    for (method, seed), (steps, returns) in curves.items():
        lines.append(f"| {method} seed {seed} | {returns[0]:.1f} | {primary(returns):.1f} | "
                     f"{'yes' if learns(steps, returns) else 'no'} |")
    decided = plan(task, study_cv)
    pebble = decided["pebble"]
    oracle = learns(*curves[("anf_sac_stored_noise", 901)])
    lines += [
        "",
        f"- Stop rule (2): anf_sac_stored_noise {'learns' if oracle else 'does NOT learn: look for a bug first'}.",
        f"- Spread (3): pilot CV {decided['pilot_cv']:.3f} (PEBBLE {pebble[0]:.1f} and {pebble[1]:.1f}), stored-noise "
        f"study CV {study_cv:.3f}: CV = {decided['cv']:.3f}.",
        f"- Effect (4): g = {decided['gain']:.4f}, half of it on the pilot PEBBLE's mean {pebble.mean():.1f} is "
        f"{decided['effect']:.1f} points; d = {decided['d']:.3f}.",
        f"- Seeds (5): {decided['n']} per arm, power {decided['power']:.2f}: {decided['kind']}.",
    ]
    if task == "cartpole-swingup":
        level = []
        for key in (("pebble_stored_noise", 901), ("pebble_stored_noise", 902), ("r2n_pebble_stored_noise", 901)):
            steps, returns = curves[key]
            window = float(np.mean([returns[steps == s][0] for s in SHORT_WINDOW]))
            level.append(abs(window - primary(returns)) <= 0.1 * abs(primary(returns)))
        lines.append(f"- Length (6): {SHORT_LENGTH} steps" if all(level) else "- Length (6): 250 000 steps "
                     "(a PbRL run is not within 10% of its primary metric by 150 000)")
    used = {key: feedback_used(runs[key], budget) for key in runs if is_pbrl(key[0])}
    for (method, seed), (labels, rounds, short, last) in used.items():
        lines.append(f"- Feedback (7): {method} seed {seed}: {labels} of {budget} labels in {rounds} rounds "
                     f"({short} short), the last at step {last}.")
    kept = all(u[0] == budget and u[2] == 0 and u[3] <= SPENT_BY for u in used.values())
    lines.append("- Feedback (7): " + ("unchanged." if kept else "a run could not use it: part 2 says what changes."))
    return lines


if __name__ == "__main__":
    study_cv = stored_noise_cv()
    print(f"# The stored-table pilot's decisions (PROTOCOL.md, part 1)\n\nThe stored-noise study's CV: {study_cv:.3f}\n")
    for task in TASKS:
        print("\n".join(report(task, study_cv)) + "\n")
