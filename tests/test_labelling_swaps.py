"""Another file in the place of a round's queries (issue 92): a copier or a sync tool puts it there, even within a
millisecond of the run's own write. The run knows its queries file by its bytes and writes it again; a bare list of
answers that came meanwhile is not trained on; the app takes answers only with the digest of the queries they
answer, and takes them for the queries the run waits for; the page keeps a person's answers while the run's queries
are the ones answered, and its notices say what happened."""
import contextlib
import hashlib
import io
import json
import os
import re
import subprocess
import sys
import threading
import time

import numpy as np

from test_label_app import (answer_queries, answer_round, get_state, make_run, open_page, prefetched, request, serve,
                            write_teacher)
from test_label_app_session import write_queries
from test_labelling import EXTERNAL, answers_enabled, chrome, needs_chromium, oracle_answers
from test_scripts import ROOT

sys.path.insert(0, ROOT)
import label_app  # noqa: E402
from r2n_harness.external_teacher import file_digest  # noqa: E402
from r2n_harness.preferences import read_preferences  # noqa: E402

# The run's os.replace, slowed after each write of queries/0.npz: another writer's file lands between the run's
# write and its next look every time, as a copier reacting within 2 ms did in 8 of 10 trials.
SLOW_WRITE = """
import os, runpy, sys, time
replace = os.replace
def slow_replace(src, dst, **kwargs):
    replace(src, dst, **kwargs)
    if str(dst).endswith(os.path.join("queries", "0.npz")):
        time.sleep(0.3)
os.replace = slow_replace
sys.argv = sys.argv[1:]
sys.path.insert(0, os.path.dirname(sys.argv[0]))
runpy.run_path(sys.argv[0], run_name="__main__")
"""


def other_queries() -> tuple:
    """The bytes of a queries file of the run's shapes that the run never drew, and their true rewards."""
    rng = np.random.default_rng(0)
    arrays = dict(env_id="cartpole-swingup", obs=rng.normal(size=(5, 2, 20, 51)).astype(np.float32),
                  actions=rng.normal(size=(5, 2, 20, 1)).astype(np.float32), physics=rng.normal(size=(5, 2, 20, 4)),
                  true_rewards=rng.normal(size=(5, 2, 20)).astype(np.float32))
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    return buffer.getvalue(), arrays["true_rewards"]


def copy_over(path, content, bare, swaps, stop):
    """A copier: each time the run has written its own file at `path`, put `content` in its place (within a
    millisecond or so), `swaps` times. After the first, a program answers what it finds there with a bare list
    (`bare`), as the docs allow a program to."""
    done = 0
    while done < swaps and not stop.is_set():
        try:
            found = path.read_bytes()
        except FileNotFoundError:
            found = None
        if found is not None and found != content:
            path.with_name("copy.tmp").write_bytes(content)
            os.replace(path.with_name("copy.tmp"), path)
            if done == 0:
                labels = path.parent.parent / "labels"
                labels.mkdir(exist_ok=True)
                (labels / "0.tmp").write_text(json.dumps(bare))
                os.replace(labels / "0.tmp", labels / "0.json")
            done += 1
        time.sleep(0.001)


def test_a_queries_file_swapped_at_the_runs_own_write_with_a_real_run_and_app(tmp_path):
    """A real `--teacher external` run whose queries file is swapped right after each of its own writes, twice: it
    says so and writes its file again until its own stays; the program's bare list, written while the other file was
    there, is moved aside, not trained on. Then the app refuses a bare list (one line, nothing written) and takes
    the page's answers, bound to the run's digest, which the run trains on."""
    run = tmp_path / "runs" / "ext"
    content, rewards = other_queries()
    bare = oracle_answers({"true_rewards": rewards})  # a program's answers to the other queries
    stop = threading.Event()
    copier = threading.Thread(target=copy_over, args=(run / "queries" / "0.npz", content, bare, 2, stop))
    copier.start()
    log = str(tmp_path / "run.log")
    process = subprocess.Popen([sys.executable, "-c", SLOW_WRITE, os.path.join(ROOT, "pebble.py"), *EXTERNAL],
                               cwd=tmp_path, stdout=open(log, "w"), stderr=subprocess.STDOUT,
                               env=dict(os.environ, OMP_NUM_THREADS="1", PYTHONWARNINGS="ignore"))

    def until(condition, seconds=300, answered=False):
        deadline = time.time() + seconds
        while not condition():
            assert answered or not (run / "preferences" / "0.npz").exists(), "round 0 was trained on other answers"
            assert process.poll() is None and time.time() < deadline, open(log).read()[-3000:]
            time.sleep(0.05)

    try:
        until(lambda: "waiting for labels: runs/ext/labels/0.json" in open(log).read())
        digest = re.search(r"\(digest ([0-9a-f]{16});", open(log).read()).group(1)
        until(lambda: file_digest(str(run / "queries" / "0.npz")) == digest and "labels:" in open(log).read(), 30)
        copier.join(timeout=60)
        time.sleep(1.5)  # a look more: the run's own file stays
        lines = open(log).read().splitlines()
        assert [line for line in lines if line.startswith("queries:")] == [
            f"queries: runs/ext/queries/0.npz is no longer the file this run wrote for round 0 (digest {digest}); "
            "writing it again"] * 2
        [aside] = [name for name in os.listdir(run / "labels") if name.startswith("0.json.unbound-")]
        assert [line for line in lines if line.startswith("labels:")] == [
            "labels: runs/ext/labels/0.json: a bare list, which names no queries, came while runs/ext/queries/0.npz "
            f"was not the file this run wrote: it may answer those; kept as runs/ext/labels/{aside}; waiting for "
            "labels of runs/ext/queries/0.npz"]
        assert json.loads((run / "labels" / aside).read_text()) == bare
        assert json.loads((run / "teacher.json").read_text())["digest"] == digest  # the page's word on the queries
        with np.load(run / "queries" / "0.npz") as data:
            answers = oracle_answers({"true_rewards": data["true_rewards"]})
        with serve(run) as address:
            assert get_state(address)["queries_digest"] == digest
            status, reply = request(address, "POST", "/api/labels/0", json.dumps(answers).encode())
            assert status == 400 and reply.decode() == (
                'round 0\'s answers were not saved: they name no queries; send {"queries": digest, "answers": [...]} '
                "with the digest of the queries answered, as the page does (a program may write a bare list to "
                "labels/0.json itself)")
            assert not (run / "labels" / "0.json").exists()
            time.sleep(1.5)  # a look of the run's: still waiting
            assert process.poll() is None and not (run / "preferences" / "0.npz").exists()
            body = json.dumps({"queries": digest, "answers": answers}).encode()
            assert request(address, "POST", "/api/labels/0", body)[0] == 200
        until(lambda: (run / "preferences" / "0.npz").exists(), answered=True)
        data = read_preferences(str(run / "preferences"))
        np.testing.assert_array_equal(data["labels"], np.array(answers, np.float32))
        assert data["label_sha256"].tolist() == [hashlib.sha256((run / "labels" / "0.json").read_bytes()).hexdigest()]
    finally:
        stop.set()
        copier.join(timeout=60)
        process.kill()
        process.wait(timeout=60)


def put_back(path, content):
    """What the run does at its next look: its own queries file again, written whole."""
    path.with_name("back.tmp").write_bytes(content)
    os.replace(path.with_name("back.tmp"), path)


@needs_chromium
def test_label_app_keeps_the_answers_while_another_file_lies_in_the_queries_place_in_a_headless_browser(tmp_path):
    """The run waits for round 0's queries (its teacher.json names their digest) while another file lies in their
    place, mid-round and again at the moment of submit. The page keeps the answers and says whose file is there; a
    clip it cannot have says why, not that the app does not answer; the submit saves the answers, bound to the
    queries they answer, which are the run's."""
    from selenium.webdriver.common.keys import Keys
    from selenium.webdriver.support.ui import WebDriverWait

    run = make_run(tmp_path, (3,))
    path = run / "queries" / "0.npz"
    own, digest = path.read_bytes(), label_app.read_queries(str(run), 0).digest
    write_teacher(run, round=0, queries=3, digest=digest)
    with serve(run) as address, contextlib.closing(chrome()) as driver:
        text = open_page(driver, address)
        answer_queries(driver, [Keys.ARROW_LEFT], first=1)
        write_queries(run, 0, 3, right=-0.5)  # mid-round
        other = label_app.read_queries(str(run), 0).digest
        WebDriverWait(driver, 30).until(lambda d: (
            f"queries/0.npz is not the file the run wrote for round 0 (it holds the queries of digest {other}; the "
            f"run's are {digest}): the run writes its own again at its next look") in text("notices"))
        answer_queries(driver, [Keys.ARROW_RIGHT], first=2)  # its clips were fetched ahead
        WebDriverWait(driver, 30).until(lambda d: "did not load" in text("drawing"))
        assert re.fullmatch(r"the clips of query 3 did not load \(try \d\): HTTP 404: queries/0.npz is not the file "
                            r"the run wrote for round 0 .*; trying again in [0-9.]+ s", text("drawing")), text("drawing")
        assert text() == "round 0: query 3 of 3" and driver.execute_script("return answers") == [0, 1]
        put_back(path, own)
        answer_round(driver, ["="], submit=False)
        # at the moment of submit: the page has not seen the other file
        driver.execute_cdp_cmd("Network.enable", {})
        driver.execute_cdp_cmd("Network.setBlockedURLs", {"urls": ["*/api/state"]})
        write_queries(run, 0, 3, right=-0.5)
        answer_round(driver, [])
        WebDriverWait(driver, 30).until(lambda d: text("message") == "round 0 saved (labels/0.json)")
        assert json.loads((run / "labels" / "0.json").read_text()) == {"queries": digest, "answers": [0, 1, 0.5]}
        driver.execute_cdp_cmd("Network.setBlockedURLs", {"urls": []})
        put_back(path, own)
        WebDriverWait(driver, 30).until(lambda d: text() == "no round is waiting for labels; this page checks every 2 s")
        assert text("message") == "round 0 saved (labels/0.json)"


@needs_chromium
def test_label_app_notices_say_what_happened_in_a_headless_browser(tmp_path):
    """A clip refused because the round's queries changed says the app's reason, not that the app does not answer.
    A round saved whose labels the run then sets aside (they answer queries it did not write) no longer reads
    "saved": the page says that they are not the round's answer, and asks the round again."""
    from selenium.webdriver.common.keys import Keys
    from selenium.webdriver.support.ui import WebDriverWait

    run = make_run(tmp_path, (3,))  # no teacher.json: an older run, or a new run in the folder that has not asked yet
    with serve(run) as address, contextlib.closing(chrome()) as driver:
        text = open_page(driver, address)
        WebDriverWait(driver, 60).until(lambda d: text() == "round 0: query 1 of 3" and answers_enabled(d))
        WebDriverWait(driver, 60).until(lambda d: prefetched(d, 1))
        driver.execute_cdp_cmd("Network.enable", {})  # the page does not hear of the new queries before a clip
        driver.execute_cdp_cmd("Network.setBlockedURLs", {"urls": ["*/api/state"]})
        write_queries(run, 0, 3, right=-0.5)
        answer_queries(driver, [Keys.ARROW_LEFT, Keys.ARROW_RIGHT], first=1)
        WebDriverWait(driver, 30).until(lambda d: "did not load" in text("drawing"))
        assert re.fullmatch(r"the clips of query 3 did not load \(try \d\): HTTP 404: round 0's queries have changed "
                            r"since the page asked for this clip: .*; trying again in [0-9.]+ s", text("drawing"))
        driver.execute_cdp_cmd("Network.setBlockedURLs", {"urls": []})
        WebDriverWait(driver, 30).until(lambda d: text("message") == (
            "round 0's queries have changed (a new run in the folder ext?): your 2 answers to it were not used"))
        answer_round(driver, ["=", "=", "="])
        WebDriverWait(driver, 30).until(lambda d: text("message") == "round 0 saved (labels/0.json)")
        # the run sets them aside and asks round 0 again, with its own queries
        os.rename(run / "labels" / "0.json", run / "labels" / "0.json.mismatch-1")
        write_queries(run, 0, 3, right=0.25)
        said = "labels: runs/ext/labels/0.json: answers the queries of another digest; kept as ..."
        write_teacher(run, round=0, queries=3, digest=label_app.read_queries(str(run), 0).digest, message=said)
        WebDriverWait(driver, 30).until(lambda d: text("message") == (
            "round 0 was saved, but labels/0.json is no longer its answer (the run's line above says why): answer "
            "round 0 again"))
        assert f"the run says: {said}" in text("notices")
        WebDriverWait(driver, 60).until(lambda d: text() == "round 0: query 1 of 3")
