"""Where the labelling app's memory goes (a side check of the session, issue 43): start label_app.py on a session's
run folder, fetch N distinct clips from it three requests at a time (as a page's clip, prefetch and poll), and print
the app's RSS every 10 s. Run it with glibc's default malloc arenas and with MALLOC_ARENA_MAX=2 to see how much of
the RSS is the allocator's per-thread arenas (the app serves each request in a new thread):

    python results/label-session/memory_probe.py /tmp/label-session/runs/session 60 default
    python results/label-session/memory_probe.py /tmp/label-session/runs/session 60 2
"""
import glob
import hashlib
import os
import subprocess
import sys
import threading
import time
import urllib.request

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, os.path.join(ROOT, "tests"))
from test_labelling import free_port  # noqa: E402


def main():
    run_dir, n, arena = sys.argv[1], int(sys.argv[2]), sys.argv[3]
    env = dict(os.environ, OMP_NUM_THREADS="1")
    if arena != "default":
        env["MALLOC_ARENA_MAX"] = arena
    port = free_port()
    app = subprocess.Popen([sys.executable, os.path.join(ROOT, "label_app.py"), run_dir, "--port", str(port)],
                           env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)

    def rss() -> int:
        with open(f"/proc/{app.pid}/status") as f:
            return int(next(line for line in f if line.startswith("VmRSS")).split()[1]) // 1024

    base = f"http://127.0.0.1:{port}"
    for _ in range(600):
        try:
            urllib.request.urlopen(base + "/api/state").read()
            break
        except OSError:
            time.sleep(0.2)
    print("baseline rss", rss(), flush=True)
    jobs = []
    rounds = sorted(int(os.path.basename(p)[:-4]) for p in glob.glob(f"{run_dir}/queries/*.npz"))
    for r in rounds:
        with np.load(f"{run_dir}/queries/{r}.npz") as data:
            physics, env_id = data["physics"], str(data["env_id"])
        digest = hashlib.sha256(f"{env_id} {physics.dtype} {physics.shape}".encode() + physics.tobytes()).hexdigest()
        jobs += [f"{base}/clip/{r}/{q}/{s}.gif?queries={digest[:16]}" for q in range(len(physics)) for s in (0, 1)]
    jobs, lock = jobs[:n], threading.Lock()

    def worker():
        while True:
            with lock:
                if not jobs:
                    return
                url = jobs.pop(0)
            urllib.request.urlopen(url, timeout=120).read()
            urllib.request.urlopen(base + "/api/state").read()

    threads = [threading.Thread(target=worker) for _ in range(3)]
    for thread in threads:
        thread.start()
    started = time.time()
    while any(thread.is_alive() for thread in threads):
        time.sleep(10)
        print(f"{time.time() - started:5.0f} s: {len(jobs)} clips left, rss {rss()}", flush=True)
    print(f"MALLOC_ARENA_MAX {arena}: final rss {rss()}", flush=True)
    app.terminate()
    app.wait()


if __name__ == "__main__":
    main()
