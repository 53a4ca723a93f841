"""The labelling page through a long session (issue 43): clips that follow the queries file and a memory bound on
them, a tab's answers its own and the other tabs of the browser in view, keys with modifiers left to the browser, a
folder in place of a labels file, a `teacher.json` with NaN, canonical round numbers, the labels files' mode, and
a poll that reads no unchanged file."""
import builtins
import contextlib
import json
import os
import stat
import sys

import numpy as np
import pytest
import tyro

from test_label_app import (answer_queries, answer_round, bound, get_state, make_run, open_page, page_answers, request,
                            serve, write_teacher)
from test_labelling import answers_enabled, chrome, needs_chromium
from test_scripts import ROOT

sys.path.insert(0, ROOT)
import label_app  # noqa: E402


def write_queries(run, r, n, right=0.5):
    """Round r's queries (n of them), written as the run writes them (a new file, renamed into place); the right
    segment's cart stands at `right`, so queries with another `right` draw other clips."""
    physics = np.zeros((n, 2, 3, 4))
    physics[:, 1, :, 0] = right
    path = run / "queries" / f"{r}.npz"
    with open(f"{path}.tmp", "wb") as f:
        np.savez(f, env_id="cartpole-swingup", obs=np.zeros((n, 2, 3, 5), np.float32),
                 actions=np.zeros((n, 2, 3, 1), np.float32), physics=physics, true_rewards=np.zeros((n, 2, 3)))
    os.replace(f"{path}.tmp", path)


def test_label_app_clips_follow_the_queries_file(tmp_path):
    """A run folder used again while the app runs (new queries under round 0): the page gets the new queries' clips,
    and a clip asked for under the old queries' digest is refused."""
    run = make_run(tmp_path, (2,))
    with serve(run) as address:
        old = get_state(address)["queries_digest"]
        status, before = request(address, "GET", f"/clip/0/0/1.gif?queries={old}")
        assert status == 200
        write_queries(run, 0, 2, right=-0.5)
        new = get_state(address)["queries_digest"]
        assert new != old
        status, after = request(address, "GET", "/clip/0/0/1.gif")
        assert status == 200 and after != before
        assert request(address, "GET", f"/clip/0/0/1.gif?queries={new}") == (200, after)
        status, reply = request(address, "GET", f"/clip/0/0/1.gif?queries={old}")
        assert status == 404 and reply.decode() == ("round 0's queries have changed since the page asked for this "
                                                    "clip: it shows the new ones within 2 s")
    with serve(run) as address:  # the same clip as a fresh app draws
        assert request(address, "GET", "/clip/0/0/1.gif") == (200, after)


def test_label_app_keeps_the_clips_last_shown_within_a_bound(tmp_path, monkeypatch, capsys):
    """The clips are an LRU cache bounded in bytes (`--clip-cache-mb`): the least recently shown goes first."""
    run = make_run(tmp_path, (4,))
    drawn = []

    def render_states(env_id, states, physics=None):  # frames of noise, of one size, without MuJoCo
        drawn.append(len(drawn))
        return np.random.default_rng(len(drawn)).integers(0, 256, (3, 24, 32, 3), dtype=np.uint8)

    monkeypatch.setattr(label_app.ene, "render_states", render_states)
    monkeypatch.setattr(label_app.ene, "dmc_physics", lambda env_id: None)
    size = len(label_app.Clips(str(run), 25, 10 ** 9).gif(0, 0, 0))
    clips = label_app.Clips(str(run), 25, int(2.5 * size))  # room for two clips
    drawn.clear()
    for query in (0, 1, 0, 2, 0, 1):  # 0 is shown again before 2 comes: 1 goes, 0 stays
        clips.gif(0, query, 0)
    assert len(drawn) == 4 and clips.kept_bytes <= 2.5 * size
    assert [key[1] for key in clips.kept] == [0, 1]
    assert len(label_app.Clips(str(run), 25, 0).gif(0, 3, 1)) > 0  # larger than the bound: drawn, not kept
    assert tyro.cli(label_app.Args, args=[str(run)]).clip_cache_mb == 256
    assert tyro.cli(label_app.Args, args=[str(run), "--clip-cache-mb", "64"]).clip_cache_mb == 64
    with pytest.raises(SystemExit):
        tyro.cli(label_app.Args, args=["--help"])
    assert "megabytes of rendered clips kept in memory" in " ".join(capsys.readouterr().out.split())


def test_label_app_labels_file_that_is_a_folder(tmp_path):
    """A folder at labels/0.json: the state says what is wrong and what to do, a submit is refused with the same
    sentence (the page keeps the answers), nothing is moved or written; once it is moved away, a submit writes."""
    run = make_run(tmp_path, (2,))
    (run / "labels" / "0.json").mkdir(parents=True)
    sentence = ("labels/0.json is a folder, not a file: the run cannot read round 0's labels from it, nor can this "
                "page write them; move it away (mv labels/0.json labels/0.json.moved), then submit round 0")
    with serve(run) as address:
        state = get_state(address)
        assert state["round"] == 0 and state["blocked"] == sentence and state["malformed"] is None
        assert request(address, "POST", "/api/labels/0", bound(run, 0, [0, 1])) == (500, sentence.encode())
        assert os.listdir(run / "labels") == ["0.json"] and os.listdir(run / "labels" / "0.json") == []
        os.rename(run / "labels" / "0.json", run / "labels" / "0.json.moved")
        assert get_state(address)["blocked"] is None
        assert request(address, "POST", "/api/labels/0", bound(run, 0, [0, 1]))[0] == 200
        assert page_answers(run, 0) == [0, 1]


def strict_json(body: bytes):
    """JSON as a browser reads it: NaN and Infinity are not JSON."""
    def refuse(constant):
        raise ValueError(f"{constant} is not JSON")

    return json.loads(body, parse_constant=refuse)


def test_label_app_state_is_json_whatever_teacher_json_holds(tmp_path):
    run = make_run(tmp_path, (3,), teacher={})
    with serve(run) as address:
        for text, value in [("NaN", "NaN"), ("Infinity", "Infinity"), ("-Infinity", "-Infinity"), ("1e999", "Infinity")]:
            content = (run / "teacher.json").read_text()
            (run / "teacher.json").write_text(content.replace('"step": 500', f'"step": {text}'))
            status, body = request(address, "GET", "/api/state")
            assert status == 200
            state = strict_json(body)
            assert state["teacher"] is None and state["round"] == 0, text
            assert state["teacher_problem"] == (f"teacher.json cannot be read (step is {value}, not a finite number): "
                                                "the page shows what the run's files say"), text
            write_teacher(run)
        assert strict_json(request(address, "GET", "/api/state")[1])["teacher_problem"] is None


def test_label_app_round_numbers_are_canonical(tmp_path):
    """`/api/labels/00` is no round (the run writes round 0 as 0): it writes nothing; so for clips and a stray
    queries/00.npz."""
    run = make_run(tmp_path, (3,))
    with serve(run) as address:
        for method, path, body in [("POST", "/api/labels/00", b"[0, 0, 0]"), ("GET", "/clip/00/0/0.gif", None),
                                   ("GET", "/clip/0/01/0.gif", None)]:
            status, reply = request(address, method, path, body)
            assert status == 404, (path, status, reply)
        assert not (run / "labels").exists()
        os.link(run / "queries" / "0.npz", run / "queries" / "00.npz")
        assert request(address, "POST", "/api/labels/0", bound(run, 0, [0, 0, 0]))[0] == 200
        assert get_state(address)["round"] is None
    assert os.listdir(run / "labels") == ["0.json"]


def test_label_app_labels_files_are_group_readable_as_the_run_files(tmp_path):
    """A labels file gets the mode every file of the run gets (0666 less the umask), not a temporary file's 0600."""
    from r2n_harness.query_log import write_npz

    run = make_run(tmp_path, (3,))
    umask = os.umask(0o022)
    try:
        label_app.write_labels(str(run), 0, bound(run, 0, [0, 1, 0.5]))
        write_npz(str(run / "preferences" / "0.npz"), labels=np.zeros(3))
    finally:
        os.umask(umask)
    modes = [stat.S_IMODE(os.stat(path).st_mode) for path in (run / "labels" / "0.json", run / "preferences" / "0.npz")]
    assert modes == [0o644, 0o644]


def test_label_app_poll_reads_no_unchanged_file(tmp_path, monkeypatch):
    """The state, asked for every 2 s, reads a file only when it has changed: its cost does not grow with the
    rounds' queries."""
    run = make_run(tmp_path, (3,) * 30)
    (run / "labels").mkdir()
    for r in range(29):
        (run / "labels" / f"{r}.json").write_text("[0, 1, 0]")
    opened = []
    real_open = builtins.open

    def counting_open(file, *args, **kwargs):
        opened.append(os.path.relpath(file, run) if isinstance(file, (str, os.PathLike)) else file)
        return real_open(file, *args, **kwargs)

    monkeypatch.setattr(builtins, "open", counting_open)
    first = label_app.state(str(run))
    assert first["round"] == 29 and first["rounds_answered"] == 29
    assert len(opened) >= 59  # the first poll reads every file
    opened.clear()
    assert label_app.state(str(run)) == first
    assert opened == ["teacher.json"]  # the run's status alone (it has none here), one small file
    write_queries(run, 29, 3, right=-0.5)  # a changed file is read again, and only it
    (run / "labels" / "28.json").write_text('["skip", 1, 0]')
    opened.clear()
    second = label_app.state(str(run))
    assert sorted(opened) == ["labels/28.json", "queries/29.npz", "teacher.json"]
    assert second["queries_digest"] != first["queries_digest"] and second["labels"] == first["labels"] - 1


def stored(driver):
    """The answers this tab keeps, by key."""
    return {key: json.loads(value)["answers"] for key, value in
            driver.execute_script("return Object.fromEntries(Object.entries(sessionStorage))").items()}


def new_tab(driver, address):
    """A second tab of the same browser, on the page; the driver is then in it."""
    driver.switch_to.new_window("tab")
    return open_page(driver, address)


@needs_chromium
def test_label_app_tabs_keep_their_own_answers_in_a_headless_browser(tmp_path):
    """Two tabs of one browser answer one round: each keeps its own answers, and a reload brings back its own."""
    from selenium.webdriver.common.keys import Keys
    from selenium.webdriver.support.ui import WebDriverWait

    run = make_run(tmp_path, (3,))
    with serve(run) as address, contextlib.closing(chrome()) as driver:
        first = driver.current_window_handle
        text = open_page(driver, address)
        answer_queries(driver, [Keys.ARROW_LEFT, Keys.ARROW_LEFT], first=1)
        new_tab(driver, address)
        answer_queries(driver, [Keys.ARROW_RIGHT], first=1)
        driver.switch_to.window(first)
        driver.refresh()
        WebDriverWait(driver, 60).until(lambda d: text() == "round 0: query 3 of 3")
        assert text("message") == "your 2 answers to round 0, kept in this tab, are back"
        answer_round(driver, ["="])
        WebDriverWait(driver, 30).until(lambda d: text("message") == "round 0 saved (labels/0.json)")
        assert page_answers(run, 0) == [0, 0, 0.5]


@needs_chromium
def test_label_app_tabs_see_each_other_in_a_headless_browser(tmp_path):
    """A tab sees at once that another tab of the browser is answering its round, with its answers; the notice goes
    when the other tab closes."""
    from selenium.webdriver.common.keys import Keys
    from selenium.webdriver.support.ui import WebDriverWait

    run = make_run(tmp_path, (3,))
    notice = ("another tab of this browser is answering round 0 too ({}): answer in one tab only; the first to submit "
              "is kept, and the other's answers are not used")
    with serve(run) as address, contextlib.closing(chrome()) as driver:
        first = driver.current_window_handle
        text = open_page(driver, address)
        answer_queries(driver, [Keys.ARROW_LEFT, "s"], first=1)
        text = new_tab(driver, address)
        second = driver.current_window_handle
        WebDriverWait(driver, 30).until(lambda d: text("notices") == notice.format("its 2 answers so far: \u2190 s"))
        assert text() == "round 0: query 1 of 3"  # told before answering
        answer_queries(driver, ["="], first=1)
        driver.switch_to.window(first)
        WebDriverWait(driver, 30).until(lambda d: text("notices") == notice.format("its 1 answer so far: ="))
        driver.switch_to.window(second)
        driver.close()
        driver.switch_to.window(first)
        WebDriverWait(driver, 30).until(lambda d: text("notices") == "")


KEY_EVENTS = """
    window.keys = [];  // each keydown the page saw, and whether it kept the browser from acting on it
    window.addEventListener("keydown", (e) => window.keys.push([e.key, e.defaultPrevented]));
"""


@needs_chromium
def test_label_app_keys_with_modifiers_are_the_browsers_in_a_headless_browser(tmp_path):
    """Ctrl+=, Ctrl+S, Alt+←, Shift+← neither answer nor are kept from the browser; only keys without a modifier
    answer, a letter with Caps Lock too; Enter and Space on a focused answer button answer it, once."""
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.by import By
    from selenium.webdriver.common.keys import Keys
    from selenium.webdriver.support.ui import WebDriverWait

    run = make_run(tmp_path, (4,))
    with serve(run) as address, contextlib.closing(chrome()) as driver:
        text = open_page(driver, address)
        WebDriverWait(driver, 60).until(lambda d: text() == "round 0: query 1 of 4" and answers_enabled(d))
        driver.execute_script(KEY_EVENTS)
        for modifier, key in [(Keys.CONTROL, "="), (Keys.CONTROL, "s"), (Keys.ALT, Keys.ARROW_LEFT),
                              (Keys.SHIFT, Keys.ARROW_LEFT), (Keys.CONTROL, Keys.BACKSPACE)]:
            ActionChains(driver).key_down(modifier).send_keys(key).key_up(modifier).perform()
        seen = driver.execute_script("return window.keys")
        assert [prevented for key, prevented in seen if key not in ("Control", "Alt", "Shift")] == [False] * 5, seen
        assert text() == "round 0: query 1 of 4" and stored(driver) == {}
        # s with Caps Lock on: the key "S" without Shift
        caps = {"key": "S", "code": "KeyS", "text": "S", "windowsVirtualKeyCode": 83, "nativeVirtualKeyCode": 83}
        driver.execute_cdp_cmd("Input.dispatchKeyEvent", {"type": "keyDown", **caps})
        driver.execute_cdp_cmd("Input.dispatchKeyEvent", {"type": "keyUp", **caps})
        WebDriverWait(driver, 30).until(lambda d: text() == "round 0: query 2 of 4")
        for position, (button, key) in enumerate([("answer-right", Keys.ENTER), ("answer-left", Keys.SPACE)], 3):
            WebDriverWait(driver, 60).until(answers_enabled)
            driver.find_element(By.ID, button).send_keys(key)  # focuses the button, then presses the key
            WebDriverWait(driver, 30).until(lambda d: text() == f"round 0: query {position} of 4")
        assert list(stored(driver).values()) == [["skip", 1, 0]]
        # Enter held on a focused button: one answer
        WebDriverWait(driver, 60).until(answers_enabled)
        driver.execute_script("document.getElementById('answer-equal').focus()")
        enter = {"key": "Enter", "code": "Enter", "text": "\r", "windowsVirtualKeyCode": 13, "nativeVirtualKeyCode": 13}
        driver.execute_cdp_cmd("Input.dispatchKeyEvent", {"type": "keyDown", **enter})
        for _ in range(30):
            driver.execute_cdp_cmd("Input.dispatchKeyEvent", {"type": "keyDown", "autoRepeat": True, **enter})
        driver.execute_cdp_cmd("Input.dispatchKeyEvent", {"type": "keyUp", **enter})
        WebDriverWait(driver, 30).until(lambda d: text() == "round 0: all 4 answered")
        assert list(stored(driver).values()) == [["skip", 1, 0, 0.5]]


@needs_chromium
def test_label_app_page_words_in_a_headless_browser(tmp_path):
    """One answer kept is one answer "is back"; the question is asked only while a query is shown."""
    from selenium.webdriver.common.by import By
    from selenium.webdriver.common.keys import Keys
    from selenium.webdriver.support.ui import WebDriverWait

    run = make_run(tmp_path, (2,), teacher={})
    with serve(run) as address, contextlib.closing(chrome()) as driver:
        text = open_page(driver, address)
        question = driver.find_element(By.TAG_NAME, "h2")
        answer_queries(driver, [Keys.ARROW_LEFT], first=1, n=2)
        assert question.is_displayed()
        driver.refresh()
        WebDriverWait(driver, 60).until(lambda d: text() == "round 0: query 2 of 2")
        assert text("message") == "your 1 answer to round 0, kept in this tab, is back"
        answer_round(driver, [Keys.ARROW_RIGHT])
        WebDriverWait(driver, 30).until(lambda d: text("message") == "round 0 saved (labels/0.json)")
        write_teacher(run, phase="finished", round=None, labelled=2, step=1500)
        WebDriverWait(driver, 30).until(lambda d: text() == "the run has finished: 2 labels in 1 rounds")
        assert not driver.find_element(By.TAG_NAME, "h2").is_displayed()


@needs_chromium
def test_label_app_new_queries_for_the_round_on_the_page_in_a_headless_browser(tmp_path):
    """A run folder used again while a round is on the page: the page drops the answers to the old queries, says so,
    and shows the new queries' clips."""
    from selenium.webdriver.common.by import By
    from selenium.webdriver.common.keys import Keys
    from selenium.webdriver.support.ui import WebDriverWait

    run = make_run(tmp_path, (3,))
    with serve(run) as address, contextlib.closing(chrome()) as driver:
        text = open_page(driver, address)
        answer_queries(driver, [Keys.ARROW_LEFT], first=1)
        write_queries(run, 0, 3, right=-0.5)
        digest = get_state(address)["queries_digest"]
        WebDriverWait(driver, 30).until(lambda d: text("message") == (
            "round 0's queries have changed (a new run in the folder ext?): your 1 answer to it was not used"))
        WebDriverWait(driver, 60).until(lambda d: text() == "round 0: query 1 of 3" and answers_enabled(d))
        assert driver.find_element(By.ID, "right").get_attribute("src").endswith(f"/clip/0/0/1.gif?queries={digest}")
        assert stored(driver) == {}


def test_label_app_memory_grows_per_clip_by_the_clip_alone_with_a_real_app(tmp_path, monkeypatch):
    """A real app draws 10 clips of 20 real cartpole steps, one after another. Past the first three (the renderer's
    one-time start), its peak memory grows by the clips it keeps and by at most 0.5 MB a clip besides. Drawing each
    clip in the request's own thread, as the app did, grew it by some 3 MB a clip: each thread's malloc arena kept
    its clip's peak. `results/label-session/memory_200.py` runs the same probe over a 200-clip session at 50 steps."""
    monkeypatch.setenv("MUJOCO_GL", "egl")
    sys.path.insert(0, os.path.join(ROOT, "results", "label-session"))
    import memory_200
    from test_labelling import free_port

    run = str(tmp_path / "run")
    memory_200.write_run(run, "cartpole-swingup", 1, 5, 20)
    record = memory_200.probe(run, free_port(), 1, 5)
    warm = record["rss_after_each_clip_mb"][2]
    kept = sum(record["clip_mb"][3:])  # the default 256 MB cache keeps them all
    assert record["clips"] == 10
    assert record["peak_mb"] - warm - kept <= 0.5 * 7, record
