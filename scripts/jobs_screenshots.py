"""Screenshots of the dashboard's Failures and Fine-tune tabs for docs/dashboard.md, driven through the page.

    .venv/bin/python scripts/jobs_screenshots.py [--preset paper] [--checkpoint DIR] [--out docs]

Serves the dashboard in-process on a fresh data folder, opens it in headless Chromium, evaluates the checkpoint on
the first --episodes test environments from the page, replays a failure (docs/dashboard_failures.png, the replay
mid-flight beside the failure browser), launches a tiny DAggerFM run on the failures (docs/dashboard_finetune.png,
its progress and curves, taken after its second iteration), and reruns the episodes with its checkpoint
(docs/dashboard_before_after.png). Without --checkpoint it uses an untrained GSMN biased to fly, whose maps and
attributions mean nothing: the pictures show the tool, not a result.

    .venv/bin/python scripts/jobs_screenshots.py --checkpoint checkpoints/gsmn --regions runs/eval13_k_plain.json \
        --record runs/eval13_k_plain_rec

instead loads a `gsmn eval --json` file made with that checkpoint (and its --record folder), filters its failures
to those that flew through the success region and replays the first (docs/dashboard_failure_regions.png).
"""

from __future__ import annotations

import argparse
import re
import shutil
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_dashboard import CHROMIUM_ARGS, dismiss_notifications, field  # noqa: E402 - the page helpers, shared


def wait(condition, timeout: float = 900.0, what: str = "") -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            raise TimeoutError(f"timed out waiting for {what}")
        time.sleep(0.2)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="paper", choices=("paper", "tiny"))
    ap.add_argument("--checkpoint", default=None, help="default: an untrained GSMN biased to fly")
    ap.add_argument("--episodes", type=int, default=8, help="test environments to evaluate")
    ap.add_argument("--iterations", type=int, default=4, help="iterations of the tiny run")
    ap.add_argument("--out", default=str(ROOT / "docs"))
    ap.add_argument("--regions", default=None, help="a `gsmn eval --json` file: take the success-region picture only")
    ap.add_argument("--record", default=None, help="that evaluation's --record folder (attribution and P(stop))")
    a = ap.parse_args(argv)

    import playwright.sync_api as playwright_api

    from app.live.commands import SetSpeed
    from app.live.fixtures import make_untrained_checkpoint
    from app.server import Dashboard
    from gsmn.config import preset

    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if not chromium:
        raise SystemExit("no chromium: apt-get install chromium")
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix="gsmn-shots-"))
    checkpoint = Path(a.checkpoint or make_untrained_checkpoint(tmp / "checkpoints" / "gsmn", preset_name=a.preset))
    dashboard = Dashboard(preset(a.preset), checkpoint=checkpoint.name, port=0, api_port=0, data_dir=tmp / "data",
                          checkpoints_root=checkpoint.parent)  # by name: the page lists it as "gsmn"
    try:
        with playwright_api.sync_playwright() as p:
            browser = p.chromium.launch(executable_path=chromium, args=CHROMIUM_ARGS)
            page = browser.new_page(viewport={"width": 1500, "height": 1000})
            page.set_default_timeout(120_000)
            page.goto(dashboard.urls.page)
            page.get_by_role("button", name="Run", exact=True).wait_for()
            if a.regions:
                regions_shot(page, dashboard, a.regions, a.record, out)
                browser.close()
                return 0

            # evaluate from the page, then replay a failure
            page.get_by_role("tab", name="Failures").click()
            episodes = field(page, "Episodes")
            episodes.fill(str(a.episodes))
            episodes.press("Enter")
            page.get_by_role("button", name="Evaluate", exact=True).click()
            wait(lambda: (e := dashboard.jobs.db.evaluation(1)) is not None and e.status != "running",
                 what="the evaluation")
            page.get_by_text(f"{a.episodes}/{a.episodes} episodes").first.wait_for()
            failures = dashboard.jobs.db.episodes(1, failed_only=True)
            long = [r for r in failures if r.steps >= 60] or failures  # a long flight, to catch it mid-way ...
            pick = min(long, key=lambda r: r.goal_distance)  # ... that stays near the field
            field(page, "Relevance map").click()
            dashboard.runner.call(SetSpeed(5.0))
            page.get_by_role("button", name=re.compile(rf"^▶ {pick.env_id} ")).click()
            wait(lambda: dashboard.runner.live is not None and len(dashboard.runner.live.steps) >= min(
                45, pick.steps // 2), what="the replay mid-flight")
            shoot_details(page, out / "dashboard_failures.png")
            dashboard.runner.call(SetSpeed(None))

            # a tiny fine-tuning run on the failures
            page.get_by_role("tab", name="Fine-tune").click()
            iterations = field(page, "Iterations")
            iterations.fill(str(a.iterations))
            iterations.press("Enter")
            page.wait_for_timeout(500)
            page.get_by_role("button", name="Launch", exact=True).click()
            wait(lambda: (r := dashboard.jobs.db.run(1)) is not None and (
                len(r.metrics) >= 2 and (r.progress or {}).get("iteration", 0) >= 2
                or r.status in ("finished", "failed", "cancelled")), what="two iterations")
            page.wait_for_timeout(1500)
            dismiss_notifications(page)
            page.screenshot(path=str(out / "dashboard_finetune.png"))
            print(f"wrote {out / 'dashboard_finetune.png'}")
            wait(lambda: dashboard.jobs.db.run(1).status != "running", what="the run to end")
            page.get_by_text("checkpoint run-1").first.wait_for()
            page.get_by_role("button", name="Before/after", exact=True).click()
            wait(lambda: (e := dashboard.jobs.db.evaluation(2)) is not None and e.status != "running",
                 what="the before/after evaluation")
            page.wait_for_function("() => !!document.querySelector('.gsmn-compare')")
            page.get_by_role("button", name="Fly with it", exact=True).click()
            page.wait_for_timeout(1500)
            page.locator(".gsmn-compare").scroll_into_view_if_needed()
            page.wait_for_timeout(500)
            dismiss_notifications(page)
            page.screenshot(path=str(out / "dashboard_before_after.png"))
            print(f"wrote {out / 'dashboard_before_after.png'}")
            browser.close()
    finally:
        dashboard.close()
        shutil.rmtree(tmp, ignore_errors=True)
    return 0


def shoot_details(page, path: Path, what: str = "") -> None:
    """Capture the page with the episode's details under the failure browser in view."""
    page.locator(".gsmn-episode").scroll_into_view_if_needed()
    page.wait_for_timeout(500)
    dismiss_notifications(page)
    page.mouse.move(700, 900)
    page.screenshot(path=str(path))
    print(f"wrote {path}" + (f" ({what})" if what else ""))


def regions_shot(page, dashboard, results: str, record: str | None, out: Path) -> None:
    """The failure browser on an imported evaluation, filtered to the failures that flew through the success
    region, with the first of them replaying in the live view."""
    from app.live.commands import SetSpeed

    e = dashboard.jobs.import_evaluation(results, record)
    page.set_viewport_size({"width": 1500, "height": 1300})  # the counts under the bars and the details, both
    page.get_by_role("tab", name="Failures").click()
    page.get_by_text(f"{e.total}/{e.total} episodes").first.wait_for()
    field(page, "Success region").click()
    page.get_by_role("option", name="flew through it", exact=True).click()
    (first, *_) = dashboard.jobs.db.episodes(e.id, failed_only=True, entered_region=True)
    button = page.get_by_role("button", name=re.compile(rf"^▶ {first.env_id} "))
    button.wait_for()
    dashboard.runner.call(SetSpeed(5.0))
    button.click()
    wait(lambda: dashboard.runner.live is not None and len(dashboard.runner.live.steps) > max(first.region_steps),
         what="the replay past the success region")
    shoot_details(page, out / "dashboard_failure_regions.png", f"evaluation {e.id}, environment {first.env_id}")
    dashboard.runner.call(SetSpeed(None))


if __name__ == "__main__":
    sys.exit(main())
