# docs and usage: docs/labelling.md
"""A local web page for labelling the queries of a run started with `--teacher external`, by hand.

    python label_app.py runs/RUN_NAME            # then open http://localhost:8000

It shows the pending round's queries one at a time: the two segments as clips, side by side, rendered with MuJoCo's
offscreen renderer from the physics states stored with each query. The answer is left, right, equal or skip, by
mouse or keyboard (arrow keys, `=`/space, `s` or `S`; a key with Ctrl, Alt or Meta is the browser's, never an
answer; Enter or Space on a focused button presses that button); the answer buttons and keys wait until both clips
of the query have loaded and been shown for a second (the next query's clips are fetched ahead; a line says while
they are drawn, and why one did not load: the app's own sentence, or that it does not answer), and a key held down
answers once. Backspace or "undo" takes back the last answer; after the last query "submit round r" (or Enter)
writes `labels/{round}.json`, which the run is waiting for, and the page waits for the next round. Standard library
only (plus the project's numpy, imageio and dm_control): the training scripts need no web dependency.

Clips are rendered once and kept in memory by the digest of the queries they show, so a run folder used again (new
queries under old round numbers) gets new clips; beyond `--clip-cache-mb` the least recently shown are dropped. The
page asks for the state every 2 s; the app then reads only the files that have changed (by inode, size and mtime).

Labels you can trust:
- A round's labels file is written once. The app writes a temporary file, fsyncs it, then hard-links it to
  `labels/{round}.json`, which fails if that file exists: a valid labels file (a JSON list of one answer per query,
  each exactly 0, 1, 0.5 or "skip", the rule the run reads by, with the digest of the queries it answers: the page
  sends it) is final, and a second answer to its round (another tab, another app, a script) gets HTTP 409 and
  changes nothing. So do answers to other queries than the round's: those the run wrote while it waits for the
  round (its `teacher.json` names their digest; another file may lie in their place for a moment, until the run
  writes its own again), else those of the round's file (`round_queries`). Answers that name no queries get HTTP
  400: the run would take them for whatever queries it holds. It gets the mode of the run's other files (0666 less
  the umask).
- A person's answers live in the page until the app says they are saved: the tab keeps them (sessionStorage: each
  tab its own, by run and round, for the round's queries only), so a reload or a failed submit (HTTP 500, the app
  gone) loses none, and the page says what failed; a closed tab keeps them only if the browser reopens it
  ("reopen closed tab"). A 200 drops them, and so does a 409 for a round already answered; a round answered
  elsewhere or new queries for the round (which the page notices within a poll, 2 s) drop them once the page has
  said so. Any other refusal keeps them, as a failed submit does; the state, asked at once, then says whether the
  round still waits for the queries they answer. A round the page saved that waits again (the run set its labels
  aside) is said so, not left as "saved".
- The tabs of one browser tell each other (BroadcastChannel) which round they answer and their answers so far: a
  tab shows at once that another tab is answering its round, with that tab's answers, before effort is spent twice.
- Only the page's own origin can write labels. Every request must name the app's address in its Host header (a
  name of someone else's that resolves to this machine, DNS rebinding, gets 403); a POST with an Origin header must
  come from the page's own origin (else 403) and send `Content-Type: application/json` (else 415), which a page of
  another origin can send only after a CORS preflight, which gets 405.
- A malformed labels file leaves its round pending; the page shows why it is not valid, and submitting the round's
  answers moves it aside to `labels/{round}.json.rejected-{unix time}` (nothing a person wrote is deleted). A labels
  file that cannot be read at all (a folder at `labels/{round}.json`) is a notice saying what to do; a submit gets
  HTTP 500 and the same sentence, and the page keeps the answers.
- The page tells the run's state from the run's `teacher.json` when there is one (task, labels so far, training at
  step s, finished, stopped, and "not responding": a run waiting with no news for 15 s, or a run of this machine
  whose process has gone), else from the run's files alone, with one line saying why when it cannot read it (a
  NaN or Infinity in it too: `/api/state` is always strict JSON).
- A bad request gets its HTTP code and one line (404, 400, 403, 405 for methods other than GET, HEAD and POST, 413
  above 64 KiB, 415), never a traceback, and the app serves on; a port in use is one line on stderr and exit code 1.

The pending round is the lowest round with queries (`queries/{round}.npz`) and no valid labels file for its queries
(`round_queries`); a round's number is written as the run writes it (`00` is no round). The app reads `teacher.json`
(keys task, run, pid, host, phase, round, queries, digest, asked, labelled, budget, step, total_steps, message,
updated; written by the run; an older run's has no digest) but never writes it.

It binds to localhost. On a remote machine, forward the port: `ssh -L 8000:localhost:8000 host`, then open
http://localhost:8000 on your own (the Host check takes any port: a tunnel may forward another one). Without a
display MuJoCo needs `MUJOCO_GL=egl` (GPU or Mesa) or `MUJOCO_GL=osmesa` (software); the app sets `egl` when
neither `MUJOCO_GL` nor `DISPLAY` is set. For tests only, `R2N_LABEL_APP_CLIP_DELAY=SECONDS` delays every clip, so
that a test sees the page before the clips have loaded, and `R2N_LABEL_APP_STATE_DELAY=SECONDS` every state reply
once the state is read, so that a test sees a state that a submit has made stale.
"""
import errno
import glob
import hashlib
import io
import ipaddress
import json
import os
import re
import secrets
import socket
import sys
import threading
import time
from collections import OrderedDict
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Optional
from urllib.parse import parse_qs, urlsplit

import numpy as np
import tyro

if "MUJOCO_GL" not in os.environ and "DISPLAY" not in os.environ:
    os.environ["MUJOCO_GL"] = "egl"  # before dm_control is imported (by ene.render_states)

import ene  # noqa: E402

MAX_BODY = 64 * 1024  # bytes of a POST: a round's answers take a few KiB at most
SILENT_SECONDS = 15  # a waiting run rewrites teacher.json every ~2 s: this long without news, it is not responding
CLIP_DELAY = float(os.environ.get("R2N_LABEL_APP_CLIP_DELAY", "0"))  # tests only: see the module docstring
STATE_DELAY = float(os.environ.get("R2N_LABEL_APP_STATE_DELAY", "0"))  # tests only: see the module docstring


@dataclass
class Args:
    run_dir: tyro.conf.Positional[str]
    """the run folder of a `--teacher external` run, e.g. `runs/cartpole-swingup__pebble__1__1700000000`"""
    port: int = 8000
    """the port of the page"""
    host: str = "127.0.0.1"
    """the address to bind; the default serves this machine only (use an SSH tunnel from elsewhere)"""
    fps: int = 25
    """frames per second of the clips"""
    clip_cache_mb: float = 256
    """megabytes of rendered clips kept in memory (a cartpole clip takes about 0.33 MB at 20 steps, 0.9 MB at 50), the
    least recently shown dropped first; a dropped clip is rendered again when asked for"""


class Refused(Exception):
    """A request answered with an HTTP error `code` and one sentence."""

    def __init__(self, code: int, sentence: str):
        super().__init__(sentence)
        self.code = code


ROUND = r"(0|[1-9][0-9]*)"  # a round's number as the run writes it: each round has one name, so 00 is no round


def rounds(run_dir: str) -> list:
    """The rounds with queries, in order."""
    return sorted(int(m.group(1)) for path in glob.glob(os.path.join(run_dir, "queries", "*.npz"))
                  if (m := re.fullmatch(ROUND + r"\.npz", os.path.basename(path))))


class ReadOnChange:
    """What `make` makes of a file's bytes, kept by path and made again only when the file changes (its inode, size,
    mtime or ctime): the page asks for the state every 2 s, and then reads no file that has not changed, so a poll
    costs a stat per round however long the run. The run replaces its files (a new inode); a file edited in place
    gets a new mtime."""

    def __init__(self, make):
        self.make, self.kept, self.lock = make, {}, threading.Lock()

    def __call__(self, path: str):
        seen = stamp(os.stat(path))  # FileNotFoundError if there is none
        with self.lock:
            kept = self.kept.get(path)
        if kept is not None and kept[0] == seen:
            return kept[1]
        with open(path, "rb") as f:  # IsADirectoryError for a folder
            seen = stamp(os.fstat(f.fileno()))  # of the bytes read: the file may have changed since the stat
            made = self.make(f.read())
        with self.lock:
            self.kept[path] = seen, made
        return made


def stamp(stat: os.stat_result) -> tuple:
    return stat.st_dev, stat.st_ino, stat.st_size, stat.st_mtime_ns, stat.st_ctime_ns


@dataclass(frozen=True)
class Queries:
    env_id: str
    n: int  # the number of queries
    digest: str  # of the task and the physics states: the same queries, the same digest (a resumed run rewrites its
                 # file with other bytes, the same queries); a clip is kept, and the page keeps answers, by it


def parse_queries(content: bytes) -> tuple:
    """The Queries of a queries file's bytes, and their physics states (n, 2, T, D)."""
    with np.load(io.BytesIO(content)) as data:
        env_id, physics = str(data["env_id"]), data["physics"]
    digest = hashlib.sha256(f"{env_id} {physics.dtype} {physics.shape}".encode() + physics.tobytes()).hexdigest()
    return Queries(env_id, len(physics), digest[:16]), physics


QUERIES = ReadOnChange(lambda content: parse_queries(content)[0])  # not the physics: a few MB a round


def queries_path(run_dir: str, round_index: int) -> str:
    return os.path.join(run_dir, "queries", f"{round_index}.npz")


def read_queries(run_dir: str, round_index: int) -> Queries:
    """A round's Queries, read only when its file has changed; Refused(404) if the round has none."""
    try:
        return QUERIES(queries_path(run_dir, round_index))
    except FileNotFoundError:
        raise Refused(404, f"round {round_index} has no queries (queries/{round_index}.npz)") from None


def load_queries(run_dir: str, round_index: int) -> tuple:
    """A round's Queries and physics states, read now; Refused(404) if the round has none."""
    try:
        with open(queries_path(run_dir, round_index), "rb") as f:
            return parse_queries(f.read())
    except FileNotFoundError:
        raise Refused(404, f"round {round_index} has no queries (queries/{round_index}.npz)") from None


def labels_path(run_dir: str, round_index: int) -> str:
    return os.path.join(run_dir, "labels", f"{round_index}.json")


LABEL_NUMBERS = {"0": 0, "1": 1, "0.5": 0.5}  # a number is a label only written exactly so: not 1.0, 1e0, -0 or 0.50


def parse_labels(text: bytes, n: int) -> tuple:
    """(answers, digest) of `text` if it holds valid labels for a round of n queries, by the rule the run reads by:
    `{"queries": digest, "answers": list}`, the digest (16 hex digits) naming the queries answered, or a bare list
    (unbound: digest None); n answers, each exactly 0, 1, 0.5 or "skip". Else ValueError, one line saying why."""
    number = LABEL_NUMBERS.get  # any other number becomes None, which is no label
    try:
        answers = json.loads(text, parse_int=number, parse_float=number, parse_constant=number)
    except RecursionError:  # json gives up on deep nesting this way
        raise ValueError("not JSON: nested too deeply") from None
    except ValueError as e:  # JSONDecodeError, UnicodeDecodeError
        raise ValueError(f"not JSON: {e}") from None
    digest = None
    if isinstance(answers, dict) and set(answers) == {"queries", "answers"}:
        answers, digest = answers["answers"], answers["queries"]
        if not (isinstance(digest, str) and re.fullmatch(r"[0-9a-f]{16}", digest)):
            raise ValueError('its "queries" is not a digest of 16 hex digits')
    # true and false are bools, which Python counts as 1 and 0
    if not isinstance(answers, list) or len(answers) != n or any(
            isinstance(a, bool) or a not in (0, 1, 0.5, "skip") for a in answers):
        raise ValueError(f'expected a list of {n} answers, each 0, 1, 0.5 or "skip"')
    return answers, digest


def parse_answers(text: bytes, n: int) -> list:
    """The answers of `parse_labels`."""
    return parse_labels(text, n)[0]


def read_labels(path: str, n: int) -> tuple:
    """(answers, digest) of the labels file `path` for a round of n queries: ValueError if it is not valid,
    FileNotFoundError if there is none, another OSError (IsADirectoryError) if it cannot be read."""
    with open(path, "rb") as f:
        return parse_labels(f.read(), n)


def answering(digest: Optional[str], queries_digest: str) -> Optional[str]:
    """Why labels of `digest` do not answer the queries of `queries_digest`, or None (an unbound file: None)."""
    if digest is None or digest == queries_digest:
        return None
    return (f"it answers the queries of digest {digest}, not this round's ({queries_digest}): the queries file was "
            "replaced after they were shown")


LABEL_FILES = ReadOnChange(bytes)  # a labels file's bytes, for the state; a writer reads the file itself, now


def unreadable(round_index: int, error: OSError) -> str:
    """What a person does about a labels file that neither the run nor the app can read (a folder, say)."""
    name = f"labels/{round_index}.json"
    what = "is a folder, not a file" if isinstance(error, IsADirectoryError) else f"cannot be read ({error.strerror})"
    return (f"{name} {what}: the run cannot read round {round_index}'s labels from it, nor can this page write them; "
            f"move it away (mv {name} {name}.moved), then submit round {round_index}")


def is_valid(path: str, n: int, queries_digest: Optional[str] = None) -> bool:
    """Whether `path` holds valid labels for n queries and, given `queries_digest`, for those queries."""
    try:
        _, digest = read_labels(path, n)
    except (FileNotFoundError, ValueError):
        return False
    return queries_digest is None or answering(digest, queries_digest) is None


def reserve_rejected_name(path: str) -> str:
    """A free name `{path}.rejected-{unix time}[-k]`, reserved by creating it empty and exclusively: renaming onto a
    name that only looked free could delete an earlier rejected file, if another process took it in between."""
    stamp, k = int(time.time()), 1
    while True:
        rejected = f"{path}.rejected-{stamp}" + (f"-{k}" if k > 1 else "")
        try:
            os.close(os.open(rejected, os.O_CREAT | os.O_EXCL | os.O_WRONLY))
            return rejected
        except FileExistsError:
            k += 1


def keeps_existing(path: str, n: int, queries_digest: Optional[str] = None) -> bool:
    """True if the labels file at `path` is the round's answer (valid, for these queries: final). Else False, and
    `path` is free for the caller's answers: a malformed file, or one for other queries, has been moved aside to
    `{path}.rejected-{unix time}` (whole and atomically: nothing a person wrote is deleted), or it had gone."""
    if is_valid(path, n, queries_digest=queries_digest):
        return True
    rejected = reserve_rejected_name(path)
    try:
        os.rename(path, rejected)  # replaces only the empty placeholder that reserved the name
    except FileNotFoundError:
        os.remove(rejected)
        return False
    if not is_valid(rejected, n, queries_digest=queries_digest):
        return False
    # between the check and the move, someone replaced the malformed file with a valid one: that is the answer
    try:
        os.link(rejected, path)
        os.remove(rejected)
    except FileExistsError:  # and yet another file came meanwhile: keep both, never delete
        pass
    return True


WRITING = threading.Lock()  # the app's own writers, one at a time; the hard link guards against everyone else


def write_labels(run_dir: str, round_index: int, body: bytes):
    """Write the answers in `body` as the round's labels file, once, with the digest of the queries they answer:
    Refused(409) if a valid one exists, or if `body` names other queries than the round's (`round_queries`: the run's
    while it waits for them, else its file's); ValueError if the answers are not valid, Refused(400) if they name no
    queries. A reader (the run) sees no file or the whole file, never a part."""
    queries = read_queries(run_dir, round_index)
    n, expected = round_queries(round_index, queries, awaited(read_teacher(run_dir)[0]))
    answers, digest = parse_labels(body, n)
    if digest is None:  # a bare list would bind the answers to whatever queries the run holds when it reads them
        raise Refused(400, f'round {round_index}\'s answers were not saved: they name no queries; send {{"queries": '
                           f'digest, "answers": [...]}} with the digest of the queries answered, as the page does (a '
                           f'program may write a bare list to labels/{round_index}.json itself)')
    mismatch = answering(digest, expected)
    if mismatch is not None:
        raise Refused(409, f"round {round_index}'s answers were not saved: {mismatch}; the page shows the new ones")
    path = labels_path(run_dir, round_index)
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with WRITING:
        fd, tmp = create_temporary(os.path.dirname(path), f".{round_index}.json.")
        try:
            with os.fdopen(fd, "w") as f:
                json.dump(answers if digest is None else {"queries": digest, "answers": answers}, f)
                f.flush()
                os.fsync(f.fileno())  # on disk before it is visible under its name
            while True:
                try:
                    os.link(tmp, path)  # unlike a rename, fails if the file exists
                    return
                except FileExistsError:
                    try:
                        answered = keeps_existing(path, n, queries_digest=expected)
                    except OSError as e:  # a folder in the way: the person moves it, the page keeps the answers
                        raise Refused(500, unreadable(round_index, e)) from None
                    if answered:
                        raise Refused(409, f"round {round_index} is already answered (labels/{round_index}.json); "
                                           "a round's labels are written once and never change") from None
        finally:
            os.remove(tmp)


def create_temporary(folder: str, prefix: str) -> tuple:
    """A new file `{folder}/{prefix}{random}.tmp`, open for writing: (its descriptor, its path). Its mode is the one
    `open` gives every other file of the run (0666 less the umask, group-readable as a rule), not mkstemp's 0600."""
    while True:
        path = os.path.join(folder, f"{prefix}{secrets.token_hex(8)}.tmp")
        try:
            return os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o666), path
        except FileExistsError:  # a name taken already: draw another
            pass


# what the run writes in teacher.json; and `digest`, which an older run's lacks (read_teacher makes it None)
TEACHER_KEYS = ("task", "run", "pid", "host", "phase", "round", "queries", "asked", "labelled", "budget", "step",
                "total_steps", "message", "updated")


def read_teacher(run_dir: str) -> tuple:
    """The run's status file `teacher.json`, and why it cannot be read. (None, None): an older run, or one that has
    not asked yet, has none. (None, a sentence): the file is not the run's (the run writes it whole, atomically)."""
    try:
        with open(os.path.join(run_dir, "teacher.json"), "rb") as f:
            teacher = json.load(f)
    except FileNotFoundError:
        return None, None
    except OSError as e:
        return None, f"{type(e).__name__}: {e.strerror}"
    except (ValueError, RecursionError) as e:  # JSONDecodeError, UnicodeDecodeError; deep nesting
        return None, f"not JSON: {e}".splitlines()[0]
    if not isinstance(teacher, dict):
        return None, "not a JSON object"
    missing = [key for key in TEACHER_KEYS if key not in teacher]
    if missing:
        return None, f"it lacks the keys {', '.join(missing)}"
    for key, value in teacher.items():
        try:
            json.dumps(value, allow_nan=False)  # json reads NaN, Infinity and 1e999, which are no JSON to send on
        except ValueError:
            return None, f"{key} is {json.dumps(value)}, not a finite number"
    # the app computes with these two: the age of the news, and whether the run's process lives
    if isinstance(teacher["updated"], bool) or not isinstance(teacher["updated"], (int, float)):
        return None, f"updated is {json.dumps(teacher['updated'])}, not a number"
    if isinstance(teacher["pid"], bool) or not isinstance(teacher["pid"], int) or not 0 < teacher["pid"] < 2 ** 31:
        return None, f"pid is {json.dumps(teacher['pid'])}, not a positive whole number"
    digest = teacher.setdefault("digest", None)
    if digest is not None and not (isinstance(digest, str) and re.fullmatch(r"[0-9a-f]{16}", digest)):
        return None, f"digest is {json.dumps(digest)}, not a digest of 16 hex digits"
    return teacher, None


def awaited(teacher: Optional[dict]) -> Optional[tuple]:
    """(round, number of queries, digest) of the queries the run wrote and waits for, by its `teacher.json`; None if
    it waits for none or does not say which (an older run's names no digest)."""
    if teacher is None or teacher["phase"] != "waiting" or teacher["digest"] is None:
        return None
    r, n = teacher["round"], teacher["queries"]
    if not all(isinstance(x, int) and not isinstance(x, bool) and x >= 0 for x in (r, n)):
        return None
    return r, n, teacher["digest"]


def round_queries(round_index: int, queries: Queries, waiting: Optional[tuple]) -> tuple:
    """(n, digest) of round `round_index`'s queries: those the run wrote while it waits for them (`waiting`, from
    `awaited`), else those of its queries file (`queries`). Answers are taken for these queries only: the run reads
    a labels file by the same digest, whatever file lies in the queries' place for a moment."""
    if waiting is not None and waiting[0] == round_index:
        return waiting[1], waiting[2]
    return queries.n, queries.digest


def not_the_runs(round_index: int, held: str, runs: str) -> str:
    """What a person learns when round `round_index`'s queries file holds the queries of digest `held` while the run
    waits for its own (`runs`)."""
    return (f"queries/{round_index}.npz is not the file the run wrote for round {round_index} (it holds the queries "
            f"of digest {held}; the run's are {runs}): the run writes its own again at its next look")


def alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)  # signal 0: only checks that the process exists
    except ProcessLookupError:
        return False
    except PermissionError:  # it exists, under another user
        pass
    return True


def silent_for(teacher: dict) -> Optional[float]:
    """Seconds since the run last wrote `teacher.json` if it is not responding, else None: a waiting run rewrites it
    every ~2 s, and a waiting or training run of this machine has a live process."""
    age = time.time() - teacher["updated"]
    if teacher["phase"] == "waiting" and age > SILENT_SECONDS:
        return age
    if teacher["phase"] in ("waiting", "training") and teacher["host"] == socket.gethostname() and not alive(
            teacher["pid"]):
        return age
    return None


def state(run_dir: str) -> dict:
    """What the page shows, as `/api/state` answers it: the pending round from the files (its queries by
    `round_queries`), the run's status from its `teacher.json` when it has one."""
    teacher, problem = read_teacher(run_dir)
    waiting = awaited(teacher)
    pending, n, digest, malformed, blocked, answered, labels, task = None, None, None, None, None, 0, 0, None
    foreign = None
    for r in rounds(run_dir):
        queries = read_queries(run_dir, r)
        task = queries.env_id
        round_n, round_digest = round_queries(r, queries, waiting)
        try:
            answers, answered_digest = parse_labels(LABEL_FILES(labels_path(run_dir, r)), round_n)
            if (mismatch := answering(answered_digest, round_digest)) is not None:
                raise ValueError(mismatch)  # the run moves it aside and asks again
        except (OSError, ValueError) as e:  # FileNotFoundError: not answered yet
            if pending is None:
                pending, n, digest = r, round_n, round_digest
                if queries.digest != round_digest:  # another file lies in the run's queries' place for a moment
                    foreign = not_the_runs(r, queries.digest, round_digest)
                malformed = str(e) if isinstance(e, ValueError) else None
                blocked = None if isinstance(e, (ValueError, FileNotFoundError)) else unreadable(r, e)
            continue
        answered += 1
        labels += sum(a != "skip" for a in answers)
    return {
        "run": teacher["run"] if teacher else os.path.basename(os.path.abspath(run_dir)),
        "task": teacher["task"] if teacher else task,  # None before the first round of a run without teacher.json
        "round": pending,  # the lowest round with queries and no valid labels file, or None
        "n": n,  # its number of queries
        "queries_digest": digest,  # round_queries' digest: the page keeps a round's answers for these queries only
        "foreign": foreign,  # why its queries file is not the run's (`not_the_runs`), or None
        "malformed": malformed,  # why its labels file, if it has one, is not valid
        "blocked": blocked,  # why its labels file cannot be read (a folder in its place), and what to do; or None
        "rounds_answered": answered,  # rounds with a valid labels file
        "labels": teacher["labelled"] if teacher else labels,  # answers other than "skip": the run's count, else the files'
        "teacher": teacher,  # teacher.json as the run wrote it, or None
        "teacher_problem": problem and f"teacher.json cannot be read ({problem}): the page shows what the run's "
                                      "files say",  # or None
        "silent_for": silent_for(teacher) if teacher else None,  # seconds since the run's last news, if not responding
    }


class Clips:
    """GIF clips of the queries' segments, rendered once and kept while they fit in `max_bytes`, the least recently
    shown dropped first. A clip is kept by the digest of the queries it shows, not by its round's number: a run
    folder used again (other queries under the same round numbers) gets its own clips."""

    def __init__(self, run_dir: str, fps: int, max_bytes: int):
        self.run_dir, self.fps, self.max_bytes, self.lock = run_dir, fps, max_bytes, threading.Lock()
        self.kept, self.kept_bytes = OrderedDict(), 0  # (digest, query, side) -> GIF, least recently shown first
        # One thread draws every clip, with one physics per task: one MuJoCo context, made once, and one malloc
        # arena. Each request's own thread would leave its arena holding its clip's peak (docs/labelling.md).
        self.drawer, self.physics = ThreadPoolExecutor(1, thread_name_prefix="clips"), {}

    def gif(self, round_index: int, query: int, side: int, digest: Optional[str] = None) -> bytes:
        """The clip of a query's segment (side 0: the first); with `digest`, only of the queries of that digest."""
        with self.lock:  # one MuJoCo renderer at a time
            key = self.key(round_index, read_queries(self.run_dir, round_index), query, side, digest)
            if key not in self.kept:
                queries, physics = load_queries(self.run_dir, round_index)
                key = self.key(round_index, queries, query, side, digest)  # the file may have changed meanwhile
                self.kept[key] = self.drawer.submit(self.draw, queries.env_id, physics[query, side]).result()
                self.kept_bytes += len(self.kept[key])
            self.kept.move_to_end(key)
            clip = self.kept[key]
            while self.kept_bytes > self.max_bytes:  # a clip larger than the bound is served, not kept
                self.kept_bytes -= len(self.kept.popitem(last=False)[1])
            return clip

    def draw(self, env_id: str, states: np.ndarray) -> bytes:
        """The GIF of one segment's physics `states` (in the drawing thread)."""
        import imageio.v3 as iio

        if env_id in ene.dmc_tasks() and env_id not in self.physics:
            self.physics[env_id] = ene.dmc_physics(env_id)
        frames = ene.render_states(env_id, states, physics=self.physics.get(env_id))
        buffer = io.BytesIO()
        iio.imwrite(buffer, frames, extension=".gif", duration=1000 / self.fps, loop=0)
        return buffer.getvalue()

    def key(self, round_index: int, queries: Queries, query: int, side: int, digest: Optional[str]) -> tuple:
        """The clip's key in `kept`; Refused(404) if the queries file does not hold the queries of `digest`."""
        if digest is not None and digest != queries.digest:
            waiting = awaited(read_teacher(self.run_dir)[0])
            if waiting is not None and waiting[0] == round_index and waiting[2] == digest:  # the run's, not there
                raise Refused(404, not_the_runs(round_index, queries.digest, digest))
            # a page that has not seen the new queries yet
            raise Refused(404, f"round {round_index}'s queries have changed since the page asked for this clip: "
                               "it shows the new ones within 2 s")
        if query >= queries.n:
            raise Refused(404, f"round {round_index} has {queries.n} queries, not {query + 1}")
        return queries.digest, query, side


PAGE = """<!doctype html>
<html><head><meta charset="utf-8"><title>R2N: label preferences</title>
<style>
 [hidden] { display: none !important; }  /* else .clips' display: flex would show hidden clips */
 body { font-family: sans-serif; margin: 2em; background: #fafafa; }
 .clips { display: flex; gap: 2em; } .clip { text-align: center; }
 img { width: 320px; height: 240px; border: 3px solid #ccc; background: #000; }
 button { font-size: 1.1em; margin: 0.5em 0.3em; padding: 0.4em 1em; }
 #progress { font-weight: bold; } #run { color: #555; }
 #notices p, #message:not(:empty) { background: #fff3cd; border-left: 4px solid #e0a800; padding: 0.4em 0.8em; }
 #drawing { color: #555; }
</style></head>
<body>
<h2 id="question" hidden>Which segment is better?</h2>
<p id="run"></p>
<div id="notices"></div>
<p id="progress">loading...</p>
<p id="message"></p>
<p id="drawing"></p>
<div class="clips" id="clips" hidden>
 <div class="clip"><img id="left" alt="left clip"><div>left (first segment)</div></div>
 <div class="clip"><img id="right" alt="right clip"><div>right (second segment)</div></div>
</div>
<div id="answers" hidden>
 <button id="answer-left" disabled>&larr; left is better</button>
 <button id="answer-equal" disabled>= equal</button>
 <button id="answer-right" disabled>right is better &rarr;</button>
 <button id="answer-skip" disabled>s: skip</button>
</div>
<button id="submit" hidden></button>
<button id="undo" hidden>&#9003; undo</button>
<script>
const $ = (id) => document.getElementById(id);
const SHOWN_MS = 1000;  // a query takes answers once its clips have been shown this long: a double click cannot
                        // answer the next query, whose clips were fetched ahead and appear at once
let state = null, timer = null;  // the app's last /api/state, and the next refresh
let submits = 0;  // submits ended: a state asked for before the last one ended may be older than its labels
let round = null, n = 0, answers = [], submitting = false;  // the round being answered, and its answers so far
let saved = null;  // the round this page saved last: should it wait again, the run did not take its labels
let key = null, digest = null, storageProblem = null;  // where this tab keeps the answers, for which queries
let shown = 0, ready = false, ahead = [];  // queries shown (a late image of an earlier one is ignored), whether
                                           // this one takes answers, the next one's clips
const clip = (r, i, side) => `/clip/${r}/${i}/${side}.gif?queries=${digest}`;  // these queries' clip, not newer ones'
const count = (k) => `${k} answer${k === 1 ? "" : "s"}`;
const LABELS = {left: 0, right: 1, equal: 0.5, skip: "skip"};
const SYMBOLS = {0: "\\u2190", 1: "\\u2192", 0.5: "=", skip: "s"};  // an answer as its key

// The answers of a round stay in this tab's storage (sessionStorage: each tab has its own, and a reload keeps it)
// until the app says it has saved them: a reload or a failed submit loses none. They are kept by run and round, with
// the digest of the round's queries, so that another run of the same name never gets them.
function keep(failure = null) {
  try {
    sessionStorage.setItem(key, JSON.stringify({digest, answers, failure}));
    storageProblem = null;
  } catch (error) {
    storageProblem = `this browser cannot keep your answers (${error.message}): a reload would lose them`;
  }
  tell("mine");
}
function forget(storageKey = key) {
  try { sessionStorage.removeItem(storageKey); } catch (error) { /* nothing was kept */ }
}
function kept(storageKey) {  // the answers kept under storageKey, or null
  try {
    const saved = JSON.parse(sessionStorage.getItem(storageKey));
    if (Array.isArray(saved?.answers) && saved.answers.every((a) => Object.values(LABELS).includes(a))) return saved;
  } catch (error) { /* none, or not the page's */ }
  return null;
}
function forgetAnswered() {  // answers kept for rounds of this run that are no longer waiting: tell, then drop them
  const prefix = `r2n-labels/${state.run}/`, told = [];
  let storageKeys = [];
  try { storageKeys = Object.keys(sessionStorage).filter((k) => k.startsWith(prefix)); } catch (error) { return; }
  for (const storageKey of storageKeys) {
    const r = Number(storageKey.slice(prefix.length)), saved = kept(storageKey);
    if (state.round !== null && r >= state.round) continue;
    const k = saved?.answers.length;
    if (k) told.push(`your ${count(k)} to round ${r}, kept in this tab, ${k === 1 ? "was" : "were"} not used: ` +
                     "it was answered elsewhere");
    forget(storageKey);
  }
  if (told.length) $("message").textContent = told.join("; ");
}

// The tabs of this browser tell each other which round they answer, and their answers so far (BroadcastChannel):
// a tab sees at once that another answers its round, before it spends effort on the same queries. A tab asks at
// every poll; every other tab replies at once, a hidden one too (messages are not throttled as timers are).
const TAB = Math.random().toString(36).slice(2);  // this page's name among the tabs
const channel = typeof BroadcastChannel === "function" ? new BroadcastChannel("r2n-labels") : null;
const others = new Map();  // another tab's name -> what it last said, and when (`heard`)
const HEARD_MS = 5000;  // a tab not heard from this long has gone (closed without a word, or frozen)
function tell(type) {  // "who": this tab asks the others; "mine": it says what it answers; "gone": it closes
  channel?.postMessage({type, tab: TAB, run: state?.run, round, digest, answers});
}
if (channel) channel.onmessage = ({data}) => {
  if (data.type === "who") tell("mine");
  if (data.type === "gone" || data.round === null) others.delete(data.tab);
  else others.set(data.tab, {...data, heard: Date.now()});
  if (state !== null) render();
};
addEventListener("pagehide", () => tell("gone"));
function othersNotice() {  // a sentence per other tab answering the pending round, with its answers
  return [...others.values()].filter((other) => other.run === state.run && other.round === state.round &&
                                              other.digest === state.queries_digest &&
                                              Date.now() - other.heard < HEARD_MS).map((other) => {
    const k = other.answers.length, given = other.answers.map((a) => SYMBOLS[a]).join(" ");
    return `another tab of this browser is answering round ${other.round} too (` +
      (k ? `its ${count(k)} so far: ${given}` : "no answers yet") + "): answer in one tab only; the first to " +
      "submit is kept, and the other's answers are not used";
  });
}

function start() {  // the round the app says is waiting, with the answers this tab kept for it
  round = state.round; n = state.n; digest = state.queries_digest; key = `r2n-labels/${state.run}/${round}`;
  const saved = kept(key), ours = saved?.digest === digest && saved.answers.length <= n;
  if (saved !== null && !ours) forget();  // kept for another run of the same name
  answers = ours ? saved.answers : [];
  if (answers.length)
    $("message").textContent = `your ${count(answers.length)} to round ${round}, kept in this tab, ` +
      `${answers.length === 1 ? "is" : "are"} back` + (saved.failure ? ` (the last submit: ${saved.failure})` : "");
  tell("mine");
  show();
}
function enable(on) {
  for (const button of document.querySelectorAll("#answers button")) button.disabled = !on;
}
function hide() {  // no round on the page
  ++shown; ready = false; enable(false); $("drawing").textContent = "";
  $("question").hidden = $("clips").hidden = $("answers").hidden = $("submit").hidden = $("undo").hidden = true;
  tell("mine");
}
const RETRY_S = [0.5, 1, 2, 4, 8];  // a failed clip load is tried again after these waits, then every 8 s
function show(attempt = 0) {  // the current query (one per answer so far), or the submit step after the last
  const i = answers.length, token = ++shown;
  ready = false; enable(false);
  $("clips").hidden = true; $("question").hidden = $("answers").hidden = i === n; $("undo").hidden = i === 0;
  $("submit").hidden = i < n; $("submit").textContent = `\\u23ce submit round ${round}`;
  if (i === n) {
    $("progress").textContent = `round ${round}: all ${n} answered`; $("drawing").textContent = "";
    return;
  }
  $("progress").textContent = `round ${round}: query ${i + 1} of ${n}`;
  if (!attempt) $("drawing").textContent = `the app is drawing the clips of query ${i + 1}...`;  // seconds, unkept
  const again = attempt ? `&try=${attempt}` : "";  // a new address: nothing of the failed load is reused
  $("left").src = clip(round, i, 0) + again; $("right").src = clip(round, i, 1) + again;
  Promise.all([$("left").decode(), $("right").decode()]).then(() => {
    if (token !== shown) return;
    $("drawing").textContent = attempt ? `the clips of query ${i + 1} loaded on try ${attempt + 1}` : "";
    $("clips").hidden = false;
    if (i + 1 < n) ahead = [0, 1].map((side) => Object.assign(new Image(), {src: clip(round, i + 1, side)}));
    setTimeout(() => { if (token === shown) { ready = true; enable(true); } }, SHOWN_MS);
  }, async () => {  // the app stopped or is restarting, or answers why not: say which, and try again
    if (token !== shown) return;
    const why = await whyNot([$("left").src, $("right").src]);
    if (token !== shown) return;
    const wait = RETRY_S[Math.min(attempt, RETRY_S.length - 1)];
    $("drawing").textContent = `the clips of query ${i + 1} did not load (try ${attempt + 1}): ${why}; ` +
      `trying again in ${wait} s`;
    setTimeout(() => { if (token === shown) show(attempt + 1); }, 1000 * wait);
  });
}
async function whyNot(urls) {  // why a clip did not load: an image tells nothing, so the page asks again
  for (const url of urls) {
    try {
      const reply = await fetch(url);
      if (!reply.ok) return `HTTP ${reply.status}: ${await reply.text()}`;  // the app's sentence
    } catch (error) {
      return `the app does not answer (${error.message})`;
    }
  }
  return "they load now";
}
function answer(choice) {
  if (round === null || !ready) return;
  answers.push(LABELS[choice]); keep(); show();
}
function undo() {
  if (round === null || submitting || answers.length === 0) return;
  answers.pop(); keep(); show();
}
function drop(why) {  // the round on the page is no longer the one waiting: say why, and what became of the answers
  const k = answers.length;
  $("message").textContent = why + (k ? `: your ${count(k)} to it ${k === 1 ? "was" : "were"} not used` : "");
  forget(); round = null; hide();
}
async function submit() {
  if (round === null || submitting || answers.length < n) return;
  submitting = true; $("submit").hidden = $("undo").hidden = true;
  $("progress").textContent = `round ${round}: saving...`;
  let failure = null;
  try {
    const reply = await fetch(`/api/labels/${round}`,
      {method: "POST", headers: {"Content-Type": "application/json"},
       body: JSON.stringify({queries: digest, answers})});  // the digest of the queries these answers are for
    const said = reply.ok ? "" : await reply.text();
    if (reply.ok || reply.status === 409 && said.includes("already answered")) {  // saved, or answered for good
      $("message").textContent = reply.ok ? `round ${round} saved (labels/${round}.json)`
        : `round ${round} was already answered, perhaps in another tab: your answers for it were not used`;
      saved = reply.ok ? round : null; forget(); round = null; hide();
    } else {  // kept: the state, asked at once, says whether the round still waits for the queries they answer
      failure = `HTTP ${reply.status}: ${said}`;
    }
  } catch (error) {  // the app is not there
    failure = `the app does not answer: ${error.message}`;
  }
  if (failure !== null) {  // the answers stay, in the page and in this tab's storage, to submit again
    keep(failure);
    $("message").textContent = `round ${round} was not saved (${failure}); your answers are kept in this tab: ` +
      "submit again";
    show();
  }
  submitting = false; ++submits; clearTimeout(timer); refresh();
}
function idle() {  // what the run is doing when no round is waiting
  const t = state.teacher;
  if (t?.phase === "finished") return `the run has finished: ${state.labels} labels in ${state.rounds_answered} rounds`;
  if (t?.phase === "training") return `no round is waiting; the run is training (step ${t.step} of ${t.total_steps})`;
  return "no round is waiting for labels; this page checks every 2 s";
}
function render() {
  const t = state.teacher, notices = [];
  $("run").textContent = `${state.task ?? "task not known yet"} \\u00b7 run ${state.run} \\u00b7 ` +
    `${state.labels} labels so far` + (t ? ` (budget ${t.budget})` : "");
  if (state.blocked !== null) notices.push(state.blocked);
  if (state.foreign !== null) notices.push(state.foreign);
  if (state.malformed !== null)
    notices.push(`labels/${state.round}.json is not valid: ${state.malformed}. Submitting round ${state.round}'s ` +
                 `answers from this page replaces it (the old file is kept as labels/${state.round}.json.rejected-...).`);
  notices.push(...othersNotice());
  if (state.silent_for !== null)
    notices.push(`the run is not responding (last heard ${Math.round(state.silent_for)} s ago): ` +
                 "running the same command again resumes it");
  if (t?.phase === "stopped") notices.push(`the run has stopped: ${t.message ?? "no reason given"}`);
  if (t?.phase === "waiting" && t.message) notices.push(`the run says: ${t.message}`);
  if (state.teacher_problem !== null) notices.push(state.teacher_problem);
  if (storageProblem !== null) notices.push(storageProblem);
  $("notices").replaceChildren(...notices.map((text) => Object.assign(document.createElement("p"), {textContent: text})));
  if (round === null && !submitting) $("progress").textContent = idle();
}
async function refresh() {
  const asked = submits;
  try {
    const reply = await fetch("/api/state");
    if (!reply.ok) throw new Error(await reply.text());
    const latest = await reply.json();
    if (asked !== submits) return;  // asked for before a submit ended: the submit's own refresh polls on
    state = latest;
    if (round !== null && !submitting && state.round !== round)
      drop(`round ${round} was answered elsewhere (another tab, another app or a script)`);
    if (round !== null && !submitting && state.queries_digest !== digest)  // a new run in this run's folder
      drop(`round ${round}'s queries have changed (a new run in the folder ${state.run}?)`);
    if (saved !== null && round === null && !submitting && state.round === saved) {  // its labels were set aside
      const says = state.teacher?.phase === "waiting" && state.teacher.message;
      $("message").textContent = `round ${saved} was saved, but labels/${saved}.json is no longer its answer` +
        (says ? " (the run's line above says why)" : "") + `: answer round ${saved} again`;
      saved = null;
    }
    render();
    if (round === null && !submitting) {
      forgetAnswered();
      if (state.round !== null) start();
    }
    tell("who");
  } catch (error) {
    if (asked !== submits) return;
    $("notices").replaceChildren(Object.assign(document.createElement("p"),
      {textContent: `the page could not get the run's state (${error.message}); it tries again every 2 s`}));
  }
  timer = setTimeout(refresh, 2000);
}
for (const choice of Object.keys(LABELS)) $(`answer-${choice}`).onclick = () => answer(choice);
$("undo").onclick = undo; $("submit").onclick = submit;
// a button clicked with the mouse leaves the focus to the page, so that Space and Enter stay the page's keys
document.addEventListener("click", (e) => { if (e.detail > 0) e.target.closest("button")?.blur(); });
const KEYS = {ArrowLeft: () => answer("left"), ArrowRight: () => answer("right"), "=": () => answer("equal"),
              " ": () => answer("equal"), s: () => answer("skip"), Backspace: undo, Enter: submit};
const modified = (e) => e.ctrlKey || e.altKey || e.metaKey || e.shiftKey;
const pressing = (e) => e.target.closest?.("button") && (e.key === "Enter" || e.key === " ");
document.addEventListener("keydown", (e) => {
  const typed = e.key.length === 1 && e.key !== " ";  // a character, which a keyboard may type with Shift ("=")
  if (pressing(e)) {  // presses the focused button: unmodified, once (a held key does not press it again)
    if (e.repeat || modified(e)) e.preventDefault();
    return;
  }
  if (e.ctrlKey || e.altKey || e.metaKey || e.shiftKey && !typed) return;  // the browser's: zoom, save, back...
  const action = KEYS[typed ? e.key.toLowerCase() : e.key];  // "S" (Caps Lock) is "s"
  if (!action) return;
  e.preventDefault();
  if (!e.repeat) action();  // a key held down acts once
});
// Space presses a button when it comes up: a modifier held then, or at its keydown, presses nothing
document.addEventListener("keyup", (e) => { if (pressing(e) && modified(e)) e.preventDefault(); });
refresh();
</script></body></html>
"""


class Address:
    """The host names under which the app is this machine's, for the Host header of every request: the address it
    binds, and for a loopback address (the default) `localhost`; for a wildcard address (0.0.0.0, ::), any IP address,
    `localhost` and the machine's name. A name of someone else's that resolves to this machine (DNS rebinding) is
    none of them. The port is not checked: an SSH tunnel may forward another one."""

    def __init__(self, bound: str):
        self.bound = bound.strip("[]").lower()
        self.names = {self.bound}
        self.any_ip = self.bound in ("", "0.0.0.0", "::")
        if self.any_ip:
            self.names |= {"localhost", socket.gethostname().lower()}
        elif self.bound == "localhost" or is_ip(self.bound) and ipaddress.ip_address(self.bound).is_loopback:
            self.names |= {"localhost", "127.0.0.1", "::1"}

    def serves(self, host: Optional[str]) -> bool:
        """Whether a request's Host header (`name`, `name:port`, `[v6]:port`) names this machine."""
        match = re.fullmatch(r"(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9.-]+)(:\d+)?", host or "")
        if not match:
            return False
        name = match.group(1).strip("[]").lower()
        return name in self.names or self.any_ip and is_ip(name)

    def __str__(self) -> str:
        if self.any_ip:
            return f"an IP address of this machine, localhost or {socket.gethostname()}"
        return f"{self.bound} or localhost" if "localhost" in self.names - {self.bound} else self.bound


def is_ip(name: str) -> bool:
    try:
        ipaddress.ip_address(name)
    except ValueError:
        return False
    return True


def make_handler(run_dir: str, clips: Clips, address: Address):
    class Handler(BaseHTTPRequestHandler):
        timeout = 60  # seconds: a client that sends less than its Content-Length does not hold a thread for ever

        def reply(self, code: int, body: bytes, content_type: str = "text/plain; charset=utf-8"):
            self.send_response(code)
            self.send_header("Content-Type", content_type)
            self.send_header("Content-Length", str(len(body)))
            if code == HTTPStatus.METHOD_NOT_ALLOWED:
                self.send_header("Allow", "GET, HEAD, POST")
            self.end_headers()
            if self.command != "HEAD":  # a reply to HEAD has the headers of GET's, and no body
                self.wfile.write(body)

        def send_error(self, code: int, message: Optional[str] = None, explain: Optional[str] = None):
            """http.server's own refusals, as one line: a method without a `do_` method here (501 there) gets 405,
            a malformed request its code and http.server's sentence."""
            if code == HTTPStatus.NOT_IMPLEMENTED:
                code = HTTPStatus.METHOD_NOT_ALLOWED
                message = f"the method {self.command} is not allowed: the app answers GET, HEAD and POST"
            self.close_connection = True
            self.reply(code, (message or HTTPStatus(code).phrase).encode())

        def answer(self, route):
            """Answer with `route`'s reply; a refused request gets its code and one line, never a traceback."""
            try:
                host = self.headers.get("Host")
                if not address.serves(host):  # a page under another name (DNS rebinding)
                    raise Refused(403, f"refused: {host or 'no Host header'} is not this app's address ({address})")
                reply = route(urlsplit(self.path))
            except Refused as e:
                reply = e.code, str(e).encode()
            except ValueError as e:
                reply = 400, str(e).encode()
            except Exception as e:  # a bug, or a renderer that fails: one line here and on the page; the app serves on
                sentence = f"{type(e).__name__}: {e}".splitlines()[0]
                print(f"label_app: {self.command} {self.path}: {sentence}", file=sys.stderr, flush=True)
                reply = 500, sentence.encode()
            if reply[0] >= 400:
                self.close_connection = True  # the body of a refused request may be left unread
            self.reply(*reply)

        def do_GET(self):
            self.answer(self.get)

        def do_HEAD(self):
            self.answer(self.get)

        def do_POST(self):
            self.answer(self.post)

        def get(self, url) -> tuple:
            if url.path == "/":
                return 200, PAGE.encode(), "text/html; charset=utf-8"
            if url.path == "/api/state":  # strict JSON, which a browser can read: no NaN or Infinity
                body = json.dumps(state(run_dir), allow_nan=False).encode()
                time.sleep(STATE_DELAY)
                return 200, body, "application/json"
            match = re.fullmatch(rf"/clip/{ROUND}/{ROUND}/([01])\.gif", url.path)
            if not match:
                raise Refused(404, f"no such page: {url.path}")
            digest = parse_qs(url.query).get("queries", [None])[-1]  # the page names the queries it shows
            time.sleep(CLIP_DELAY)
            return 200, clips.gif(*map(int, match.groups()), digest), "image/gif"

        def post(self, url) -> tuple:
            path = url.path
            origin = self.headers.get("Origin")  # a browser sends it with every POST; a script need not
            if origin is not None and origin.lower() not in (f"http://{self.headers['Host']}".lower(),
                                                             f"https://{self.headers['Host']}".lower()):
                raise Refused(403, f"refused: only this app's page can write labels, not a page from {origin}")
            match = re.fullmatch(rf"/api/labels/{ROUND}", path)
            if not match:
                raise Refused(404, f"no such page: {path}")
            # a page may send another origin a form or text unasked, but JSON only after a preflight (OPTIONS),
            # which gets 405 here
            content_type = self.headers.get("Content-Type", "").split(";")[0].strip().lower()
            if content_type != "application/json":
                raise Refused(415, f"expected Content-Type: application/json, not {content_type or 'none'}")
            length = self.headers.get("Content-Length", "")
            if not re.fullmatch(r"\d+", length):
                raise ValueError("expected a Content-Length header: the size of the body in bytes")
            if int(length) > MAX_BODY:  # refused before reading it
                raise Refused(413, f"the body has {length} bytes; at most {MAX_BODY} are accepted")
            round_index = int(match.group(1))
            write_labels(run_dir, round_index, self.rfile.read(int(length)))
            return 200, f"round {round_index} saved (labels/{round_index}.json)".encode()

        def log_message(self, *args):  # no line per request
            pass

    return Handler


class Server(ThreadingHTTPServer):
    def handle_error(self, request, client_address):
        if not isinstance(sys.exc_info()[1], ConnectionError):  # a page that moves on drops its pending clips
            super().handle_error(request, client_address)


def main(args: Args) -> int:
    if not os.path.isdir(args.run_dir):
        print(f"label_app: error: run_dir: no such folder: {args.run_dir}", file=sys.stderr)
        return 1
    try:
        clips = Clips(args.run_dir, args.fps, int(args.clip_cache_mb * 1e6))
        handler = make_handler(args.run_dir, clips, Address(args.host))
        server = Server((args.host, args.port), handler)
    except OSError as e:
        flag = f"--port {args.port}" if e.errno == errno.EADDRINUSE else f"--host {args.host}"
        print(f"label_app: error: {flag}: {(e.strerror or str(e)).lower()}", file=sys.stderr)
        return 1
    print(f"labelling {args.run_dir} at http://{args.host}:{server.server_port} (remote: ssh -L "
          f"{server.server_port}:localhost:{server.server_port} HOST, then open http://localhost:{server.server_port})",
          flush=True)
    try:
        server.serve_forever()
    except KeyboardInterrupt:
        pass
    return 0


if __name__ == "__main__":
    sys.exit(main(tyro.cli(Args)))
