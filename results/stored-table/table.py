"""The study's table for users (issue 41), from the committed event files: per task, the paper's PEBBLE and R2N-PEBBLE,
ours, the difference with its CI, p and the power achieved, and the gains in percent; and the tasks' curves side by
side.

    python results/stored-table/table.py          # writes table.md, curves.png and the two READMEs' table blocks
    python results/stored-table/table.py --check  # exit 1 if table.md or a README block is not what the runs give

The study's README gets the whole table; the root README's results, its short form (the paper's gain, ours, the
difference, p and the power achieved).

Cheetah-run's row is the stored-noise study's, as committed (its own protocol, 8 seeds per arm, its effect of interest
79.4). The other tasks' rows come from their primary runs (`runs/`, PROTOCOL.md part 2) once all of them are in; before
that a row says how many are in. Statistics as `analyze.py`'s tables: the primary metric (the mean of a run's last 3
evaluations), mean ± SE over seeds, the one-tailed Welch p of R2N-PEBBLE > PEBBLE, the exact permutation p and the
percentile bootstrap 95% CI of the difference, each with `analyze.py`'s functions and seeds. The power achieved is that
of the test for the task's effect of interest (half the paper's relative gain on the pilot PEBBLE's mean, PROTOCOL.md
rule 4) at the achieved pooled SD and seeds (`analyze.power`). Holm's correction runs over this study's powered tasks
(the cheetah row's test was its own study's) once all of them are in. Each arm's wall time is the mean over its runs
of the time from a run's first to its last event, summed over the starts of a resumed run (`analyze.read_folder`):
one CPU core per run, two runs on the machine at a time.
"""
import argparse
import os
import sys
import warnings

import numpy as np

STUDY = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, STUDY)
import power  # noqa: E402 (the pilot's plan per task, the run reading)
from power import analyze  # noqa: E402

RUNS = os.path.join(STUDY, "runs")
METHODS = ("pebble_stored_noise", "r2n_pebble_stored_noise")
# task -> (noise, budget, paper PEBBLE, paper R2N-PEBBLE), in the paper's order
TASKS = dict(list(power.TASKS.items())[:2] + [("cheetah-run", (0.9, 1000, 237.62, 404.59))]
             + list(power.TASKS.items())[2:])
CHEETAH = dict(folder=power.STORED_NOISE, n=8, kind="powered", effect=79.4)  # results/stored-noise/PROTOCOL.md
MARKERS = ("<!-- table.py: start -->", "<!-- table.py: end -->")
README = os.path.join(STUDY, "README.md")
ROOT_MARKERS = ("<!-- results/stored-table/table.py: start -->", "<!-- results/stored-table/table.py: end -->")
ROOT_README = os.path.join(power.ROOT, "README.md")


def task_plan(task: str, study_cv: float):
    """(folder, seeds per arm, powered or exploratory, effect of interest), or None while the pilot is not in."""
    if task == "cheetah-run":
        return CHEETAH
    if power.missing_runs(task):
        return None
    decided = power.plan(task, study_cv)
    return dict(folder=RUNS, n=decided["n"], kind=decided["kind"], effect=decided["effect"])


def arm_folders(folder: str, method: str, task: str, n: int) -> list:
    """The finished runs of seeds 1 to `n` (the protocol's), in seed order."""
    noise, budget = TASKS[task][:2]
    folders = [os.path.join(folder, f"{method}__{task}__noise{noise:g}__budget{budget}__seed{seed}")
               for seed in range(1, n + 1)]
    return [f for f in folders if os.path.exists(os.path.join(f, "done"))]


def primary(returns: np.ndarray) -> float:
    """The primary metric over the finite evaluations: a run stopped by a non-finite value counts with what it
    reached (PROTOCOL.md part 2)."""
    return power.primary(returns[np.isfinite(returns)])


def holm(pvalues: dict) -> dict:
    """Holm's step-down adjusted p-values."""
    order = sorted(pvalues, key=pvalues.get)
    adjusted, running = {}, 0.0
    for i, name in enumerate(order):
        running = max(running, min(1.0, (len(order) - i) * pvalues[name]))
        adjusted[name] = running
    return adjusted


def rows() -> list:
    study_cv = power.stored_noise_cv()
    out = []
    for task, (noise, budget, paper_pebble, paper_r2n) in TASKS.items():
        row = dict(task=task, noise=noise, budget=budget, paper=(paper_pebble, paper_r2n),
                   paper_gain=paper_r2n / paper_pebble - 1, plan=task_plan(task, study_cv))
        if row["plan"] is not None:
            folders = {m: arm_folders(row["plan"]["folder"], m, task, row["plan"]["n"]) for m in METHODS}
            row["runs_in"] = sum(map(len, folders.values()))
            if all(len(f) == row["plan"]["n"] for f in folders.values()):
                read = {m: [power.read(f) for f in fs] for m, fs in folders.items()}
                row["curves"] = {m: [run.scalars[analyze.EVAL_TAG] for run in runs] for m, runs in read.items()}
                row["hours"] = {m: np.mean([run.wall_seconds for run in runs]) / 3600 for m, runs in read.items()}
                row["arms"] = {m: np.array([primary(c[1]) for c in cs]) for m, cs in row["curves"].items()}
        out.append(row)
    powered = {r["task"]: r for r in out if r["task"] != "cheetah-run" and r["plan"] and r["plan"]["kind"] == "powered"}
    for r in out:
        if "arms" in r:
            r2n, pebble = r["arms"]["r2n_pebble_stored_noise"], r["arms"]["pebble_stored_noise"]
            r["welch"] = analyze.welch_p(r2n, pebble)
            r["permutation"] = analyze.permutation_p(r2n, pebble)[0]
            r["ci"] = analyze.bootstrap_ci(r2n, pebble)
            sd = float(np.sqrt((np.var(r2n, ddof=1) + np.var(pebble, ddof=1)) / 2))
            r["power"] = analyze.power(r["plan"]["effect"], sd, len(pebble))
    # Holm's family is known once every task's pilot has said whether it is powered
    if powered and all(r["plan"] for r in out) and all("arms" in r for r in powered.values()):
        for task, p in holm({t: r["welch"] for t, r in powered.items()}).items():
            powered[task]["holm"] = p
    return out


def percent(x: float) -> str:
    return f"{100 * x:+.1f}%"


COLUMNS = ("task", "noise / budget", "paper: PEBBLE", "paper: R2N-PEBBLE", "paper's gain", "ours: PEBBLE",
           "ours: R2N-PEBBLE", "difference [95% CI]", "our gain", "Welch p (Holm)", "permutation p", "power achieved",
           "hours per run (PEBBLE / R2N-PEBBLE)", "test")
SHORT = ("task", "noise / budget", "paper's gain", "ours: PEBBLE", "ours: R2N-PEBBLE", "difference [95% CI]", "our gain",
         "Welch p (Holm)", "power achieved", "test")


def cells(r: dict) -> dict:
    """The row's cell per column; a task not yet decided or not yet run fills only a few."""
    out = {"task": r["task"], "noise / budget": f"{r['noise']:g} / {r['budget']}", "paper: PEBBLE": f"{r['paper'][0]:.2f}",
           "paper: R2N-PEBBLE": f"{r['paper'][1]:.2f}", "paper's gain": percent(r["paper_gain"])}
    plan = r["plan"]
    if plan is None:
        out["ours: PEBBLE"] = "pilot under way"
        return out
    kind = "powered, the stored-noise study's" if r["task"] == "cheetah-run" else plan["kind"]
    if "arms" not in r:
        out["ours: PEBBLE"] = f"{r['runs_in']} of {2 * plan['n']} runs in"
        out["test"] = f"{kind}, {plan['n']} seeds per arm"
        return out
    (pm, ps), (rm, rs) = (analyze.mean_se(r["arms"][m]) for m in METHODS)
    n = len(r["arms"][METHODS[0]])
    holm_p = f" ({analyze.p_text(r['holm'])})" if "holm" in r else ""
    out.update({"ours: PEBBLE": f"{pm:.1f} ± {ps:.1f} ({n})", "ours: R2N-PEBBLE": f"{rm:.1f} ± {rs:.1f} ({n})",
                "difference [95% CI]": f"{rm - pm:+.1f} [{r['ci'][0]:+.1f}, {r['ci'][1]:+.1f}]",
                "our gain": percent(rm / pm - 1), "Welch p (Holm)": f"{analyze.p_text(r['welch'])}{holm_p}",
                "permutation p": analyze.p_text(r["permutation"]),
                "power achieved": f"{r['power']:.2f} (for {plan['effect']:+.1f})",
                "hours per run (PEBBLE / R2N-PEBBLE)": " / ".join(f"{r['hours'][m]:.1f}" for m in METHODS),
                "test": kind})
    return out


def markdown_row(values) -> str:
    return "|" + "|".join(f" {v} " if v else " " for v in values) + "|"


def table_lines(out: list, columns: tuple = COLUMNS) -> list:
    """A markdown table of the rows, in the given columns."""
    return ([markdown_row(columns), "|" + "---|" * len(columns)]
            + [markdown_row(cells(r).get(c) for c in columns) for r in out])


def arm_curve(curves: list) -> tuple:
    """An arm's (steps, mean, SE) over its runs' evaluation curves, as `analyze.py`'s: a run stopped by a non-finite
    value counts with the evaluations it reached and does not shorten the others."""
    steps = max((c[0] for c in curves), key=len)
    values = np.full((len(curves), len(steps)), np.nan)
    for row, (_, returns) in zip(values, curves):
        row[: len(returns)] = np.where(np.isfinite(returns), returns, np.nan)
    with warnings.catch_warnings():  # a step that one run reached alone has no SE
        warnings.simplefilter("ignore", RuntimeWarning)
        se = np.nanstd(values, axis=0, ddof=1) / np.sqrt(np.isfinite(values).sum(axis=0))
    return steps, np.nanmean(values, axis=0), se


def write_curves(out: list, path: str):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(out), figsize=(4 * len(out), 3.4), squeeze=False)
    for ax, r in zip(axes[0], out):
        ax.set_title(f"{r['task']} {r['noise']:g}/{r['budget']}", fontsize=10)
        ax.set_xlabel("steps")
        if "curves" not in r:
            ax.text(0.5, 0.5, "pending", ha="center", va="center", transform=ax.transAxes)
            continue
        for method, colour in zip(METHODS, ("tab:blue", "tab:red")):
            steps, mean, se = arm_curve(r["curves"][method])
            ax.plot(steps, mean, color=colour, label=f"{method} ({len(r['curves'][method])})")
            ax.fill_between(steps, mean - se, mean + se, color=colour, alpha=0.2)
        ax.legend(fontsize=7)
    axes[0][0].set_ylabel("evaluation return (mean ± SE)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)


def readme_with(path: str, markers: tuple, block: list) -> str:
    """The file's text with its table block replaced."""
    text = open(path).read()
    start, end = text.index(markers[0]), text.index(markers[1])
    return text[: start + len(markers[0])] + "\n" + "\n".join(block) + "\n" + text[end:]


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="compare with the committed table.md and README blocks")
    out = rows()
    block = table_lines(out)
    texts = {os.path.join(STUDY, "table.md"): "\n".join(block) + "\n",
             README: readme_with(README, MARKERS, block),
             ROOT_README: readme_with(ROOT_README, ROOT_MARKERS, table_lines(out, SHORT))}
    if parser.parse_args().check:
        stale = [path for path, text in texts.items() if not os.path.exists(path) or open(path).read() != text]
        if stale:
            raise SystemExit(f"not what the runs give: {', '.join(map(os.path.relpath, stale))}; "
                             "regenerate with python results/stored-table/table.py")
        print("table.md and the README blocks are what the runs give")
        return
    for path, text in texts.items():
        with open(path, "w") as f:
            f.write(text)
    write_curves(out, os.path.join(STUDY, "curves.png"))
    print("\n".join(block))


if __name__ == "__main__":
    main()
