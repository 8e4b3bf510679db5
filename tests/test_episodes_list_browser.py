"""In headless Chromium, the Episodes tab and a fresh tab as new users meet them (issue 77, items 5 and 17).

The Episodes list names who flew each episode (the checkpoint, as a mirror ensemble, the expert), marks a fork and
a comparison's side, draws a success green, a failure red and a cancelled one grey with no text cut off, says how it
ended in the words and number of its result line, offers each checkpoint flown under "Flown by", and counts what
it shows as the storage line under it counts the kept episodes. A fresh tab starts on the server's world with "Show
episodes started elsewhere" unticked: not on the world another tab showed last, and not jumping to another tab's
run.

Worlds here are ones no other test uses (203, 211, 217, 226)."""

from __future__ import annotations

import re

import browser_support
import pytest
from browser_support import until

from app.browser import field
from app.live.commands import CancelEpisode, SetSpeed, StartEpisode
from app.live.compare import ForkEpisode, PolicySpec, StartComparison
from app.live.fixtures import make_untrained_checkpoint

pytestmark = pytest.mark.browser
HORIZON = 70  # the expert stops in world 226 after 65 steps; the untrained model flies to the horizon
SERVER_WORLD = 203


def flown(runner, command):
    """Fly a command's episode (or comparison) to its end."""
    made = runner.call(command)
    episodes = made.episodes if hasattr(made, "episodes") else (made,)
    until(lambda: not any(e.live for e in episodes), what=f"{command} to end", timeout=300)
    return made


@pytest.fixture(scope="module")
def dashboard(tmp_path_factory, untrained_checkpoint):
    root = tmp_path_factory.mktemp("offered")
    make_untrained_checkpoint(root / "other", seed=3)  # a second checkpoint, offered by the name "other"
    with browser_support.dashboard(tmp_path_factory, HORIZON, checkpoint=untrained_checkpoint,
                                   checkpoints_root=root, env_id=SERVER_WORLD) as d:
        r = d.runner
        d.model = flown(r, StartEpisode(217, None, "model", None))  # to the horizon: a failure
        d.expert = flown(r, StartEpisode(226, None, "expert", None))  # says STOP at the goal: a success
        d.fork = flown(r, ForkEpisode(d.model.id, 60, checkpoint="other"))
        d.pair = flown(r, StartComparison(203, None, [PolicySpec("expert"), PolicySpec("mirror")])).episodes
        cancelled = r.call(StartEpisode(226, None, "model", None, paused=True))
        r.call(CancelEpisode(cancelled.id))
        until(lambda: not cancelled.live, what="the cancelled episode to end")
        d.cancelled = cancelled
        d.keeper.flush()
        yield d


@pytest.fixture(scope="module")
def browser(dashboard):
    with browser_support.chromium() as browser:
        yield browser


def rows(page) -> dict[int, dict]:
    """The Episodes tab's row buttons by episode id: their text, background colour, and whether any text is cut
    off (the label wider or taller than its box)."""
    found = page.evaluate("""() => [...document.querySelectorAll('button')]
        .filter(b => /^#\\d+ · /.test(b.innerText.trim()) && b.offsetParent !== null)
        .map(b => {const l = b.querySelector('.mantine-Button-label') || b;
                   return {text: b.innerText.replace(/\\s+/g, ' ').trim(), color: getComputedStyle(b).backgroundColor,
                           cut: l.scrollWidth > l.clientWidth + 1 || l.scrollHeight > l.clientHeight + 1
                                || b.scrollWidth > b.clientWidth + 1}})""")
    return {int(re.match(r"#(\d+)", r["text"]).group(1)): r for r in found}


def body_text(page) -> str:
    return re.sub(r"\s+", " ", page.evaluate("() => document.body.innerText"))


def test_each_row_says_who_flew_it_how_it_ended_and_where_it_comes_from(dashboard, browser, tmp_path):
    page = browser.new_page(viewport={"width": 1500, "height": 1000})
    page.set_default_timeout(60_000)
    page.goto(dashboard.urls.page)
    page.get_by_role("tab", name="Episodes").click()
    model, expert, fork, (side_1, side_2), cancelled = (dashboard.model, dashboard.expert, dashboard.fork,
                                                        dashboard.pair, dashboard.cancelled)
    shown = browser_support.poll(lambda: rows(page), lambda r: len(r) == 6, "the six kept episodes listed")
    page.screenshot(path=str(tmp_path / "episodes.png"))
    assert not [r["text"] for r in shown.values() if r["cut"]], "a row's text is cut off"
    for episode in (model, expert, fork, side_1, side_2, cancelled):
        assert episode.instruction in shown[episode.id]["text"]

    assert "· model gsmn ·" in shown[model.id]["text"]
    assert "· expert ·" in shown[expert.id]["text"]
    assert f"· model other · fork of #{model.id} at step 60 ·" in shown[fork.id]["text"]
    assert f"· expert · side 1 of a comparison with #{side_2.id} ·" in shown[side_1.id]["text"]
    assert f"· model gsmn, mirror ensemble · side 2 of a comparison with #{side_1.id} ·" in shown[side_2.id]["text"]

    # how it ended, as its result line counts it: the actions flown, not the steps recorded (one more)
    assert expert.result.success and expert.result.stopped and not model.result.success
    assert "· success · " in shown[expert.id]["text"] and "· failure · " in shown[model.id]["text"]
    assert f"said STOP after {expert.result.steps} steps" in shown[expert.id]["text"]
    assert f"ran out of steps after {HORIZON} steps" in shown[model.id]["text"]
    assert "· cancelled · " in shown[cancelled.id]["text"]

    # a success, a failure and a cancelled one look different
    colours = {shown[e.id]["color"] for e in (expert, model, cancelled)}
    assert len(colours) == 3, colours

    # the list's count and the storage line's agree
    text = body_text(page)
    assert "6 of 6 kept episodes shown." in text and "6 kept, 0 pinned" in text

    # the replayed episode's result line says the same as its row
    page.get_by_role("button", name=re.compile(rf"^#{expert.id} · ")).click()
    until(lambda: dashboard.viewer.view.episode is not None and dashboard.viewer.view.episode.id == expert.id,
          what="the expert's episode replayed")
    said = f"said STOP after {expert.result.steps} steps"
    browser_support.poll(lambda: body_text(page), lambda t: t.count(said) == 2, "the row and the result line alike")
    page.close()


def test_the_policy_filter_offers_each_checkpoint_flown(dashboard, browser):
    page = browser.new_page(viewport={"width": 1500, "height": 1000})
    page.set_default_timeout(60_000)
    page.goto(dashboard.urls.page)
    page.get_by_role("tab", name="Episodes").click()
    browser_support.poll(lambda: rows(page), lambda r: len(r) == 6, "the six kept episodes listed")
    view = dashboard.tab().episodes_view
    assert set(view.search_policy.options) == {"any policy", "model gsmn", "model other", "expert",
                                               "model gsmn, mirror ensemble"}
    field(page, "Flown by").click()
    page.get_by_role("option", name="model other", exact=True).click()
    browser_support.poll(lambda: rows(page), lambda r: set(r) == {dashboard.fork.id}, "only the fork listed")
    text = body_text(page)
    assert "1 of 6 kept episodes shown: 1 matches the search." in text and "6 kept, 0 pinned" in text
    field(page, "Flown by").click()
    page.get_by_role("option", name="expert", exact=True).click()
    expert_flown = {dashboard.expert.id, dashboard.pair[0].id}
    browser_support.poll(lambda: rows(page), lambda r: set(r) == expert_flown, "the expert's two episodes")
    page.close()


def test_a_fresh_tab_starts_on_its_own(dashboard, browser):
    """Tab A shows world 226 and flies there; B, opened after A's world, and C, opened while A's episode flies, start
    on the server's world with the box unticked, stay there, and say that an episode flies elsewhere."""
    context = browser.new_context(viewport={"width": 1400, "height": 900})

    def open_tab(name: str):
        known = set(dashboard.tabs)
        page = context.new_page()
        page.set_default_timeout(60_000)
        page.goto(dashboard.urls.page)
        page.get_by_role("button", name="Run", exact=True).wait_for()
        (tab_id,) = until(lambda: tuple(set(dashboard.tabs) - known), what=f"tab {name} to connect")
        return page, dashboard.tabs[tab_id].viewer

    a, viewer_a = open_tab("a")
    field(a, "Environment id").fill("226")
    until(lambda: viewer_a.world_shown is not None and viewer_a.world_shown.world.env_id == 226, 60, "A on 226")
    b, viewer_b = open_tab("b")
    until(lambda: viewer_b.world_shown is not None, 60, "B's first world")
    assert viewer_b.world_shown.world.env_id == SERVER_WORLD, "a fresh tab opened on another tab's world"
    assert field(b, "Environment id").input_value() == str(SERVER_WORLD)
    assert not viewer_b.watch_others.value and not field(b, "Show episodes started elsewhere").is_checked()

    field(a, "Policy").click()
    a.get_by_role("option", name="Expert (oracle)", exact=True).click()
    dashboard.runner.call(SetSpeed(5.0))  # slow enough for C to open while it flies
    try:
        a.get_by_role("button", name="Run", exact=True).click()
        until(lambda: viewer_a.view.episode is not None and viewer_a.view.episode.live, what="A's episode")
        episode = viewer_a.view.episode
        c, viewer_c = open_tab("c")
        for page, viewer in ((b, viewer_b), (c, viewer_c)):
            page.get_by_text(f"Episode {episode.id} is flying, started in another tab").first.wait_for()
            assert viewer.view.episode is None and viewer.world_shown.world.env_id == SERVER_WORLD
            assert not viewer.watch_others.value
        assert episode.live, "A's episode ended before C opened: the test's timing is off"
    finally:
        dashboard.runner.call(SetSpeed(None))
    dashboard.runner.call(CancelEpisode(episode.id))
    until(lambda: not episode.live, what="A's episode to end")
    assert viewer_b.view.episode is None and viewer_c.view.episode is None  # neither jumped to it
    context.close()
