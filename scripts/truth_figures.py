#!/usr/bin/env python
"""The agreement figures with the ground truth (gsmn.analysis.truth) at the end of a checkpoint's episodes, and the
step each stage went wrong for good, as the dashboard computes them (docs/compare.md, "Ground truth").

    python scripts/truth_figures.py --checkpoint checkpoints/gsmn --env-ids 70:81      # paper preset
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--checkpoint", default="checkpoints/gsmn")
    ap.add_argument("--preset", default="paper", choices=("tiny", "paper"))
    ap.add_argument("--env-ids", default="70:81", help="first:last+1")
    ap.add_argument("--policy", default="model", choices=("model", "mirror", "expert"))
    a = ap.parse_args()

    import torch

    from app.live.commands import StartEpisode
    from app.live.runner import Runner
    from app.render.truth import step_figures, went_wrong
    from gsmn.config import preset

    torch.set_num_threads(1)
    first, last = (int(x) for x in a.env_ids.split(":"))
    runner = Runner(preset(a.preset), checkpoint=a.checkpoint, require_checkpoint=True).start()
    heads = runner.models[runner.default_model].heads
    try:
        print("env  success  steps  perception  relevance_auc  goal_mass  went_wrong")
        for env_id in range(first, last):
            e = runner.call(StartEpisode(env_id, None, a.policy))
            while e.live:
                time.sleep(0.05)
            figures = step_figures(e, heads, runner.config.task.success_radius)
            f = figures[-1]

            def fmt(x):
                return "  n/a" if x is None else f"{x:5.2f}"

            print(f"{env_id:4d}  {e.result.success!s:7}  {len(e.steps):5d}  {fmt(f.perception):>10}  "
                  f"{fmt(f.relevance):>13}  {fmt(f.goal):>9}  {went_wrong(figures, heads)}", flush=True)
    finally:
        runner.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
