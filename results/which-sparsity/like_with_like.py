"""Does today's code compute what e6130f6 computed? Two runs of each reference arm, one per commit, on one machine.

    python results/which-sparsity/like_with_like.py   # reads like-with-like/{e6130f6,today}/{arm}/

Each arm ran the stored-noise preset's command for seed 1 at both commits, side by side on one machine, and was
stopped with SIGTERM after its first feedback rounds. Compared, over the steps both runs reached:
- every scalar both event files logged (the losses, the evaluation, the reward's training), bit for bit, but the
  wall-clock ones;
- every queried pair's observations, actions, true rewards, physics states and label (the query log), bit for bit.
The query log moved from one file (`preferences.npz`) to one file per round (`preferences/{k}.npz`) between the
commits; the rounds both wrote are compared.
"""
import glob
import hashlib
import json
import os
import sys

import numpy as np

STUDY = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(STUDY, "..", ".."))
import analyze  # noqa: E402 (the repository's: its run reading)

FOLDER = os.path.join(STUDY, "like-with-like")
ARMS = ("pebble_stored_noise", "r2n_pebble_stored_noise")
WALL_CLOCK = ("charts/SPS", "charts/eval_seconds", "charts/wall_seconds")  # differ run to run by design
ARRAYS = ("obs", "actions", "true_rewards", "physics", "labels", "steps")


def scalars(run_dir: str) -> dict:
    [run] = analyze.read_folder(sorted(glob.glob(os.path.join(run_dir, "events.out.tfevents.*"))))
    return run.scalars


def query_digests(run_dir: str) -> dict:
    """round -> the sha256 of each array of its queried pairs, from the run's query log, kept in `queries.json` (the
    logs themselves, 5-7 MB a run, are not committed)."""
    kept = os.path.join(run_dir, "queries.json")
    if os.path.exists(kept):
        return {int(r): d for r, d in json.load(open(kept)).items()}
    one = os.path.join(run_dir, "preferences.npz")
    if os.path.exists(one):
        data = np.load(one)
        rounds = {int(r): {k: data[k][data["rounds"] == r] for k in ARRAYS} for r in np.unique(data["rounds"])}
    else:
        rounds = {int(os.path.basename(p)[:-4]): dict(np.load(p)) for p in glob.glob(os.path.join(run_dir, "preferences", "*.npz"))}
    digests = {r: {k: hashlib.sha256(np.ascontiguousarray(arrays[k]).tobytes()).hexdigest() for k in ARRAYS}
               | {"pairs": len(arrays["labels"])} for r, arrays in sorted(rounds.items())}
    json.dump(digests, open(kept, "w"), indent=1)
    return digests


def compare(arm: str) -> tuple:
    """(text, same): the comparison of one arm's two runs."""
    old, new = (os.path.join(FOLDER, commit, arm) for commit in ("e6130f6", "today"))
    a, b = scalars(old), scalars(new)
    # the steps both runs reached (each was stopped at its own step), the wall-clock tags left out
    last = min(max(steps[-1] for steps, _ in run.values()) for run in (a, b))
    tags = sorted(t for t in set(a) & set(b) if t not in WALL_CLOCK)
    points, differ = 0, []
    for tag in tags:
        (sa, va), (sb, vb) = a[tag], b[tag]
        keep_a, keep_b = sa <= last, sb <= last
        if not np.array_equal(sa[keep_a], sb[keep_b]) or not np.array_equal(va[keep_a], vb[keep_b]):
            differ.append(tag)
        points += int(keep_a.sum())
    qa, qb = query_digests(old), query_digests(new)
    common = sorted(set(qa) & set(qb))
    pairs = sum(qa[r]["pairs"] for r in common)
    differing_rounds = [r for r in common if qa[r] != qb[r]]
    evaluation = a[analyze.EVAL_TAG][1][a[analyze.EVAL_TAG][0] <= last]
    text = (f"{arm}: {len(tags)} tags logged by both up to step {last}, {points} values: "
            f"{len(differ)} tags differ{' (' + ', '.join(differ) + ')' if differ else ''}; "
            f"{len(common)} feedback rounds in both query logs ({pairs} pairs): {len(differing_rounds)} differ; "
            f"evaluation at step 10 000 {', '.join(f'{v:.2f}' for v in evaluation)}")
    only = sorted(set(a) ^ set(b))
    if only:
        text += f"; logged by one commit only, not compared: {', '.join(only)}"
    return text, not differ and not differing_rounds and points > 0 and len(common) > 0


if __name__ == "__main__":
    results = [compare(arm) for arm in ARMS]
    for text, _ in results:
        print(text)
    same = all(ok for _, ok in results)
    print("today's code computes what e6130f6 computed, bit for bit, over these steps" if same else "THE COMMITS DIFFER")
    raise SystemExit(0 if same else 1)
