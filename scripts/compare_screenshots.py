#!/usr/bin/env python
"""Screenshots of the comparison view, a fork and the ground truth in the dashboard (docs/dashboard.md), in
headless Chromium through Playwright:

- dashboard_compare.png: two policies side by side (the loaded model and --other), scrubbed to the step they part;
- dashboard_fork.png: an episode forked at --fork-step with --fork-instruction (another landmark);
- dashboard_truth.png: the truth layers beside the maps and the agreement figures over the episode.

    python scripts/compare_screenshots.py --preset paper --checkpoint checkpoints/gsmn --other expert --out docs
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

from app.browser import CHROMIUM_ARGS, dismiss_notifications, field

os.environ.setdefault("MUJOCO_GL", "egl")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))





def choose(page, label: str, option: str) -> None:
    field(page, label).click()
    page.get_by_role("option", name=option, exact=True).click()


def wait(condition, timeout: float = 600.0) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            raise TimeoutError("timed out")
        time.sleep(0.1)


def scrub_to(page, step: int) -> None:
    slider = page.get_by_role("slider").first
    slider.focus()
    page.keyboard.press("Home")
    for _ in range(step):
        page.keyboard.press("ArrowRight")
    page.wait_for_timeout(1500)


def open_tab(page, name: str) -> None:
    page.get_by_role("tab", name=name).click()
    page.wait_for_timeout(800)


def reset_camera(dashboard, look_at: tuple[float, float] | None = None) -> None:
    """Every open page's 3D view back to the dashboard's opening one (a drag or a key may have moved it), or looking
    down at a point from the south-east."""
    from app.page.scene import DEFAULT_CAMERA

    target = DEFAULT_CAMERA["look_at"] if look_at is None else (look_at[0], look_at[1], 0.0)
    position = DEFAULT_CAMERA["position"] if look_at is None else (look_at[0] + 12.0, look_at[1] - 22.0, 22.0)
    for client in dashboard.viser.get_clients().values():
        client.camera.position = position
        client.camera.look_at = target
        client.camera.up_direction = DEFAULT_CAMERA["up"]


def open_page(playwright, dashboard, chromium: str):
    """A headless Chromium and a 1600x1000 page open on the dashboard, its scene arrived and its WebGL notice closed."""
    browser = playwright.chromium.launch(executable_path=chromium, args=CHROMIUM_ARGS)
    page = browser.new_page(viewport={"width": 1600, "height": 1000})
    page.set_default_timeout(120_000)
    page.goto(dashboard.urls.page)
    page.get_by_role("button", name="Run", exact=True).wait_for()
    page.wait_for_timeout(3000)
    dismiss_notifications(page)  # "software WebGL"
    return browser, page


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", default="tiny", choices=("tiny", "paper"))
    ap.add_argument("--checkpoint", default="checkpoints/gsmn")
    ap.add_argument("--other", default="expert", help="'expert' or a checkpoint name under checkpoints/")
    ap.add_argument("--env-id", type=int, default=72)
    ap.add_argument("--fork-env-id", type=int, default=73)
    ap.add_argument("--fork-step", type=int, default=30)
    ap.add_argument("--fork-instruction", default="go to the right side of the stone circle")
    ap.add_argument("--out", default="docs")
    ap.add_argument("--chromium", default=os.environ.get("GSMN_CHROMIUM") or shutil.which("chromium"))
    a = ap.parse_args()

    from playwright.sync_api import sync_playwright

    from app.server import Dashboard
    from gsmn.config import preset

    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    dashboard = Dashboard(preset(a.preset), checkpoint=a.checkpoint, port=0, api_port=0, env_id=a.env_id,
                          data_dir=tempfile.mkdtemp(prefix="gsmn-shots-"))
    runner = dashboard.runner
    try:
        with sync_playwright() as p:
            browser, page = open_page(p, dashboard, a.chromium)

            # 1. side by side
            page.get_by_text("Compare and fork").first.click()
            other = "Expert" if a.other == "expert" else None
            if other is None:
                other = next(f"Model: {c.label or c.name}" for c in runner.checkpoint_list() if c.name == a.other)
            options = dashboard.viewer.compare.other.options
            choose(page, "Compare with", next(o for o in options if o.lower().startswith(other.lower()[:6])))
            before = set(runner.pairs.store)
            page.get_by_role("button", name="Run both", exact=True).click()
            wait(lambda: set(runner.pairs.store) - before)
            c = runner.comparison(max(set(runner.pairs.store) - before))
            wait(lambda: not any(e.live for e in c.episodes))
            part = c.diverged_at()
            print(f"comparison {c.id}: episodes {[e.id for e in c.episodes]}, part at {part}, results "
                  f"{[(e.result.success, e.result.steps) for e in c.episodes]}", flush=True)
            scrub_to(page, part if part is not None else len(c.episodes[0].steps) // 2)
            open_tab(page, "Comparison")
            reset_camera(dashboard)
            page.wait_for_timeout(1500)
            page.screenshot(path=str(out / "dashboard_compare.png"))

            # 2. a fork at step t with another instruction
            field(page, "Environment id").fill(str(a.fork_env_id))
            field(page, "Environment id").press("Enter")
            page.get_by_role("button", name="Show", exact=True).click()
            page.wait_for_timeout(1500)
            choose(page, "Policy", dashboard.viewer.policy.options[0])
            field(page, "Instruction").fill("")
            before = {e.id for e in runner.episodes.all()}
            page.get_by_role("button", name="Run", exact=True).click()
            wait(lambda: {e.id for e in runner.episodes.all()} - before)
            original = runner.episodes.get(max({e.id for e in runner.episodes.all()} - before))
            wait(lambda: not original.live)
            t = min(a.fork_step, len(original.steps) - 1)
            scrub_to(page, t)
            field(page, "Fork instruction").fill(a.fork_instruction)
            field(page, "Fork instruction").press("Enter")
            before = {e.id for e in runner.episodes.all()}
            page.get_by_role("button", name="Fork here", exact=True).click()
            wait(lambda: {e.id for e in runner.episodes.all()} - before)
            fork = runner.episodes.get(max({e.id for e in runner.episodes.all()} - before))
            wait(lambda: not fork.live)
            print(f"fork {fork.id} of {original.id} at {t}: {fork.result}", flush=True)
            page.wait_for_timeout(2500)
            open_tab(page, "Comparison")
            reset_camera(dashboard, fork.steps[t].position[:2])
            page.wait_for_timeout(1500)
            page.screenshot(path=str(out / "dashboard_fork.png"))

            # 3. the ground truth beside the maps, and the figures over the episode
            page.get_by_text("Truth beside the maps").first.click()
            scrub_to(page, len(fork.steps) - 1)
            open_tab(page, "Camera and maps")
            page.locator(".gsmn-truth").first.scroll_into_view_if_needed()
            reset_camera(dashboard, fork.steps[t].position[:2])
            page.wait_for_timeout(1500)
            page.screenshot(path=str(out / "dashboard_truth.png"))
            open_tab(page, "Actions")
            page.screenshot(path=str(out / "dashboard_truth_plot.png"))
            browser.close()
    finally:
        dashboard.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
