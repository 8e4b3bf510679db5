"""Presenter mode at 1280x800 and what it hands on, in headless Chromium (issue 77, items 12, 14 and 15): the Share
folder stays, and a link copied there opens in presenter mode; the 3D view has most of the screen, framed on the
field, with the drone marked and the colours of the paths named; the semantic map reads as this world's landmarks
or nothing, in the card, as an option of the normal page, and in the HTML export, whose top-down view keeps every
landmark's name inside it.

Worlds here are ones no other browser test uses (233, 238, 245)."""

from __future__ import annotations

import browser_support
import numpy as np
import pytest

from app.browser import field
from app.live.commands import StartEpisode
from app.page.scene import DEFAULT_CAMERA

pytestmark = pytest.mark.browser
HORIZON = 20
SIZE = {"width": 1280, "height": 800}


@pytest.fixture(scope="module")
def dashboard(tmp_path_factory):
    with browser_support.dashboard(tmp_path_factory, HORIZON, env_id=233) as d:
        d.flown = {}
        for env_id in (233, 238, 245):
            episode = d.runner.call(StartEpisode(env_id, None, "model", None))
            browser_support.until(lambda episode=episode: not episode.live, 120, f"the episode in {env_id} to end")
            d.flown[env_id] = episode
        d.keeper.flush()
        yield d


@pytest.fixture(scope="module")
def browser(dashboard):
    with browser_support.chromium() as browser:
        yield browser


def card_step(page) -> dict:
    return page.evaluate("""() => {
        const c = document.querySelector('.gsmn-presenter');
        return {episode: c ? +c.dataset.episode : null, step: c ? +c.dataset.step : null};
    }""")


def test_a_link_copied_in_presenter_mode_opens_in_presenter_mode(dashboard, browser):
    """Item 12: the Share folder (link, Copy link, Export) stays in presenter mode, and its link keeps the mode."""
    episode = dashboard.flown[233]
    context = browser.new_context(viewport=SIZE, permissions=["clipboard-read", "clipboard-write"])
    page = context.new_page()
    page.set_default_timeout(60_000)
    page.goto(f"{dashboard.urls.page}/?episode={episode.id}&step=5")
    page.get_by_role("button", name="Run", exact=True).wait_for()
    field(page, "Presenter mode").check()
    browser_support.poll(lambda: card_step(page), lambda s: s["episode"] == episode.id and s["step"] == 5,
                         "the presenter card at step 5")
    # the Share folder's link follows the view twice a second (app/page/episodes_view.py), so the card can show
    # step 5 before the link says presenter mode: its new HTML replaces the button. Wait for it first.
    link = browser_support.poll(lambda: page.locator(".gsmn-share input").input_value(),
                                lambda v: "presenter=1" in v and v.startswith(dashboard.urls.page),
                                "the link in presenter mode, with the page's address")
    copy = page.locator("button.gsmn-copy-link")
    copy.scroll_into_view_if_needed()
    assert copy.is_visible() and page.get_by_role("button", name="HTML", exact=True).is_visible()
    assert f"episode={episode.id}&step=5" in link
    copy.click()
    page.get_by_text("Copied").first.wait_for()
    assert page.evaluate("() => navigator.clipboard.readText()") == link
    with page.expect_download() as download:  # Export works in presenter mode
        page.get_by_role("button", name="HTML", exact=True).click()
    assert download.value.suggested_filename == f"episode-{episode.id}.html"
    # the copied link, opened in a new tab, opens in presenter mode at that step
    other = context.new_page()
    other.set_default_timeout(60_000)
    other.goto(link)
    browser_support.poll(lambda: card_step(other), lambda s: s["episode"] == episode.id and s["step"] == 5,
                         "the copied link in presenter mode")
    assert field(other, "Presenter mode").is_checked()
    assert not other.get_by_text("Environment id").first.is_visible()
    context.close()


def test_presenter_mode_gives_the_3d_view_most_of_the_screen_and_names_its_colours(dashboard, browser):
    """Item 14 (and 15 in the card): at 1280x800 the 3D view is most of the screen and framed on the field, the
    drone is marked, the card says what the paths' colours and the semantic map's mean; Run and the timeline stay
    on the screen."""
    episode = dashboard.flown[238]
    page = browser.new_page(viewport=SIZE)
    page.set_default_timeout(60_000)
    page.goto(f"{dashboard.urls.page}/?episode={episode.id}&step=10&layers=goal&presenter=1")
    browser_support.poll(lambda: card_step(page), lambda s: s["episode"] == episode.id, "the presenter card")
    browser_support.poll(lambda: page.evaluate("() => Math.max(...[...document.querySelectorAll('canvas')].map("
                                               "c => c.getBoundingClientRect().width))"),
                         lambda width: width >= 0.6 * SIZE["width"], "the 3D view over 60 % of the screen's width")
    for control in (page.get_by_role("button", name="Run", exact=True), page.get_by_role("slider").first):
        where = control.bounding_box()
        assert where is not None and where["y"] + where["height"] <= SIZE["height"], where
    tab = dashboard.tab()
    scene, camera = tab.viewer.scene, tab.viewer.client.camera
    assert scene.drone_marked and scene.mark is not None and scene.mark.visible  # the ring and "drone" label
    target = np.asarray(DEFAULT_CAMERA["look_at"])
    first = np.linalg.norm(np.asarray(DEFAULT_CAMERA["position"]) - target)
    browser_support.until(lambda: np.linalg.norm(np.asarray(camera.position) - target) < 0.85 * first, 30,
                          "the 3D view's camera brought nearer the field")
    paths = page.locator(".gsmn-presenter .gsmn-paths-legend").inner_text()
    assert "yellow ring: the drone" in paths and "blue line: the path the drone flew" in paths
    assert "red line: the demonstration path" in paths
    legend = page.locator(".gsmn-presenter .gsmn-legend").inner_text()
    names = sorted({lm.noun_phrase for lm in episode.task.world.landmarks})
    assert all(name in legend for name in names) and "nothing (none of these)" in legend
    assert "other classes" not in legend
    assert tab.viewer.semantic_reading.value == "this world's landmarks"  # the ground reads so too
    tab.presenter.set(False)  # off again, and it stays off: the page's own width, camera, reading and drone
    page.locator(".gsmn-presenter").wait_for(state="hidden")
    page.get_by_text("Environment id").first.wait_for()
    page.wait_for_timeout(2000)  # the Share folder went back in its place; the page's link is not read again
    assert not tab.presenter.on and not page.locator(".gsmn-presenter").is_visible()
    browser_support.until(lambda: not scene.mark.visible, 10, "the drone's mark hidden")
    browser_support.until(lambda: np.linalg.norm(np.asarray(camera.position) - target) > 0.95 * first, 30,
                          "the camera put back")
    assert tab.viewer.semantic_reading.value == "all 63 landmark classes"
    page.close()


def test_the_normal_page_offers_this_worlds_reading_and_names_the_paths(dashboard, browser):
    """Items 14 and 15 outside presenter mode: the paths' legend under the Layers folder's box, and the semantic
    map read as this world's landmarks when chosen."""
    episode = dashboard.flown[238]
    page = browser.new_page(viewport=SIZE)
    page.set_default_timeout(60_000)
    page.goto(f"{dashboard.urls.page}/?episode={episode.id}&step=10&layers=semantic")
    page.get_by_text("Semantic map: most likely landmark").first.wait_for()
    legend = page.locator(".gsmn-paths-legend").first
    legend.scroll_into_view_if_needed()
    assert legend.is_visible() and "blue line: the path the drone flew" in legend.inner_text()
    reads = field(page, "Semantic map reads")
    reads.scroll_into_view_if_needed()
    reads.click()
    page.get_by_role("option", name="this world's landmarks").click()
    page.get_by_text("Semantic map: which of this world's landmarks, or nothing").first.wait_for()
    assert page.get_by_text("nothing (none of these)").first.is_visible()
    page.close()


def test_the_html_export_reads_this_worlds_landmarks_and_keeps_names_inside_its_top_down_view(dashboard, browser,
                                                                                              tmp_path):
    """Item 15's export: the legend of this world's landmarks under the semantic map, and in world 245 the names
    near the east edge ("satellite dish", "stone circle"), once cut, drawn whole inside the top-down view."""
    from app.render.export import export_episode, heads_for

    episode = dashboard.flown[245]
    out = tmp_path / "episode.html"
    out.write_bytes(export_episode(episode, "html", heads_for(dashboard.runner, episode)))
    page = browser.new_page(viewport=SIZE)
    # every name drawn in the top-down view, with the box it takes
    page.add_init_script("""(() => {
        const draw = CanvasRenderingContext2D.prototype.fillText;
        window.drawn = [];
        CanvasRenderingContext2D.prototype.fillText = function (text, x, y) {
            const m = this.measureText(text);
            window.drawn.push({text, left: x, right: x + m.width, top: y - m.actualBoundingBoxAscent,
                               bottom: y + m.actualBoundingBoxDescent, width: this.canvas.width,
                               height: this.canvas.height, align: this.textAlign});
            return draw.apply(this, arguments);
        };
    })()""")
    page.goto(out.as_uri())
    drawn = page.evaluate("() => window.drawn")
    names = {lm.noun_phrase for lm in episode.task.world.landmarks}
    assert {"satellite dish", "stone circle"} <= names and names <= {d["text"] for d in drawn}
    for d in drawn:
        assert d["align"] == "start" and 0 <= d["left"] and d["right"] <= d["width"], d
        assert 0 <= d["top"] and d["bottom"] <= d["height"], d
    legend = page.locator("#legend").inner_text()
    assert all(name in legend for name in names) and "nothing (none of these)" in legend
    page.close()
