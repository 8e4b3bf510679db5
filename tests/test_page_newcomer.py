"""The page as a new user sees it (issue 51), walked in headless Chromium: the landmark count matches the names, the
semantic-map legend lists only this world's landmarks, an ambiguous name says which landmark it means and the four
sides are drawn around it, the word chips and a landmark clicked in the 3D view fill the instruction in, a refused
Run says so once (and the Run button is grey while the text cannot be flown), a bad environment id is refused rather
than read as 0, the split follows the id typed, the what-if box is checked as typed and a refused Ground drops the
old what-if maps, the header names the policy that flies, Stop names the step the timeline ends at, the timeline's
labels do not meet, the Actions plot's cursor moves with the timeline, and at 1280 x 800 the camera, the four maps
and the result show without scrolling.

The tiny preset and an untrained checkpoint (as the other browser tests); a Chromium as in
tests/test_dashboard_browser.py (it fails, not skips, without one).
"""

from __future__ import annotations

import re

import browser_support
import numpy as np
import pytest
from browser_support import until

from app.browser import field

pytestmark = pytest.mark.browser

HORIZON = 40
ENV = 76  # two palm trees


@pytest.fixture(scope="module")
def dashboard(tmp_path_factory):
    with browser_support.dashboard(tmp_path_factory, HORIZON, env_id=70) as d:
        yield d


@pytest.fixture(scope="module")
def page(dashboard):
    with browser_support.page_on(dashboard, 1500, 1000) as page:
        yield page


def body(page) -> str:
    return page.evaluate("() => document.body.innerText")


def finished(dashboard):
    episodes = dashboard.runner.episodes.all()
    return episodes and not episodes[-1].live and episodes[-1].steps and episodes[-1]


def show(page, dashboard, env_id: int) -> None:
    box = field(page, "Environment id")
    box.fill(str(env_id))
    box.press("Enter")
    page.get_by_role("button", name="Show", exact=True).click()
    until(lambda: dashboard.viewer.world_shown and dashboard.viewer.world_shown.world.env_id == env_id,
          what=f"environment {env_id} shown")
    page.get_by_text(f"Environment {env_id}").first.wait_for()


def type_instruction(page, text: str) -> None:
    box = field(page, "Instruction")
    box.fill("")  # a change even when the box holds this text already (the world's own instruction)
    box.type(text[:-1])
    box.type(text[-1])
    box.press("Enter")


def screen_point(point, width: float, height: float) -> tuple[float, float]:
    """Where the 3D view's first camera (app.page.scene.DEFAULT_CAMERA) shows a world point, in canvas pixels."""
    import math

    from app.page.scene import DEFAULT_CAMERA

    eye, target, up = (np.asarray(DEFAULT_CAMERA[k], float) for k in ("position", "look_at", "up"))
    forward = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    d = np.asarray(point, float) - eye
    focal = height / 2 / math.tan(DEFAULT_CAMERA["fov"] / 2)
    return width / 2 + focal * (d @ right) / (d @ forward), height / 2 + focal * (d @ down) / (d @ forward)


def cursor_column(page) -> float:
    """The x (in the plot's canvas pixels) of the Actions plot's near-black cursor line."""
    png = page.locator(".uplot canvas").first.screenshot()
    from app.render.colors import decode_image

    rgb = decode_image(png).astype(int)
    dark = (rgb.max(-1) < 70)  # the cursor #222; axes and text are grey or thin
    columns = dark.sum(0)
    assert columns.max() > 0.4 * rgb.shape[0], "no vertical cursor line in the Actions plot"
    return float(np.argmax(columns))


def test_a_newcomer_walks_the_page(dashboard, page):
    from app.page.scene import SIDE_TURN, _has

    viewer = dashboard.viewer
    show(page, dashboard, ENV)
    world = viewer.world_shown.world
    # the landmark count matches the names, a shared name counted (item 6)
    status = re.search(rf"Environment {ENV} \(test\): (\d+) landmarks: ([^.]*)\. Press", body(page))
    assert status and int(status[1]) == len(world.landmarks), body(page)
    parts = status[2].split(", ")
    assert sum(int(p.split(" ")[0]) if p[0].isdigit() else 1 for p in parts) == len(world.landmarks)
    assert "2 palm trees" in parts

    # an ambiguous name says which landmark it means, and the four sides are drawn around it (items 7, 8)
    type_instruction(page, "go to the right side of the palm tree")
    page.get_by_text("it means the one at").first.wait_for()
    until(lambda: all(_has(viewer.client.scene, f"/sides/{side}") for side in SIDE_TURN), what="the four sides")
    assert "Sides are seen from the start" in body(page)

    # the chips fill the template in: a landmark name, then a side (instruction help)
    page.get_by_role("button", name="cone", exact=True).click()
    until(lambda: field(page, "Instruction").input_value() == "go to the right side of the cone", what="the chip")
    page.get_by_role("button", name="back", exact=True).click()
    until(lambda: field(page, "Instruction").input_value() == "go to the back side of the cone", what="the side")

    # a refused Run says so once, and Run is grey while the text cannot be flown (item 13)
    type_instruction(page, "go to the left side of the barrel")
    page.get_by_text("Cannot fly this").first.wait_for()
    until(lambda: viewer.run_button.color == "gray", what="a grey Run")
    page.get_by_role("button", name="Run", exact=True).click()
    page.get_by_text("Not started").first.wait_for()
    page.wait_for_timeout(500)
    assert body(page).count("there is no barrel in this world") == 1, body(page)

    # a bad environment id is refused, not read as 0; the split follows the id typed (item 16)
    box = field(page, "Environment id")
    for bad in ("-5", "abc"):
        box.fill(bad)
        box.press("Enter")
        page.get_by_role("button", name="Show", exact=True).click()
        page.get_by_text("must be a whole number").first.wait_for()
        assert viewer.world_shown.world.env_id == ENV
    box.fill("5")
    box.press("Enter")
    until(lambda: field(page, "Split").input_value() == "train", what="the split to follow the id")
    show(page, dashboard, ENV)
    assert field(page, "Split").input_value() == "test"

    # the header names the policy that flies (item 11)
    field(page, "Policy").click()
    page.get_by_role("option", name="Expert (oracle)", exact=True).click()
    page.get_by_text("Flies:").first.wait_for()
    field(page, "Policy").click()
    page.get_by_role("option", name=re.compile("^Model: ")).first.click()
    until(lambda: "Flies:" not in body(page), what="the header back on the loaded model")

    # a landmark clicked in the 3D view goes into the instruction (instruction help): a click on the tent's mesh,
    # where the first camera shows it
    type_instruction(page, "go to the front side of the box")
    until(lambda: viewer.instruction.value == "go to the front side of the box", what="the text at the server")
    left, top, width, height = page.evaluate("""() => { const c = [...document.querySelectorAll('canvas')]
        .sort((a, b) => b.width - a.width)[0].getBoundingClientRect(); return [c.left, c.top, c.width, c.height]; }""")
    tent = next(lm for lm in world.landmarks if lm.noun_phrase == "tent")
    x, y = screen_point((tent.x, tent.y, 0.8), width, height)
    page.mouse.click(left + x, top + y)
    until(lambda: field(page, "Instruction").input_value() == "go to the front side of the tent", what="the click")

    # run it to the end: the legend lists only this world's landmarks (item 5)
    type_instruction(page, "go to the right side of the palm tree")
    page.get_by_role("button", name="Run", exact=True).click()
    episode = until(lambda: finished(dashboard), timeout=120, what="the episode to finish")
    page.get_by_text(f"Episode {episode.id}: ").first.wait_for()
    legend = page.locator(".gsmn-maps .gsmn-legend").first.inner_text()
    names = {lm.noun_phrase for lm in world.landmarks}
    listed = [re.sub(r" \d+%.*$", "", item).strip() for item in re.split(r"\n|(?<=%)\s+", legend) if "%" in item]
    assert listed, legend
    for name in listed:
        assert name in names or name in ("other classes (not in this world)", "not seen yet"), (name, legend)
    assert len(listed) == len(set(listed)), legend

    # the timeline's labels do not print over each other (item 1)
    boxes = page.evaluate("""() => [...document.querySelectorAll('.mantine-Slider-markLabel')]
        .filter(e => e.getBoundingClientRect().width > 0 && e.innerText.trim())
        .map(e => { const r = e.getBoundingClientRect(); return [r.left, r.right, r.top, e.innerText]; })""")
    timeline = [b for b in boxes if abs(b[2] - boxes[0][2]) < 2]  # the first slider: the timeline
    timeline.sort()
    assert all(a[1] <= b[0] for a, b in zip(timeline, timeline[1:], strict=False)), timeline

    # the Actions plot draws at full size when its tab opens, and its cursor follows the timeline
    page.get_by_role("tab", name="Actions").click()
    page.locator(".uplot canvas").first.wait_for()
    assert page.locator(".uplot").first.bounding_box()["width"] > 300
    at_end = cursor_column(page)
    step = page.locator("input.mantine-NumberInput-input").first
    step.fill("0")
    step.press("Enter")
    until(lambda: viewer.view.cursor == 0, what="the timeline at step 0")
    page.wait_for_timeout(800)
    at_start = cursor_column(page)
    assert at_start < at_end - 50, (at_start, at_end)
    page.get_by_role("tab", name="Camera and maps").click()

    # the what-if box is checked as typed; a refused Ground drops the old what-if maps (item 14)
    whatif = field(page, "What if")
    whatif.fill("go to the left side of the moon")
    whatif.press("Enter")
    page.get_by_text("Cannot ground this").first.wait_for()
    whatif.fill("go to the left side of the tent")
    whatif.press("Enter")
    page.get_by_role("button", name="Ground", exact=True).click()
    until(lambda: page.evaluate("() => document.querySelector('.gsmn-maps').dataset.counterfactual") == "1",
          what="the what-if maps")
    whatif.fill("go to the left side of the moon")
    whatif.press("Enter")
    page.get_by_role("button", name="Ground", exact=True).click()
    until(lambda: page.evaluate("() => document.querySelector('.gsmn-maps').dataset.counterfactual") == "0",
          what="the old what-if maps dropped")

    # Stop names the step the timeline ends at (item 12)
    page.get_by_role("button", name="Clear", exact=True).click()
    field(page, "Speed").click()
    page.get_by_role("option", name="slow (2 steps/s)", exact=True).click()
    page.get_by_role("button", name="Run", exact=True).click()
    until(lambda: (e := dashboard.runner.episodes.all()[-1]) is not episode and len(e.steps) >= 3, what="a live one")
    page.get_by_role("button", name="Stop", exact=True).click()
    stopped = until(lambda: finished(dashboard), what="the stop")
    page.get_by_text("Stopped early").first.wait_for()
    until(lambda: f"cancelled at step {len(stopped.steps) - 1}, the timeline's last" in body(page), what="the step")
    until(lambda: viewer.timeline.max == len(stopped.steps) - 1, what="the timeline's end")
    field(page, "Speed").click()
    page.get_by_role("option", name="as fast as it goes", exact=True).click()

    # at 1280 x 800 the camera, the four maps and the result show without scrolling
    page.get_by_role("button", name="Run", exact=True).click()
    last = until(lambda: (e := finished(dashboard)) and e is not stopped and e, timeout=120, what="one more episode")
    page.get_by_text(f"Episode {last.id}: ").first.wait_for()
    page.set_viewport_size({"width": 1280, "height": 800})
    page.wait_for_timeout(1500)
    seen = page.evaluate("""() => {
        const box = e => { const r = e.getBoundingClientRect(); return [r.top, r.bottom, r.left, r.right]; };
        const maps = [...document.querySelectorAll('.gsmn-maps img[data-layer]')].slice(0, 4).map(box);
        const result = [...document.querySelectorAll('h4')].filter(h => /^Episode \\d+:/.test(h.innerText)).map(box);
        return {camera: box(document.querySelector('img.gsmn-camera')), maps, result};
    }""")
    assert len(seen["maps"]) == 4 and seen["result"], seen
    for top, bottom, left, right in [seen["camera"], *seen["maps"], seen["result"][0]]:
        assert 0 <= top and bottom <= 800 and 0 <= left and right <= 1280, seen
