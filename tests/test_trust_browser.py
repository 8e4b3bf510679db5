"""In headless Chromium, what the page says is about what it shows (the page's trust defects, as a new user met
them): a comparison names who flew each side under both cameras and over the second set of maps, with its step;
an environment id typed shows that world, its instruction and its landmarks; a refused Run says which episode is
still shown; the fork note goes with the fork.

Worlds here are ones no other browser test uses (174, 181, 192)."""

from __future__ import annotations

import re

import browser_support
import httpx
import numpy as np
import pytest

from app.browser import field
from app.live.fixtures import make_untrained_checkpoint
from app.page.controls import INSPECT_HINT
from app.page.events import CursorMoved
from gsmn.task.rollout import task_for_env

pytestmark = pytest.mark.browser
HORIZON = 24


def _first_person_checkpoint(folder):
    from gsmn.config import preset
    from gsmn.model import build_model, save_checkpoint
    from gsmn.model.vocabulary import Vocabulary

    config, vocabulary = preset("tiny"), Vocabulary.default()
    save_checkpoint(folder, build_model("gs-fpv", config, vocabulary), config, vocabulary, {"note": "untrained"})


@pytest.fixture(scope="module")
def dashboard(tmp_path_factory, untrained_checkpoint):
    root = tmp_path_factory.mktemp("offered")
    make_untrained_checkpoint(root / "other", seed=3)  # a second checkpoint to compare with, offered by name
    _first_person_checkpoint(root / "fpv")  # a first-person baseline: evaluated from the page, not flown live
    with browser_support.dashboard(tmp_path_factory, HORIZON, checkpoint=untrained_checkpoint,
                                   checkpoints_root=root, env_id=174) as d:
        yield d


@pytest.fixture(scope="module")
def page(dashboard):
    with browser_support.page_on(dashboard, 1500, 1000) as page:
        yield page


def text_of(page, selector: str) -> str:
    return page.evaluate(f"() => document.querySelector('{selector}')?.innerText ?? ''")


def test_an_environment_id_typed_shows_its_world_and_instruction(dashboard, page):
    viewer = dashboard.viewer
    field(page, "Environment id").fill("181")
    browser_support.until(lambda: viewer.world_shown is not None and viewer.world_shown.world.env_id == 181, 60,
                          "world 181 shown after typing its id")
    own = task_for_env(181, dashboard.runner.config).instruction.text
    browser_support.until(lambda: field(page, "Instruction").input_value() == own, 30, "its instruction")
    assert viewer.scene.world.env_id == 181, "the 3D view draws the world the box names"


def test_a_comparison_names_who_flew_each_side_and_the_step_of_each_view(dashboard, page):
    viewer = dashboard.viewer
    field(page, "Environment id").fill("192")
    browser_support.until(lambda: viewer.world_shown is not None and viewer.world_shown.world.env_id == 192, 60,
                          "world 192")
    page.get_by_text("Compare and fork").first.click()
    other = next(o for o in viewer.compare.other.options if o.startswith("Model: other"))
    field(page, "Compare with").click()
    page.get_by_role("option", name=other, exact=True).click()
    before = set(dashboard.runner.pairs.store)
    page.get_by_role("button", name="Run both", exact=True).click()
    browser_support.until(lambda: set(dashboard.runner.pairs.store) - before, 240, "the comparison")
    comparison = dashboard.runner.comparison(max(set(dashboard.runner.pairs.store) - before))
    a, b = comparison.episodes
    browser_support.until(lambda: not a.live and not b.live, 240, "both episodes ended")
    page.get_by_role("tab", name="Comparison").click()
    page.get_by_text("Side by side").first.wait_for()
    caption_a = browser_support.poll(lambda: text_of(page, ".gsmn-camera-a-caption"), lambda t: "episode" in t,
                                     "the blue camera's caption")
    caption_b = text_of(page, ".gsmn-camera-b-caption")
    assert f"episode {a.id}" in caption_a and "model gsmn" in caption_a
    assert f"episode {b.id}" in caption_b and "model other" in caption_b
    title = text_of(page, ".gsmn-partner-title")
    assert title.startswith("Magenta's maps") and f"episode {b.id}" in title and "model other" in title
    assert "step" in title
    summary = page.get_by_text("model other").count()
    assert summary >= 2, "the table and the captions name the second checkpoint"
    # the second set of maps reads the semantic map as the first does: this world's landmarks named, the rest one
    # "other classes" entry (found in the walk-through: a legend of landmarks the world lacks)
    assert "not in this world" in viewer.compare.partner_maps.content
    # item 10: the other drone's frustum is made once and moved, never drawn anew (a new node shows at the origin)
    nodes = viewer.compare.partner_nodes
    assert nodes is not None
    for step in (0, len(b.steps) - 1):
        viewer._events.put(CursorMoved(step))
        browser_support.until(lambda step=step: viewer.view.cursor == step, 30, f"step {step} shown")
        frustum = viewer.compare.partner_nodes[0]
        browser_support.until(lambda step=step, frustum=frustum: np.allclose(
            frustum.position, b.steps[step].T_world_camera[:3, 3]), 30, "the frustum moved to the step")
        assert viewer.compare.partner_nodes is nodes


def test_a_refused_run_says_which_episode_is_still_shown(dashboard, page):
    viewer = dashboard.viewer
    page.get_by_role("tab", name="Camera and maps").click()
    shown = viewer.view.episode
    assert shown is not None
    field(page, "Instruction").fill("go to the left side of the unicorn")
    page.get_by_role("button", name="Run", exact=True).click()
    status = browser_support.poll(lambda: viewer.status.content, lambda s: "Not started" in s, "the refusal")
    assert f"Still shown: episode {shown.id}" in status
    assert not viewer.compare.note.content.startswith("Showing") or viewer.compare.partner_of(shown) is not None


def test_a_first_person_baseline_is_offered_where_it_can_be_used_and_said_where_not(dashboard, page):
    """Issue 77, item 11: GS-FPV, listed by GET /api/checkpoints, is in the Failures tab's evaluation menu and the
    Fine-tune tab's; the live view's Policy menu leaves it out and its hint says why; the API says which fly live."""
    viewer, jobs = dashboard.viewer, dashboard.jobs_view
    assert not any("fpv" in o for o in viewer.policy.options)
    assert "Not flown here: fpv" in viewer.policy.hint and "build no map" in viewer.policy.hint
    assert "Model: fpv" in jobs.eval_checkpoint.options and "Model: fpv" in jobs.run_checkpoint.options
    page.get_by_role("tab", name="Failures").click()
    field(page, "Checkpoint").first.click()
    assert page.get_by_role("option", name="Model: fpv", exact=True).count() == 1
    page.keyboard.press("Escape")
    listed = {c["name"]: c for c in httpx.get(f"{dashboard.urls.api}/api/checkpoints", timeout=30).json()}
    assert listed["fpv"]["kind"] == "gs-fpv" and listed["fpv"]["live"] is False and listed["other"]["live"] is True


def test_a_world_map_clicked_reads_its_cell_as_the_field_does(dashboard, page):
    """Issue 77, item 6: clicking a world map panel reads the cell under the pointer (its outline on the ground, the
    readout, and a notification, since the readout lies under the maps)."""
    viewer = dashboard.viewer
    page.get_by_role("tab", name="Camera and maps").click()
    if viewer.view.episode is None:  # run alone: an episode of its own
        page.get_by_role("button", name="Run", exact=True).click()
        browser_support.until(lambda: viewer.view.episode is not None and not viewer.view.episode.live, 240,
                              "an episode flown")
    assert viewer.view.episode.steps[-1].maps is not None
    box = page.locator('.gsmn-maps img[data-layer="semantic"]').locator("xpath=..")
    box.wait_for()
    size = box.bounding_box()
    box.click(position={"x": size["width"] * 0.25 + 1, "y": size["height"] * 0.75 + 1})
    n = dashboard.runner.config.model.map_size
    row, col = int(0.75 * n), int(0.25 * n)
    text = browser_support.poll(lambda: viewer.inspector.content, lambda t: f"Cell ({row}, {col})" in t,
                                "the clicked cell's readout")
    assert "perception" in text
    # item 16: the terms of art carry their gloss as a tooltip, in the maps' legends and the readout
    assert page.locator('.gsmn-maps span[title^="how likely a map cell holds"]').count() >= 1
    assert 'title="how likely a map cell' in text
    page.get_by_text(re.compile(rf"Cell \({row}, {col}\)")).first.wait_for()  # the notification, in view
    assert viewer.view.inspected is not None
    assert not page.get_by_text("gsmn-cell", exact=True).is_visible(), "the field the click script types into is hidden"
    # another world: the reading of this one goes with it (found in the walk-through: a stale "truly there")
    shown = viewer.scene.world.env_id
    field(page, "Environment id").fill("181" if shown != 181 else "174")
    browser_support.until(lambda: viewer.scene.world.env_id != shown, 60, "another world shown")
    browser_support.until(lambda: viewer.inspector.content == INSPECT_HINT and viewer.view.inspected is None, 30,
                          "the cell reading cleared")


def test_a_goal_drawn_says_when_it_is_not_the_typed_instructions(dashboard, page):
    """Issue 77 (the typist): while the typed text cannot be flown, or names another instruction, the goal drawn (the
    world's own instruction's, or the shown episode's) is labelled as not the typed one; cleared, it is "goal"."""
    viewer = dashboard.viewer
    page.get_by_role("tab", name="Camera and maps").click()
    browser_support.until(lambda: viewer.scene.task is not None, 60, "a goal drawn")
    drawn = viewer.scene.task
    box = field(page, "Instruction")
    box.fill("go to the left side of the unicorn")
    browser_support.until(lambda: viewer.scene.goal_label == "goal (not of the typed text)", 30, "the label changed")
    box.fill(drawn.text)
    browser_support.until(lambda: viewer.scene.goal_label == "goal", 30, "the goal's own label for its instruction")
    box.fill("")
    browser_support.until(lambda: viewer.scene.goal_label == "goal", 30, "the plain label with nothing typed")
