"""Fine-tune a checkpoint on its own failures with DAggerFM, through the dashboard's API, and report before/after.

    .venv/bin/python scripts/finetune_failures.py                       # checkpoints/gsmn, defaults below
    .venv/bin/python scripts/finetune_failures.py --preset tiny --episodes 6 --heldout-episodes 6 \\
        --checkpoint /tmp/ckpt --server-preset tiny --out /tmp/ft      # a few minutes, to try it

1. starts `gsmn serve` on a data folder (or uses a running one: --api URL);
2. evaluates the checkpoint on the first --episodes environments of --split (default dev) and on a held-out set
   (--heldout-split test), both with failure attribution;
3. fine-tunes it with DAggerFM on the failures of the first evaluation (--preset small: 10 iterations, N_D 8, M 40;
   the dataset starts from --expert-data when given, else from expert demonstrations of those failures);
4. reruns both evaluations with the fine-tuned checkpoint;
5. writes OUT/finetune_before_after.png and OUT/finetune_before_after.md (the numbers, the attribution counts and
   the commands), and with --results-md replaces the section between the markers
   <!-- finetune-failures:start --> and <!-- finetune-failures:end --> of that file (appended if missing).

The episodes the run trained on are the first evaluation's failures, so its before/after shows what fine-tuning
fixed on data it saw; the held-out rows show whether that carries over. Everything is recorded in the data folder
and shows in the dashboard (Failures and Fine-tune tabs) while it runs. Needs matplotlib (`pip install -e .[docs]`).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import httpx

from gsmn.analysis.compare import figure, rows_stages

ROOT = Path(__file__).resolve().parents[1]
START, END = "<!-- finetune-failures:start -->", "<!-- finetune-failures:end -->"


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--checkpoint", default=str(ROOT / "checkpoints" / "gsmn"), help="the checkpoint to fine-tune")
    p.add_argument("--split", default="dev", choices=("train", "test", "dev"), help="where its failures come from")
    p.add_argument("--episodes", type=int, default=100, help="environments of --split to evaluate")
    p.add_argument("--heldout-split", default="test", choices=("train", "test", "dev"))
    p.add_argument("--heldout-episodes", type=int, default=100, help="0: no held-out evaluation")
    p.add_argument("--preset", default="small", choices=("tiny", "small", "paper"), help="run preset")
    for name, kind in (("iterations", int), ("rollouts-per-iteration", int), ("dataset-size", int),
                       ("beta0", float), ("learning-rate", float)):
        p.add_argument(f"--{name}", type=kind, default=None, help="override the preset")
    p.add_argument("--expert-data", default=None, help="expert episode store the dataset starts from (e.g. "
                   "data/expert_train); default: expert demonstrations of the failures, collected")
    p.add_argument("--workers", type=int, default=2, help="evaluation worker processes")
    p.add_argument("--data-dir", default=str(ROOT / "data" / "dashboard"), help="the dashboard's data folder")
    p.add_argument("--server-preset", default="paper", choices=("paper", "tiny"), help="gsmn serve --preset")
    p.add_argument("--api", default=None, help="use this running dashboard API instead of starting one")
    p.add_argument("--out", default=str(ROOT / "docs"), help="folder for the figure and the markdown")
    p.add_argument("--results-md", default=None, help="also put the section into this file (e.g. docs/results.md)")
    return p.parse_args(argv)


class Server:
    """`gsmn serve` in a child process, stopped at the end."""

    def __init__(self, args: argparse.Namespace):
        self.lines: list[str] = []
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "gsmn.cli", "serve", "--checkpoint", args.checkpoint, "--data-dir", args.data_dir,
             "--preset", args.server_preset, "--port", "0", "--api-port", "0"], cwd=ROOT, text=True,
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, env={**os.environ, "PYTHONUNBUFFERED": "1"})
        threading.Thread(target=lambda: self.lines.extend(iter(self.proc.stdout.readline, "")), daemon=True).start()
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline and self.proc.poll() is None:
            text = "".join(self.lines)
            if m := re.search(r"API: (http://\S+?)/api", text):
                self.api = m.group(1)
                page = re.search(r"gsmn dashboard: (\S+)", text)
                print(f"dashboard: {page.group(1) if page else '?'} (watch it there)", flush=True)
                return
            time.sleep(0.2)
        raise SystemExit("gsmn serve did not start:\n" + "".join(self.lines))

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self.proc.kill()


def wait(client: httpx.Client, path: str, describe) -> dict:
    last = ""
    while True:
        body = client.get(path).json()
        line = describe(body)
        if line != last:
            print(f"  {line}", flush=True)
            last = line
        if body["status"] not in ("queued", "running"):
            if body["status"] != "finished":
                raise SystemExit(f"{path} {body['status']}: {body.get('error')}")
            return body
        time.sleep(5)


def evaluate(client: httpx.Client, what: str, **request) -> dict:
    r = client.post("/api/evaluations", json=request)
    if r.status_code != 201:
        raise SystemExit(f"evaluation refused: {r.json()['detail']}")
    e = r.json()
    print(f"evaluation {e['id']}: {what} ({e['label']})", flush=True)
    return wait(client, f"/api/evaluations/{e['id']}", lambda b: f"{b['status']}: {b['done']}/{b['total']} episodes")


def fmt(v, unit: str = " %") -> str:
    return "n/a" if v is None else f"{v:.1f}{unit}"


def markdown(args, run: dict, rows: list[tuple[str, dict, dict]], compares: list[dict], png: str) -> str:
    s = run["settings"]
    lines = [START, "## Fine-tuning on failures (DAggerFM from the dashboard)", "",
             f"`{Path(args.checkpoint).name}` fine-tuned with DAggerFM (run-{run['id']}, preset {s['preset']}: "
             f"{s['iterations']} iterations, N_D {s['rollouts_per_iteration']}, M {s['dataset_size']}, beta0 "
             f"{s['beta0']}, learning rate {s['learning_rate']}) on the {len(run['env_ids'] or [])} failures of "
             f"{args.episodes} {args.split} environments, then the same episodes flown again.", "",
             "| episodes | success before | after | landmark success before | after | mean distance before | after "
             "| fixed | broken |", "|---|---|---|---|---|---|---|---|---|"]
    for (name, before, after), c in zip(rows, compares, strict=True):
        b, a = before["summary"] or {}, after["summary"] or {}
        lines.append(f"| {name} | {fmt(b.get('success'))} | {fmt(a.get('success'))} | "
                     f"{fmt(b.get('landmark_success'))} | {fmt(a.get('landmark_success'))} | "
                     f"{fmt(b.get('mean_distance'), ' m')} | {fmt(a.get('mean_distance'), ' m')} | {c['fixed']} | "
                     f"{c['broken']} |")
    stages = rows_stages(rows)
    lines += ["", f"Failures by attribution ({' / '.join(k.replace('_', ' ') for k in stages)}), before -> after:",
              ""]
    for (name, before, after) in rows:
        def counts(e: dict) -> str:
            return " / ".join(str(e["stages"].get(k, 0)) for k in stages)

        lines.append(f"- {name}: {counts(before)} -> {counts(after)}")
    lines += ["", f"![before and after]({png})", "", "Reproduce: `.venv/bin/python scripts/finetune_failures.py "
              + " ".join(sys.argv[1:]) + "`", END]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    server = None if args.api else Server(args)
    api = args.api or server.api
    try:
        with httpx.Client(base_url=api, timeout=120) as client:
            ckpt = str(Path(args.checkpoint).resolve())
            source = evaluate(client, f"{args.checkpoint} on {args.split}", checkpoint=ckpt, split=args.split,
                              episodes=args.episodes, workers=args.workers)
            heldout = evaluate(client, f"held out, {args.heldout_split}", checkpoint=ckpt, split=args.heldout_split,
                               episodes=args.heldout_episodes, workers=args.workers) if args.heldout_episodes else None
            request = {"preset": args.preset, "checkpoint": ckpt, "evaluation_id": source["id"],
                       "expert_data": str(Path(args.expert_data).resolve()) if args.expert_data else None}
            for name in ("iterations", "rollouts_per_iteration", "dataset_size", "beta0", "learning_rate"):
                if getattr(args, name) is not None:
                    request[name] = getattr(args, name)
            r = client.post("/api/runs", json=request)
            if r.status_code != 201:
                raise SystemExit(f"run refused: {r.json()['detail']}")
            run = r.json()
            print(f"run {run['id']}: DAggerFM on {len(run['env_ids'])} failures", flush=True)
            run = wait(client, f"/api/runs/{run['id']}",
                       lambda b: f"{b['status']}: {(b['progress'] or {}).get('text', 'starting')}")
            print(f"checkpoint run-{run['id']}: {run['checkpoint']}", flush=True)
            rows, compares = [], []
            for name, before in ((f"{args.split} (trained on its failures)", source),
                                 (f"{args.heldout_split} (held out)", heldout)):
                if before is None:
                    continue
                after = evaluate(client, f"{name} with run-{run['id']}", run_id=run["id"], baseline_id=before["id"],
                                 workers=args.workers)
                rows.append((name, before, after))
                compares.append(client.get(f"/api/evaluations/{before['id']}/compare/{after['id']}").json())
    finally:
        if server is not None:
            server.stop()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    png = out / "finetune_before_after.png"
    figure(rows, png)
    results = Path(args.results_md) if args.results_md else None
    rel = os.path.relpath(png, results.parent if results else out)
    section = markdown(args, run, rows, compares, rel)
    (out / "finetune_before_after.md").write_text(section)
    (out / "finetune_before_after.json").write_text(json.dumps({"run": run, "compare": compares}, indent=1) + "\n")
    print(section)
    if results is not None:
        text = results.read_text() if results.is_file() else ""
        if START in text and END in text:
            text = text[:text.index(START)] + section.rstrip("\n") + text[text.index(END) + len(END):]
        else:
            text = text.rstrip("\n") + "\n\n" + section
        results.write_text(text)
        print(f"updated {results}")
    print(f"wrote {png}, {out / 'finetune_before_after.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
