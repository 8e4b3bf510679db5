#!/usr/bin/env python
"""Screenshots of world edits and map interventions in the dashboard (docs/compare.md), in headless Chromium through
Playwright:

- dashboard_world_edit.png: an environment flown with a landmark moved and another removed ("World edits"), the
  result panel saying what was changed;
- dashboard_painted_goal.png: a failure forked at --fork-step with its goal map painted (the blob where it went
  erased, a peak put on the true goal), flown beside the original in the comparison view.

    python scripts/intervention_screenshots.py --preset paper --checkpoint checkpoints/gsmn --out docs
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))
os.environ.setdefault("MUJOCO_GL", "egl")

from compare_screenshots import choose, open_page, open_tab, reset_camera, scrub_to, wait  # noqa: E402

from app.browser import field  # noqa: E402


def run_and_wait(page, runner, button: str):
    """Press `button` and wait for the new episode it makes to end; that episode."""
    before = {e.id for e in runner.episodes.all()}
    page.get_by_role("button", name=button, exact=True).click()
    wait(lambda: {e.id for e in runner.episodes.all()} - before)
    episode = runner.episodes.get(max({e.id for e in runner.episodes.all()} - before))
    wait(lambda: not episode.live)
    return episode


def show_environment(page, env_id: int) -> None:
    field(page, "Environment id").fill(str(env_id))
    field(page, "Environment id").press("Enter")
    page.get_by_role("button", name="Show", exact=True).click()
    page.wait_for_timeout(1500)


def goal_peaks(dashboard, episode, t: int, most: int = 4) -> list[tuple[float, float]]:
    """Where the model's goal map peaked from step t to the end (every 5th step; at most `most` places, 3 m apart):
    the blobs a painter erases."""
    from gsmn.attribution import goal_peak
    from gsmn.model.grid import cell_centre

    heads = dashboard.runner.models[episode.checkpoint].heads
    field_size, places = episode.task.world.field_size, []
    for step in episode.steps[t::5]:
        row, col, _ = goal_peak(step.maps.maps["goal_map_w"].astype("float32"), heads)
        xy = cell_centre(row, col, field_size, step.maps.maps["goal_map_w"].shape[-1])
        if all((xy[0] - x) ** 2 + (xy[1] - y) ** 2 > 9 for x, y in places):
            places.append(xy)
    return places[:most]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", default="tiny", choices=("tiny", "paper"))
    ap.add_argument("--checkpoint", default="checkpoints/gsmn")
    ap.add_argument("--edit-env-id", type=int, default=70)
    ap.add_argument("--edits", default="remove box; move pumpkin to 16.8 14.5")
    ap.add_argument("--fork-env-id", type=int, default=72, help="an environment the model fails")
    ap.add_argument("--fork-step", type=int, default=10)
    ap.add_argument("--out", default="docs")
    ap.add_argument("--chromium", default=os.environ.get("GSMN_CHROMIUM") or shutil.which("chromium"))
    a = ap.parse_args()

    from playwright.sync_api import sync_playwright

    from app.server import Dashboard
    from gsmn.config import preset

    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    dashboard = Dashboard(preset(a.preset), checkpoint=a.checkpoint, port=0, api_port=0, env_id=a.edit_env_id,
                          data_dir=tempfile.mkdtemp(prefix="gsmn-shots-"))
    runner = dashboard.runner
    try:
        with sync_playwright() as p:
            browser, page = open_page(p, dashboard, a.chromium)
            choose(page, "Policy", dashboard.viewer.policy.options[0])

            # 1. an edited world, flown by the model
            show_environment(page, a.edit_env_id)
            field(page, "World edits").fill(a.edits)
            field(page, "World edits").press("Enter")
            edited = run_and_wait(page, runner, "Run")
            print(f"edited world: episode {edited.id}, {edited.world_edits}, {edited.result}", flush=True)
            field(page, "World edits").fill("")
            field(page, "World edits").press("Enter")
            scrub_to(page, len(edited.steps) - 1)
            open_tab(page, "Camera and maps")
            reset_camera(dashboard, edited.steps[-1].position[:2])
            page.wait_for_timeout(1500)
            page.screenshot(path=str(out / "dashboard_world_edit.png"))

            # 2. a failure forked with its goal map painted: the blob where it went erased, a peak on the true goal
            show_environment(page, a.fork_env_id)
            original = run_and_wait(page, runner, "Run")
            goal = original.task.instruction
            print(f"original: episode {original.id}, {original.result}", flush=True)
            t = min(a.fork_step, len(original.steps) - 1)
            paint = "; ".join([*(f"erase {x:.1f} {y:.1f} 3" for x, y in goal_peaks(dashboard, original, t)),
                               f"peak {goal.goal_x:.1f} {goal.goal_y:.1f}"])
            print(f"paint: {paint}", flush=True)
            scrub_to(page, t)
            page.get_by_text("Compare and fork").first.click()
            choose(page, "Fork maps", "Painted goal map")
            field(page, "Paint").fill(paint)
            field(page, "Paint").press("Enter")
            fork = run_and_wait(page, runner, "Fork here")
            print(f"painted fork: episode {fork.id}, {fork.intervention}, {fork.result}", flush=True)
            scrub_to(page, len(fork.steps) - 1)
            open_tab(page, "Comparison")
            reset_camera(dashboard, fork.steps[t].position[:2])
            page.wait_for_timeout(2000)
            page.screenshot(path=str(out / "dashboard_painted_goal.png"))
            browser.close()
    finally:
        dashboard.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
