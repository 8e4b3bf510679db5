"""In headless Chromium, with three tabs on one dashboard: every tab has its own view.

Tab B opens an old episode by its link and scrubs it while tab A shows another world and flies a new episode:
neither's timeline, episode or world moves the other's, B is told that an episode flies elsewhere, and tab C (once
its "Show episodes started elsewhere" is ticked: a new tab starts unticked, on its own) watches A's. C showing a
world mid-flight ends nobody's episode and moves nobody else, and its "Watch episode N" goes back to it, even when
the click reaches the tab only after N landed. The pace, set in code or chosen in one tab, shows in every tab's Speed
box. A tab that closes leaves the runner's listeners."""

from __future__ import annotations

import time

import browser_support
import pytest
from browser_support import until

from app.browser import field
from app.live.commands import Resume, SetSpeed, StartEpisode
from app.page.controls import speed_choice
from app.page.events import WatchLive

pytestmark = pytest.mark.browser


@pytest.fixture(scope="module")
def dashboard(tmp_path_factory):
    with browser_support.dashboard(tmp_path_factory, 60) as d:
        old = d.runner.call(StartEpisode(71, None, "model", None))  # over the API: an episode to replay
        until(lambda: not old.live, what="the old episode to end", timeout=120)
        d.keeper.flush()
        d.old = old
        yield d


@pytest.fixture(scope="module")
def browser(dashboard):
    with browser_support.chromium() as browser:
        yield browser


def shown(page) -> dict:
    """The episode and step a tab's map panel shows, and its environment box."""
    return page.evaluate("""() => {
        const m = document.querySelector('.gsmn-maps');
        return {episode: m && m.dataset.episode ? +m.dataset.episode : null,
                step: m && m.dataset.step ? +m.dataset.step : null};
    }""")


def test_each_tab_has_its_own_timeline_episode_and_world(dashboard, browser):
    old = dashboard.old
    context = browser.new_context(viewport={"width": 1400, "height": 900})
    base = dashboard.urls.page
    pages = {}
    for count, (name, query) in enumerate((("a", ""), ("b", f"/?episode={old.id}&step=3"), ("c", "")), start=1):
        page = context.new_page()
        page.set_default_timeout(60_000)
        page.goto(base + query)
        until(lambda count=count: len(dashboard.tabs) == count, what=f"tab {name} to connect")
        pages[name] = page
    a, b, c = pages["a"], pages["b"], pages["c"]
    tab_a, tab_b, tab_c = list(dashboard.tabs.values())  # in the order they connected
    until(lambda: shown(b) == {"episode": old.id, "step": 3}, what="tab B on the old episode at step 3")
    assert not tab_b.viewer.watch_others.value  # opening a kept episode keeps the tab on it
    assert not tab_a.viewer.watch_others.value and not tab_c.viewer.watch_others.value  # a new tab: its own
    field(c, "Show episodes started elsewhere").check()  # C follows the others' episodes
    until(lambda: tab_c.viewer.watch_others.value, what="C's box ticked")

    # A shows another world: B's world and episode stay
    box = field(a, "Environment id")
    box.fill("75")
    box.press("Enter")
    a.get_by_role("button", name="Show", exact=True).click()
    a.get_by_text("Environment 75").first.wait_for()
    assert tab_a.viewer.scene.world.env_id == 75
    assert tab_b.viewer.scene.world.env_id == 71 and shown(b) == {"episode": old.id, "step": 3}
    assert field(b, "Environment id").input_value() == "71"

    # A flies a new episode with the expert (an untrained model may stop at once), slowly enough for the steps
    # below to happen while it flies, on a busy machine too (the simulator's speed is shared: set here)
    field(a, "Policy").click()
    a.get_by_role("option", name="Expert (oracle)", exact=True).click()
    dashboard.runner.call(SetSpeed(1.2))
    try:
        for page in (a, b, c):  # the pace is the simulator's: every tab's Speed box shows it, even one set in code
            until(lambda page=page: field(page, "Speed").input_value() == speed_choice(1.2), what="the pace shown")
        a.get_by_role("button", name="Run", exact=True).click()
        new = until(lambda: shown(a)["episode"] not in (None, old.id) and shown(a),
                    what="A's new episode")["episode"]
        episode = dashboard.runner.episodes.get(new)
        assert episode.origin == tab_a.viewer.origin and episode.env_id == 75
        until(lambda: shown(c)["episode"] == new, what="tab C watching A's episode")
        b.get_by_text("is flying, started in another tab").first.wait_for()

        # B scrubs its old episode while A's flies: B moves, A follows its live step
        b.get_by_role("slider").first.focus()
        for _ in range(4):
            b.keyboard.press("ArrowRight")
        until(lambda: shown(b) == {"episode": old.id, "step": 7}, what="B scrubbed to step 7")
        assert episode.live, "the new episode ended before B scrubbed: the test's timing is off"
        before = shown(a)["step"]
        until(lambda: shown(a)["episode"] == new and shown(a)["step"] > before, what="A's live steps going on")
        assert tab_a.viewer.view.follow and tab_a.viewer.view.episode is episode

        # C shows another world while A's episode flies (a second simulator renders it): A's episode flies on, A
        # still shows it, and C can go back to it
        box = field(c, "Environment id")
        box.fill("72")
        box.press("Enter")
        c.get_by_role("button", name="Show", exact=True).click()
        c.get_by_text("Environment 72").first.wait_for()
        assert tab_c.viewer.scene.world.env_id == 72 and tab_c.viewer.view.episode is None
        assert episode.status != "cancelled", "showing a world ended the flying episode"
        assert episode.live, "the new episode ended before C showed its world: the test's timing is off"
        assert tab_a.viewer.view.episode is episode
        assert shown(a)["episode"] == new and tab_a.viewer.scene.world.env_id == 75
        c.get_by_role("button", name=f"Watch episode {new}").click()
        until(lambda: shown(c)["episode"] == new, what="C back on A's episode")
        until(lambda: not episode.live, what="the new episode to end", timeout=120)
    finally:
        dashboard.runner.call(SetSpeed(None))
    last = len(episode.steps) - 1
    until(lambda: shown(a) == {"episode": new, "step": last}, what="A at its episode's last step")
    assert shown(b) == {"episode": old.id, "step": 7}  # B never moved
    assert tab_b.viewer.scene.world.env_id == 71 and tab_a.viewer.scene.world.env_id == 75
    until(lambda: b.get_by_text("is flying, started in another tab").count() == 0
          or not b.get_by_text("is flying, started in another tab").first.is_visible(), what="B's note to go")

    # and A scrubbing back leaves B where it is
    browser_support.scrub_home_until(a, shown, lambda s: s == {"episode": new, "step": 0}, "A back at step 0")
    time.sleep(0.5)
    assert shown(b) == {"episode": old.id, "step": 7}

    # a pace chosen in one tab shows in the others
    field(c, "Speed").click()
    c.get_by_role("option", name="slow (2 steps/s)", exact=True).click()
    until(lambda: dashboard.runner.speed == 2.0, what="C's pace reaching the simulator")
    for page in (a, b):
        until(lambda page=page: field(page, "Speed").input_value() == "slow (2 steps/s)",
              what="the other tabs' Speed boxes following C's")
    dashboard.runner.call(SetSpeed(None))
    until(lambda: field(b, "Speed").input_value() == "as fast as it goes", what="B's Speed box following SetSpeed")

    # a tab that goes leaves nothing behind
    viewer_c = tab_c.viewer
    c.close()
    until(lambda: len(dashboard.tabs) == 2, what="tab C to be dropped")
    parts = (viewer_c, tab_c.episodes_view, tab_c.jobs_view)
    until(lambda: not any(part in dashboard.runner.listeners for part in parts), what="tab C's listeners to go",
          timeout=15)
    until(lambda: not viewer_c.thread.is_alive(), what="tab C's UI thread to end", timeout=15)
    assert len([x for x in dashboard.runner.listeners if x in (tab_a.viewer, tab_b.viewer)]) == 2
    context.close()


def test_watch_episode_pressed_as_it_lands_shows_it_landed(dashboard, browser):
    """"Watch episode N" pressed while N flies elsewhere, the click reaching the tab only after N landed (on a busy
    machine the tab's queue lags; the button is gone by then): the tab shows N at its last step, with its result,
    where it used to do nothing."""
    before = set(dashboard.tabs)
    context = browser.new_context(viewport={"width": 1400, "height": 900})
    page = context.new_page()
    page.set_default_timeout(60_000)
    page.goto(dashboard.urls.page)
    tab = until(lambda: next((t for k, t in dashboard.tabs.items() if k not in before), None), what="the tab")
    episode = dashboard.runner.call(StartEpisode(72, None, "expert", None, paused=True))  # over the API
    button = page.get_by_role("button", name=f"Watch episode {episode.id}")
    button.wait_for()
    dashboard.runner.call(Resume())
    until(lambda: not episode.live, what="the episode to land", timeout=120)
    button.wait_for(state="hidden")
    tab.viewer._events.put(WatchLive())  # the click that was on its way
    last = len(episode.steps) - 1
    until(lambda: shown(page) == {"episode": episode.id, "step": last}, what="the landed episode at its last step")
    page.get_by_text(f"Episode {episode.id} (finished)").first.wait_for()
    context.close()
