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


def test_a_landmark_picked_in_the_3d_view_is_removed_or_moved_and_the_edited_world_flies(tmp_path_factory):
    """"Pick to edit": the box clicked in the 3D view and removed, the pumpkin clicked and then the ground where it
    goes: the World edits box holds both edits in words, and Run flies that world with the pumpkin where the ground
    was clicked."""
    from test_page_newcomer import screen_point

    with browser_support.dashboard(tmp_path_factory, 20, env_id=70) as d, \
            browser_support.page_on(d, 1500, 1000) as page:
        world = task_for_env(70, preset("tiny")).world
        browser_support.choose(page, "Policy", EXPERT_CHOICE)
        page.get_by_text("Pick to edit").first.click()
        page.get_by_text("Click a landmark in the 3D view.").first.wait_for()
        left, top, width, height = page.evaluate("""() => { const c = [...document.querySelectorAll('canvas')]
            .sort((a, b) => b.width - a.width)[0].getBoundingClientRect();
            return [c.left, c.top, c.width, c.height]; }""")

        def click(point) -> None:
            x, y = screen_point(point, width, height)
            page.mouse.click(left + x, top + y)

        box, pumpkin = (next(lm for lm in world.landmarks if lm.noun_phrase == name) for name in ("box", "pumpkin"))
        click((box.x, box.y, 0.8))
        page.get_by_text("Picked box").first.wait_for()
        page.get_by_role("button", name="Remove", exact=True).click()
        browser_support.until(lambda: field(page, "World edits").input_value() == "remove box", what="the remove")
        click((pumpkin.x, pumpkin.y, 0.5))
        page.get_by_text("Picked pumpkin").first.wait_for()
        click((12.0, 12.0, 0.0))
        browser_support.until(lambda: field(page, "World edits").input_value().startswith("remove box; move pumpkin"),
                              what="the move")
        page.get_by_role("button", name="Run", exact=True).click()
        page.get_by_text("world edited").first.wait_for(timeout=120_000)
        (episode,) = d.runner.episodes.all()
        remove, move = episode.world_edits
        assert (remove.op, remove.landmark, move.op, move.landmark) == ("remove", 4, "move", 2)
        assert abs(move.x - 12.0) < 0.3 and abs(move.y - 12.0) < 0.3, move
        moved = next(lm for lm in episode.task.world.landmarks if lm.noun_phrase == "pumpkin")
        assert (round(moved.x, 1), round(moved.y, 1)) == (move.x, move.y)
