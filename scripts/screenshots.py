#!/usr/bin/env python
"""Every screenshot of the page in the docs, taken again from the page as it is now, so none shows an old layout.

    .venv/bin/python scripts/screenshots.py                 # all of them, with the shipped GSMN (about 20 minutes)
    .venv/bin/python scripts/screenshots.py --only kept     # one group

Each group is one script that serves the dashboard on a throw-away data folder, drives the page in headless
Chromium and writes its pictures:

| group | script | pictures |
|---|---|---|
| page | scripts/page_screenshots.py | docs/img/page_1500x1000.png, docs/img/page_typing_1280x800.png |
| live | scripts/bench_dashboard.py --screenshots docs | docs/dashboard_live.png, docs/dashboard_counterfactual.png |
| compare | scripts/compare_screenshots.py | docs/dashboard_compare.png, _fork, _truth, _truth_plot |
| jobs | scripts/jobs_screenshots.py | docs/dashboard_failures.png, dashboard_finetune.png, dashboard_before_after.png |
| kept | scripts/kept_screenshots.py | docs/dashboard_episodes.png, docs/dashboard_presenter.png |
| analysis | scripts/analysis_screenshots.py | docs/dashboard_analysis.png, docs/dashboard_analysis_confusion.png |
| interventions | scripts/intervention_screenshots.py | docs/dashboard_world_edit.png, docs/dashboard_painted_goal.png |

Not taken here: docs/dashboard_failure_regions.png (`scripts/jobs_screenshots.py --regions EVAL.json --record DIR`,
from a recorded evaluation of 500 test environments) and the figures of results (accuracy curves, maps,
finetune_before_after.png), which the commands in docs/training.md and docs/results.md draw.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def groups(checkpoint: str, preset: str) -> dict[str, list[str]]:
    scripts = ROOT / "scripts"
    return {
        "page": [str(scripts / "page_screenshots.py"), "--preset", preset, "--checkpoint", checkpoint,
                 "--out", str(ROOT / "docs" / "img")],
        "live": [str(scripts / "bench_dashboard.py"), "--preset", preset, "--checkpoint", checkpoint, "--env-id", "73",
                 "--runs", "1",
                 "--groundings", "3", "--screenshots", str(ROOT / "docs")],
        "compare": [str(scripts / "compare_screenshots.py"), "--preset", preset, "--checkpoint", checkpoint,
                    "--other", "expert", "--out", str(ROOT / "docs")],
        "jobs": [str(scripts / "jobs_screenshots.py"), "--preset", preset, "--checkpoint", checkpoint,
                 "--out", str(ROOT / "docs")],
        "kept": [str(scripts / "kept_screenshots.py"), "--preset", preset, "--checkpoint", checkpoint,
                 "--out", str(ROOT / "docs")],
        "analysis": [str(scripts / "analysis_screenshots.py"), "--preset", preset, "--checkpoint", checkpoint,
                     "--out", str(ROOT / "docs")],
        "interventions": [str(scripts / "intervention_screenshots.py"), "--preset", preset, "--checkpoint", checkpoint,
                          "--out", str(ROOT / "docs")],
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--checkpoint", default=str(ROOT / "checkpoints" / "gsmn"))
    ap.add_argument("--preset", default="paper", choices=("paper", "tiny"))
    ap.add_argument("--only", nargs="+", default=None, help="groups to take (default: all)")
    args = ap.parse_args()
    todo = groups(args.checkpoint, args.preset)
    unknown = set(args.only or ()) - set(todo)
    if unknown:
        ap.error(f"unknown group(s) {', '.join(sorted(unknown))}; choose from {', '.join(todo)}")
    failed = []
    for name in args.only or todo:
        t0 = time.perf_counter()
        print(f"== {name}: {' '.join(Path(a).name if a.startswith(str(ROOT)) else a for a in todo[name])}",
              flush=True)
        if subprocess.run([sys.executable, *todo[name]], cwd=ROOT).returncode != 0:
            failed.append(name)
        print(f"== {name}: {'failed' if name in failed else 'done'} in {time.perf_counter() - t0:.0f} s", flush=True)
    if failed:
        print(f"failed: {', '.join(failed)}", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
