"""A soak of a live `gsmn serve`: API clients fly, read and cancel episodes and browser tabs stay open on the page for
a while, and the server's resident memory, threads and open files are sampled; prints a table and whether memory
levelled off (its growth over the last third of the soak against the first third).

    python scripts/soak.py --minutes 60 --clients 4 --tabs 2 --json runs/soak.json

The server flies the tiny preset on an untrained checkpoint by default (`--preset paper --checkpoint
checkpoints/gsmn` for the real thing), keeps episodes in a throw-away data folder with a 50 MB retention limit, and is
stopped at the end. Figures: docs/dashboard.md, "Memory over a soak".
"""

from __future__ import annotations

import argparse
import json
import os
import random
import re
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import httpx

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def proc_figures(pid: int) -> dict:
    """Resident memory (MB), threads and open file descriptors of a process, from /proc."""
    status = Path(f"/proc/{pid}/status").read_text()
    rss = int(re.search(r"VmRSS:\s+(\d+)", status).group(1)) / 1024
    threads = int(re.search(r"Threads:\s+(\d+)", status).group(1))
    return {"rss_mb": round(rss, 1), "threads": threads, "fds": len(os.listdir(f"/proc/{pid}/fd"))}


def client_loop(api: str, stop: threading.Event, counts: dict, seed: int) -> None:
    rng = random.Random(seed)
    with httpx.Client(base_url=api, timeout=60) as c:
        while not stop.is_set():
            try:
                env_id = rng.choice([70 + k + 100 * j for k in range(15) for j in range(5)])
                policy = rng.choice(["model", "model", "expert", "mirror"])
                r = c.post("/api/episodes", json={"env_id": env_id, "policy": policy})
                counts["requests"] += 1
                if r.status_code != 201:
                    counts["refused"] += 1
                    time.sleep(1)
                    continue
                eid = r.json()["id"]
                if rng.random() < 0.15:
                    c.delete(f"/api/episodes/{eid}")
                    counts["requests"] += 1
                while not stop.is_set():
                    e = c.get(f"/api/episodes/{eid}").json()
                    counts["requests"] += 1
                    if e["status"] not in ("queued", "running", "paused"):
                        break
                    time.sleep(0.5)
                steps = c.get(f"/api/episodes/{eid}/steps").json().get("steps", [])
                counts["requests"] += 1
                for s in rng.sample(steps, min(3, len(steps))):
                    c.get(f"/api/episodes/{eid}/steps/{s['step']}/camera.jpg")
                    c.get(f"/api/episodes/{eid}/steps/{s['step']}/maps/{rng.choice(['semantic', 'goal'])}.png")
                    counts["requests"] += 2
                c.get("/api/episodes", params={"limit": 20})
                c.get("/api/storage")
                counts["requests"] += 2
                if counts["requests"] % 7 == 0:
                    c.get(f"/api/episodes/{eid}/export", params={"format": "html"})
                    counts["requests"] += 1
            except httpx.HTTPError:
                counts["errors"] += 1
                time.sleep(1)


def tabs_loop(page_url: str, tabs: int, stop: threading.Event) -> None:
    from playwright.sync_api import sync_playwright

    from app.browser import CHROMIUM, CHROMIUM_ARGS

    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        pages = [browser.new_page(viewport={"width": 1280, "height": 800}) for _ in range(tabs)]
        for page in pages:
            page.goto(page_url)
        while not stop.wait(120):  # a reload now and then, as people come and go
            for page in pages:
                page.reload()
        browser.close()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--minutes", type=float, default=60)
    ap.add_argument("--clients", type=int, default=4)
    ap.add_argument("--tabs", type=int, default=2)
    ap.add_argument("--every", type=float, default=30, help="seconds between samples")
    ap.add_argument("--preset", default="tiny")
    ap.add_argument("--checkpoint", default=None, help="default: an untrained checkpoint made for the soak")
    ap.add_argument("--json", default=None, help="write the samples here")
    args = ap.parse_args()

    folder = Path(tempfile.mkdtemp(prefix="gsmn-soak-"))
    checkpoint = args.checkpoint
    if checkpoint is None:
        from app.live.fixtures import make_untrained_checkpoint

        checkpoint = str(make_untrained_checkpoint(folder / "checkpoint", args.preset))
    server = subprocess.Popen(
        [sys.executable, "-m", "gsmn.cli", "serve", "--preset", args.preset, "--checkpoint", checkpoint,
         "--port", "0", "--api-port", "0", "--data-dir", str(folder / "data"), "--keep-mb", "50"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=ROOT,
        env={**os.environ, "PYTHONUNBUFFERED": "1"})
    lines: list[str] = []
    threading.Thread(target=lambda: lines.extend(iter(server.stdout.readline, "")), daemon=True).start()
    deadline = time.monotonic() + 180
    while time.monotonic() < deadline and not re.search(r"API: (http://\S+)/api", "".join(lines)):
        time.sleep(0.2)
    api = re.search(r"API: (http://127\.0\.0\.1:\d+)/api", "".join(lines)).group(1)
    page = re.search(r"gsmn dashboard: (http://127\.0\.0\.1:\d+\S*)", "".join(lines)).group(1)
    stop = threading.Event()
    counts = {"requests": 0, "refused": 0, "errors": 0}
    workers = [threading.Thread(target=client_loop, args=(api, stop, counts, k), daemon=True)
               for k in range(args.clients)]
    if args.tabs:
        workers.append(threading.Thread(target=tabs_loop, args=(page, args.tabs, stop), daemon=True))
    for w in workers:
        w.start()
    samples = []
    start = time.monotonic()
    print(f"{'minute':>6} {'RSS MB':>8} {'threads':>8} {'fds':>5} {'requests':>9}")
    try:
        while time.monotonic() - start < args.minutes * 60:
            sample = {"minute": round((time.monotonic() - start) / 60, 2), **proc_figures(server.pid),
                      "requests": counts["requests"]}
            samples.append(sample)
            print(f"{sample['minute']:6.1f} {sample['rss_mb']:8.1f} {sample['threads']:8d} {sample['fds']:5d} "
                  f"{sample['requests']:9d}", flush=True)
            time.sleep(args.every)
    finally:
        stop.set()
        for w in workers:
            w.join(30)
        server.send_signal(signal.SIGINT)
        try:
            server.wait(30)
        except subprocess.TimeoutExpired:
            server.kill()
    third = max(1, (len(samples) - 1) // 3)  # samples apart: the first third's span, and the last third's
    first = samples[min(third, len(samples) - 1)]["rss_mb"] - samples[0]["rss_mb"]
    last = samples[-1]["rss_mb"] - samples[max(0, len(samples) - 1 - third)]["rss_mb"]
    print(f"\n{counts['requests']} requests, {counts['refused']} refused, {counts['errors']} transport errors; "
          f"RSS {samples[0]['rss_mb']:.0f} -> {samples[-1]['rss_mb']:.0f} MB (peak "
          f"{max(s['rss_mb'] for s in samples):.0f}); growth over the first third {first:+.0f} MB, over the last "
          f"third {last:+.0f} MB; threads {samples[0]['threads']} -> {samples[-1]['threads']}")
    if args.json:
        Path(args.json).write_text(json.dumps({"samples": samples, "counts": counts, "args": vars(args)}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
