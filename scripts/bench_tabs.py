"""What a browser tab costs the server: each tab gets its own page (app.server.Tab), built when it connects. Opens
`--tabs` tabs one after another in headless Chromium on a dashboard with the bundled checkpoint and prints each
tab's build time (`Tab.built_seconds`), the threads and the server's resident memory before and after.

    MUJOCO_GL=egl python scripts/bench_tabs.py --tabs 5
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def rss_mb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--tabs", type=int, default=5)
    p.add_argument("--preset", default="paper")
    args = p.parse_args()
    import playwright.sync_api as playwright_api

    from app.browser import CHROMIUM, CHROMIUM_ARGS
    from app.server import Dashboard
    from gsmn.config import preset

    with tempfile.TemporaryDirectory() as data:
        d = Dashboard(preset(args.preset), port=0, api_port=0, data_dir=data)
        try:
            before = (rss_mb(), threading.active_count())
            with playwright_api.sync_playwright() as pw:
                browser = pw.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
                for k in range(args.tabs):
                    browser.new_page().goto(d.urls.page)
                    deadline = time.monotonic() + 60
                    while len(d.tabs) < k + 1 and time.monotonic() < deadline:
                        time.sleep(0.05)
                time.sleep(2)
                after = (rss_mb(), threading.active_count())
                times = [t.built_seconds for t in d.tabs.values()]
                browser.close()
        finally:
            d.close()
    print(f"{len(times)} tabs built in {', '.join(f'{t:.2f}' for t in times)} s "
          f"(median {statistics.median(times):.2f} s; the first includes warming up)")
    per_tab = (after[0] - before[0]) / len(times)
    print(f"server: {before[0]:.0f} -> {after[0]:.0f} MB resident ({per_tab:.0f} MB a tab), "
          f"{before[1]} -> {after[1]} threads")


if __name__ == "__main__":
    main()
