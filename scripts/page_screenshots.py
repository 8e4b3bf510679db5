"""Screenshots of the page as a new user sees it (docs/dashboard.md): at 1500 x 1000 an episode of the shipped GSMN
flown to its end, and at 1280 x 800 the same page with another instruction being typed, its four sides drawn
around the landmark it names.

    python scripts/page_screenshots.py [--preset paper] [--env-id 72] [--out docs/img]
"""

from __future__ import annotations

import argparse
import os
import shutil
import tempfile
import time
from pathlib import Path

from PIL import Image

from app.browser import dismiss_notifications, field

CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--enable-unsafe-swiftshader", "--disable-quic", "--no-first-run"]





def save(page, path: Path) -> None:
    """A compact PNG: the screenshot quantised to 256 colours (the page is flat colours and a few images)."""
    raw = path.with_suffix(".raw.png")
    page.screenshot(path=str(raw))
    Image.open(raw).convert("RGB").quantize(256, method=Image.Quantize.MEDIANCUT).save(path, optimize=True)
    raw.unlink()
    print(f"{path} ({path.stat().st_size // 1024} kB)", flush=True)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", default="paper", choices=("tiny", "paper"))
    ap.add_argument("--checkpoint", default=None, help="default: checkpoints/gsmn")
    ap.add_argument("--env-id", type=int, default=72)
    ap.add_argument("--typed", default="go to the left side of the tower", help="the instruction shown being typed")
    ap.add_argument("--out", default="docs/img")
    ap.add_argument("--chromium", default=os.environ.get("GSMN_CHROMIUM") or shutil.which("chromium"))
    a = ap.parse_args()
    os.environ.setdefault("MUJOCO_GL", "egl")

    from playwright.sync_api import sync_playwright

    from app.server import Dashboard
    from gsmn.config import preset

    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    d = Dashboard(preset(a.preset), checkpoint=a.checkpoint, port=0, api_port=0, env_id=a.env_id,
                  data_dir=tempfile.mkdtemp(prefix="gsmn-shots-"))
    try:
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=a.chromium, args=CHROMIUM_ARGS)
            page = browser.new_page(viewport={"width": 1500, "height": 1000})
            page.set_default_timeout(120_000)
            page.goto(d.urls.page)
            page.get_by_role("button", name="Run", exact=True).wait_for()
            page.wait_for_timeout(3000)
            page.get_by_role("button", name="Run", exact=True).click()
            time.sleep(1)
            deadline = time.monotonic() + 600
            while time.monotonic() < deadline and (not d.runner.episodes.all() or d.runner.episodes.all()[-1].live):
                time.sleep(0.5)
            page.wait_for_timeout(3000)
            dismiss_notifications(page)
            page.wait_for_timeout(500)
            save(page, out / "page_1500x1000.png")
            page.set_viewport_size({"width": 1280, "height": 800})
            page.wait_for_timeout(2000)
            box = field(page, "Instruction")
            box.fill("")
            box.type(a.typed, delay=20)
            page.wait_for_timeout(2500)
            save(page, out / "page_typing_1280x800.png")
            browser.close()
    finally:
        d.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
