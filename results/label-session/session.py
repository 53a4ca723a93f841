"""A scripted labelling session (issue 43, "Labelling for an hour"): a person's long session with the labelling page,
played by a script in Debian's headless Chromium, against a real `--teacher external` run.

    python results/label-session/session.py --minutes 15 --out /tmp/label-session

The run (pebble.py on cartpole-swingup, small networks, 10 queries a round) asks round after round; the script answers
each query with a random key once the page takes answers, with the keys a person also presses by mistake or on
purpose: undo, a reload mid-round, Ctrl+= (zoom: no answer), Caps Lock's S. Every few minutes it opens a second tab
of the same browser, which must show at once that the first tab is answering the round, then closes it. At the end it
checks that every labels file holds exactly the answers the script gave for its round, and writes `summary.json`:
rounds, answers, the app's memory (RSS, each minute: the clip cache is bounded), the slowest `/api/state`, the
notices seen, and any traceback in the app's or the run's output (there must be none).
"""
import argparse
import json
import os
import random
import subprocess
import sys
import time
import urllib.request

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, os.path.join(ROOT, "tests"))
from test_labelling import chrome, free_port  # noqa: E402  (Debian's chromium, headless, as the tests drive it)

RUN = ["--env-id", "cartpole-swingup", "--noise", "0.9", "--total-timesteps", "200000", "--learning-starts", "200",
       "--unsup-steps", "300", "--feedback-freq", "500", "--episode-length", "100", "--eval-freq", "5000",
       "--eval-episodes", "2", "--segment-size", "20", "--max-feedback", "5000", "--queries-per-round", "10",
       "--hidden-dim", "32", "--batch-size", "32", "--reward-hidden-dim", "16", "--reward-layers", "2",
       "--reward-epochs", "20", "--teacher", "external", "--run-name", "session"]
KEYS = {"\ue012": 0, "\ue014": 1, "=": 0.5, "s": "skip"}  # selenium's ← and →, then = and s


def rss_mb(pid: int) -> float:
    with open(f"/proc/{pid}/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("VmRSS:")) / 1024


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--minutes", type=float, default=15)
    parser.add_argument("--out", default="/tmp/label-session")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.by import By
    from selenium.webdriver.common.keys import Keys

    rng = random.Random(args.seed)
    os.makedirs(args.out, exist_ok=True)
    run_dir = os.path.join(args.out, "runs", "session")
    if os.path.exists(run_dir):
        sys.exit(f"session.py: error: --out {args.out} holds an earlier session: choose another folder")
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONWARNINGS="ignore")
    run_log, app_log = (open(os.path.join(args.out, name), "w") for name in ("run.log", "app.log"))
    run = subprocess.Popen([sys.executable, os.path.join(ROOT, "pebble.py"), *RUN], cwd=args.out, env=env,
                           stdout=run_log, stderr=subprocess.STDOUT)
    while not os.path.isdir(run_dir):
        assert run.poll() is None, "the run ended at its start: see run.log"
        time.sleep(0.2)
    port = free_port()
    app = subprocess.Popen([sys.executable, os.path.join(ROOT, "label_app.py"), run_dir, "--port", str(port)],
                           env=env, stdout=app_log, stderr=subprocess.STDOUT)
    address = f"http://127.0.0.1:{port}"
    driver = chrome()
    given, summary = {}, {"rss_mb": [], "slowest_state_s": 0.0, "notices": set(), "reloads": 0, "undos": 0,
                          "second_tabs": 0, "second_tab_saw_first": 0}
    text = lambda element="progress": driver.find_element(By.ID, element).text  # noqa: E731
    end, next_minute, next_tab = time.time() + 60 * args.minutes, time.time(), time.time() + 60
    try:
        for _ in range(600):  # the app starts (imports MuJoCo)
            try:
                urllib.request.urlopen(f"{address}/api/state", timeout=5).read()
                break
            except OSError:
                time.sleep(0.2)
        driver.get(address)
        main_tab = driver.current_window_handle
        while time.time() < end:
            if time.time() >= next_minute:  # the app's memory, and how fast it answers the poll
                next_minute += 60
                summary["rss_mb"].append(round(rss_mb(app.pid), 1))
                started = time.time()
                urllib.request.urlopen(f"{address}/api/state", timeout=30).read()
                summary["slowest_state_s"] = max(summary["slowest_state_s"], round(time.time() - started, 3))
            summary["notices"].update(p.text for p in driver.find_elements(By.CSS_SELECTOR, "#notices p"))
            progress = text()
            if progress.endswith("answered") and driver.find_element(By.ID, "submit").is_displayed():
                driver.find_element(By.TAG_NAME, "body").send_keys(Keys.ENTER)
                time.sleep(0.5)
                continue
            if ": query " not in progress or not driver.find_element(By.ID, "answer-left").is_enabled():
                time.sleep(0.2)  # the run trains, or the clips load
                continue
            round_index, query = int(progress.split()[1].rstrip(":")), int(progress.split()[3]) - 1
            roll = rng.random()
            if time.time() >= next_tab:  # a second tab of the browser: it must see the first at once
                next_tab += 180
                summary["second_tabs"] += 1
                driver.switch_to.new_window("tab")
                driver.get(address)
                time.sleep(2)
                notices = [p.text for p in driver.find_elements(By.CSS_SELECTOR, "#notices p")]
                summary["second_tab_saw_first"] += any("another tab of this browser" in n for n in notices)
                driver.close()
                driver.switch_to.window(main_tab)
            elif roll < 0.03 and query > 0:  # a reload mid-round: the answers come back
                summary["reloads"] += 1
                driver.refresh()
                time.sleep(1)
            elif roll < 0.05:  # Ctrl+= zooms, and answers nothing
                ActionChains(driver).key_down(Keys.CONTROL).send_keys("=").key_up(Keys.CONTROL).perform()
                time.sleep(0.5)
                assert text() == progress, "Ctrl+= answered"
            else:  # an answer (S: the s of a keyboard with Caps Lock or Shift), or undo
                undo, key = roll < 0.10 and query > 0, rng.choice([*KEYS, "S"])
                driver.find_element(By.TAG_NAME, "body").send_keys(Keys.BACKSPACE if undo else key)
                if undo:
                    summary["undos"] += 1
                    given[round_index].pop()
                else:
                    given.setdefault(round_index, []).append(KEYS.get(key, "skip"))
                deadline = time.time() + 30
                while text() == progress and time.time() < deadline:
                    time.sleep(0.05)  # the page moves to the next query (the previous one, after undo)
                assert text() != progress, f"{progress}: the page did not take the key"
    finally:
        driver.quit()
        app.terminate()
        run.terminate()
        app.wait(timeout=30)
        run.wait(timeout=60)
    written = {}
    for name in os.listdir(os.path.join(run_dir, "labels")) if os.path.isdir(os.path.join(run_dir, "labels")) else []:
        if name.endswith(".json"):
            with open(os.path.join(run_dir, "labels", name)) as f:
                written[int(name[:-5])] = json.load(f)
    summary.update(run_exit_code=run.returncode, rounds_written=len(written), answers_written=sum(map(len, written.values())),
                   labels_match=all(written[r] == given.get(r) for r in written),
                   tracebacks=[name for name in ("app.log", "run.log")
                               if "Traceback" in open(os.path.join(args.out, name)).read()],
                   notices=sorted(summary["notices"]))
    with open(os.path.join(args.out, "summary.json"), "w") as f:
        json.dump(summary, f, indent=1)
    print(json.dumps(summary, indent=1))
    return 0 if summary["labels_match"] and not summary["tracebacks"] else 1


if __name__ == "__main__":
    sys.exit(main())
