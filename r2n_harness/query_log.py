"""`--query-log`: every query a run asks, in `runs/{run_name}/preferences/`, one `.npz` a round
(docs/labelling.md). `--preferences` reads it back as a later run's first labelled pairs, and
the labelling page shows it. `--teacher external` turns it on: a person's labels are bound to
the queries they saw."""
import os

import numpy as np


def write_npz(path: str, **arrays):
    """`np.savez` to a temp file, then rename: no reader sees half a file; a kill keeps the last."""
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(f"{path}.tmp", "wb") as f:
        np.savez(f, **arrays)
    os.replace(f"{path}.tmp", path)


class QueryLog:
    """Every query asked so far, on the host: both segments' [obs, action] rows (noise included),
    true rewards and physics states, the label (NaN: skipped), the round (-1: `--preferences`), the
    env step. Per round, the SHA-256 of its labels file (`--teacher external`; else empty). The
    run's folder `preferences/` holds it too, one file per round (`read_preferences` joins them)."""

    def __init__(self, segment_steps: int, input_dim: int, physics_dim: int):
        self.inputs = np.zeros((0, 2, segment_steps, input_dim), np.float32)
        self.true_rewards = np.zeros((0, 2, segment_steps), np.float32)
        self.physics = np.zeros((0, 2, segment_steps, physics_dim))
        self.labels, self.rounds, self.steps = (
            np.zeros(0, np.float32), np.zeros(0, np.int64), np.zeros(0, np.int64)
        )
        self.label_sha256 = np.zeros(0, "<U64")  # indexed by round

    @property
    def next_round(self) -> int:
        return int(self.rounds.max(initial=-1)) + 1

    def add(self, inputs, true_rewards, physics, labels, round_index: int, step: int,
            label_sha256: str = ""):
        new = dict(inputs=inputs, true_rewards=true_rewards, physics=physics, labels=labels,
                   rounds=np.full(len(labels), round_index), steps=np.full(len(labels), step))
        for name, value in new.items():
            setattr(self, name, np.concatenate([getattr(self, name),
                                                np.asarray(value, getattr(self, name).dtype)]))
        if round_index >= 0:  # padded: older states (no SHA-256 kept) resume with none per round
            self.label_sha256 = np.concatenate([
                self.label_sha256, np.full(round_index - len(self.label_sha256), ""), [label_sha256]
            ]).astype("<U64")

    def save_round(self, folder: str, env_id: str, obs_dim: int, round_index: int):
        """Write one round's queries to `{folder}/{round}.npz` (from `--preferences`: `seeded.npz`).
        Each round has its own file: it writes its own queries, not the whole log again."""
        rows = self.rounds == round_index
        inputs = self.inputs[rows]
        sha256 = (self.label_sha256[round_index:round_index + 1] if round_index >= 0
                  else self.label_sha256[:0])
        name = round_index if round_index >= 0 else "seeded"
        write_npz(f"{folder}/{name}.npz", env_id=env_id, obs=inputs[..., :obs_dim],
                  actions=inputs[..., obs_dim:], true_rewards=self.true_rewards[rows],
                  physics=self.physics[rows], labels=self.labels[rows], rounds=self.rounds[rows],
                  steps=self.steps[rows], label_sha256=sha256)


def log_queries(queries: QueryLog, folder: str, env_id: str, obs_dim: int,
                segments, true_rewards, physics: np.ndarray,
                labels, step: int, sha256: str):
    """Add a round's queries to the run's query log and write them to `{folder}/{round}.npz`.
    Labels are NaN where skipped."""
    round_index = queries.next_round
    queries.add(segments.cpu().numpy(), true_rewards.cpu().numpy(), physics, labels.cpu().numpy(),
                round_index, step, sha256)
    queries.save_round(folder, env_id, obs_dim, round_index)
