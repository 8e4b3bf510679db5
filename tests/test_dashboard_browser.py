"""End to end in headless Chromium: the page loads, an instruction is typed and run, the camera panel and the map
layers update while the episode flies, the episode finishes with its result shown, and a counterfactual is
grounded on the map already built.

Needs the `playwright` package (a dev extra) and a Chromium (Debian's /usr/bin/chromium, which ./test.sh
installs, or GSMN_CHROMIUM). Without them the test fails rather than skips: a browser test that does not run
proves nothing.
"""

from __future__ import annotations

import browser_support
import pytest

from app.browser import field

pytestmark = pytest.mark.browser

HORIZON = 60


@pytest.fixture(scope="module")
def dashboard(tmp_path_factory):
    with browser_support.dashboard(tmp_path_factory, HORIZON) as d:  # the episodes it flies are kept
        yield d


@pytest.fixture(scope="module")
def page(dashboard):
    with browser_support.page_on(dashboard, 1400, 900) as page:
        yield page


def maps_state(page) -> dict:
    return page.evaluate("""() => {
        const m = document.querySelector('.gsmn-maps');
        const img = document.querySelector('img.gsmn-camera');
        const layer = document.querySelector('.gsmn-maps img[data-layer="goal"]');
        return {episode: m ? m.dataset.episode : null, step: m && m.dataset.step !== '' ? +m.dataset.step : -1,
                counterfactual: m ? m.dataset.counterfactual : null, camera: img ? img.src : null,
                goal: layer ? layer.src : null};
    }""")


def wait_until(page, predicate, timeout: float = 90.0, what: str = "") -> dict:
    return browser_support.poll(lambda: maps_state(page), predicate, what, timeout)


def test_type_run_watch_finish_and_ask_what_if(dashboard, page):
    run = page.get_by_role("button", name="Run", exact=True)
    run.wait_for()
    instruction = field(page, "Instruction")
    # opens on environment 70 with its own instruction, filled in once the world is built and its first frame
    # rendered, which may come after the Run button shows
    browser_support.poll(instruction.input_value, lambda text: "pumpkin" in text, "environment 70's instruction")

    # an instruction naming no landmark of this world is refused, with the reason shown
    instruction.fill("go to the left side of the anvil")
    instruction.press("Enter")
    page.get_by_text("no anvil in this world").first.wait_for()
    run.click()
    page.get_by_text("Not started").first.wait_for()
    instruction.fill("go to the left side of the moon")
    instruction.press("Enter")
    page.get_by_text("not a landmark: moon").first.wait_for()

    instruction.fill("go to the back side of the box")
    instruction.press("Enter")
    page.get_by_text("Understood").first.wait_for()
    field(page, "Relevance map").click()  # a second ground layer on
    before = maps_state(page)
    run.click()
    first = wait_until(page, lambda s: s["episode"] not in (None, "", before["episode"]) and s["step"] >= 0,
                       what="the first streamed frame")
    later = wait_until(page, lambda s: s["episode"] == first["episode"] and s["step"] >= first["step"] + 3,
                       what="later frames")
    assert later["camera"] and later["camera"] != first["camera"]  # the camera panel moves with the drone
    assert later["goal"] and later["goal"] != first["goal"]  # the map panels update at every step
    scene = dashboard.viewer.scene
    assert scene.layers["goal"].visible and scene.layers["relevance"].visible  # the ground layers are drawn
    assert not scene.layers.get("semantic") or not scene.layers["semantic"].visible

    episode = dashboard.runner.episodes.get(int(first["episode"]))
    assert episode.instruction == "go to the back side of the box"
    page.get_by_text("P(stop) at the end").first.wait_for(timeout=120_000)  # the result table
    assert page.get_by_text("Success").count() + page.get_by_text("Failure").count() >= 1
    assert page.get_by_text("distance to goal").count() >= 1
    assert episode.status == "finished"

    # scrub the timeline: every view follows the cursor
    page.get_by_role("button", name="Step", exact=True).click()  # a finished episode: Step moves the cursor
    wait_until(page, lambda s: s["step"] == len(episode.steps) - 1, what="the cursor at the end")

    # counterfactual on the map already built: no new episode, the maps marked as what-if
    episodes_before = len(dashboard.runner.episodes)
    whatif = field(page, "What if")
    whatif.fill("go to the front side of the car")
    whatif.press("Enter")
    page.get_by_role("button", name="Ground", exact=True).click()
    wait_until(page, lambda s: s["counterfactual"] == "1", what="the counterfactual maps")
    page.get_by_text("What if \"go to the front side of the car\"").first.wait_for()
    assert len(dashboard.runner.episodes) == episodes_before
    page.get_by_role("button", name="Clear", exact=True).click()
    wait_until(page, lambda s: s["counterfactual"] == "0", what="the episode's own maps again")
