"""World edits from the page in headless Chromium: typed in the Episode panel's World edits box, the episode flies the
edited world (its summary lists the edits, the result panel says what was changed); an edit that cannot be read or
cannot stand is refused in the status, and nothing flies."""

from __future__ import annotations

import browser_support
import pytest

from app.browser import field
from app.page.controls import EXPERT_CHOICE
from gsmn.config import preset
from gsmn.task.edits import edited_task, edits_from_text
from gsmn.task.rollout import task_for_env

pytestmark = pytest.mark.browser


def test_typed_world_edits_fly_an_edited_world_and_bad_ones_are_refused(tmp_path_factory):
    with browser_support.dashboard(tmp_path_factory, 20) as d, browser_support.page_on(d, 1280, 800) as page:
        text = "remove box; move pumpkin to 16.8 14.5"
        task = task_for_env(70, preset("tiny"))
        expected = edited_task(task, edits_from_text(text, task.world), preset("tiny")).instruction
        browser_support.choose(page, "Policy", EXPERT_CHOICE)
        box = field(page, "World edits")
        box.fill(text)
        box.press("Enter")
        page.get_by_role("button", name="Run", exact=True).click()
        page.get_by_text("world edited").first.wait_for(timeout=120_000)
        (episode,) = d.runner.episodes.all()
        assert [e.to_dict() for e in episode.world_edits] == [e.to_dict() for e in edits_from_text(text, task.world)]
        assert episode.task.instruction == expected and episode.task.world != task.world
        page.get_by_text("removed landmark 4; moved landmark 2 to (16.8, 14.5)").first.wait_for()
        box.fill("move anvil to 3 4")
        box.press("Enter")
        page.get_by_role("button", name="Run", exact=True).click()
        page.get_by_text("no anvil in this world").first.wait_for()
        box.fill("move pumpkin to 29 29")
        box.press("Enter")
        page.get_by_role("button", name="Run", exact=True).click()
        page.get_by_text("would be off the field").first.wait_for()
        assert len(d.runner.episodes.all()) == 1, "nothing else flew"
