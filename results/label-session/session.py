"""A scripted labelling session (issues 43 and 72): a person's long session with the labelling page, played by a
script in Debian's headless Chromium, against a real `--teacher external` run.

    python results/label-session/session.py --minutes 15 --out /tmp/label-session

The run (pebble.py on cartpole-swingup, small networks; by default a round every 300 steps, 3 queries a round,
segments of 10 steps: on the busy 2-core machine without a GPU where it ran, the app took 6-9 s to render a clip
of 20 steps, and these settings gave a round every ~25 s, 32 in 15 minutes) asks round after round; the script
answers each query with a random key once the page takes answers, with the keys a person also presses by
mistake or on purpose: undo, a reload mid-round (the page must bring this tab's answers back), Ctrl+= (zoom: no
answer), Caps Lock's S. Each answer is recorded with the clips the page showed for it (their URLs carry the digest
of the queries they render). During the session:

- a second tab of the same browser stays open for `--second-tab-seconds` while the first answers: it must show at
  once that the first tab answers the round, with the first tab's answers, and the first tab must show the second;
  every few minutes a second tab is also opened for a moment;
- the run folder's queries are replaced once (`--replace-at`, a fraction of the session): while a round is on the
  page with some answers given, its `queries/R.npz` is replaced (temp file, then os.replace) by other queries of
  the same number (an earlier round's, the two segments swapped and the order reversed: queries the app has never
  rendered). The run must say at once that its queries file changed under it and write it again; the page must end
  on the clips of the run's own queries (the digest in the clips' URLs; the other digest's clip URL gets 404),
  having dropped its answers with its notice if it saw the other queries meanwhile; the round's labels must carry
  the run's digest;
- a reload is forced once soon after the replacement (besides the random ones);
- the app is stopped (SIGTERM) once while the page fetches a round's first clips (`--restart-at`) and started again
  on its port a moment later: the page must take answers again by itself, without a reload, its notice naming the
  failed tries and the one that loaded.

At the end it checks, with digests, that every labels file holds exactly the answers the script gave for its
round, each given while the page showed the clips of that round's queries as they are in the run folder at the
end; that the labels file names those queries' digest; and that the run's query log (`preferences/R.npz`) holds
the same answers for queries of the same digest, with the SHA-256 of that labels file. It writes
`summary.json` (every check, and `ok`: all of them held) and `session.log` (what the script did, when): rounds,
answers, the app's memory (RSS every 10 s, and each app's peak, VmHWM, against `--rss-bound-mb`: the clip cache is
bounded by `--clip-cache-mb`), the slowest `/api/state`, the notices seen, and any traceback in the app's or the
run's output (there must be none). The exit code is 0 when every check held.
"""
import argparse
import hashlib
import json
import os
import random
import subprocess
import sys
import time
import traceback
import urllib.error
import urllib.request
from urllib.parse import parse_qs, urlsplit

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, os.path.join(ROOT, "tests"))
from test_labelling import chrome, free_port  # noqa: E402  (Debian's chromium, headless, as the tests drive it)

RUN = ["--env-id", "cartpole-swingup", "--noise", "0.9", "--total-timesteps", "200000", "--learning-starts", "200",
       "--unsup-steps", "300", "--episode-length", "100", "--eval-freq", "5000",
       "--eval-episodes", "2", "--max-feedback", "5000",
       "--hidden-dim", "32", "--batch-size", "32", "--reward-hidden-dim", "16", "--reward-layers", "2",
       "--reward-epochs", "20", "--teacher", "external", "--run-name", "session"]
KEYS = {"\ue012": 0, "\ue014": 1, "=": 0.5, "s": "skip"}  # selenium's ← and →, then = and s
SYMBOLS = {0: "\u2190", 1: "\u2192", 0.5: "=", "skip": "s"}  # an answer as the page's notices write it
OTHER_TAB = "another tab of this browser is answering round"
RSS_BOUND_MB = 800  # docs/labelling.md's bound for a 200-clip session with the default cache (memory_200.py)


def rss_mb(pid: int, field: str = "VmRSS") -> float:
    """A process's resident memory (VmRSS) or its peak so far (VmHWM), in MB."""
    with open(f"/proc/{pid}/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith(f"{field}:")) / 1024


def digest_of(physics: np.ndarray, env_id: str) -> str:
    """The digest of a queries file as docs/labelling.md describes it (of the task and the physics states): the
    page's clip URLs carry it."""
    return hashlib.sha256(f"{env_id} {physics.dtype} {physics.shape}".encode() + physics.tobytes()).hexdigest()[:16]


def logged_answer(label: float):
    """A query log's label as the page's answer: NaN is a skipped query."""
    return "skip" if np.isnan(label) else float(label)


def file_digest(path: str) -> str:
    with np.load(path) as data:
        return digest_of(data["physics"], str(data["env_id"]))


def count(k: int) -> str:
    return f"{k} answer{'' if k == 1 else 's'}"


def replace_queries(run_dir: str, round_index: int) -> dict:
    """Replace the round's queries file, atomically, by other queries of the same number: the latest earlier round
    of the same shape, its two segments swapped and its order reversed (never rendered by the app); without one,
    this round's own, so changed."""
    path = os.path.join(run_dir, "queries", f"{round_index}.npz")
    with np.load(path) as data:
        old = {name: data[name] for name in data.files}
    donor = None
    for r in range(round_index - 1, -1, -1):
        with np.load(os.path.join(run_dir, "queries", f"{r}.npz")) as data:
            if data["physics"].shape == old["physics"].shape:
                donor, arrays = r, {name: data[name] for name in data.files}
                break
    if donor is None:
        arrays = old
    new = {name: (value[::-1, ::-1].copy() if value.ndim >= 2 and len(value) == len(old["physics"]) else value)
           for name, value in arrays.items()}  # obs, actions, physics, true_rewards: (n, 2, ...)
    tmp = f"{path}.session-tmp"
    with open(tmp, "wb") as f:
        np.savez(f, **new)
    os.replace(tmp, path)
    return {"donor_round": donor, "old_digest": digest_of(old["physics"], str(old["env_id"])),
            "new_digest": digest_of(new["physics"], str(new["env_id"])), "n": len(new["physics"])}


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--minutes", type=float, default=15)
    parser.add_argument("--out", default="/tmp/label-session")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--queries-per-round", type=int, default=3, help="the run's")
    parser.add_argument("--segment-size", type=int, default=10, help="the run's: frames a clip")
    parser.add_argument("--feedback-freq", type=int, default=300, help="the run's: steps between rounds")
    parser.add_argument("--clip-cache-mb", type=float, default=256, help="the app's --clip-cache-mb")
    parser.add_argument("--rss-bound-mb", type=float, default=RSS_BOUND_MB, help="each app's peak RSS must stay below")
    parser.add_argument("--second-tab-at", type=float, default=0.25, help="fraction of the session")
    parser.add_argument("--second-tab-seconds", type=float, default=120)
    parser.add_argument("--replace-at", type=float, default=0.5, help="fraction of the session")
    parser.add_argument("--restart-at", type=float, default=0.7, help="fraction of the session")
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
    session_log = open(os.path.join(args.out, "session.log"), "w")
    began = time.time()

    def log(line: str):
        line = f"[{time.time() - began:7.1f} s] {line}"
        print(line, flush=True)
        print(line, file=session_log, flush=True)

    command = [sys.executable, os.path.join(ROOT, "pebble.py"), *RUN, "--queries-per-round",
               str(args.queries_per_round), "--segment-size", str(args.segment_size), "--feedback-freq",
               str(args.feedback_freq)]
    log("run: " + " ".join(command[1:]))
    run = subprocess.Popen(command, cwd=args.out, env=env, stdout=run_log, stderr=subprocess.STDOUT)
    while not os.path.isdir(run_dir):
        assert run.poll() is None, "the run ended at its start: see run.log"
        time.sleep(0.2)
    port = free_port()
    command = [sys.executable, os.path.join(ROOT, "label_app.py"), run_dir, "--port", str(port),
               "--clip-cache-mb", str(args.clip_cache_mb)]
    log("app: " + " ".join(command[1:]))
    start_app = lambda: subprocess.Popen(command, env=env, stdout=app_log, stderr=subprocess.STDOUT)  # noqa: E731
    app, app_peaks = start_app(), []  # the app now, and the peak RSS (VmHWM) of each app stopped
    address = f"http://127.0.0.1:{port}"
    driver = chrome()
    given = {}  # round -> the answers the script gave, in order (less those undone, or dropped by a replacement)
    shown = {}  # round -> the digest of the clips shown for each of those answers
    summary = {"minutes": args.minutes, "queries_per_round": args.queries_per_round,
               "clip_cache_mb": args.clip_cache_mb, "rss_bound_mb": args.rss_bound_mb, "rss_mb_each_minute": [],
               "rss_peak_mb": 0.0, "rss_baseline_mb": None, "slowest_state_s": 0.0, "notices": set(),
               "messages": set(), "reloads": 0, "reloads_restored": 0, "undos": 0, "ctrl_equals": 0, "answers": 0,
               "second_tabs": 0, "second_tab_saw_first": 0, "sustained_second_tab": None, "replacement": None,
               "restart": None}
    # read in one script each: the page replaces its notices at every render (a found element can go stale)
    text = lambda element="progress": driver.execute_script(  # noqa: E731
        "return document.getElementById(arguments[0]).textContent", element)
    notices = lambda: driver.execute_script(  # noqa: E731
        "return [...document.querySelectorAll('#notices p')].map((p) => p.textContent)")
    body = lambda: driver.find_element(By.TAG_NAME, "body")  # noqa: E731

    def clip_digests() -> tuple:
        """The (round, query, side, digest) of the two clips the page shows."""
        out = []
        for side in ("left", "right"):
            url = urlsplit(driver.find_element(By.ID, side).get_attribute("src"))
            _, _, r, q, s = url.path.split("/")
            out.append((int(r), int(q), int(s[:-4]), parse_qs(url.query)["queries"][0]))
        return tuple(out)

    def wait_until(condition, seconds: float) -> bool:
        deadline = time.time() + seconds
        while time.time() < deadline:
            try:
                if condition():
                    return True
            except Exception:  # noqa: BLE001  (an element replaced meanwhile: look again)
                pass
            time.sleep(0.1)
        return False

    def taking(round_index: int, query: int) -> bool:
        """The page shows this query of this round, and takes answers."""
        return (text() == f"round {round_index}: query {query + 1} of {args.queries_per_round}"
                and driver.find_element(By.ID, "answer-left").is_enabled())

    clip_bytes = {}  # clip URL -> its size, as the browser fetched it (resource timing): the clips rendered

    def collect_clips():
        for url, size in driver.execute_script(
                "const clips = performance.getEntriesByType('resource').filter((e) => e.name.includes('/clip/'))"
                ".map((e) => [e.name, e.encodedBodySize]); performance.clearResourceTimings(); return clips"):
            if size:
                clip_bytes[urlsplit(url)._replace(netloc="").geturl()] = size

    def sample_memory():
        rss = round(rss_mb(app.pid), 1)
        summary["rss_peak_mb"] = max(summary["rss_peak_mb"], rss)
        return rss

    end = began + 60 * args.minutes
    next_minute, next_sample, next_tab = time.time(), time.time(), time.time() + 90
    tab_at, replace_at = began + 60 * args.minutes * args.second_tab_at, began + 60 * args.minutes * args.replace_at
    restart_at = began + 60 * args.minutes * args.restart_at
    second = None  # the sustained second tab: {"handle", "until", ...}
    force_reload, last_round = False, None
    try:
        for _ in range(600):  # the app starts (imports MuJoCo)
            try:
                urllib.request.urlopen(f"{address}/api/state", timeout=5).read()
                break
            except OSError:
                time.sleep(0.2)
        summary["rss_baseline_mb"] = sample_memory()
        log(f"app up: RSS {summary['rss_baseline_mb']} MB before any clip")
        driver.get(address)
        main_tab = driver.current_window_handle
        while time.time() < end:
            if time.time() >= next_sample:  # the app's memory every 10 s, and how fast it answers the poll
                next_sample += 10
                rss = sample_memory()
                collect_clips()
                if time.time() >= next_minute:
                    next_minute += 60
                    summary["rss_mb_each_minute"].append(rss)
                    log(f"app RSS {rss} MB (peak {summary['rss_peak_mb']} MB); rounds answered: "
                        f"{sum(1 for r in given if os.path.exists(os.path.join(run_dir, 'labels', f'{r}.json')))}")
                started = time.time()
                urllib.request.urlopen(f"{address}/api/state", timeout=30).read()
                summary["slowest_state_s"] = max(summary["slowest_state_s"], round(time.time() - started, 3))
            seen = notices()
            summary["notices"].update(seen)
            message = text("message")
            if message:
                summary["messages"].add(message)
            progress = text()
            if progress.endswith("answered") and driver.find_element(By.ID, "submit").is_displayed():
                round_index = int(progress.split()[1].rstrip(":"))
                body().send_keys(Keys.ENTER)
                log(f"round {round_index}: submitted {given.get(round_index)}")
                time.sleep(0.5)
                continue
            loading = ": query " in progress and not driver.find_element(By.ID, "answer-left").is_enabled()
            if (loading and summary["restart"] is None and time.time() >= restart_at
                    and progress.endswith(f"query 1 of {args.queries_per_round}") and driver.execute_script(
                        "return !document.getElementById('left').complete")):  # its clips not there yet
                # the app stopped while the page fetches this round's first clips, and started again on its port
                round_index = int(progress.split()[1].rstrip(":"))
                app_peaks.append(rss_mb(app.pid, "VmHWM"))
                app.terminate()
                app.wait(timeout=30)
                stopped = time.time()
                log(f"round {round_index}: the app stopped (SIGTERM) while the page fetched the round's first clips")
                tries = set()
                wait_until(lambda: tries.add(text("drawing")) or "did not load (try" in text("drawing"), 30)
                time.sleep(2)  # the app is away a while; the page keeps trying
                app = start_app()
                log(f"round {round_index}: the app started again on port {port} after {time.time() - stopped:.1f} s")
                recovered = wait_until(lambda: tries.add(text("drawing")) or taking(round_index, 0), 120)
                tries.add(text("drawing"))
                tries.discard("")
                summary["restart"] = {
                    "round": round_index, "recovered_without_reload": recovered,
                    "seconds_to_answers": round(time.time() - stopped, 1), "messages": sorted(tries),
                    "ok": bool(recovered and any("did not load (try" in m for m in tries)
                               and any("loaded on try" in m for m in tries))}
                log(f"round {round_index}: the page takes answers again by itself: {recovered}, "
                    f"{summary['restart']['seconds_to_answers']} s after the stop; its messages: {sorted(tries)}")
                continue
            if ": query " not in progress or not driver.find_element(By.ID, "answer-left").is_enabled():
                time.sleep(0.2)  # the run trains, or the clips load
                continue
            round_index, query = int(progress.split()[1].rstrip(":")), int(progress.split()[3]) - 1
            if round_index != last_round:
                last_round = round_index
                log(f"round {round_index}: on the page ({progress})")
            assert len(given.get(round_index, [])) == query, f"{progress}: the script gave {given.get(round_index)}"
            if second is not None:  # the first tab shows the second, which is on the same round
                second["samples"] += 1
                second["first_saw_second"] += any(n.startswith(f"{OTHER_TAB} {round_index} too") for n in seen)
            roll = rng.random()
            if summary["replacement"] is None and time.time() >= replace_at and query >= 2 and second is None:
                # the run folder's queries replaced while this round is on the page with `query` answers
                before = clip_digests()
                replaced = replace_queries(run_dir, round_index)
                log(f"round {round_index}: queries/{round_index}.npz replaced with {query} answers given "
                    f"({replaced}); page's clips: digest {before[0][3]}")
                started = time.time()
                said = f"queries: {os.path.join('runs', 'session', 'queries', f'{round_index}.npz')} is no longer"
                seen_messages = set()
                run_said = wait_until(lambda: seen_messages.add(text("message")) or
                                      said in open(os.path.join(args.out, "run.log")).read(), 30)
                run_said_after_s = round(time.time() - started, 1)
                settle = time.time() + 3  # the page polls every 2 s: it has seen the file as the run wrote it again
                wait_until(lambda: seen_messages.add(text("message")) or time.time() > settle, 5)
                handled = wait_until(lambda: seen_messages.add(text("message")) or
                                     (taking(round_index, 0) or taking(round_index, query)) and
                                     all(c[3] == replaced["old_digest"] for c in clip_digests()), 30)
                seen_messages.discard("")
                dropped = taking(round_index, 0)  # the page saw the other queries and dropped its answers
                replaced.update(round=round_index, answers_before=list(given[round_index]),
                                page_digest_before=before[0][3], run_said_so=run_said,
                                run_said_after_s=run_said_after_s, page_settled=handled, page_dropped=dropped,
                                settled_after_s=round(time.time() - started, 1), message=text("message"),
                                messages=sorted(seen_messages), progress=text(),
                                page_digest_after=clip_digests()[0][3],
                                file_digest_after=file_digest(os.path.join(run_dir, "queries", f"{round_index}.npz")))
                state = json.loads(urllib.request.urlopen(f"{address}/api/state", timeout=30).read())
                replaced["state_digest"] = state["queries_digest"]
                for name, d in (("old_clip_http", replaced["old_digest"]), ("new_clip_http", replaced["new_digest"])):
                    try:
                        replaced[name] = urllib.request.urlopen(
                            f"{address}/clip/{round_index}/0/0.gif?queries={d}", timeout=60).status
                    except urllib.error.HTTPError as e:
                        replaced[name] = e.code
                replaced["handled"] = bool(
                    run_said and handled and replaced["page_digest_before"] == replaced["old_digest"]
                    and replaced["page_digest_after"] == replaced["old_digest"] == replaced["state_digest"]
                    == replaced["file_digest_after"]
                    and (not dropped or any(f"your {count(query)} to it were not used" in m for m in seen_messages))
                    and replaced["old_clip_http"] == 200 and replaced["new_clip_http"] == 404)
                log(f"round {round_index}: the run said so after {run_said_after_s} s: {run_said}; the page "
                    f"{'settled' if handled else 'did NOT settle'} on the run's queries after "
                    f"{replaced['settled_after_s']} s ({'answers dropped' if dropped else 'answers kept'}): message "
                    f"{replaced['message']!r}, progress {replaced['progress']!r}, clips' digest "
                    f"{replaced['page_digest_after']}, the run's queries' clip HTTP {replaced['old_clip_http']}, "
                    f"the other queries' clip HTTP {replaced['new_clip_http']}")
                summary["replacement"] = replaced
                if dropped:  # the labels are the answers that follow
                    given[round_index], shown[round_index] = [], []
                force_reload = True
            elif second is None and summary["sustained_second_tab"] is None and time.time() >= tab_at and query >= 1:
                # a second tab that stays open while the first answers
                k = query
                driver.switch_to.new_window("tab")
                handle = driver.current_window_handle
                driver.get(address)
                expected = (f"{OTHER_TAB} {round_index} too (its {count(k)} so far: "
                            f"{' '.join(SYMBOLS[a] for a in given[round_index])})")
                saw = wait_until(lambda: any(n.startswith(expected) for n in notices()), 15)
                second_notices = notices()
                driver.switch_to.window(main_tab)
                mine = f"{OTHER_TAB} {round_index} too (no answers yet)"
                first_saw = wait_until(lambda: any(n.startswith(mine) for n in notices()), 15)
                second = {"handle": handle, "opened": time.time(), "round": round_index,
                          "second_saw_first_at_once": saw, "second_notices_at_open": second_notices,
                          "first_saw_second_at_once": first_saw, "samples": 0, "first_saw_second": 0}
                log(f"round {round_index}: second tab opened and left open; it shows the first's {count(k)}: {saw} "
                    f"({second_notices}); the first shows it: {first_saw}")
            elif second is not None and time.time() >= second["opened"] + args.second_tab_seconds:
                driver.switch_to.window(second["handle"])
                expected = (f"{OTHER_TAB} {round_index} too (" +
                            (f"its {count(query)} so far: {' '.join(SYMBOLS[a] for a in given[round_index])})"
                             if query else "no answers yet)"))
                second["second_saw_first_at_close"] = wait_until(
                    lambda: any(n.startswith(expected) for n in notices()), 15)
                second["second_notices_at_close"], second["second_progress_at_close"] = notices(), text()
                driver.close()
                driver.switch_to.window(main_tab)
                second["first_cleared"] = wait_until(lambda: not any(OTHER_TAB in n for n in notices()), 15)
                second["open_s"] = round(time.time() - second.pop("opened"), 1)
                second.pop("handle")
                second["ok"] = bool(second["second_saw_first_at_once"] and second["first_saw_second_at_once"] and
                                    second["second_saw_first_at_close"] and second["first_cleared"] and
                                    second["first_saw_second"] > 0)
                log(f"round {round_index}: second tab closed after {second['open_s']} s, from round "
                    f"{second['round']}: it showed the first's answers at close: {second['second_saw_first_at_close']} "
                    f"({second['second_notices_at_close']}); the first showed it in {second['first_saw_second']} of "
                    f"{second['samples']} looks; the first's notice gone after the close: {second['first_cleared']}")
                summary["sustained_second_tab"], second = second, None
            elif second is None and time.time() >= next_tab:  # a second tab for a moment: it sees the first at once
                next_tab += 180
                summary["second_tabs"] += 1
                driver.switch_to.new_window("tab")
                driver.get(address)
                saw = wait_until(lambda: any(f"{OTHER_TAB} {round_index} too" in n for n in notices()), 10)
                summary["second_tab_saw_first"] += saw
                driver.close()
                driver.switch_to.window(main_tab)
                log(f"round {round_index}: a second tab for a moment: it showed the first: {saw}")
            elif query > 0 and (roll < 0.03 or force_reload and query >= 2):  # a reload mid-round: answers come back
                forced, force_reload = force_reload and query >= 2, force_reload and query < 2
                summary["reloads"] += 1
                collect_clips()
                driver.refresh()
                back = wait_until(lambda: taking(round_index, query) and "are back" in text("message")
                                  if query > 1 else taking(round_index, query) and "is back" in text("message"), 30)
                summary["reloads_restored"] += back
                log(f"round {round_index}: reload{' (forced, after the replacement)' if forced else ''} at query "
                    f"{query + 1}: {text('message')!r}, back at {text()!r}: {back}")
            elif roll < 0.05:  # Ctrl+= zooms, and answers nothing
                summary["ctrl_equals"] += 1
                ActionChains(driver).key_down(Keys.CONTROL).send_keys("=").key_up(Keys.CONTROL).perform()
                time.sleep(0.5)
                assert text() == progress, "Ctrl+= answered"
            else:  # an answer (S: the s of a keyboard with Caps Lock or Shift), or undo
                undo, key = roll < 0.10 and query > 0, rng.choice([*KEYS, "S"])
                if not undo:  # the clips on the page when the key is pressed: this round's, this query's
                    clips = clip_digests()
                    assert clips[0][:3] == (round_index, query, 0) and clips[1][:3] == (round_index, query, 1) and \
                        clips[0][3] == clips[1][3], f"{progress}: the page shows the clips {clips}"
                body().send_keys(Keys.BACKSPACE if undo else key)
                if undo:
                    summary["undos"] += 1
                    given[round_index].pop()
                    shown[round_index].pop()
                else:
                    summary["answers"] += 1
                    given.setdefault(round_index, []).append(KEYS.get(key, "skip"))
                    shown.setdefault(round_index, []).append(clips[0][3])
                deadline = time.time() + 30
                while text() == progress and time.time() < deadline:
                    time.sleep(0.05)  # the page moves to the next query (the previous one, after undo)
                assert text() != progress, f"{progress}: the page did not take the key"
    except Exception as e:
        log(f"session.py: the session failed: {type(e).__name__}: {e}\n{traceback.format_exc()}")
        summary["failure"] = f"{type(e).__name__}: {e}"
    finally:
        try:
            collect_clips()
        except Exception:  # noqa: BLE001  (the browser has gone)
            pass
        try:
            summary["rss_final_mb"] = sample_memory()
            app_peaks.append(rss_mb(app.pid, "VmHWM"))
        except (OSError, StopIteration):  # the app has gone
            summary["rss_final_mb"] = None
        driver.quit()
        app.terminate()
        run.terminate()
        app.wait(timeout=30)
        run.wait(timeout=60)
    written, digests, named, sha256 = {}, {}, {}, {}
    labels = os.path.join(run_dir, "labels")
    for name in os.listdir(labels) if os.path.isdir(labels) else []:
        if name.endswith(".json"):
            with open(os.path.join(labels, name), "rb") as f:
                content = f.read()
            r, labels_file = int(name[:-5]), json.loads(content)
            written[r], named[r] = labels_file["answers"], labels_file["queries"]
            sha256[r] = hashlib.sha256(content).hexdigest()
            digests[r] = file_digest(os.path.join(run_dir, "queries", name[:-5] + ".npz"))
    logged = {}  # round -> (answers, queries digest, labels file's SHA-256) of the run's query log
    for r in written:
        path = os.path.join(run_dir, "preferences", f"{r}.npz")
        if os.path.exists(path):
            with np.load(path) as data:
                logged[r] = ([logged_answer(x) for x in data["labels"]],
                             digest_of(data["physics"], str(data["env_id"])),
                             str(data["label_sha256"][0]) if len(data["label_sha256"]) else "")
    replacement = summary["replacement"] or {}
    summary.update(
        run_exit_code=run.returncode, rounds_written=len(written), answers_written=sum(map(len, written.values())),
        labels_match=all(written[r] == given.get(r) for r in written),
        labels_of_clips_shown=all(shown.get(r) == [digests[r]] * len(written[r]) for r in written),
        labels_name_their_queries=all(named[r] == digests[r] for r in written),
        rounds_logged=len(logged),
        query_log_equals_labels=all(logged[r] == (written[r], named[r], sha256[r]) for r in logged),
        unlogged_rounds=sorted(set(written) - set(logged)),
        replaced_round_labels=written.get(replacement.get("round")),
        replaced_round_labels_are_the_runs=replacement.get("round") in written and
        written[replacement["round"]] == given[replacement["round"]] and
        digests[replacement["round"]] == named[replacement["round"]] == replacement["old_digest"],
        app_peaks_mb=[round(p, 1) for p in app_peaks],
        rss_below_bound=max(app_peaks + [summary["rss_peak_mb"]]) < args.rss_bound_mb,
        clips_fetched=len(clip_bytes), clips_fetched_mb=round(sum(clip_bytes.values()) / 2 ** 20, 1),
        tracebacks=[name for name in ("app.log", "run.log")
                    if "Traceback" in open(os.path.join(args.out, name)).read()],
        notices=sorted(summary["notices"]), messages=sorted(summary["messages"]),
        minutes_run=round((time.time() - began) / 60, 2))
    summary["checks"] = {
        "labels files equal the answers given": summary["labels_match"],
        "each answer given with its round's clips": summary["labels_of_clips_shown"],
        "at least 20 rounds": summary["rounds_written"] >= 20,
        "each labels file names the digest of its round's queries": summary["labels_name_their_queries"],
        "the query log holds the same answers, digests and labels files' SHA-256":
            summary["query_log_equals_labels"] and summary["rounds_logged"] >= 20
            and len(summary["unlogged_rounds"]) <= 1,  # the last round may still be training at the end
        "queries replaced once and handled": bool(replacement.get("handled")),
        "the replaced round's labels answer the run's queries": summary["replaced_round_labels_are_the_runs"],
        "the app restarted mid-fetch, the page recovering by itself": bool((summary["restart"] or {}).get("ok")),
        "a second tab open a while, each tab showing the other": bool((summary["sustained_second_tab"] or {}).get("ok")),
        "every momentary second tab showed the first": summary["second_tab_saw_first"] == summary["second_tabs"],
        "reloads, each bringing the answers back": 0 < summary["reloads"] == summary["reloads_restored"],
        f"each app's peak RSS below {args.rss_bound_mb:g} MB": summary["rss_below_bound"],
        "no traceback": not summary["tracebacks"],
        "no failure": "failure" not in summary}
    summary["ok"] = all(summary["checks"].values())
    log(f"checks: {json.dumps(summary['checks'], indent=1)}")
    with open(os.path.join(args.out, "summary.json"), "w") as f:
        json.dump(summary, f, indent=1)
    print(json.dumps(summary, indent=1))
    return 0 if summary["ok"] else 1


if __name__ == "__main__":
    sys.exit(main())
