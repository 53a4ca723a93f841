"""`--teacher external`: a run's queries and labels through files, the protocol of the labelling page (docs/labelling.md).
The run writes `queries/{round}.npz` and `teacher.json`; a person (`label_app.py`) or a program writes
`labels/{round}.json`."""
import hashlib
import io
import json
import math
import os
import socket
import time
from typing import Optional

import numpy as np
import torch


class ExternalTeacher:
    """`--teacher external` (docs/labelling.md): queries go to `queries/{round}.npz`, labels come
    from `labels/{round}.json`: a JSON list with, per query, 1 (second segment preferred), 0 (the
    first), 0.5 (equal) or "skip". The run reads a round's file once it is valid and records its
    SHA-256. A resume checks that the files it trained on are unchanged (`check_labels_unchanged`).
    `teacher.json` tells the labelling page what the run does: waiting for a round (rewritten every
    poll), training (step rewritten every `step_seconds`), finished or stopped."""

    step_seconds = 2.0  # while training, teacher.json's step is rewritten at most this often
                        # (the page polls every 2 s)

    def __init__(self, folder: str, args, stop_signals: list, stopped: type, poll_seconds: float = 1.0):
        """`stopped`: the script's exception that ends the run once its state is saved, raised at a stop signal."""
        self.folder, self.stop_signals, self.poll_seconds = folder, stop_signals, poll_seconds
        self.stopped = stopped
        self.run = dict(task=args.env_id, run=os.path.basename(folder), pid=os.getpid(),
                        host=socket.gethostname(), budget=args.max_feedback,
                        total_steps=args.total_timesteps)
        # the last status written; when the step was (training seconds)
        self.status, self.told = None, -math.inf

    def nap(self):
        """Sleep `poll_seconds`, or until a stop signal. Python resumes a sleep after the signal's
        handler, so the wait sleeps in short naps to end at once."""
        until = time.monotonic() + self.poll_seconds
        while not self.stop_signals and time.monotonic() < until:
            time.sleep(0.05)

    def tell(self, phase: str, step: int, asked: int, labelled: int, round_index=None, queries=None,
             message=None, digest=None):
        """Write `teacher.json`: what the labelling page shows. While waiting, `digest` names the
        queries this run wrote for the round: the page takes answers to those only."""
        self.write(dict(self.run, phase=phase, round=round_index, queries=queries, digest=digest,
                        asked=asked, labelled=labelled, step=step, message=message))

    def training(self, step: int, seconds: float):
        """Called every step (`Run.step_starts`). While the run trains after a round, `teacher.json`
        says the current step, rewritten every `step_seconds` of training (`seconds`) at most."""
        if (self.status is None or self.status["phase"] != "training"
                or seconds - self.told < self.step_seconds):
            return
        self.told = seconds
        self.write(dict(self.status, step=step))

    def write(self, status: dict):
        """Write `status` as `teacher.json`, atomically, with the time of writing."""
        self.status = dict(status, updated=time.time())
        with open(f"{self.folder}/teacher.json.tmp", "w") as f:
            json.dump(self.status, f)
        os.replace(f"{self.folder}/teacher.json.tmp", f"{self.folder}/teacher.json")

    def ask(self, round_index: int, env_id: str, obs_dim: int, segments: torch.Tensor,
            true_rewards: torch.Tensor, physics: np.ndarray, step: int, asked: int,
            labelled: int) -> tuple:
        """Write the round's queries, then wait for a valid labels file that answers them. A malformed
        one gets one line (and the page's notice), and the wait goes on. So does a valid one for other
        queries (its digest is not theirs): it is moved aside, never deleted, and the round is asked
        again. The queries file is known by its bytes: one that differs from what the run wrote, or
        is gone, is said at once and written again; a folder in its place is said once (and on the
        page), and the queries are written when it is moved. A bare list of answers names no
        queries: it is read only at a look that finds the run's own queries file in place, else moved
        aside too. Both files are read by their content at every poll, not by their time stamps.
        Returns the answered pairs' mask and labels (0 where skipped), both on the segments' device,
        the labels file's SHA-256 and the seconds waited. A stop signal raises `stopped`: the state
        written before the round resumes into it."""
        rows = segments.cpu().numpy()
        queries_file = f"{self.folder}/queries/{round_index}.npz"
        written = npz_bytes(env_id=env_id, obs=rows[..., :obs_dim], actions=rows[..., obs_dim:],
                            physics=physics, true_rewards=true_rewards.cpu().numpy())
        if not os.path.isdir(queries_file):  # a folder there is said in the wait below
            write_bytes(queries_file, written)
        digest = queries_digest(env_id, physics)
        path, n, started, seen, problem = (
            f"{self.folder}/labels/{round_index}.json", len(rows), time.monotonic(), None, None
        )
        print(f"waiting for labels: {path}, one per query of {queries_file} (digest {digest}; by "
              f"hand: python label_app.py {self.folder})", flush=True)
        while True:
            if self.stop_signals:
                import gc

                gc.freeze()  # run ends; exit skips collecting torch's and the run's objects (1 s+)
                raise self.stopped(f"stopped by {self.stop_signals[0]} while waiting for {path}; "
                                   f"the state before this round is saved: run the same command "
                                   f"with --run-name {self.run['run']} to resume")
            # By its bytes, not its time stamp: another write may land between a write and a stat,
            # or within one tick of it.
            own = read_bytes(queries_file) == written
            if not own and os.path.isdir(queries_file):  # cannot be replaced: said once, and on the page
                notice = (f"queries: {queries_file}: a folder, not a file: move it; this run writes "
                          f"round {round_index}'s queries there")
                if notice != problem:
                    print(notice, flush=True)
                problem, seen = notice, False  # the labels are looked at again once it is moved
                self.tell("waiting", step, asked, labelled, round_index, n, problem, digest)
                self.nap()
                continue
            if not own:
                print(f"queries: {queries_file} is no longer the file this run wrote for round "
                      f"{round_index} (digest {digest}); writing it again", flush=True)
                write_bytes(queries_file, written)
            content = read_bytes(path)
            if content != seen:
                seen = content
                problem = ("a folder, not a file: move it" if os.path.isdir(path)
                           else None if content is None else labels_problem(content, n))
                if content is not None and problem is None:
                    answered = parse_labels(content)[1]
                    if answered == digest or answered is None and own:
                        break
                    # A bare list seen while other queries were in the file may answer those.
                    problem = (f"answers the queries of digest {answered}, not this round's "
                               f"({digest}); kept as {move_aside(path, 'mismatch')}"
                               if answered is not None else
                               f"a bare list, which names no queries, came while {queries_file} "
                               f"was not the file this run wrote: it may answer those; kept as "
                               f"{move_aside(path, 'unbound')}")
                    seen = None
                if problem is not None:
                    problem = f"labels: {path}: {problem}; waiting for labels of {queries_file}"
                    print(problem, flush=True)
            self.tell("waiting", step, asked, labelled, round_index, n, problem, digest)
            self.nap()
        answers = np.array([np.nan if a == "skip" else a for a in parse_labels(content)[0]],
                           np.float32)
        keep, labels = (torch.as_tensor(~np.isnan(answers)),
                        torch.nan_to_num(torch.as_tensor(answers)))
        self.tell("training", step, asked + n, labelled + int(keep.sum()))
        sha256 = hashlib.sha256(content).hexdigest()
        return (keep.to(segments.device), labels.to(segments.device), sha256,
                time.monotonic() - started)


def queries_digest(env_id: str, physics: np.ndarray) -> str:
    """The digest of a round's queries: of the task and the physics states the page draws (the same
    rule as label_app.parse_queries). A labels file names the digest of the queries it answers."""
    header = f"{env_id} {physics.dtype} {physics.shape}".encode()
    return hashlib.sha256(header + np.ascontiguousarray(physics).tobytes()).hexdigest()[:16]


def npz_bytes(**arrays) -> bytes:
    """The bytes of `np.savez(arrays)`: the run keeps them to know its queries file by."""
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    return buffer.getvalue()


def write_bytes(path: str, content: bytes):
    """Write `content` to a temporary file, then rename it to `path`: a reader sees the old file or
    the whole new one."""
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(f"{path}.tmp", "wb") as f:
        f.write(content)
    os.replace(f"{path}.tmp", path)


def file_digest(path: str) -> Optional[str]:
    """The queries digest of a queries file, or None if it is missing or not one."""
    try:
        with np.load(path) as data:
            return queries_digest(str(data["env_id"]), data["physics"])
    except Exception:  # missing, half a file, another format: not the queries this run wrote
        return None


def read_bytes(path: str) -> Optional[bytes]:
    """A file's bytes; None if there is none (a folder in its place: empty)."""
    if os.path.isdir(path):
        return b""
    try:
        with open(path, "rb") as f:
            return f.read()
    except FileNotFoundError:
        return None


def move_aside(path: str, why: str) -> str:
    """Move `path` to a free `{path}.{why}-{unix time}[-k]` (reserved by creating it exclusively,
    so that no earlier file is replaced) and return that name: nothing a person wrote is deleted."""
    stamp, k = int(time.time()), 1
    while True:
        aside = f"{path}.{why}-{stamp}" + (f"-{k}" if k > 1 else "")
        try:
            os.close(os.open(aside, os.O_CREAT | os.O_EXCL | os.O_WRONLY))
            break
        except FileExistsError:
            k += 1
    os.replace(path, aside)
    return aside


def check_labels_unchanged(folder: str, queries: dict):
    """On resume (`queries`: the saved `QueryLog`): every labels file the run trained on still holds
    what it read, or a ValueError says which."""
    for round_index, recorded in enumerate(queries.get("label_sha256", [])):
        path = f"{folder}/labels/{round_index}.json"
        if recorded and file_sha256(path) != recorded:
            raise ValueError(f"{path} is not the labels file this run trained on (SHA-256 "
                             f"{recorded[:12]}...); put it back as it was (the run's "
                             f"preferences/{round_index}.npz holds its labels)")


LABEL_NUMBERS = {"0": 0, "1": 1, "0.5": 0.5}  # exactly these spellings: not 1.0, 1e0, -0 or 0.50
DIGEST_CHARACTERS = frozenset("0123456789abcdef")


def parse_labels(content: bytes) -> tuple:
    """(answers, queries digest or None) of a labels file's bytes: `{"queries": digest, "answers":
    [...]}` (what the labelling page writes), or a bare list of answers (unbound: nothing says which
    queries it answers). Any other number than 0, 1 and 0.5 reads as None. ValueError if not JSON."""
    number = LABEL_NUMBERS.get  # any other number becomes None, which is no label
    try:
        labels = json.loads(content, parse_int=number, parse_float=number, parse_constant=number)
    except RecursionError:
        raise ValueError("not JSON (RecursionError)") from None
    if isinstance(labels, dict) and set(labels) == {"queries", "answers"}:
        digest = labels["queries"]
        return labels["answers"], digest if isinstance(digest, str) else ""  # "": no digest, refused
    return labels, None


def labels_problem(content: bytes, n: int) -> Optional[str]:
    """Why a labels file's bytes are not n valid answers, or None. Valid: a JSON list, each exactly
    0, 1, 0.5 or "skip", alone or as `{"queries": digest, "answers": list}` with a digest of 16 hex
    digits. The labelling page checks by the same rule (label_app.parse_labels)."""
    try:
        answers, digest = parse_labels(content)
    except ValueError as e:  # JSONDecodeError, UnicodeDecodeError: ValueErrors
        return f"not JSON ({type(e).__name__})"
    if digest is not None and not (len(digest) == 16 and set(digest) <= DIGEST_CHARACTERS):
        return "its \"queries\" is not a digest of 16 hex digits"
    # true and false are bools, which Python counts as 1 and 0
    if not isinstance(answers, list) or len(answers) != n or any(
            isinstance(a, bool) or a not in (0, 1, 0.5, "skip") for a in answers):
        return f'expected a list of {n} answers, each 0, 1, 0.5 or "skip"'
    return None


def file_sha256(path: str) -> Optional[str]:
    if not os.path.isfile(path):  # a folder in the file's place reads as a missing file
        return None
    with open(path, "rb") as f:
        return hashlib.sha256(f.read()).hexdigest()
