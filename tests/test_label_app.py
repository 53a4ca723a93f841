"""The labelling page (docs/labelling.md), on a run folder written by hand: labels written once (409 for a
second answer, a malformed file set aside, never deleted), by the page's own origin only, the run's state from
`teacher.json`, bad requests, and the page in a real headless Chromium (two tabs, clips shown before answers, undo,
answers kept through a reload and a server error, a round answered elsewhere, a double click and a held key, another
origin's page, the run's states)."""
import contextlib
import http.client
import http.server
import json
import os
import resource
import shutil
import socket
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from label_examples import INVALID, VALID
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
def serve(run, processes=None, **env):
    """The app on a free port, as a subprocess: yields its address (and appends its process to `processes`, if
    given); afterwards, its output has no traceback."""
    port = free_port()
    app = subprocess.Popen([sys.executable, LABEL_APP, str(run), "--port", str(port)], stdout=subprocess.PIPE,
                           stderr=subprocess.STDOUT, text=True, env=dict(os.environ, OMP_NUM_THREADS="1", **env))
    if processes is not None:
        processes.append(app)
    try:
        assert app.stdout.readline().startswith(f"labelling {run} at http://127.0.0.1:{port}"), "the app did not start"
        yield f"127.0.0.1:{port}"
    finally:
        app.terminate()
        output = app.communicate(timeout=30)[0]
    assert "Traceback" not in output, output


JSON = {"Content-Type": "application/json"}


def request(address, method, path, body=None, headers=None, reply_headers=False):
    """(status, body) of one request, with exactly the given headers (a body gets its Content-Length and the JSON
    Content-Type unless headers are given; Host is the address unless given); with `reply_headers`, (status, body,
    the reply's headers)."""
    connection = http.client.HTTPConnection(address, timeout=30)
    headers = {"Content-Length": str(len(body)), **JSON} if headers is None and body is not None else headers or {}
    connection.putrequest(method, path, skip_host="Host" in headers)
    for key, value in headers.items():
        connection.putheader(key, value)
    connection.endheaders()
    if body is not None:
        connection.send(body)
    reply = connection.getresponse()
    result = reply.status, reply.read(), dict(reply.getheaders())
    connection.close()
    return result if reply_headers else result[:2]


def bound(run, round_index, answers):
    """A POST body as the page sends it: the answers, with the digest of the round's queries file."""
    import label_app

    return json.dumps({"queries": label_app.read_queries(str(run), round_index).digest, "answers": answers}).encode()


def page_answers(run, round_index):
    """The answers of a labels file that the page wrote: bound to the digest of the round's queries file."""
    import label_app

    written = json.loads((run / "labels" / f"{round_index}.json").read_text())
    assert set(written) == {"queries", "answers"}, written
    assert written["queries"] == label_app.read_queries(str(run), round_index).digest
    return written["answers"]


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
        status, body = request(address, "POST", "/api/labels/0", bound(run, 0, [0, 0, 0]))
        assert status == 409 and body.decode() == ("round 0 is already answered (labels/0.json); a round's labels are "
                                                   "written once and never change")
        assert (run / "labels" / "0.json").read_bytes() == written
        assert request(address, "POST", "/api/labels/1", bound(run, 1, [0.5, 1, "skip"]))[0] == 200
        assert request(address, "POST", "/api/labels/1", bound(run, 1, [0, 0, 0]))[0] == 409
        assert page_answers(run, 1) == [0.5, 1, "skip"]
        assert get_state(address)["round"] is None
    assert sorted(os.listdir(run / "labels")) == ["0.json", "1.json"]  # no temporary file left


def test_label_app_refuses_answers_that_name_no_queries(tmp_path):
    """Answers sent without the digest of the queries they answer would be bound to whatever queries the run holds
    when it reads them: one line, HTTP 400, nothing written. A program may still write a bare list into `labels/`."""
    run = make_run(tmp_path, (3,))
    with serve(run) as address:
        status, reply = request(address, "POST", "/api/labels/0", b"[0, 1, 0.5]")
        assert status == 400 and reply.decode() == (
            'round 0\'s answers were not saved: they name no queries; send {"queries": digest, "answers": [...]} with '
            "the digest of the queries answered, as the page does (a program may write a bare list to labels/0.json "
            "itself)")
        assert not (run / "labels").exists() and get_state(address)["round"] == 0
        (run / "labels").mkdir()
        (run / "labels" / "0.json").write_text("[0, 1, 0.5]")  # a program's, by hand: the round is answered
        assert get_state(address)["round"] is None


def test_label_app_draws_a_gymnasium_segment_again_as_the_run_drew_it(tmp_path, monkeypatch):
    """A queried segment of a gymnasium task (Hopper-v5, with the noise), stored as a run stores it (the physics state
    of each step), comes back from the page as the frames drawn during the run: equal up to the GIF's palette, and
    each frame nearer its own step than any other step of the segment."""
    import imageio.v3 as iio

    sys.path.insert(0, ROOT)
    import ene

    monkeypatch.setenv("MUJOCO_GL", "egl")  # the run's drawing, here; the app sets it for itself
    env = ene.make_env("Hopper-v5", seed=0, noise=0.9, episode_length=100)
    obs, _ = env.reset(seed=0)
    draw = ene.MujocoFrames(env.unwrapped, 240, 320)  # the page's size
    rows, states, drawn = [], [], []
    for t in range(48):
        action = env.action_space.sample()
        if t % 4 == 0:  # every 4th step: frames that differ clearly
            rows.append((obs, action))
            states.append(env.physics_state())
            drawn.append(draw(states[-1]))
        obs = env.step(action)[0]
    draw.close()
    env.close()
    shape = (1, 2, 6)  # one query of two 6-step segments: the first and the second half of the steps
    run = tmp_path / "runs" / "ext"
    (run / "queries").mkdir(parents=True)
    np.savez(run / "queries" / "0.npz", env_id="Hopper-v5", obs=np.stack([o for o, _ in rows]).reshape(*shape, 111),
             actions=np.stack([a for _, a in rows]).reshape(*shape, 3), physics=np.stack(states).reshape(*shape, 12),
             true_rewards=np.zeros(shape))
    with serve(run) as address:
        clips = [request(address, "GET", f"/clip/0/0/{side}.gif") for side in (0, 1)]
    assert [status for status, _ in clips] == [200, 200]
    frames = np.concatenate([iio.imread(body, index=None, extension=".gif")[..., :3] for _, body in clips])
    drawn = np.stack(drawn)
    assert frames.shape == drawn.shape == (12, 240, 320, 3)
    errors = np.abs(frames[:, None].astype(int) - drawn[None].astype(int)).mean((2, 3, 4))  # (page frame, run frame)
    assert np.all(np.diag(errors) < 1.0), np.diag(errors)
    assert np.array_equal(errors.argmin(1), np.arange(12)), errors.argmin(1)


def test_label_app_takes_exactly_the_labels_the_run_takes():
    """The page's check of a labels file, on the table the run's check is tested on (tests/label_examples.py)."""
    sys.path.insert(0, ROOT)
    import label_app

    for content, n in VALID:
        loaded = json.loads(content)
        assert label_app.parse_answers(content, n) == (loaded["answers"] if isinstance(loaded, dict) else loaded), content
    for content, n in INVALID:
        with pytest.raises(ValueError):
            label_app.parse_answers(content, n)


def test_label_app_sets_aside_malformed_files_only(tmp_path, monkeypatch):
    sys.path.insert(0, ROOT)
    import label_app

    path = str(tmp_path / "0.json")
    for text in ("[1, 2", "[1, 0"):  # two malformed files within a second: both kept
        (tmp_path / "0.json").write_text(text)
        assert not label_app.keeps_existing(path, 2) and not os.path.exists(path)
    kept = sorted(name for name in os.listdir(tmp_path))
    assert len(kept) == 2 and kept[0].startswith("0.json.rejected-") and kept[1] == kept[0] + "-2"
    assert [(tmp_path / name).read_text() for name in kept] == ["[1, 2", "[1, 0"]
    # a name taken by another process after it looked free is not renamed onto: the reservation is exclusive
    (tmp_path / "0.json").write_text("[0, 1")
    with monkeypatch.context() as race:
        race.setattr(label_app.os.path, "exists", lambda p: False)
        assert not label_app.keeps_existing(path, 2)
    assert [(tmp_path / name).read_text() for name in kept] == ["[1, 2", "[1, 0"]
    [third] = set(os.listdir(tmp_path)) - set(kept)  # the race's file, set aside under a name of its own
    assert (tmp_path / third).read_text() == "[0, 1"
    (tmp_path / third).unlink()
    # a file that is gone meanwhile leaves no placeholder behind
    assert not label_app.keeps_existing(path, 2) and sorted(os.listdir(tmp_path)) == kept
    # a valid file that replaced the malformed one between the check and the move is moved back: it is the answer
    (tmp_path / "0.json").write_text("[1, 0]")
    checks = iter([False])  # the check before the move saw the malformed file
    monkeypatch.setattr(label_app, "is_valid", lambda p, n, queries_digest=None: next(checks, True))
    assert label_app.keeps_existing(path, 2)
    assert (tmp_path / "0.json").read_text() == "[1, 0]" and sorted(os.listdir(tmp_path)) == ["0.json", *kept]


def test_label_app_state_from_the_files_and_teacher_json(tmp_path):
    run = make_run(tmp_path, (3, 3, 3))
    (run / "labels").mkdir()
    (run / "labels" / "0.json").write_text('[1, "skip", 0.5]')
    (run / "labels" / "1.json").write_text("[1, 0]")
    with serve(run) as address:
        # no teacher.json (an older run, or one that has not asked yet): the files alone
        state = get_state(address)
        assert len(state.pop("queries_digest")) == 16
        assert state == {
            "run": "ext", "task": "cartpole-swingup", "round": 1, "n": 3,
            "malformed": 'expected a list of 3 answers, each 0, 1, 0.5 or "skip"', "blocked": None, "foreign": None,
            "rounds_answered": 1, "labels": 2, "teacher": None, "teacher_problem": None, "silent_for": None}
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
            ("POST", "/api/labels/0", None, JSON, 400),  # no Content-Length
            ("POST", "/api/labels/0", b"[0, 0, 0]", {"Content-Length": "three", **JSON}, 400),
            ("POST", "/api/labels/0", b"[0, 0, 0]", {"Content-Length": "-9", **JSON}, 400),
            ("POST", "/api/labels/0", b"[0, 0,", None, 400),
            ("POST", "/api/labels/0", b"\xff\xfe", None, 400),
            ("POST", "/api/labels/0", nested, None, 400),
            ("POST", "/api/labels/0", b"[0, 2, 0]", None, 400),
            ("POST", "/api/labels/0", b"[0, 1]", None, 400),
            ("POST", "/api/labels/0", b'{"answers": [0, 1, 0]}', None, 400),
            ("POST", "/api/labels/0", None, {"Content-Length": "70000", **JSON}, 413),  # refused before a body is sent
        ]:
            status, reply = request(address, method, path, body, headers)
            assert status == code and len(reply.decode().splitlines()) == 1, (method, path, status, reply)
            assert get_state(address)["round"] == 0  # serving on, nothing written
        assert not (run / "labels").exists() or os.listdir(run / "labels") == []


def test_label_app_writes_for_its_own_page_only(tmp_path):
    """Another origin's page, a DNS rebinding (a host name of the attacker's that resolves to this machine) and a
    body that is not JSON cannot write labels; the page's own origin and a script (no Origin header) can."""
    run = make_run(tmp_path, (3, 3, 3))
    with serve(run) as address:
        port = address.split(":")[1]
        body = bound(run, 0, [0, 0, 0])  # the three rounds hold the same queries
        length = {"Content-Length": str(len(body))}
        for headers, code in [
            ({**length, **JSON, "Origin": "http://evil.example"}, 403),
            ({**length, **JSON, "Origin": f"http://127.0.0.1:{int(port) + 1}"}, 403),  # another port: another origin
            ({**length, **JSON, "Origin": "null"}, 403),  # a sandboxed frame or a file
            ({**length, **JSON, "Host": f"evil.example:{port}", "Origin": f"http://evil.example:{port}"}, 403),
            ({**length, **JSON, "Host": f"127.0.0.1.evil.example:{port}"}, 403),
            ({**length, **JSON, "Host": f"evil.example@127.0.0.1:{port}"}, 403),
            ({**length, "Content-Type": "text/plain"}, 415),  # what a page may send to another origin unasked
            ({**length, "Content-Type": "application/x-www-form-urlencoded"}, 415),
            ({**length, "Content-Type": "multipart/form-data; boundary=x"}, 415),
            (length, 415),
        ]:
            status, reply = request(address, "POST", "/api/labels/0", body, headers)
            assert status == code and len(reply.decode().splitlines()) == 1, (headers, status, reply)
        for path in ("/", "/api/state", "/clip/0/0/0.gif"):  # a rebound name reads nothing either
            status, reply = request(address, "GET", path, headers={"Host": f"evil.example:{port}"})
            assert status == 403 and reply.decode() == (
                f"refused: evil.example:{port} is not this app's address (127.0.0.1 or localhost)"), reply
        # a preflight, which a page needs to send JSON to another origin, is refused
        status, reply, headers = request(address, "OPTIONS", "/api/labels/0", headers={
            "Origin": "http://evil.example", "Access-Control-Request-Method": "POST",
            "Access-Control-Request-Headers": "content-type"}, reply_headers=True)
        assert status == 405 and not [key for key in headers if key.lower().startswith("access-control-")]
        assert not (run / "labels").exists() or os.listdir(run / "labels") == []
        # the page's own origin, under each name of this machine's loopback address; a script sends no Origin
        for r, host in enumerate([f"127.0.0.1:{port}", f"localhost:{port}", f"LocalHost:{port}"]):
            headers = {**length, "Content-Type": "application/json; charset=utf-8", "Host": host,
                       "Origin": f"http://{host.lower()}"}
            assert request(address, "POST", f"/api/labels/{r}", body, headers)[0] == 200, host
        assert sorted(os.listdir(run / "labels")) == ["0.json", "1.json", "2.json"]


def test_label_app_host_names():
    """The names a request's Host may give, by the address the app binds: any port (a tunnel may forward another)."""
    sys.path.insert(0, ROOT)
    import label_app

    loopback, wildcard, lan = (label_app.Address(bound) for bound in ("127.0.0.1", "0.0.0.0", "192.168.1.5"))
    for host in ("127.0.0.1:8000", "localhost:8000", "LOCALHOST:9000", "[::1]:8000", "localhost"):
        assert loopback.serves(host) and wildcard.serves(host), host
    for host in ("192.168.1.5:8000", "10.0.0.7:8000", "[fe80::1]:8000", f"{socket.gethostname()}:8000"):
        assert wildcard.serves(host) and not loopback.serves(host), host
    assert lan.serves("192.168.1.5:8000") and not lan.serves("localhost:8000") and not lan.serves("10.0.0.7:8000")
    for host in (None, "", "evil.example:8000", "127.0.0.1.nip.io:8000", "localhost.evil.example", "a@127.0.0.1:8000",
                 "127.0.0.1:80:80", "127.0.0.1 :8000"):
        assert not loopback.serves(host) and not wildcard.serves(host), host
    assert (str(loopback), str(label_app.Address("localhost")), str(lan)) == (
        "127.0.0.1 or localhost", "localhost", "192.168.1.5")


def test_label_app_other_methods_get_one_line(tmp_path):
    """Methods other than GET, HEAD and POST: 405 and one line; HEAD is GET without the body."""
    run = make_run(tmp_path, (3,))
    with serve(run) as address:
        for method in ("PUT", "DELETE", "PATCH", "OPTIONS", "TRACE", "CONNECT", "BREW"):
            status, reply, headers = request(address, method, "/api/labels/0", b"[0, 0, 0]", reply_headers=True)
            assert status == 405 and headers["Allow"] == "GET, HEAD, POST", (method, status)
            assert reply.decode() == f"the method {method} is not allowed: the app answers GET, HEAD and POST"
        host, port = address.split(":")
        with socket.create_connection((host, int(port)), timeout=30) as raw:
            raw.sendall(b"GET /a b HTTP/1.1\r\n\r\n")  # a malformed request line: http.server's own 400
            reply = http.client.HTTPResponse(raw)
            reply.begin()
            assert reply.status == 400 and reply.read() == b"Bad request syntax ('GET /a b HTTP/1.1')"
        status, reply, headers = request(address, "HEAD", "/api/state", reply_headers=True)
        assert status == 200 and reply == b"" and int(headers["Content-Length"]) > 0
        assert headers["Content-Type"] == "application/json"
        assert request(address, "HEAD", "/nothing")[0] == 404
        assert get_state(address)["round"] == 0
    assert not (run / "labels").exists()


def test_label_app_state_with_a_teacher_json_it_cannot_read(tmp_path):
    """A `teacher.json` that is not the run's: the state from the files, and one line saying why, not a 500."""
    run = make_run(tmp_path, (3,))
    with serve(run) as address:
        for text, problem in [
            ('{"phase": "training", "step": 3}', "teacher.json cannot be read (it lacks the keys task, run, pid, "
                                                  "host, round, queries, asked, labelled, budget, total_steps, "
                                                  "message, updated): the page shows what the run's files say"),
            ("[1, 2]", "teacher.json cannot be read (not a JSON object): the page shows what the run's files say"),
            ("{", "teacher.json cannot be read (not JSON: Expecting property name enclosed in double quotes: line 1 "
                  "column 2 (char 1)): the page shows what the run's files say"),
        ]:
            (run / "teacher.json").write_text(text)
            state = get_state(address)
            assert state["teacher_problem"] == problem and state["teacher"] is None and state["round"] == 0
        for key, value in [("updated", "yesterday"), ("pid", "1234"), ("pid", 0), ("pid", 2 ** 80), ("pid", True)]:
            write_teacher(run, **{key: value})
            state = get_state(address)
            assert state["teacher_problem"] == f"teacher.json cannot be read ({key} is {json.dumps(value)}, not a "  \
                f"{'positive whole number' if key == 'pid' else 'number'}): the page shows what the run's files say"
            assert state["teacher"] is None
        write_teacher(run)
        assert get_state(address)["teacher_problem"] is None


def test_label_app_port_in_use(tmp_path):
    run = make_run(tmp_path)
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        result = subprocess.run([sys.executable, LABEL_APP, str(run), "--port", str(port)], capture_output=True,
                                text=True, timeout=120, env=dict(os.environ, OMP_NUM_THREADS="1"))
    assert result.returncode == 1 and result.stderr == f"label_app: error: --port {port}: address already in use\n"


def open_page(driver, address):
    from selenium.webdriver.common.by import By

    driver.get(f"http://{address}/")
    return lambda element="progress": driver.find_element(By.ID, element).text


def answer_round(driver, keys, submit=True):
    """Answer the queries shown, one key each once the page takes answers, then submit with Enter."""
    from selenium.webdriver.common.by import By
    from selenium.webdriver.common.keys import Keys
    from selenium.webdriver.support.ui import WebDriverWait

    body = driver.find_element(By.TAG_NAME, "body")
    for key in keys:
        WebDriverWait(driver, 60).until(answers_enabled)
        body.send_keys(key)
    WebDriverWait(driver, 30).until(lambda d: d.find_element(By.ID, "submit").is_displayed())
    if submit:
        body.send_keys(Keys.ENTER)


@needs_chromium
def test_label_app_two_tabs_answering_a_round_in_a_headless_browser(tmp_path):
    from selenium.webdriver.common.keys import Keys
    from selenium.webdriver.support.ui import WebDriverWait

    run = make_run(tmp_path, (2,))
    with serve(run) as address, contextlib.closing(chrome()) as first, contextlib.closing(chrome()) as second:
        texts = [open_page(driver, address) for driver in (first, second)]
        for driver, text in zip((first, second), texts):
            WebDriverWait(driver, 60).until(lambda d: text() == "round 0: query 1 of 2")
        answer_round(first, [Keys.ARROW_LEFT, Keys.ARROW_RIGHT], submit=False)
        answer_round(second, [Keys.ARROW_RIGHT, "="], submit=False)
        # the second tab hears nothing from the app until it submits, so it cannot see the round answered before
        second.execute_cdp_cmd("Network.enable", {})
        second.execute_cdp_cmd("Network.setBlockedURLs", {"urls": ["*/api/state"]})
        WebDriverWait(second, 30).until(lambda d: texts[1]("notices").startswith("the page could not get the run's state"))
        answer_round(first, [])  # the first tab submits first and wins
        WebDriverWait(first, 30).until(lambda d: texts[0]("message") == "round 0 saved (labels/0.json)")
        answer_round(second, [])
        WebDriverWait(second, 30).until(lambda d: texts[1]("message") == (
            "round 0 was already answered, perhaps in another tab: your answers for it were not used"))
        assert page_answers(run, 0) == [0, 1]
        assert stored(first) == stored(second) == {}  # told, then dropped
        second.execute_cdp_cmd("Network.setBlockedURLs", {"urls": []})
        for driver, text in zip((first, second), texts):  # both move on
            WebDriverWait(driver, 30).until(lambda d: text() == "no round is waiting for labels; this page checks every 2 s")


@needs_chromium
def test_label_app_malformed_labels_file_in_a_headless_browser(tmp_path):
    from selenium.webdriver.common.keys import Keys
    from selenium.webdriver.support.ui import WebDriverWait

    run = make_run(tmp_path, (2,))
    (run / "labels").mkdir()
    (run / "labels" / "0.json").write_bytes(b"[1, 2")  # by hand, unfinished
    with serve(run) as address, contextlib.closing(chrome()) as driver:
        text = open_page(driver, address)
        WebDriverWait(driver, 60).until(lambda d: text() == "round 0: query 1 of 2")
        WebDriverWait(driver, 30).until(lambda d: text("notices").startswith("labels/0.json is not valid: not JSON: "))
        assert text("notices").endswith("Submitting round 0's answers from this page replaces it (the old file is kept "
                                        "as labels/0.json.rejected-...).")
        answer_round(driver, ["s", Keys.ARROW_LEFT])
        WebDriverWait(driver, 30).until(lambda d: text("message") == "round 0 saved (labels/0.json)")
        assert page_answers(run, 0) == ["skip", 0]
        rejected = [name for name in os.listdir(run / "labels") if name != "0.json"]
        assert len(rejected) == 1 and rejected[0].startswith("0.json.rejected-")
        assert abs(int(rejected[0].split("-")[1]) - time.time()) < 60
        assert (run / "labels" / rejected[0]).read_bytes() == b"[1, 2"
        WebDriverWait(driver, 30).until(lambda d: text("notices") == "")


@needs_chromium
def test_label_app_state_older_than_a_submit_in_a_headless_browser(tmp_path):
    """A state read before a submit saved its round, and received after, is not the app's word that the round waits
    again: the page keeps "saved" and does not ask the round again."""
    from selenium.webdriver.common.by import By
    from selenium.webdriver.common.keys import Keys
    from selenium.webdriver.support.ui import WebDriverWait

    run = make_run(tmp_path, (2,))
    with serve(run, R2N_LABEL_APP_STATE_DELAY="3") as address, contextlib.closing(chrome()) as driver:
        text = open_page(driver, address)
        WebDriverWait(driver, 60).until(lambda d: text() == "round 0: query 1 of 2")
        answer_round(driver, [Keys.ARROW_LEFT, Keys.ARROW_RIGHT], submit=False)
        driver.execute_script("window.stale = refresh();")  # round 0 waiting, read now, received 3 s later
        time.sleep(1)
        driver.find_element(By.TAG_NAME, "body").send_keys(Keys.ENTER)
        WebDriverWait(driver, 30).until(lambda d: text("message") == "round 0 saved (labels/0.json)")
        driver.execute_async_script("window.stale.then(arguments[arguments.length - 1]);")
        WebDriverWait(driver, 30).until(lambda d: text() == "no round is waiting for labels; this page checks every 2 s")
        assert text("message") == "round 0 saved (labels/0.json)"
        assert page_answers(run, 0) == [0, 1]


@needs_chromium
def test_label_app_clips_before_answers_and_undo_in_a_headless_browser(tmp_path):
    from selenium.webdriver.common.by import By
    from selenium.webdriver.common.keys import Keys
    from selenium.webdriver.support.ui import WebDriverWait

    run = make_run(tmp_path, (3,))
    # every clip takes 2 s more: the page is seen before its clips have loaded
    with serve(run, R2N_LABEL_APP_CLIP_DELAY="2") as address, contextlib.closing(chrome()) as driver:
        text = open_page(driver, address)
        body = driver.find_element(By.TAG_NAME, "body")
        clips = driver.find_element(By.ID, "clips")
        loaded = "return document.getElementById('left').complete && document.getElementById('right').complete"

        def query(i, fresh=True):
            """Query i of 3 is shown; a fresh one (its clips never loaded) at first without clips, its answers not
            taken; then with both clips."""
            WebDriverWait(driver, 30).until(lambda d: text() == f"round 0: query {i} of 3")
            if fresh:
                assert not answers_enabled(driver) and not clips.is_displayed()
                assert text("drawing") == f"the app is drawing the clips of query {i}..."  # not a blank page
                body.send_keys(Keys.ARROW_LEFT)  # not taken
            WebDriverWait(driver, 60).until(answers_enabled)
            assert text() == f"round 0: query {i} of 3" and clips.is_displayed() and driver.execute_script(loaded)
            assert text("drawing") == ""

        query(1)
        driver.find_element(By.ID, "answer-left").click()
        query(2)  # its clips were fetched ahead, but are still on their way
        body.send_keys("=")
        query(3)
        body.send_keys("s")
        WebDriverWait(driver, 30).until(lambda d: text() == "round 0: all 3 answered")
        assert text("submit") == "\u23ce submit round 0" and not clips.is_displayed()
        driver.find_element(By.ID, "undo").click()  # the last answer too can be undone
        query(3, fresh=False)
        body.send_keys(Keys.ARROW_RIGHT)
        WebDriverWait(driver, 30).until(lambda d: text() == "round 0: all 3 answered")
        body.send_keys(Keys.BACKSPACE, Keys.BACKSPACE)  # back to query 2
        query(2, fresh=False)
        body.send_keys(Keys.ARROW_RIGHT)
        query(3, fresh=False)
        body.send_keys(Keys.ARROW_LEFT)
        WebDriverWait(driver, 30).until(lambda d: text() == "round 0: all 3 answered")
        assert not (run / "labels" / "0.json").exists()  # nothing is written before the round is submitted
        body.send_keys(Keys.ENTER)
        WebDriverWait(driver, 30).until(lambda d: text("message") == "round 0 saved (labels/0.json)")
        assert page_answers(run, 0) == [0, 1, 0]


@needs_chromium
def test_label_app_run_states_in_a_headless_browser(tmp_path):
    from selenium.webdriver.support.ui import WebDriverWait

    run = make_run(tmp_path, (3, 3), teacher={"phase": "training", "round": None, "queries": None, "asked": 6,
                                             "labelled": 5, "step": 1000})
    (run / "labels").mkdir()
    (run / "labels" / "0.json").write_text('[1, 0, "skip"]')
    (run / "labels" / "1.json").write_text("[1, 0, 0]")
    with serve(run) as address, contextlib.closing(chrome()) as driver:
        text = open_page(driver, address)
        WebDriverWait(driver, 30).until(lambda d: text() == "no round is waiting; the run is training (step 1000 of 1500)")
        assert text("run") == "cartpole-swingup \u00b7 run ext \u00b7 5 labels so far (budget 10)" and text("notices") == ""
        gone = subprocess.Popen(["true"])
        gone.wait()
        write_teacher(run, phase="training", pid=gone.pid, round=None, step=1000, updated=time.time() - 42)
        WebDriverWait(driver, 30).until(lambda d: text("notices").startswith("the run is not responding (last heard 4"))
        assert text("notices").endswith(" s ago): running the same command again resumes it")
        message = "stopped by SIGTERM while waiting for labels/2.json: run the same command again to resume"
        write_teacher(run, phase="stopped", pid=gone.pid, message=message)
        WebDriverWait(driver, 30).until(lambda d: text("notices") == f"the run has stopped: {message}")
        write_teacher(run, phase="finished", pid=gone.pid, round=None, labelled=5, step=1500)
        WebDriverWait(driver, 30).until(lambda d: text() == "the run has finished: 5 labels in 2 rounds")
        assert text("notices") == ""
        driver.save_screenshot(str(tmp_path / "label_app_finished.png"))
        if os.environ.get("R2N_SCREENSHOT_FINISHED"):  # to refresh the README's picture
            shutil.copy(tmp_path / "label_app_finished.png", os.environ["R2N_SCREENSHOT_FINISHED"])
        (run / "teacher.json").write_text('{"phase": "training"}')  # not the run's: the files say what they can
        WebDriverWait(driver, 30).until(lambda d: text("notices").startswith("teacher.json cannot be read (it lacks "))
        assert text() == "no round is waiting for labels; this page checks every 2 s"


def stored(driver):
    """The answers the page keeps in this tab, by key."""
    return driver.execute_script("return Object.fromEntries(Object.entries(sessionStorage))")


def answer_queries(driver, keys, first, n=3):
    """Answer queries `first`, `first` + 1, ... of the round shown (of n), one key each once the page takes answers."""
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import WebDriverWait

    text = lambda: driver.find_element(By.ID, "progress").text  # noqa: E731
    body = driver.find_element(By.TAG_NAME, "body")
    for i, key in enumerate(keys, first):
        WebDriverWait(driver, 60).until(lambda d: text().endswith(f": query {i} of {n}") and answers_enabled(d))
        body.send_keys(key)
        WebDriverWait(driver, 30).until(lambda d: not text().endswith(f": query {i} of {n}"))


@needs_chromium
def test_label_app_keeps_answers_through_a_reload_and_a_server_error_in_a_headless_browser(tmp_path):
    from selenium.webdriver.common.keys import Keys
    from selenium.webdriver.support.ui import WebDriverWait

    run = make_run(tmp_path, (3,))
    apps = []
    with serve(run, apps) as address, contextlib.closing(chrome()) as driver:
        text = open_page(driver, address)
        answer_queries(driver, [Keys.ARROW_LEFT, Keys.ARROW_RIGHT], first=1)
        driver.refresh()  # mid-round: the two answers are kept
        WebDriverWait(driver, 60).until(lambda d: text() == "round 0: query 3 of 3")
        assert text("message") == "your 2 answers to round 0, kept in this tab, are back"
        answer_queries(driver, ["="], first=3)
        WebDriverWait(driver, 30).until(lambda d: text() == "round 0: all 3 answered")
        # the app cannot write a byte, as on a full disk: HTTP 500
        resource.prlimit(apps[0].pid, resource.RLIMIT_FSIZE, (0, resource.RLIM_INFINITY))
        answer_round(driver, [])
        failure = "HTTP 500: OSError: [Errno 27] File too large"
        WebDriverWait(driver, 30).until(lambda d: text("message") == (
            f"round 0 was not saved ({failure}); your answers are kept in this tab: submit again"))
        assert text() == "round 0: all 3 answered"
        driver.refresh()  # after the failure: the answers are kept, and the page says what failed
        WebDriverWait(driver, 60).until(lambda d: text() == "round 0: all 3 answered")
        assert text("message") == f"your 3 answers to round 0, kept in this tab, are back (the last submit: {failure})"
        resource.prlimit(apps[0].pid, resource.RLIMIT_FSIZE, (resource.RLIM_INFINITY, resource.RLIM_INFINITY))
        answer_round(driver, [])
        WebDriverWait(driver, 30).until(lambda d: text("message") == "round 0 saved (labels/0.json)")
        assert page_answers(run, 0) == [0, 1, 0.5]
        assert stored(driver) == {}  # saved: the browser's copy is gone
        assert os.listdir(run / "labels") == ["0.json"]  # the failed write left nothing behind
        driver.refresh()
        WebDriverWait(driver, 60).until(lambda d: text() == "no round is waiting for labels; this page checks every 2 s")
        assert text("message") == ""


@needs_chromium
def test_label_app_notices_a_round_answered_elsewhere_in_a_headless_browser(tmp_path):
    from selenium.webdriver.common.keys import Keys
    from selenium.webdriver.support.ui import WebDriverWait

    run = make_run(tmp_path, (3, 3))
    with serve(run) as address, contextlib.closing(chrome()) as driver:
        text = open_page(driver, address)
        answer_queries(driver, [Keys.ARROW_LEFT], first=1)
        assert text() == "round 0: query 2 of 3"
        assert request(address, "POST", "/api/labels/0", bound(run, 0, [1, 1, 1]))[0] == 200  # another tab
        # told within a poll, before answering more of it: the next answer is round 1's
        WebDriverWait(driver, 30).until(lambda d: text("message") == (
            "round 0 was answered elsewhere (another tab, another app or a script): your 1 answer to it was not used"))
        WebDriverWait(driver, 30).until(lambda d: text() == "round 1: query 1 of 3")
        assert stored(driver) == {}
        answer_queries(driver, [Keys.ARROW_RIGHT], first=1)
        assert page_answers(run, 0) == [1, 1, 1]
        assert [json.loads(value)["answers"] for value in stored(driver).values()] == [[1]]
        # the page closed mid-round, and the round answered meanwhile: told when the page opens again
        driver.get("about:blank")
        assert request(address, "POST", "/api/labels/1", bound(run, 1, [0, 0, 0]))[0] == 200
        text = open_page(driver, address)
        WebDriverWait(driver, 60).until(lambda d: text() == "no round is waiting for labels; this page checks every 2 s")
        assert text("message") == "your 1 answer to round 1, kept in this tab, was not used: it was answered elsewhere"
        assert stored(driver) == {}


def prefetched(driver, query):
    """Whether both clips of `query` of round 0 have arrived in the browser (fetched ahead, not shown yet)."""
    return driver.execute_script("""
        const query = arguments[0];
        const fetched = performance.getEntriesByType("resource").map((entry) => new URL(entry.name).pathname);
        return [0, 1].every((side) => fetched.includes(`/clip/0/${query}/${side}.gif`));
    """, query)


@needs_chromium
def test_label_app_one_answer_per_double_click_or_held_key_in_a_headless_browser(tmp_path):
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import WebDriverWait

    run = make_run(tmp_path, (4,))
    with serve(run) as address, contextlib.closing(chrome()) as driver:
        text = open_page(driver, address)
        WebDriverWait(driver, 60).until(lambda d: text() == "round 0: query 1 of 4" and answers_enabled(d))
        WebDriverWait(driver, 60).until(lambda d: prefetched(d, 1))  # query 2's clips are ready at once
        right = driver.find_element(By.ID, "answer-right")
        ActionChains(driver).click(right).pause(0.15).click().perform()  # a double click
        WebDriverWait(driver, 60).until(answers_enabled)
        assert text() == "round 0: query 2 of 4"
        WebDriverWait(driver, 60).until(lambda d: prefetched(d, 2))
        # ← held down for 2 s: one keydown, then the keyboard's repeats
        key = {"key": "ArrowLeft", "code": "ArrowLeft", "windowsVirtualKeyCode": 37, "nativeVirtualKeyCode": 37}
        driver.execute_cdp_cmd("Input.dispatchKeyEvent", {"type": "rawKeyDown", **key})
        for _ in range(40):
            time.sleep(0.05)  # the keyboard's repeat rate
            driver.execute_cdp_cmd("Input.dispatchKeyEvent", {"type": "rawKeyDown", "autoRepeat": True, **key})
        driver.execute_cdp_cmd("Input.dispatchKeyEvent", {"type": "keyUp", **key})
        WebDriverWait(driver, 60).until(lambda d: answers_enabled(d) or d.find_element(By.ID, "submit").is_displayed())
        assert text() == "round 0: query 3 of 4"
        answer_round(driver, ["=", "s"])
        WebDriverWait(driver, 30).until(lambda d: text("message") == "round 0 saved (labels/0.json)")
        assert page_answers(run, 0) == [1, 0, 0.5, "skip"]


@contextlib.contextmanager
def another_origin(page: str):
    """`page` served from another origin: a second tiny server, on another port of this machine."""
    class Page(http.server.BaseHTTPRequestHandler):
        def do_GET(self):
            self.send_response(200)
            self.send_header("Content-Type", "text/html; charset=utf-8")
            self.send_header("Content-Length", str(len(page.encode())))
            self.end_headers()
            self.wfile.write(page.encode())

        def log_message(self, *args):
            pass

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Page)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        yield f"127.0.0.1:{server.server_port}"
    finally:
        server.shutdown()
        server.server_close()


@needs_chromium
def test_label_app_another_origin_cannot_write_labels_in_a_headless_browser(tmp_path):
    """Any page the labeller opens could try to answer the pending round: without CORS (text, as a form may send)
    the app refuses its Origin and its Content-Type; with JSON the browser asks first (a preflight), and the app
    refuses that."""
    from selenium.webdriver.support.ui import WebDriverWait

    run = make_run(tmp_path, (3,))
    with serve(run) as address:
        attack = f"""<!doctype html><title>attacking</title><script>
            const target = "http://{address}/api/labels/0", body = "[0, 0, 0]";
            Promise.allSettled([
                fetch(target, {{method: "POST", mode: "no-cors", headers: {{"Content-Type": "text/plain"}}, body}}),
                fetch(target, {{method: "POST", headers: {{"Content-Type": "application/json"}}, body}}),
            ]).then((results) => {{ document.title = results.map((result) => result.status).join(" "); }});
        </script>"""
        with another_origin(attack) as elsewhere, contextlib.closing(chrome()) as driver:
            driver.get(f"http://{elsewhere}/")
            WebDriverWait(driver, 60).until(lambda d: d.title != "attacking")
            # the first was sent (its reply is opaque to the page), the second never left the browser
            assert driver.title == "fulfilled rejected"
        assert not (run / "labels").exists()
        assert get_state(address)["round"] == 0


def test_label_app_binds_the_answers_to_the_queries_shown(tmp_path):
    """A submit names the digest of the queries the page showed. Answers to queries the round's file no longer holds
    (it was replaced after the page drew it) are refused with a sentence that says so, and nothing is written; the
    right digest is recorded in the labels file. A labels file that answers other queries leaves its round pending."""
    import label_app

    run = make_run(tmp_path, (2,))
    shown = label_app.read_queries(str(run), 0).digest
    with serve(run) as address:
        physics = np.ones((2, 2, 3, 4))  # the queries file is replaced: another round's, another run's
        np.savez(run / "queries" / "0.npz", env_id="cartpole-swingup", obs=np.zeros((2, 2, 3, 5), np.float32),
                 actions=np.zeros((2, 2, 3, 1), np.float32), physics=physics, true_rewards=np.zeros((2, 2, 3)))
        now = label_app.read_queries(str(run), 0).digest
        assert now != shown
        body = json.dumps({"queries": shown, "answers": [0, 1]}).encode()
        status, reply = request(address, "POST", "/api/labels/0", body)
        assert status == 409 and f"it answers the queries of digest {shown}, not this round's ({now})" in reply.decode()
        assert not (run / "labels" / "0.json").exists()
        assert get_state(address)["queries_digest"] == now
        status, _ = request(address, "POST", "/api/labels/0", json.dumps({"queries": now, "answers": [0, 1]}).encode())
        assert status == 200 and page_answers(run, 0) == [0, 1]
        # a labels file for other queries, written by someone else: the round is pending, and the state says why
        os.replace(run / "labels" / "0.json", run / "labels" / "0.json.kept")
        (run / "labels" / "0.json").write_text(json.dumps({"queries": shown, "answers": [1, 1]}))
        state = get_state(address)
        assert state["round"] == 0 and "not this round's" in state["malformed"]
        # and the page's submit moves it aside, whole, before writing its own
        status, _ = request(address, "POST", "/api/labels/0", json.dumps({"queries": now, "answers": [1, 0]}).encode())
        assert status == 200 and page_answers(run, 0) == [1, 0]
        [aside] = [name for name in os.listdir(run / "labels") if name.startswith("0.json.rejected-")]
        assert json.loads((run / "labels" / aside).read_text()) == {"queries": shown, "answers": [1, 1]}


def test_label_app_takes_answers_for_the_queries_the_run_waits_for(tmp_path):
    """While the run waits for a round, its teacher.json names the digest of the queries it wrote: those are the
    round's, whatever file lies in their place for a moment (the run writes its own again at its next look). The
    state says so, answers to them are saved, answers to the file in their place are refused."""
    import label_app

    run = make_run(tmp_path, (2,))
    digest = label_app.read_queries(str(run), 0).digest
    write_teacher(run, round=0, queries=2, digest=digest)
    with serve(run) as address:
        np.savez(run / "queries" / "0.npz", env_id="cartpole-swingup", obs=np.zeros((3, 2, 3, 5), np.float32),
                 actions=np.zeros((3, 2, 3, 1), np.float32), physics=np.ones((3, 2, 3, 4)),
                 true_rewards=np.zeros((3, 2, 3)))
        other = label_app.read_queries(str(run), 0).digest
        state = get_state(address)
        assert (state["round"], state["n"], state["queries_digest"]) == (0, 2, digest)
        assert state["foreign"] == (f"queries/0.npz is not the file the run wrote for round 0 (it holds the queries of "
                                    f"digest {other}; the run's are {digest}): the run writes its own again at its "
                                    "next look")
        status, reply = request(address, "GET", f"/clip/0/0/0.gif?queries={digest}")
        assert status == 404 and reply.decode() == state["foreign"]
        status, reply = request(address, "POST", "/api/labels/0",
                                json.dumps({"queries": other, "answers": [0, 1]}).encode())
        assert status == 409 and f"it answers the queries of digest {other}, not this round's ({digest})" in reply.decode()
        body = json.dumps({"queries": digest, "answers": [0, 1]}).encode()
        assert request(address, "POST", "/api/labels/0", body)[0] == 200
        assert json.loads((run / "labels" / "0.json").read_text()) == {"queries": digest, "answers": [0, 1]}
        assert get_state(address)["round"] is None
        write_teacher(run, round=0, queries=2, digest="0123456789ABCDEF")
        assert get_state(address)["teacher_problem"] == ('teacher.json cannot be read (digest is "0123456789ABCDEF", '
                                                         "not a digest of 16 hex digits): the page shows what the "
                                                         "run's files say")


@needs_chromium
def test_label_app_no_modifier_combination_answers_on_a_focused_button_in_a_headless_browser(tmp_path):
    """Space and Enter press a focused button only unmodified: Ctrl, Alt, Meta or Shift with either answers nothing
    (the browser presses a button on Space's keyup, which the keydown handler alone does not stop)."""
    from selenium.webdriver.support.ui import WebDriverWait

    run = make_run(tmp_path, (2,))
    with serve(run) as address, contextlib.closing(chrome()) as driver:
        text = open_page(driver, address)
        WebDriverWait(driver, 60).until(lambda d: text() == "round 0: query 1 of 2" and answers_enabled(d))
        space = {"key": " ", "code": "Space", "windowsVirtualKeyCode": 32, "nativeVirtualKeyCode": 32, "text": " "}
        enter = {"key": "Enter", "code": "Enter", "windowsVirtualKeyCode": 13, "nativeVirtualKeyCode": 13, "text": "\r"}

        def press(key, modifiers):  # CDP's bits: Alt 1, Ctrl 2, Meta 4, Shift 8
            driver.execute_script("document.getElementById('answer-right').focus()")
            driver.execute_cdp_cmd("Input.dispatchKeyEvent", {"type": "keyDown", "modifiers": modifiers, **key})
            driver.execute_cdp_cmd("Input.dispatchKeyEvent", {"type": "keyUp", "modifiers": modifiers, **key})

        for key in (space, enter):
            for modifiers in (1, 2, 4, 8):
                press(key, modifiers)
                time.sleep(0.3)
                assert text() == "round 0: query 1 of 2", (key["key"], modifiers)
        press(space, 0)  # unmodified: the focused button answers
        WebDriverWait(driver, 30).until(lambda d: text() == "round 0: query 2 of 2")
        WebDriverWait(driver, 60).until(answers_enabled)
        press(enter, 0)
        WebDriverWait(driver, 30).until(lambda d: d.find_element("id", "submit").is_displayed())
        assert driver.execute_script("return answers") == [1, 1]


@needs_chromium
def test_label_app_page_recovers_by_itself_when_the_app_restarts_mid_fetch_in_a_headless_browser(tmp_path):
    """The app stops while the page fetches a query's clips and starts again on its port: the page tries the clips
    again, after a growing wait that its notice names ("did not load (try 3): the app does not answer (Failed to
    fetch); trying again in 2 s"), and takes answers without a reload."""
    from selenium.webdriver.common.keys import Keys
    from selenium.webdriver.support.ui import WebDriverWait

    run = make_run(tmp_path, (3,))
    port = free_port()

    def app(clip_delay):
        process = subprocess.Popen([sys.executable, LABEL_APP, str(run), "--port", str(port)], stdout=subprocess.PIPE,
                                   stderr=subprocess.STDOUT, text=True,
                                   env=dict(os.environ, OMP_NUM_THREADS="1", R2N_LABEL_APP_CLIP_DELAY=clip_delay))
        assert process.stdout.readline().startswith("labelling"), "the app did not start"
        return process

    first = app("3")  # each clip takes 3 s: the app is stopped while the page waits for query 1's
    second = None
    try:
        with contextlib.closing(chrome()) as driver:
            text = open_page(driver, f"127.0.0.1:{port}")
            WebDriverWait(driver, 60).until(lambda d: text() == "round 0: query 1 of 3")
            first.terminate()
            first.communicate(timeout=30)
            WebDriverWait(driver, 30).until(lambda d: "did not load" in text("drawing"))
            assert "the app does not answer" in text("drawing")
            time.sleep(3)  # the page keeps trying while the app is away
            assert not answers_enabled(driver)
            second = app("0")
            WebDriverWait(driver, 30).until(answers_enabled)  # without a reload
            assert "the clips of query 1 loaded on try" in text("drawing")
            answer_round(driver, [Keys.ARROW_LEFT, Keys.ARROW_RIGHT, "="])
            WebDriverWait(driver, 30).until(lambda d: text("message") == "round 0 saved (labels/0.json)")
        assert page_answers(run, 0) == [0, 1, 0.5]
    finally:
        for process in (first, second):
            if process is not None and process.poll() is None:
                process.terminate()
                process.communicate(timeout=30)
