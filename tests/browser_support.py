"""What the browser tests share: a dashboard on the run's untrained tiny checkpoint with folders of its own (never the
repository's `data/dashboard`), a headless Chromium, a page open on the dashboard, and waiting for a condition.

Like the tests that use them these fail, not skip, without Playwright or a Chromium (./test.sh installs both).
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator
from typing import Any

import playwright.sync_api as playwright_api
from support import poll, until, untrained_checkpoint  # noqa: F401 - the browser tests wait through this module

from app.browser import CHROMIUM, CHROMIUM_ARGS

NO_CHROMIUM = "no Chromium found: ./test.sh installs Debian's chromium (GSMN_BROWSER=1 scripts/setup.sh)"


@contextlib.contextmanager
def dashboard(tmp_path_factory, horizon: int, **options) -> Iterator[Any]:
    """A Dashboard of the tiny preset flying `horizon` steps at most, on free ports, closed afterwards. By default
    its checkpoint is the run's untrained GSMN (support.untrained_checkpoint, built once per run), it offers no
    other, and it keeps its record in a folder of its own; `options` go to Dashboard (another `checkpoint`,
    `checkpoints_root`, `env_id`, ...)."""
    from app.server import Dashboard
    from gsmn.config import preset, with_overrides

    root = tmp_path_factory.mktemp("dashboard")
    if "checkpoint" not in options:
        options["checkpoint"] = untrained_checkpoint(tmp_path_factory)
    if "checkpoints_root" not in options:
        (root / "offered").mkdir()
        options["checkpoints_root"] = root / "offered"
    options.setdefault("data_dir", root / "data")
    d = Dashboard(with_overrides(preset("tiny"), {"task.horizon": str(horizon)}), port=0, api_port=0, **options)
    try:
        yield d
    finally:
        d.close()


@contextlib.contextmanager
def chromium() -> Iterator[playwright_api.Browser]:
    """A headless Chromium, closed afterwards."""
    assert CHROMIUM, NO_CHROMIUM
    with playwright_api.sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        try:
            yield browser
        finally:
            browser.close()


@contextlib.contextmanager
def page_on(dashboard, width: int, height: int) -> Iterator[playwright_api.Page]:
    """A page of that size in its own Chromium, open on the dashboard once its Run button shows."""
    with chromium() as browser:
        page = browser.new_page(viewport={"width": width, "height": height})
        page.set_default_timeout(60_000)
        page.goto(dashboard.urls.page)
        page.get_by_role("button", name="Run", exact=True).wait_for()
        yield page


def choose(page, label: str, option: str) -> None:
    """Pick `option` in the viser dropdown labelled `label`."""
    from app.browser import field

    field(page, label).click()
    page.get_by_role("option", name=option, exact=True).click()


def scrub_home_until(page, read: Callable[[Any], Any], done: Callable[[Any], Any], what: str) -> Any:
    """Press Home on the page's first slider until `done(read(page))`: the tab draws the steps it has queued (an
    episode's last ones, its end) after the key, each setting the slider back to the end on a busy machine; it
    applies its events in order, so once `done` holds nothing older is on its way. Returns the last reading."""
    def home() -> Any:
        page.get_by_role("slider").first.focus()
        page.keyboard.press("Home")
        return read(page)

    return poll(home, done, what, every=0.5)
