"""Real preferences (docs/labelling.md): the query log `preferences/`, the external-teacher file protocol with a
scripted teacher, `--preferences` reuse, and the labelling page in a real headless Chromium."""
import hashlib
import json
import os
import shutil
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request

import numpy as np
import pytest
import torch

from label_examples import INVALID, VALID
from test_scripts import ROOT, SPARSE_TINY, TINY, run_script, scalars

sys.path.insert(0, ROOT)
import ene  # noqa: E402
import pebble  # noqa: E402
from r2n_harness.external_teacher import labels_problem  # noqa: E402
from r2n_harness.preferences import load_preferences, read_preferences  # noqa: E402

# TINY with a budget of 10: two rounds of 5 queries (steps 500 and 1000), then SAC to 1500.
EXTERNAL = TINY + ["--total-timesteps", "1500", "--max-feedback", "10", "--teacher", "external", "--run-name", "ext"]
EXTRA = {"pebble.py": [], "r2n_surf.py": SPARSE_TINY + ["--surf-tau", "0.6"]}  # SURF: the teacher sees central steps


def start(script, cwd, args):
    log = open(os.path.join(cwd, f"{script}.log"), "w")
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONWARNINGS="ignore")
    return subprocess.Popen([sys.executable, os.path.join(ROOT, script), *args], cwd=cwd, env=env, stdout=log,
                            stderr=subprocess.STDOUT), log.name


def wait_for(condition, process, log, seconds=300):
    deadline = time.time() + seconds
    while not condition():
        assert process.poll() is None, open(log).read()[-3000:]
        assert time.time() < deadline, open(log).read()[-3000:]
        time.sleep(0.05)


def page_written(run, round_index):
    """The answers of a labels file the page wrote, bound to the digest of the queries the run wrote."""
    from r2n_harness.external_teacher import file_digest

    written = json.loads((run / "labels" / f"{round_index}.json").read_text())
    assert written["queries"] == file_digest(str(run / "queries" / f"{round_index}.npz")), written
    return written["answers"]


def oracle_answers(queries):
    """The scripted teacher: the segment with the larger true return (ties: the first), as plain numbers."""
    returns = queries["true_rewards"].astype(np.float64).sum(-1)
    return [1 if r1 > r0 else 0 for r0, r1 in returns]


@pytest.mark.parametrize("script", list(EXTRA))
def test_external_teacher_protocol_with_a_scripted_teacher(script, tmp_path):
    process, log = start(script, tmp_path, EXTERNAL + EXTRA[script])
    run = tmp_path / "runs" / "ext"
    # round 0: a malformed file first (one line, the run keeps waiting), then the oracle's answers
    wait_for(lambda: (run / "queries" / "0.npz").exists(), process, log)
    assert "waiting for labels: runs/ext/labels/0.json" in open(log).read()
    (run / "labels").mkdir()
    (run / "labels" / "0.json").write_text("[1, 2")
    wait_for(lambda: "labels: runs/ext/labels/0.json: " in open(log).read(), process, log)
    assert process.poll() is None
    with np.load(run / "queries" / "0.npz") as data:
        queries = {key: data[key] for key in data}
    assert queries["obs"].shape == (5, 2, 20, 51) and queries["physics"].shape == (5, 2, 20, 4)
    answers = oracle_answers(queries)
    true_rewards = torch.as_tensor(queries["true_rewards"])
    _, simulated = pebble.teacher(true_rewards[:, 0], true_rewards[:, 1], 0.0, -1.0, 1.0, 0.0, 0.0, 0.0)
    assert answers == simulated.tolist()  # the oracle teacher's labels, on the same queries
    (run / "labels" / "0.json").write_text(json.dumps(answers))
    # training on: teacher.json says the current step (the page shows it), not the round's
    def training_on():
        teacher = json.loads((run / "teacher.json").read_text())
        return teacher["phase"] == "training" and teacher["step"] > 500

    wait_for(training_on, process, log, seconds=120)
    # round 1: an equal and a skip among them
    wait_for(lambda: (run / "queries" / "1.npz").exists(), process, log)
    with np.load(run / "queries" / "1.npz") as data:
        round1 = oracle_answers({"true_rewards": data["true_rewards"]})[:3] + [0.5, "skip"]
    (run / "labels" / "1.json").write_text(json.dumps(round1))
    assert process.wait(timeout=300) == 0, open(log).read()[-3000:]
    values = scalars(str(run))
    assert values["pbrl/total_feedback"] == [5, 10] and values["pbrl/labeled_feedback"] == [5, 9]
    saved = read_preferences(str(run / "preferences"))
    expected = answers + round1[:4] + [np.nan]
    np.testing.assert_array_equal(saved["labels"], np.array(expected, np.float32))
    assert saved["rounds"].tolist() == [0] * 5 + [1] * 5 and saved["steps"].tolist() == [500] * 5 + [1000] * 5
    stored = 30 if "surf" in script else 20  # SURF keeps 5 more steps each side of what the teacher sees
    assert saved["obs"].shape == (10, 2, stored, 51) and saved["actions"].shape == (10, 2, stored, 1)
    assert str(saved["env_id"]) == "cartpole-swingup"
    central = slice(5, 25) if "surf" in script else slice(None)
    np.testing.assert_array_equal(saved["obs"][:5, :, central], queries["obs"])
    np.testing.assert_array_equal(saved["physics"][:5, :, central], queries["physics"])


def test_the_run_takes_exactly_the_labels_the_page_takes():
    """The run's check of a labels file, on the table the page's check is tested on (tests/label_examples.py)."""
    for content, n in VALID:
        assert labels_problem(content, n) is None, content
    for content, n in INVALID:
        assert labels_problem(content, n) is not None, content


def test_preferences_npz_of_a_simulated_run_and_its_reuse(tmp_path):
    first = tmp_path / "first"
    first.mkdir()
    run_script("pebble.py", TINY + ["--run-name", "a", "--query-log"], first)
    folder = first / "runs" / "a" / "preferences"
    assert sorted(os.listdir(folder)) == ["0.npz", "1.npz", "2.npz", "3.npz"]  # a file per round, each written once
    saved = read_preferences(str(folder))
    assert saved["obs"].shape == (20, 2, 20, 51) and saved["rounds"].tolist() == [r for r in range(4) for _ in range(5)]
    values = scalars(str(first / "runs" / "a"))
    assert np.sum(~np.isnan(saved["labels"])) == values["pbrl/labeled_feedback"][-1]
    # the stored physics states are those of the stored observations: render one step, and check the real features
    env = ene.make_env("cartpole-swingup", 0, 0.9, episode_length=100)
    env.reset(seed=0)
    physics = env.unwrapped._env.physics
    with physics.reset_context():
        physics.set_state(saved["physics"][3, 1, 7])
    observation = env.unwrapped._env.task.get_observation(physics).values()
    real = np.concatenate([np.asarray(v, np.float32).ravel() for v in observation])
    np.testing.assert_allclose(saved["obs"][3, 1, 7, :5], real, rtol=1e-5, atol=1e-6)
    # --preferences: the 20 labels seed the next run's dataset and count in its budget (30: two more rounds of 5)
    second = tmp_path / "second"
    second.mkdir()
    path = str(folder)
    run_script("pebble.py", TINY + ["--run-name", "b", "--preferences", path, "--max-feedback", "30", "--query-log"],
               second)
    values = scalars(str(second / "runs" / "b"))
    assert values["pbrl/total_feedback"] == [25, 30]
    data = read_preferences(str(second / "runs" / "b" / "preferences"))
    assert data["rounds"].tolist() == [-1] * 20 + [0] * 5 + [1] * 5
    np.testing.assert_array_equal(data["obs"][:20], saved["obs"])
    # one file of the folder seeds a run too: round 3's 5 queries
    one = load_preferences(f"{path}/3.npz", "cartpole-swingup", 52, 20, budget=15)
    np.testing.assert_array_equal(one["labels"], saved["labels"][15:])
    np.testing.assert_array_equal(one["obs"], saved["obs"][15:])
    for extra, message in [
        (["--preferences", "missing.npz"], "--preferences: no such file or folder: missing.npz"),
        (["--preferences", str(second)], "is not a run's preferences"),
        (["--preferences", path, "--max-feedback", "10"], "holds 20 queries, more than --max-feedback 10"),
        (["--preferences", path, "--segment-size", "10"], "this run needs cartpole-swingup, 10 x 52"),
    ]:
        result = run_script("pebble.py", TINY + extra, second, check=False)
        assert result.returncode == 1 and message in result.stderr, result.stderr
        assert len(result.stderr.strip().splitlines()) == 1


CHROMIUM, CHROMEDRIVER = shutil.which("chromium"), shutil.which("chromedriver")


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


needs_chromium = pytest.mark.skipif(
    os.environ.get("CI") is None and not (CHROMIUM and CHROMEDRIVER),
    reason="needs Debian's chromium and chromium-driver (installed by .ci/run, where it always runs)")


def chrome():
    """Debian's Chromium, headless, driven by selenium."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = CHROMIUM
    for flag in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--window-size=900,700"):
        options.add_argument(flag)
    return webdriver.Chrome(service=Service(CHROMEDRIVER), options=options)


def answers_enabled(driver):
    """Whether the page takes answers: both clips of the current query have loaded."""
    from selenium.webdriver.common.by import By

    return driver.find_element(By.ID, "answer-left").is_enabled()


@needs_chromium
def test_labelling_page_in_a_headless_browser(tmp_path):
    from selenium.webdriver.common.by import By
    from selenium.webdriver.common.keys import Keys
    from selenium.webdriver.support.ui import WebDriverWait

    process, log = start("pebble.py", tmp_path, EXTERNAL)
    run = tmp_path / "runs" / "ext"
    wait_for(lambda: (run / "queries" / "0.npz").exists(), process, log)
    port = free_port()
    app = subprocess.Popen([sys.executable, os.path.join(ROOT, "label_app.py"), str(run), "--port", str(port)],
                           stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    driver = chrome()
    try:
        assert app.stdout.readline().startswith(f"labelling {run} at http://127.0.0.1:{port}"), "the app did not start"
        driver.get(f"http://127.0.0.1:{port}/")
        progress = lambda: driver.find_element(By.ID, "progress").text  # noqa: E731
        WebDriverWait(driver, 60).until(lambda d: progress() == "round 0: query 1 of 5")
        loaded = "return document.getElementById('left').naturalWidth * document.getElementById('right').naturalWidth"
        WebDriverWait(driver, 120).until(lambda d: d.execute_script(loaded) > 0)  # both clips rendered
        WebDriverWait(driver, 30).until(answers_enabled)  # the page takes answers once both have loaded
        driver.save_screenshot(str(tmp_path / "label_app.png"))
        if os.environ.get("R2N_SCREENSHOT"):  # to refresh the README's picture
            shutil.copy(tmp_path / "label_app.png", os.environ["R2N_SCREENSHOT"])
        assert os.path.getsize(tmp_path / "label_app.png") > 10_000
        driver.find_element(By.ID, "answer-left").click()  # mouse
        WebDriverWait(driver, 30).until(lambda d: progress() == "round 0: query 2 of 5")
        body = driver.find_element(By.TAG_NAME, "body")
        for key, position in [(Keys.ARROW_RIGHT, 3), ("=", 4), ("s", 5)]:  # keyboard
            WebDriverWait(driver, 120).until(answers_enabled)
            body.send_keys(key)
            WebDriverWait(driver, 30).until(lambda d: progress() == f"round 0: query {position} of 5")
        WebDriverWait(driver, 120).until(answers_enabled)
        driver.find_element(By.ID, "answer-right").click()
        WebDriverWait(driver, 30).until(lambda d: progress() == "round 0: all 5 answered")
        assert not (run / "labels" / "0.json").exists()  # the last answer can still be undone
        driver.find_element(By.ID, "submit").click()
        wait_for(lambda: (run / "labels" / "0.json").exists(), process, log)
        assert page_written(run, 0) == [0, 1, 0.5, "skip", 1]
        # the run goes on: its next round appears on the page, answered by keyboard
        wait_for(lambda: (run / "queries" / "1.npz").exists(), process, log)
        WebDriverWait(driver, 60).until(lambda d: progress() == "round 1: query 1 of 5")
        for position in range(5):
            WebDriverWait(driver, 120).until(answers_enabled)
            body.send_keys(Keys.ARROW_LEFT)
        WebDriverWait(driver, 30).until(lambda d: progress() == "round 1: all 5 answered")
        body.send_keys(Keys.ENTER)
        assert process.wait(timeout=300) == 0, open(log).read()[-3000:]
        assert page_written(run, 1) == [0] * 5
        assert scalars(str(run))["pbrl/labeled_feedback"] == [4, 9]
        # the labels on disk are the training data, and the run's record of them; the page says the run finished
        files = [(run / "labels" / f"{r}.json").read_bytes() for r in (0, 1)]
        data = read_preferences(str(run / "preferences"))
        expected = [np.nan if a == "skip" else a for content in files for a in json.loads(content)["answers"]]
        np.testing.assert_array_equal(data["labels"], np.array(expected, np.float32))
        assert data["label_sha256"].tolist() == [hashlib.sha256(c).hexdigest() for c in files]  # per round
        WebDriverWait(driver, 30).until(lambda d: progress().startswith("the run has finished: 9 labels in 2 rounds"))
        again = json.dumps({"queries": json.loads(files[1])["queries"], "answers": [1] * 5}).encode()
        request = urllib.request.Request(f"http://127.0.0.1:{port}/api/labels/1", data=again, method="POST",
                                         headers={"Content-Type": "application/json"})
        with pytest.raises(urllib.error.HTTPError) as refused:
            urllib.request.urlopen(request, timeout=30)
        assert refused.value.code == 409 and (run / "labels" / "1.json").read_bytes() == files[1]
    finally:
        driver.quit()
        app.terminate()  # not SIGINT: a background job (a CI runner) ignores it, and so would the app
        app.wait(timeout=30)
        process.kill()


def test_a_round_of_equal_answers_is_trained_on_and_the_run_goes_on(tmp_path):
    """Every answer "equal" (0.5), as a person may answer: no label is strict, so the round has no training accuracy
    (0 / 0), and the run trains on the labels and goes on instead of stopping at a non-finite value."""
    process, log = start("pebble.py", tmp_path, EXTERNAL)
    run = tmp_path / "runs" / "ext"
    for round_index in range(2):  # the budget of 10 in rounds of 5
        wait_for(lambda: (run / "queries" / f"{round_index}.npz").exists(), process, log)
        (run / "labels").mkdir(exist_ok=True)
        (run / "labels" / f"{round_index}.json").write_text(json.dumps([0.5] * 5))
    assert process.wait(timeout=300) == 0, open(log).read()[-3000:]
    values = scalars(str(run))
    assert values["pbrl/labeled_feedback"] == [5, 10] and len(values["pbrl/reward_loss"]) == 2
    assert all(np.isfinite(values["pbrl/reward_loss"])) and "pbrl/reward_accuracy" not in values
    np.testing.assert_array_equal(read_preferences(str(run / "preferences"))["labels"], np.full(10, 0.5))
