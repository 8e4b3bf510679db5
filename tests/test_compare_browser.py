"""End to end in headless Chromium: two checkpoints flown side by side and scrubbed step by step with both views
changing; a fork from step t with another instruction that flies to another landmark; the ground-truth layers
toggled with their figures shown (app.page.compare_view).

Needs the `playwright` package and a Chromium, as tests/test_dashboard_browser.py.
"""

from __future__ import annotations

import browser_support
import pytest

from app.browser import field
from app.live.fixtures import make_untrained_checkpoint

pytestmark = pytest.mark.browser

HORIZON = 40


@pytest.fixture(scope="module")
def dashboard(tmp_path_factory):
    root = tmp_path_factory.mktemp("checkpoints")
    folder = make_untrained_checkpoint(root / "gsmn")
    make_untrained_checkpoint(root / "other", seed=1)  # a second checkpoint: another policy to compare with
    with browser_support.dashboard(tmp_path_factory, HORIZON, checkpoint=folder, checkpoints_root=root) as d:
        yield d


@pytest.fixture(scope="module")
def page(dashboard):
    with browser_support.page_on(dashboard, 1500, 950) as page:
        yield page


def choose(page, label: str, option: str) -> None:
    field(page, label).click()
    page.get_by_role("option", name=option, exact=True).click()


def state(page) -> dict:
    return page.evaluate("""() => {
        const get = (s) => document.querySelector(s);
        const a = get('.gsmn-maps'), b = get('.gsmn-maps-partner');
        return {step: a ? a.dataset.step : null, goal: get('.gsmn-maps img[data-layer="goal"]')?.src ?? null,
                partner_step: b ? b.dataset.step : null,
                partner_goal: get('.gsmn-maps-partner img[data-layer="goal"]')?.src ?? null,
                camera_a: get('img.gsmn-camera-a')?.src ?? null, camera_b: get('img.gsmn-camera-b')?.src ?? null,
                truth: [...document.querySelectorAll('.gsmn-truth img')].map(i => i.dataset.layer),
                figures: [...document.querySelectorAll('.gsmn-truth .gsmn-figure')].map(f => f.innerText)};
    }""")


def wait_for(page, predicate, what: str, timeout: float = 60.0) -> dict:
    return browser_support.poll(lambda: state(page), predicate, what, timeout)


def wait_runner(condition, timeout: float = 240.0) -> None:
    browser_support.until(condition, timeout, "the runner")


def newest(before: set[int], dashboard):
    wait_runner(lambda: {e.id for e in dashboard.runner.episodes.all()} - before)
    return dashboard.runner.episodes.get(max({e.id for e in dashboard.runner.episodes.all()} - before))


def scrub_home(page) -> None:
    """Scrub to step 0 (the runner ends an episode before the tab has drawn its last steps)."""
    browser_support.scrub_home_until(page, state, lambda s: s["step"] == "0", "the cursor at step 0")


def test_two_checkpoints_side_by_side_scrubbed_step_by_step(dashboard, page):
    page.get_by_text("Compare and fork").first.click()
    other = next(o for o in dashboard.viewer.compare.other.options if o.startswith("Model: other"))
    choose(page, "Compare with", other)
    before = set(dashboard.runner.pairs.store)
    page.get_by_role("button", name="Run both", exact=True).click()
    wait_runner(lambda: set(dashboard.runner.pairs.store) - before)
    comparison = dashboard.runner.comparison(max(set(dashboard.runner.pairs.store) - before))
    a, b = comparison.episodes
    assert a.checkpoint != b.checkpoint
    wait_runner(lambda: not a.live and not b.live)
    page.get_by_role("tab", name="Comparison").click()
    page.get_by_text("Side by side").first.wait_for()
    scrub_home(page)
    s = wait_for(page, lambda s: s["step"] == "0" and s["partner_step"] == "0", "both views at step 0")
    for step in range(1, 5):  # one slider scrubs both: every view of both episodes moves with it
        page.keyboard.press("ArrowRight")
        t = wait_for(page, lambda s, step=step: s["step"] == str(step) and s["partner_step"] == str(step),
                     f"both views at step {step}")
        for key in ("goal", "partner_goal", "camera_a", "camera_b"):
            assert t[key] and t[key] != s[key], f"{key} did not change at step {step}"
        s = t
    assert dashboard.viewer.compare.partner_drawn
    page.get_by_text(f"episode {b.id}").first.wait_for()  # both results side by side
    assert page.get_by_text("They part at step").count() + page.get_by_text("They have not parted").count() >= 1
    part = comparison.diverged_at()
    if part is not None and 0 < part < len(a.steps) - 1:
        page.get_by_text("parted", exact=True).first.wait_for()  # the timeline marks the parting step


def test_a_fork_with_another_instruction_flies_to_another_landmark(dashboard, page):
    choose(page, "Policy", "Expert (oracle)")
    field(page, "Instruction").fill("")
    before = {e.id for e in dashboard.runner.episodes.all()}
    page.get_by_role("button", name="Run", exact=True).click()
    original = newest(before, dashboard)
    wait_runner(lambda: not original.live)
    world = original.task.world
    t = 4
    scrub_home(page)
    for _ in range(t):
        page.keyboard.press("ArrowRight")
    wait_for(page, lambda s: s["step"] == str(t), f"the cursor at step {t}")
    from gsmn.task.understand import parse_instruction

    here = original.steps[t].position[:2]
    others = [lm for lm in world.landmarks if lm.noun_phrase != original.task.instruction.noun_phrase
              and len(world.landmarks_named(lm.noun_phrase)) == 1]
    other = min(others, key=lambda lm: (lm.x - here[0]) ** 2 + (lm.y - here[1]) ** 2)
    text = next(x for x in (f"go to the {side} side of the {other.noun_phrase}" for side in ("left", "right", "front",
                                                                                             "back"))
                if world.on_field(parse_instruction(x, world).goal))
    field(page, "Fork instruction").fill(text)
    field(page, "Fork instruction").press("Enter")
    before = {e.id for e in dashboard.runner.episodes.all()}
    page.get_by_role("button", name="Fork here", exact=True).click()
    fork = newest(before, dashboard)
    wait_runner(lambda: not fork.live)
    assert fork.fork.episode_id == original.id and fork.fork.step == t and fork.instruction == text
    assert fork.steps[:t] == original.steps[:t]
    assert fork.result.landmark_success, "the fork flies to the other landmark"
    page.get_by_role("tab", name="Comparison").click()
    page.get_by_text(f"Fork of episode {original.id} at step {t}").first.wait_for()


def test_truth_layers_toggled_with_their_figures(dashboard, page):
    page.get_by_role("tab", name="Camera and maps").click()
    assert state(page)["truth"] == []
    page.get_by_text("Truth beside the maps").first.click()
    s = wait_for(page, lambda s: len(s["truth"]) == 3, "the truth panels")
    assert s["truth"] == ["truth_semantic", "truth_relevance", "truth_goal"]
    # each beside its model map, in the same row (issue 77, item 7), not all under the maps
    boxes = page.evaluate("""() => Object.fromEntries([...document.querySelectorAll('.gsmn-maps img')].map(
        i => [i.dataset.layer, i.getBoundingClientRect().toJSON()]))""")
    for name in ("semantic", "relevance", "goal"):
        model, truth = boxes[name], boxes["truth_" + name]
        rows_overlap = truth["top"] < model["bottom"] and truth["bottom"] > model["top"]  # titles may wrap apart
        assert rows_overlap and truth["left"] > model["right"] - 1, (name, model, truth)
    assert s["figures"][0].startswith("perception") and s["figures"][1].startswith("relevance AUC")
    assert any(ch.isdigit() for ch in s["figures"][1])
    episode = dashboard.viewer.view.episode
    plot = dashboard.viewer.compare.figures_plot.data
    assert len(plot) == 5 and len(plot[0]) == len(episode.steps)  # the figures over the episode beside P(stop)
    page.get_by_text("Truth beside the maps").first.click()
    wait_for(page, lambda s: s["truth"] == [], "the truth panels gone")
