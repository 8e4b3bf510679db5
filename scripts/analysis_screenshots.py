"""The screenshots of docs/dashboard.md's "Analysis": the Analysis tab at 1280x800 on two shipped evaluations (GSMN
without J_percept against GSMN, Table 2's dev environments, imported from checkpoints/table2 into a throw-away data
folder): success by slice, then a confusion cell clicked and its episodes listed.

    python scripts/analysis_screenshots.py --out docs
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--checkpoint", default="checkpoints/gsmn")
    p.add_argument("--preset", default="paper")
    p.add_argument("--first", default="table2/no-percept/dev", help="the shipped evaluation analysed")
    p.add_argument("--versus", default="table2/gsmn/dev", help="the shipped evaluation it is compared with")
    p.add_argument("--out", default="docs")
    p.add_argument("--port", type=int, default=8660)
    args = p.parse_args()
    import playwright.sync_api as playwright_api
    from kept_screenshots import _close_notifications  # beside this script

    from app.browser import CHROMIUM, CHROMIUM_ARGS, field
    from app.page.analysis_view import SHIPPED
    from app.server import Dashboard
    from gsmn.config import preset

    out = Path(args.out)
    with tempfile.TemporaryDirectory() as folder:
        d = Dashboard(preset(args.preset), checkpoint=Path(args.checkpoint).resolve(), port=args.port,
                      api_port=args.port + 1, data_dir=folder)
        try:
            labels = {s["key"]: s["label"] for s in d.jobs.analyses.shipped()}
            with playwright_api.sync_playwright() as pw:
                browser = pw.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
                page = browser.new_page(viewport={"width": 1280, "height": 800})
                page.set_default_timeout(120_000)
                page.goto(d.urls.page)
                page.get_by_role("button", name="Run", exact=True).wait_for()
                page.get_by_role("tab", name="Analysis").click()

                def choose(label: str, option: str) -> None:
                    field(page, label).click()
                    page.get_by_role("option", name=option, exact=True).click()

                choose("Evaluation", SHIPPED + labels[args.first])
                choose("Against", SHIPPED + labels[args.versus])
                page.get_by_role("button", name="Analyse", exact=True).click()
                page.get_by_text("Bars: success with its 95 % interval").first.wait_for()
                page.wait_for_timeout(1500)
                _close_notifications(page)
                page.screenshot(path=str(out / "dashboard_analysis.png"))
                choose("Matrix", "named -> stopped at (unambiguous)")
                page.wait_for_timeout(1000)
                page.locator("[data-pick*='\"cell\": [\"stopped_at\"']").filter(
                    has=page.locator("xpath=self::*[contains(@style,'rgba')]")).first.click()
                note = page.get_by_text("Click one to fly it again").first
                note.wait_for()
                note.evaluate("e => e.scrollIntoView({block: 'center'})")  # the matrix above, the episodes below
                page.wait_for_timeout(1500)
                page.screenshot(path=str(out / "dashboard_analysis_confusion.png"))
                browser.close()
            print(f"wrote {out / 'dashboard_analysis.png'} and {out / 'dashboard_analysis_confusion.png'}")
        finally:
            d.close()


if __name__ == "__main__":
    main()
