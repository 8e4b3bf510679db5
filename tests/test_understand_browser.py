"""Typing in people's words, in headless Chromium (gsmn/task/understand.py in the page): the understood template is
shown as one types, several kinds that fit are offered as chips, a refusal says why and what to try, and the episode
flown keeps the text typed beside the template (in the page's record and over the API).

The tiny preset and an untrained checkpoint, as the other browser tests; it fails, not skips, without a Chromium.
"""

from __future__ import annotations

import json
import urllib.request

import browser_support
import pytest
from browser_support import until

from app.browser import field

pytestmark = pytest.mark.browser

HORIZON = 12
ENV = 172  # a christmas tree and a fir tree, a lighthouse, a satellite dish (and no house)


@pytest.fixture(scope="module")
def dashboard(tmp_path_factory):
    with browser_support.dashboard(tmp_path_factory, HORIZON, env_id=ENV) as d:
        yield d


@pytest.fixture(scope="module")
def page(dashboard):
    with browser_support.page_on(dashboard, 1280, 800) as page:
        yield page


def type_instruction(page, text: str) -> None:
    box = field(page, "Instruction")
    box.fill("")
    box.type(text)
    box.press("Enter")


def test_three_everyday_phrasings_understood_as_typed_and_one_flown(dashboard, page):
    browser_support.poll(field(page, "Instruction").input_value, lambda t: t != "", "the world's own instruction")

    type_instruction(page, "please fly behind the lighthous")  # a verb, politeness, a slip, "behind"
    page.get_by_text("go to the back side of the lighthouse").first.wait_for()
    page.get_by_text("Understood as").first.wait_for()

    type_instruction(page, "land in front of the big tree")  # two kinds of tree here: chips, not a guess
    page.get_by_text("Pick one").first.wait_for()
    until(lambda: dashboard.viewer.run_button.color == "gray", what="a grey Run while nothing can be flown")
    for kind in ("christmas tree", "fir tree"):
        page.get_by_role("button", name=kind, exact=True).wait_for()
    page.get_by_role("button", name="fir tree", exact=True).click()
    until(lambda: field(page, "Instruction").input_value() == "go to the front side of the fir tree",
          what="the chip's template, the side kept")

    type_instruction(page, "go to the house")  # no side, and no house here: refused, with what to try
    page.get_by_text("there is no house in this world").first.wait_for()
    page.get_by_text('Try: "go to the left side of the lighthouse"').first.wait_for()  # the nearest name first

    typed = "the satellite's left-hand side"
    type_instruction(page, typed)
    page.get_by_text("go to the left side of the satellite dish").first.wait_for()
    until(lambda: dashboard.viewer.run_button.color == "green", what="a green Run")
    page.get_by_role("button", name="Run", exact=True).click()
    episode = until(lambda: next((e for e in dashboard.runner.episodes.all() if e.typed == typed), None),
                    what="the episode flown")
    assert episode.instruction == "go to the left side of the satellite dish"
    until(lambda: not episode.live, what="the episode's end", timeout=120)
    with urllib.request.urlopen(f"{dashboard.urls.api}/api/episodes/{episode.id}") as answer:
        shown = json.loads(answer.read())
    assert (shown["typed_instruction"], shown["instruction"]) == (typed, episode.instruction)
