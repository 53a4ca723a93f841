"""The labelling page (README: "Labelling by hand"), on a run folder written by hand: labels written once (409 for a
second answer, a malformed file set aside, never deleted), the run's state from `teacher.json`, bad requests, and
the page in a real headless Chromium (two tabs, clips before answers, undo, the run's states)."""
import contextlib
import http.client
import json
import os
import shutil
import socket
import subprocess
import sys
import time

import numpy as np
import pytest

from test_labelling import answers_enabled, chrome, free_port, needs_chromium
from test_scripts import ROOT

LABEL_APP = os.path.join(ROOT, "label_app.py")


def make_run(tmp_path, queries_per_round=(3,), teacher=None):
    """A run folder as `--teacher external` writes it: `queries/{r}.npz` per round (3-step cartpole segments, which
    render fast), and `teacher.json` if given."""
    run = tmp_path / "runs" / "ext"
    (run / "queries").mkdir(parents=True)
    for r, n in enumerate(queries_per_round):
        physics = np.zeros((n, 2, 3, 4))
        physics[:, 1, :, 0] = 0.5  # the right segment's cart stands elsewhere
        np.savez(run / "queries" / f"{r}.npz", env_id="cartpole-swingup", obs=np.zeros((n, 2, 3, 5), np.float32),
                 actions=np.zeros((n, 2, 3, 1), np.float32), physics=physics, true_rewards=np.zeros((n, 2, 3)))
    if teacher is not None:
        write_teacher(run, **teacher)
    return run


def write_teacher(run, **changes):
    """The run's status file, as the run writes it (atomically), with `changes`."""
    teacher = {"task": "cartpole-swingup", "run": "ext", "pid": os.getpid(), "host": socket.gethostname(),
               "phase": "waiting", "round": 0, "queries": 3, "asked": 0, "labelled": 0, "budget": 10, "step": 500,
               "total_steps": 1500, "message": None, "updated": time.time(), **changes}
    (run / "teacher.json.tmp").write_text(json.dumps(teacher))
    os.replace(run / "teacher.json.tmp", run / "teacher.json")


@contextlib.contextmanager
def serve(run, **env):
    """The app on a free port, as a subprocess: yields its address; afterwards, its output has no traceback."""
    port = free_port()
    app = subprocess.Popen([sys.executable, LABEL_APP, str(run), "--port", str(port)], stdout=subprocess.PIPE,
                           stderr=subprocess.STDOUT, text=True, env=dict(os.environ, OMP_NUM_THREADS="1", **env))
    try:
        assert app.stdout.readline().startswith(f"labelling {run} at http://127.0.0.1:{port}"), "the app did not start"
        yield f"127.0.0.1:{port}"
    finally:
        app.terminate()
        output = app.communicate(timeout=30)[0]
    assert "Traceback" not in output, output


def request(address, method, path, body=None, headers=None):
    """(status, body) of one request, with exactly the given headers (a POST gets its Content-Length unless given)."""
    connection = http.client.HTTPConnection(address, timeout=30)
    connection.putrequest(method, path)
    headers = {"Content-Length": str(len(body))} if headers is None and body is not None else headers or {}
    for key, value in headers.items():
        connection.putheader(key, value)
    connection.endheaders()
    if body is not None:
        connection.send(body)
    reply = connection.getresponse()
    result = reply.status, reply.read()
    connection.close()
    return result


def get_state(address):
    status, body = request(address, "GET", "/api/state")
    assert status == 200
    return json.loads(body)


def test_label_app_writes_a_round_once(tmp_path):
    run = make_run(tmp_path, (3, 3))
    (run / "labels").mkdir()
    written = b'[1,  0, "skip"]\n'  # by hand: its bytes stay as they are
    (run / "labels" / "0.json").write_bytes(written)
    with serve(run) as address:
        assert get_state(address)["round"] == 1
        status, body = request(address, "POST", "/api/labels/0", b"[0, 0, 0]")
        assert status == 409 and body.decode() == ("round 0 is already answered (labels/0.json); a round's labels are "
                                                   "written once and never change")
        assert (run / "labels" / "0.json").read_bytes() == written
        assert request(address, "POST", "/api/labels/1", b'[0.5, 1, "skip"]')[0] == 200
        assert request(address, "POST", "/api/labels/1", b"[0, 0, 0]")[0] == 409
        assert json.loads((run / "labels" / "1.json").read_text()) == [0.5, 1, "skip"]
        assert get_state(address)["round"] is None
    assert sorted(os.listdir(run / "labels")) == ["0.json", "1.json"]  # no temporary file left


def test_label_app_state_from_the_files_and_teacher_json(tmp_path):
    run = make_run(tmp_path, (3, 3, 3))
    (run / "labels").mkdir()
    (run / "labels" / "0.json").write_text('[1, "skip", 0.5]')
    (run / "labels" / "1.json").write_text("[1, 0]")
    with serve(run) as address:
        # no teacher.json (an older run, or one that has not asked yet): the files alone
        assert get_state(address) == {
            "run": "ext", "task": "cartpole-swingup", "round": 1, "n": 3,
            "malformed": 'expected a list of 3 answers, each 0, 1, 0.5 or "skip"', "rounds_answered": 1, "labels": 2,
            "teacher": None, "silent_for": None}
        write_teacher(run, round=1, asked=3, labelled=2)
        state = get_state(address)
        assert state["teacher"]["phase"] == "waiting" and state["labels"] == 2 and state["silent_for"] is None
        write_teacher(run, labelled=7)
        assert get_state(address)["labels"] == 7  # the run's own count, when it has one
        write_teacher(run, updated=time.time() - 100)  # waiting, and no news for 100 s
        assert 100 <= get_state(address)["silent_for"] < 130
        gone = subprocess.Popen(["true"])
        gone.wait()
        write_teacher(run, phase="training", pid=gone.pid)  # a process of this machine that has gone
        assert get_state(address)["silent_for"] is not None
        write_teacher(run, phase="training", pid=gone.pid, host="elsewhere")  # another machine's: cannot tell
        assert get_state(address)["silent_for"] is None
        write_teacher(run, phase="finished", pid=gone.pid, updated=time.time() - 100)
        assert get_state(address)["silent_for"] is None


def test_label_app_answers_bad_requests_and_serves_on(tmp_path):
    run = make_run(tmp_path, (3,))
    nested = b"[" * 20000 + b"]" * 20000  # under the size limit, beyond json's recursion limit
    with serve(run) as address:
        for method, path, body, headers, code in [
            ("GET", "/nothing", None, None, 404),
            ("GET", "/clip/1/0/0.gif", None, None, 404),  # a round without queries
            ("GET", "/clip/0/3/0.gif", None, None, 404),  # query 3 of a round of 3 (0, 1, 2)
            ("GET", "/clip/0/0/2.gif", None, None, 404),
            ("POST", "/api/other", b"[]", None, 404),
            ("POST", "/api/labels/1", b"[0, 0, 0]", None, 404),  # a round without queries
            ("POST", "/api/labels/0", None, {}, 400),  # no Content-Length
            ("POST", "/api/labels/0", b"[0, 0, 0]", {"Content-Length": "three"}, 400),
            ("POST", "/api/labels/0", b"[0, 0, 0]", {"Content-Length": "-9"}, 400),
            ("POST", "/api/labels/0", b"[0, 0,", None, 400),
            ("POST", "/api/labels/0", b"\xff\xfe", None, 400),
            ("POST", "/api/labels/0", nested, None, 400),
            ("POST", "/api/labels/0", b"[0, 2, 0]", None, 400),
            ("POST", "/api/labels/0", b"[0, 1]", None, 400),
            ("POST", "/api/labels/0", b'{"answers": [0, 1, 0]}', None, 400),
            ("POST", "/api/labels/0", None, {"Content-Length": "70000"}, 413),  # refused before a body is sent
        ]:
            status, reply = request(address, method, path, body, headers)
            assert status == code and len(reply.decode().splitlines()) == 1, (method, path, status, reply)
            assert get_state(address)["round"] == 0  # serving on, nothing written
        assert not (run / "labels").exists() or os.listdir(run / "labels") == []


def test_label_app_port_in_use(tmp_path):
    run = make_run(tmp_path)
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        result = subprocess.run([sys.executable, LABEL_APP, str(run), "--port", str(port)], capture_output=True,
                                text=True, timeout=120, env=dict(os.environ, OMP_NUM_THREADS="1"))
    assert result.returncode == 1 and result.stderr == f"label_app: error: --port {port}: address already in use\n"
