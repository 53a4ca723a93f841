"""A person's labels and waiting time are safe (docs/labelling.md): the run records the SHA-256 of each
labels file it trains on and a resume refuses a changed one; a state is written before every round, so SIGTERM
while waiting, or a kill before any other state, resumes into the same queries; `teacher.json` says what the run
does."""
import hashlib
import json
import os
import signal
import sys
import threading
import time
from types import SimpleNamespace

import numpy as np
import pytest

from test_labelling import EXTERNAL, oracle_answers, start, wait_for
from test_resume import points
from test_scripts import ROOT

sys.path.insert(0, ROOT)
from r2n_harness.external_teacher import ExternalTeacher, check_labels_unchanged  # noqa: E402
from r2n_harness.preferences import read_preferences  # noqa: E402
from r2n_harness.query_log import QueryLog  # noqa: E402


class Stopped(Exception):
    """What a run's `Run.stop` gives the teacher to raise at a stop signal."""


def status(run):
    return json.loads((run / "teacher.json").read_text())


def answer(run, round_index, process, log):
    """The scripted teacher: waits for the round's queries, writes the oracle's answers; returns the file's bytes."""
    wait_for(lambda: (run / "queries" / f"{round_index}.npz").exists(), process, log)
    with np.load(run / "queries" / f"{round_index}.npz") as data:
        content = json.dumps(oracle_answers({"true_rewards": data["true_rewards"]})).encode()
    (run / "labels").mkdir(exist_ok=True)
    (run / "labels" / f"{round_index}.json").write_bytes(content)
    return content


def queries_of(run, round_index):
    with np.load(run / "queries" / f"{round_index}.npz") as data:
        return {key: data[key] for key in data}


def test_a_stop_ends_the_nap_at_once(tmp_path):
    """A person's stop is not kept waiting: the nap between two looks for the labels ends within a
    short nap of the stop signal, not at the end of the poll."""
    args = SimpleNamespace(env_id="cartpole-swingup", max_feedback=10, total_timesteps=100)
    stops = []
    teacher = ExternalTeacher(str(tmp_path), args, stops, Stopped, poll_seconds=60.0)
    threading.Timer(0.2, stops.append, [signal.SIGTERM]).start()
    started = time.monotonic()
    teacher.nap()
    assert 0.2 <= time.monotonic() - started < 5
    stops.clear()
    teacher.poll_seconds = 0.3
    started = time.monotonic()
    teacher.nap()  # without a stop, the whole poll
    assert time.monotonic() - started >= 0.3


def test_sigterm_while_waiting_resumes_into_the_same_round_and_a_changed_labels_file_is_refused(tmp_path):
    reference, resumed = tmp_path / "reference", tmp_path / "resumed"
    for folder in (reference, resumed):
        folder.mkdir()
    process, log = start("pebble.py", reference, EXTERNAL)
    for round_index in (0, 1):
        answer(reference / "runs" / "ext", round_index, process, log)
    assert process.wait(timeout=300) == 0, open(log).read()[-3000:]

    run = resumed / "runs" / "ext"
    process, log = start("pebble.py", resumed, EXTERNAL)
    first = answer(run, 0, process, log)
    wait_for(lambda: (run / "teacher.json").exists() and status(run)["round"] == 1, process, log)
    assert {key: status(run)[key] for key in ("task", "run", "phase", "queries", "asked", "labelled", "budget")} == {
        "task": "cartpole-swingup", "run": "ext", "phase": "waiting", "queries": 5, "asked": 5,
        "labelled": 5, "budget": 10,
    }
    asked = queries_of(run, 1)
    signalled = time.monotonic()
    process.send_signal(signal.SIGTERM)
    assert process.wait(timeout=60) == 1
    assert time.monotonic() - signalled < 1  # at once: a person's stop is not kept waiting
    last = open(log).read().strip().splitlines()[-1]
    assert "stopped by SIGTERM while waiting for runs/ext/labels/1.json" in last and "--run-name ext to resume" in last
    assert status(run)["phase"] == "stopped" and status(run)["message"] in last
    assert (run / "state.pt").exists()

    # a labels file the run trained on, changed: the resume stops with one line, before any training
    (run / "labels" / "0.json").write_text(json.dumps([0.5] * 5))
    process, log = start("pebble.py", resumed, EXTERNAL)
    assert process.wait(timeout=120) == 1
    lines = open(log).read().strip().splitlines()
    assert len(lines) == 1 and "runs/ext/labels/0.json is not the labels file this run trained on" in lines[0]

    # put back: the run resumes into round 1, with the same queries, and ends as the uninterrupted run
    (run / "labels" / "0.json").write_bytes(first)
    process, log = start("pebble.py", resumed, EXTERNAL)
    wait_for(lambda: "resuming runs/ext/state.pt at step 1000" in open(log).read(), process, log)
    second = answer(run, 1, process, log)
    assert process.wait(timeout=300) == 0, open(log).read()[-3000:]
    for key, value in queries_of(run, 1).items():
        np.testing.assert_array_equal(value, asked[key])
    assert_same_points(run, reference / "runs" / "ext")
    data = read_preferences(str(run / "preferences"))
    digests = [hashlib.sha256(content).hexdigest() for content in (first, second)]
    assert data["label_sha256"].tolist() == digests  # per round
    np.testing.assert_array_equal(data["labels"], np.array(json.loads(first) + json.loads(second), np.float32))
    assert status(run)["phase"] == "finished" and status(run)["labelled"] == 10 and status(run)["asked"] == 10


def assert_same_points(run, reference):
    """Every TensorBoard point of the uninterrupted run, bitwise (SPS aside: wall-clock)."""
    expected, actual = points(reference), points(run)
    assert sorted(expected) == sorted(actual)
    for tag in expected:
        if tag != "charts/SPS":
            assert actual[tag] == expected[tag], f"{tag} differs"


def test_a_kill_during_the_first_round_resumes_into_it(tmp_path):
    run = tmp_path / "runs" / "ext"
    process, log = start("pebble.py", tmp_path, EXTERNAL)
    wait_for(lambda: (run / "queries" / "0.npz").exists(), process, log)
    asked = queries_of(run, 0)
    assert (run / "state.pt").exists()  # written at the end of the step before the round: the run's first state
    process.send_signal(signal.SIGKILL)
    process.wait(timeout=60)
    process, log = start("pebble.py", tmp_path, EXTERNAL)
    wait_for(lambda: "resuming runs/ext/state.pt at step 500" in open(log).read(), process, log)
    answer(run, 0, process, log)
    answer(run, 1, process, log)
    assert process.wait(timeout=300) == 0, open(log).read()[-3000:]
    for key, value in queries_of(run, 0).items():
        np.testing.assert_array_equal(value, asked[key])


def test_teacher_json_says_the_step_while_training(tmp_path):
    """While the run trains, `teacher.json` says its current step: rewritten every 2 s of training at most (the
    page polls every 2 s), not at every step; waiting, it is the wait's."""
    args = SimpleNamespace(env_id="cartpole-swingup", max_feedback=10, total_timesteps=1500)
    teacher = ExternalTeacher(str(tmp_path), args, [], Stopped)
    teacher.training(0, 0.0)  # every step, as `Run.step_starts` calls it
    assert not (tmp_path / "teacher.json").exists()  # before the first round, the page reads the run's files
    teacher.tell("training", 500, asked=5, labelled=4)
    steps = []
    for step in range(501, 601):
        teacher.training(step, step / 16)  # 16 steps per second of training
        steps.append(status(tmp_path)["step"])
    assert sorted(set(steps)) == [501, 533, 565, 597]  # at once, then every 2 s
    assert {key: status(tmp_path)[key] for key in ("phase", "asked", "labelled", "round")} == {
        "phase": "training", "asked": 5, "labelled": 4, "round": None}
    assert time.time() - status(tmp_path)["updated"] < 60
    teacher.tell("waiting", 1000, asked=5, labelled=4, round_index=1, queries=5)
    teacher.training(1000, 1000.0)
    assert status(tmp_path)["phase"] == "waiting" and status(tmp_path)["step"] == 1000


def test_the_labels_sha256_are_kept_per_round_and_a_state_from_before_them_resumes():
    """A state written before the SHA-256 were kept has none for its rounds: the next rounds pad, and the resume's
    check has nothing to compare for the old ones."""
    queries = QueryLog(segment_steps=2, input_dim=3, physics_dim=1)
    rows = dict(inputs=np.zeros((2, 2, 2, 3)), true_rewards=np.zeros((2, 2, 2)), physics=np.zeros((2, 2, 2, 1)),
                labels=np.array([1.0, np.nan]))
    queries.add(**rows, round_index=-1, step=-1)  # `--preferences`: no round, no file
    queries.add(**rows, round_index=0, step=500, label_sha256="a" * 64)
    assert queries.label_sha256.tolist() == ["a" * 64]
    queries.label_sha256 = np.zeros(0, "<U64")  # as restored from an older state
    queries.add(**rows, round_index=1, step=1000, label_sha256="b" * 64)
    assert queries.label_sha256.tolist() == ["", "b" * 64] and len(queries.labels) == 6
    check_labels_unchanged("nowhere", {"rounds": queries.rounds})  # an older state: nothing recorded
    with pytest.raises(ValueError, match="nowhere/labels/1.json is not the labels file this run trained on"):
        check_labels_unchanged("nowhere", {"label_sha256": queries.label_sha256})


def test_a_round_writes_its_own_queries_only_and_the_folder_reads_as_the_whole_log(tmp_path):
    """`preferences/` gets one file per round; a later round leaves the earlier files as they are, and
    `read_preferences` joins them (seeded first) into the arrays of the whole query log."""
    queries = QueryLog(segment_steps=2, input_dim=3, physics_dim=1)
    rng = np.random.default_rng(0)
    folder = str(tmp_path / "preferences")

    def add(n, round_index, step, sha256=""):
        labels = rng.choice([0.0, 1.0, np.nan], size=n)
        queries.add(rng.normal(size=(n, 2, 2, 3)), rng.normal(size=(n, 2, 2)), rng.normal(size=(n, 2, 2, 1)), labels,
                    round_index, step, sha256)
        queries.save_round(folder, "cartpole-swingup", 2, round_index)

    add(3, -1, -1)
    add(2, 0, 500, "a" * 64)
    first = (tmp_path / "preferences" / "0.npz").read_bytes()
    stamp = os.stat(tmp_path / "preferences" / "0.npz").st_mtime_ns
    for round_index in range(1, 11):  # past 9: the rounds are read in numeric order
        add(1, round_index, 500 * (round_index + 1), f"{round_index % 10}" * 64)
    assert (tmp_path / "preferences" / "0.npz").read_bytes() == first
    assert os.stat(tmp_path / "preferences" / "0.npz").st_mtime_ns == stamp
    assert sorted(os.listdir(folder)) == sorted(["seeded.npz"] + [f"{r}.npz" for r in range(11)])
    data = read_preferences(folder)
    np.testing.assert_array_equal(data["obs"], queries.inputs[..., :2].astype(np.float32))
    np.testing.assert_array_equal(data["actions"], queries.inputs[..., 2:].astype(np.float32))
    for name in ("true_rewards", "physics", "labels", "rounds", "steps", "label_sha256"):
        np.testing.assert_array_equal(data[name], getattr(queries, name), err_msg=name)
    assert data["rounds"].tolist() == [-1] * 3 + [0] * 2 + list(range(1, 11))
    assert str(data["env_id"]) == "cartpole-swingup"
    # one file reads alone, as an earlier whole-log `.npz` does
    np.testing.assert_array_equal(read_preferences(f"{folder}/0.npz")["labels"], queries.labels[3:5])
    with pytest.raises(ValueError, match="no preferences files in"):
        read_preferences(str(tmp_path))


def test_a_folder_in_place_of_the_labels_file_is_one_line_and_the_wait_goes_on(tmp_path, capsys):
    """A folder at `labels/R.json` is a malformed labels file like any other: one line, the page's notice, and the
    run waits for a file instead of failing with a traceback. A resume that finds a folder where a labels file was
    refuses it with its one-line message."""
    import torch

    args = SimpleNamespace(env_id="cartpole-swingup", max_feedback=10, total_timesteps=100)
    teacher = ExternalTeacher(str(tmp_path), args, [], Stopped, poll_seconds=0.02)
    folder = tmp_path / "labels" / "0.json"
    folder.mkdir(parents=True)

    def answer_once_noticed():
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            if (tmp_path / "teacher.json").exists() and "folder" in (status(tmp_path)["message"] or ""):
                folder.rmdir()
                (tmp_path / "labels" / "1.tmp").write_text("[1, 0]")
                os.replace(tmp_path / "labels" / "1.tmp", folder)
                return
            time.sleep(0.02)

    helper = threading.Thread(target=answer_once_noticed)
    helper.start()
    keep, labels, _, _ = teacher.ask(0, "cartpole-swingup", 5, torch.zeros(2, 2, 3, 6), torch.zeros(2, 2, 3),
                                     np.zeros((2, 2, 3, 4)), step=0, asked=0, labelled=0)
    helper.join()
    assert keep.tolist() == [True, True] and labels.tolist() == [1.0, 0.0]
    lines = [line for line in capsys.readouterr().out.splitlines() if line.startswith("labels:")]
    assert lines == [f"labels: {folder}: a folder, not a file: move it; waiting for labels of "
                     f"{tmp_path}/queries/0.npz"]
    (tmp_path / "labels" / "1.json").mkdir()
    with pytest.raises(ValueError, match=r"1.json is not the labels file this run trained on"):
        check_labels_unchanged(str(tmp_path), {"label_sha256": ["", "0" * 64]})


def asked(tmp_path, write, seconds=60):
    """`ExternalTeacher.ask` for one round of 2 queries while `write(run)` plays the other side in a thread; the
    round is stopped after `seconds` (the test fails then, it does not hang). Returns the labels read."""
    import torch

    args = SimpleNamespace(env_id="cartpole-swingup", max_feedback=10, total_timesteps=100)
    stops = []
    teacher = ExternalTeacher(str(tmp_path), args, stops, Stopped, poll_seconds=0.02)
    timer = threading.Timer(seconds, stops.append, [signal.SIGTERM])
    timer.start()
    helper = threading.Thread(target=write, args=(tmp_path,))
    helper.start()
    physics = np.arange(2 * 2 * 3 * 4, dtype=np.float64).reshape(2, 2, 3, 4)
    try:
        _, labels, _, _ = teacher.ask(0, "cartpole-swingup", 5, torch.zeros(2, 2, 3, 6), torch.zeros(2, 2, 3), physics,
                                      step=0, asked=0, labelled=0)
    finally:
        timer.cancel()
        helper.join()
    return labels.tolist()


def wait_until(condition, seconds=30):
    deadline = time.monotonic() + seconds
    while not condition():
        assert time.monotonic() < deadline
        time.sleep(0.02)


def test_labels_for_other_queries_are_kept_aside_and_the_round_is_asked_again(tmp_path, capsys):
    """A valid labels file whose digest names other queries than those the run wrote (the page drew a replaced
    queries file) is not trained on: one line, the file moved aside whole, the page told, the round asked again."""
    from r2n_harness.external_teacher import queries_digest

    import label_app

    def write(run):
        wait_until(lambda: (run / "queries" / "0.npz").exists())
        digest = label_app.read_queries(str(run), 0).digest  # the page's digest of what the run wrote
        other = "0123456789abcdef"
        (run / "labels").mkdir()
        (run / "labels" / "0.json").write_text(json.dumps({"queries": other, "answers": [1, 1]}))
        wait_until(lambda: (run / "teacher.json").exists() and "not this round's" in (status(run)["message"] or ""))
        assert not (run / "labels" / "0.json").exists()
        (run / "labels" / "0.json").write_text(json.dumps({"queries": digest, "answers": [0, 1]}))

    assert asked(tmp_path, write) == [0.0, 1.0]
    [aside] = [p for p in os.listdir(tmp_path / "labels") if p.startswith("0.json.mismatch-")]
    assert json.loads((tmp_path / "labels" / aside).read_text()) == {"queries": "0123456789abcdef", "answers": [1, 1]}
    digest = queries_digest("cartpole-swingup", np.arange(48, dtype=np.float64).reshape(2, 2, 3, 4))
    lines = [line for line in capsys.readouterr().out.splitlines() if line.startswith("labels:")]
    assert lines == [f"labels: {tmp_path}/labels/0.json: answers the queries of digest 0123456789abcdef, not this "
                     f"round's ({digest}); kept as {tmp_path}/labels/{aside}; waiting for labels of "
                     f"{tmp_path}/queries/0.npz"]


def test_a_queries_file_replaced_under_a_waiting_run_is_said_at_once_and_written_again(tmp_path, capsys):
    import label_app

    def write(run):
        wait_until(lambda: (run / "queries" / "0.npz").exists())
        wrote = label_app.read_queries(str(run), 0).digest
        np.savez(run / "queries" / "tmp.npz", env_id="cartpole-swingup", physics=np.ones((3, 2, 3, 4)))
        os.replace(run / "queries" / "tmp.npz", run / "queries" / "0.npz")  # another round's file, in its place
        wait_until(lambda: label_app.read_queries(str(run), 0).digest == wrote)
        (run / "labels").mkdir()
        (run / "labels" / "0.json").write_text(json.dumps({"queries": wrote, "answers": [1, 0]}))

    assert asked(tmp_path, write) == [1.0, 0.0]
    lines = [line for line in capsys.readouterr().out.splitlines() if line.startswith("queries:")]
    assert len(lines) == 1 and lines[0].startswith(f"queries: {tmp_path}/queries/0.npz is no longer the file this run "
                                                   "wrote for round 0 (digest "), lines


def test_a_labels_file_is_read_by_its_content_not_its_time_stamp(tmp_path):
    """Two writes within one time-stamp tick: `[0, 1` in place, then a valid file with the same mtime. The run
    reads the second."""
    def write(run):
        wait_until(lambda: (run / "queries" / "0.npz").exists())
        (run / "labels").mkdir()
        path = run / "labels" / "0.json"
        path.write_text("[0, 1")
        stamp = os.stat(path).st_mtime_ns
        wait_until(lambda: (run / "teacher.json").exists() and "not JSON" in (status(run)["message"] or ""))
        with open(path, "w") as f:  # in place, as an editor may save
            f.write("[1, 1]")
        os.utime(path, ns=(stamp, stamp))

    assert asked(tmp_path, write) == [1.0, 1.0]


def test_a_folder_in_place_of_the_queries_file_is_one_line_and_the_wait_goes_on(tmp_path, capsys):
    """A folder at `queries/R.npz` cannot be replaced: the run says so once (and on the page) instead of failing
    with a traceback, writes the queries once it is moved, and takes the answers to them."""
    import torch

    args = SimpleNamespace(env_id="cartpole-swingup", max_feedback=10, total_timesteps=100)
    teacher = ExternalTeacher(str(tmp_path), args, [], Stopped, poll_seconds=0.02)
    folder = tmp_path / "queries" / "0.npz"
    folder.mkdir(parents=True)
    notices = []

    def answer_once_noticed():
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            message = (status(tmp_path)["message"] or "") if (tmp_path / "teacher.json").exists() else ""
            if "folder" in message and folder.is_dir():
                notices.append(message)
                time.sleep(0.1)  # a few more polls with the folder there: still one line
                folder.rmdir()
            if folder.is_file():  # answers bound to the queries now written (a bare list could race their write)
                (tmp_path / "labels").mkdir(exist_ok=True)
                answers = {"queries": status(tmp_path)["digest"], "answers": [1, 0]}
                (tmp_path / "labels" / "0.json").write_text(json.dumps(answers))
                return
            time.sleep(0.02)

    helper = threading.Thread(target=answer_once_noticed)
    helper.start()
    keep, labels, _, _ = teacher.ask(0, "cartpole-swingup", 5, torch.zeros(2, 2, 3, 6), torch.zeros(2, 2, 3),
                                     np.zeros((2, 2, 3, 4)), step=0, asked=0, labelled=0)
    helper.join()
    assert keep.tolist() == [True, True] and labels.tolist() == [1.0, 0.0]
    notice = f"queries: {folder}: a folder, not a file: move it; this run writes round 0's queries there"
    assert notices == [notice]
    lines = [line for line in capsys.readouterr().out.splitlines() if line.startswith("queries:")]
    assert lines[0] == notice and lines.count(notice) == 1
    assert status(tmp_path)["message"] is None and status(tmp_path)["phase"] == "training"
