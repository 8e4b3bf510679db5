"""The screenshots of docs/dashboard.md's "Kept episodes, links, export, presenter mode": the shipped GSMN flies a few
test environments into a throw-away data folder, then headless Chromium opens presenter mode by its link at
1280x800 and the Episodes tab.

    python scripts/kept_screenshots.py --checkpoint checkpoints/gsmn --out docs
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--checkpoint", default="checkpoints/gsmn")
    p.add_argument("--preset", default="paper")
    p.add_argument("--env-ids", type=int, nargs="+", default=[70, 72, 76, 73])
    p.add_argument("--step", type=int, default=54, help="the step of the last episode presenter mode opens at")
    p.add_argument("--out", default="docs")
    p.add_argument("--port", type=int, default=8640)
    args = p.parse_args()
    import playwright.sync_api as playwright_api

    from app.live.commands import StartEpisode
    from app.server import Dashboard
    from gsmn.config import preset

    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    out = Path(args.out)
    with tempfile.TemporaryDirectory() as folder:
        d = Dashboard(preset(args.preset), checkpoint=Path(args.checkpoint).resolve(), port=args.port,
                      api_port=args.port + 1, data_dir=folder)
        try:
            ids = []
            for env_id in args.env_ids:
                episode = d.runner.call(StartEpisode(env_id, None, "model", None))
                while episode.live:
                    time.sleep(0.2)
                ids.append(episode.id)
                print(f"episode {episode.id}: env {env_id}, {len(episode.steps)} steps, "
                      f"{'success' if episode.result and episode.result.success else 'failure'}", flush=True)
            d.keeper.flush()
            d.jobs.db.update_kept(ids[0], pinned=1)
            with playwright_api.sync_playwright() as pw:
                browser = pw.chromium.launch(executable_path=chromium, args=["--no-sandbox", "--disable-gpu",
                                                                             "--enable-unsafe-swiftshader"])
                page = browser.new_page(viewport={"width": 1400, "height": 900})
                page.goto(d.urls.page)
                page.get_by_role("tab", name="Episodes").click()
                page.get_by_role("button", name=f"#{ids[-1]} ", exact=False).first.wait_for(timeout=60_000)
                page.get_by_role("button", name=f"#{ids[1]} ", exact=False).first.click()
                page.wait_for_timeout(4000)
                page.get_by_role("tab", name="Episodes").click()
                page.wait_for_timeout(1500)
                _close_notifications(page)
                page.screenshot(path=str(out / "dashboard_episodes.png"))
                page.close()
                page = browser.new_page(viewport={"width": 1280, "height": 800})
                page.goto(f"{d.urls.page}/?episode={ids[-1]}&step={args.step}&layers=goal&presenter=1")
                page.locator(".gsmn-presenter-instruction").wait_for(timeout=60_000)
                page.wait_for_timeout(5000)
                _close_notifications(page)
                page.screenshot(path=str(out / "dashboard_presenter.png"))
                browser.close()
            print(f"wrote {out / 'dashboard_episodes.png'} and {out / 'dashboard_presenter.png'}")
        finally:
            d.close()


def _close_notifications(page) -> None:
    """Hide viser's notices (headless Chromium renders WebGL in software, and viser says so)."""
    page.add_style_tag(content="[class*='Notification']{display:none !important}")
    page.wait_for_timeout(500)


if __name__ == "__main__":
    main()
