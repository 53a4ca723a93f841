# docs and usage can be found in README.md, in the section "Labelling by hand"
"""A local web page for labelling the queries of a run started with `--teacher external`, by hand.

    python label_app.py runs/RUN_NAME            # then open http://localhost:8000

It shows the pending round's queries one at a time: the two segments as clips, side by side, rendered with MuJoCo's
offscreen renderer from the physics states stored with each query. The answer is left, right, equal or skip, by
mouse or keyboard (arrow keys, `=`/space, `s`); when the round is done the page writes `labels/{round}.json`, which
the run is waiting for, and waits for the next round. Standard library only (plus the project's imageio and
dm_control): the training scripts need no web dependency.

It binds to localhost. On a remote machine, forward the port: `ssh -L 8000:localhost:8000 host`, then open
http://localhost:8000 on your own. Without a display MuJoCo needs `MUJOCO_GL=egl` (GPU or Mesa) or `MUJOCO_GL=osmesa`
(software); the app sets `egl` when neither `MUJOCO_GL` nor `DISPLAY` is set.
"""
import glob
import io
import json
import os
import re
import sys
import threading
from dataclasses import dataclass
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import numpy as np
import tyro

if "MUJOCO_GL" not in os.environ and "DISPLAY" not in os.environ:
    os.environ["MUJOCO_GL"] = "egl"  # before dm_control is imported (by ene.render_states)

import ene  # noqa: E402

ANSWERS = {"left": 0, "right": 1, "equal": 0.5, "skip": "skip"}  # label = P[the second (right) segment is preferred]


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


def pending_round(run_dir: str):
    """The first round whose queries have no labels file yet, or None."""
    rounds = sorted(int(m.group(1)) for path in glob.glob(os.path.join(run_dir, "queries", "*.npz"))
                    if (m := re.fullmatch(r"(\d+)\.npz", os.path.basename(path))))
    return next((r for r in rounds if not os.path.exists(os.path.join(run_dir, "labels", f"{r}.json"))), None)


class Clips:
    """GIF clips of the segments of a round, rendered once and kept."""

    def __init__(self, run_dir: str, fps: int):
        self.run_dir, self.fps, self.cache, self.lock = run_dir, fps, {}, threading.Lock()

    def queries(self, round_index: int) -> dict:
        with np.load(os.path.join(self.run_dir, "queries", f"{round_index}.npz")) as data:
            return {"env_id": str(data["env_id"]), "physics": data["physics"]}

    def gif(self, round_index: int, query: int, side: int) -> bytes:
        import imageio.v3 as iio

        key = (round_index, query, side)
        with self.lock:  # one MuJoCo renderer at a time
            if key not in self.cache:
                data = self.queries(round_index)
                frames = ene.render_states(data["env_id"], data["physics"][query, side])
                buffer = io.BytesIO()
                iio.imwrite(buffer, frames, extension=".gif", duration=1000 / self.fps, loop=0)
                self.cache[key] = buffer.getvalue()
            return self.cache[key]


def write_labels(run_dir: str, round_index: int, answers: list):
    """Check the answers against the round's queries and write `labels/{round}.json` atomically."""
    with np.load(os.path.join(run_dir, "queries", f"{round_index}.npz")) as data:
        n = len(data["physics"])
    if not isinstance(answers, list) or len(answers) != n or any(a not in (0, 1, 0.5, "skip") for a in answers):
        raise ValueError(f'expected {n} answers, each 0, 1, 0.5 or "skip"')
    path = os.path.join(run_dir, "labels", f"{round_index}.json")
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(f"{path}.tmp", "w") as f:
        json.dump(answers, f)
    os.replace(f"{path}.tmp", path)


PAGE = """<!doctype html>
<html><head><meta charset="utf-8"><title>R2N: label preferences</title>
<style>
 body { font-family: sans-serif; margin: 2em; background: #fafafa; }
 .clips { display: flex; gap: 2em; } .clip { text-align: center; }
 img { width: 320px; height: 240px; border: 3px solid #ccc; background: #000; }
 button { font-size: 1.1em; margin: 0.5em 0.3em; padding: 0.4em 1em; }
 #progress { font-weight: bold; }
</style></head>
<body>
<h2>Which segment is better?</h2>
<p id="progress">loading...</p>
<div class="clips" id="clips" hidden>
 <div class="clip"><img id="left"><div>left (first segment)</div></div>
 <div class="clip"><img id="right"><div>right (second segment)</div></div>
</div>
<div id="buttons" hidden>
 <button id="answer-left">&larr; left is better</button>
 <button id="answer-equal">= equal</button>
 <button id="answer-right">right is better &rarr;</button>
 <button id="answer-skip">s: skip</button>
</div>
<script>
let round = null, n = 0, i = 0, answers = [];
const progress = document.getElementById("progress");
function show() {
  progress.textContent = `round ${round}: query ${i + 1} of ${n}`;
  document.getElementById("left").src = `/clip/${round}/${i}/0.gif`;
  document.getElementById("right").src = `/clip/${round}/${i}/1.gif`;
  document.getElementById("clips").hidden = false; document.getElementById("buttons").hidden = false;
}
async function poll() {
  const state = await (await fetch("/api/state")).json();
  if (state.round === null) {
    progress.textContent = "no round is waiting for labels; this page checks every 2 s";
    document.getElementById("clips").hidden = true; document.getElementById("buttons").hidden = true;
    setTimeout(poll, 2000); return;
  }
  round = state.round; n = state.n; i = 0; answers = []; show();
}
async function answer(choice) {
  if (round === null) return;
  answers.push({left: 0, right: 1, equal: 0.5, skip: "skip"}[choice]);
  if (++i < n) { show(); return; }
  const done = round; round = null;
  const reply = await fetch(`/api/labels/${done}`, {method: "POST", body: JSON.stringify(answers)});
  progress.textContent = reply.ok ? `round ${done} saved` : `saving failed: ${await reply.text()}`;
  setTimeout(poll, 1000);
}
for (const choice of ["left", "equal", "right", "skip"])
  document.getElementById(`answer-${choice}`).onclick = () => answer(choice);
document.addEventListener("keydown", (e) => {
  const choice = {ArrowLeft: "left", ArrowRight: "right", "=": "equal", " ": "equal", s: "skip"}[e.key];
  if (choice) { e.preventDefault(); answer(choice); }
});
poll();
</script></body></html>
"""


def make_handler(run_dir: str, clips: Clips):
    class Handler(BaseHTTPRequestHandler):
        def reply(self, code: int, body: bytes, content_type: str):
            self.send_response(code)
            self.send_header("Content-Type", content_type)
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

        def do_GET(self):
            if self.path == "/":
                return self.reply(200, PAGE.encode(), "text/html; charset=utf-8")
            if self.path == "/api/state":
                round_index = pending_round(run_dir)
                n = None if round_index is None else len(clips.queries(round_index)["physics"])
                return self.reply(200, json.dumps({"round": round_index, "n": n}).encode(), "application/json")
            match = re.fullmatch(r"/clip/(\d+)/(\d+)/([01])\.gif", self.path)
            if match:
                return self.reply(200, clips.gif(*map(int, match.groups())), "image/gif")
            self.reply(404, b"not found", "text/plain")

        def do_POST(self):
            match = re.fullmatch(r"/api/labels/(\d+)", self.path)
            if not match:
                return self.reply(404, b"not found", "text/plain")
            try:
                answers = json.loads(self.rfile.read(int(self.headers["Content-Length"])))
                write_labels(run_dir, int(match.group(1)), answers)
            except (ValueError, OSError) as e:
                return self.reply(400, str(e).encode(), "text/plain")
            self.reply(200, b"saved", "text/plain")

        def log_message(self, *args):  # no line per request
            pass

    return Handler


def main(args: Args) -> int:
    if not os.path.isdir(args.run_dir):
        print(f"label_app: error: run_dir: no such folder: {args.run_dir}", file=sys.stderr)
        return 1
    server = ThreadingHTTPServer((args.host, args.port), make_handler(args.run_dir, Clips(args.run_dir, args.fps)))
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
