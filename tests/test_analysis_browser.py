"""End to end in headless Chromium: the Analysis tab on two shipped evaluations of the same environments (an
ablation against its control, as checkpoints/table2 ships them): pick both, analyse, read a slice, click a confusion
cell and land on exactly its episodes (the API's answer for that cell), then click one and see it fly again in the
live view, shown at the step it went wrong.

Real server, real SQLite record (the shipped files imported into it), real Chromium. The shipped evaluations are
hand-made files in a checkpoints folder of the test's own, beside the run's untrained checkpoint they name."""

from __future__ import annotations

import json
import re
import shutil

import browser_support
import httpx
import pytest
from support import compact_evaluation

from app.page.analysis_view import SHIPPED
from app.render.jobs_panels import evaluation_label
from gsmn.analysis import slices
from gsmn.config import preset
from gsmn.task.rollout import task_for_env

pytestmark = pytest.mark.browser

ENVS = tuple(range(85, 97))  # dev environments
WENT_WRONG = 3


def shipped_pair(root, checkpoint) -> None:
    """The control wins all but one; the ablation loses every third, ending at another landmark of its world, its
    facts (as the programme keeps them) saying it went wrong at step WENT_WRONG."""
    for name, won in (("gsmn", lambda e: e != 86), ("no-percept", lambda e: e % 3 != 0)):
        folder = root / "table2" / name
        shutil.copytree(checkpoint, folder, copy_function=shutil.copyfile)
        evaluation = compact_evaluation(ENVS, won, name)
        for ep in evaluation["episodes"]:
            if not ep["success"]:
                world = task_for_env(ep["env_id"], preset("tiny")).world
                other = next(lm for lm in world.landmarks if lm.noun_phrase != ep["noun_phrase"])
                ep["final_x"], ep["final_y"], ep["landmark_success"] = other.x + 0.5, other.y, False
        for ep, row in zip(evaluation["episodes"], slices.with_facts(evaluation), strict=True):
            ep["facts"] = row["facts"] | ({"went_wrong": WENT_WRONG} if not ep["success"] else {})
        (folder / "evaluation.json").write_text(json.dumps(evaluation))


@pytest.fixture(scope="module")
def dashboard(tmp_path_factory):
    root = tmp_path_factory.mktemp("shipped")
    shipped_pair(root, browser_support.untrained_checkpoint(tmp_path_factory))
    with browser_support.dashboard(tmp_path_factory, 20, checkpoints_root=root) as d:
        yield d


PICKED = """() => [...document.querySelectorAll('button')].filter(b => b.offsetParent !== null)
    .map(b => b.innerText.trim()).filter(t => t.startsWith('\u25b6 '))"""
MAPS = """() => { const m = document.querySelector('.gsmn-maps');
    return m ? {episode: m.dataset.episode, step: m.dataset.step === '' ? -1 : +m.dataset.step} : null; }"""


def test_analyse_an_ablation_against_its_control_and_open_a_confusion_cell(dashboard):
    with browser_support.page_on(dashboard, 1280, 800) as page:
        page.get_by_role("tab", name="Analysis").click()
        labels = {s["key"]: s["label"] for s in dashboard.jobs.analyses.shipped()}
        browser_support.choose(page, "Evaluation", SHIPPED + labels["table2/no-percept/dev"])
        browser_support.choose(page, "Against", SHIPPED + labels["table2/gsmn/dev"])
        page.get_by_role("button", name="Analyse", exact=True).click()
        page.get_by_text("8 successes (66.7 %)").first.wait_for()
        ablation, control = (e.id for e in dashboard.jobs.db.evaluations())  # imported in that order
        assert {e.source for e in dashboard.jobs.db.evaluations()} == {"import"}
        page.get_by_text("on the 12 environments both flew: 66.7 % against 91.7 %").first.wait_for()

        # a slice: its bar opens its episodes
        browser_support.choose(page, "Slice by", slices.ATTRIBUTES["stopped"])
        page.locator("[data-pick]").filter(has_text="another landmark").first.click()
        page.get_by_text("ended at: another landmark").first.wait_for()

        # a confusion cell off the diagonal: exactly its episodes, as the API answers for that cell
        browser_support.choose(page, "Matrix", "named -> stopped at (unambiguous)")
        analysis = httpx.get(f"{dashboard.urls.api}/api/evaluations/{ablation}/slices",
                             params={"versus": control}).json()
        asked, reads = next((a, r) for a, r in analysis["confusion"]["stopped_at"].items()
                            if any(k != a for k in r))
        read = next(k for k in reads if k != asked)
        expected = httpx.get(f"{dashboard.urls.api}/api/evaluations/{ablation}/slices/episodes",
                             params={"matrix": "stopped_at", "asked": asked, "read": read, "ambiguous": "false"}).json()
        assert expected and len(expected) == reads[read]
        cell = page.locator(f'[data-pick*=\'"cell": ["stopped_at", "{asked}", "{read}"]\']')
        cell.first.click()
        page.get_by_text(f"asked {asked}, read {read}").first.wait_for()
        shown = browser_support.poll(lambda: page.evaluate(PICKED), lambda v: len(v) == len(expected), "the rows")
        assert sorted(int(t.split()[1]) for t in shown) == sorted(e["env_id"] for e in expected)

        # an episode of a hand-made file flies again, but not as the file says: the step is not claimed for it
        page.get_by_role("button", name=shown[0]).click()
        page.get_by_text(f"It went wrong at step {WENT_WRONG} of the evaluation's flight, not of this one").first \
            .wait_for(timeout=120_000)


def test_a_replayed_episode_of_a_flown_evaluation_shows_the_step_it_went_wrong(dashboard):
    """An evaluation the server flies (its maps recorded, its failures attributed): analysed, a failure picked from
    its stage's bar flies again exactly as evaluated and the timeline shows the step its stage went wrong."""
    e = dashboard.jobs.start_evaluation(None, None, None, None, [85, 86])
    done = browser_support.poll(lambda: dashboard.jobs.db.evaluation(e.id), lambda r: r.status == "finished",
                                "the evaluation", 240)
    failed = [r for r in dashboard.jobs.db.episodes(done.id) if not r.success]
    steps = {env: f.get("went_wrong") for env, f in dashboard.jobs.db.facts(done.id).items()}
    chosen = next((r for r in failed if steps.get(r.env_id) is not None), None)
    assert chosen is not None, f"no failure with a step it went wrong: {steps}"
    with browser_support.page_on(dashboard, 1280, 800) as page:
        page.get_by_role("tab", name="Analysis").click()
        browser_support.choose(page, "Evaluation", evaluation_label(done))
        page.get_by_role("button", name="Analyse", exact=True).click()
        page.get_by_text(f"Evaluation {e.id}").first.wait_for()
        browser_support.choose(page, "Slice by", slices.ATTRIBUTES["stage"])
        page.locator(f"[data-pick*='\"stage\": \"{chosen.stage}\"']").first.click()
        page.get_by_role("button", name=re.compile(f"^▶ {chosen.env_id} ")).click()
        page.get_by_text(f"Shown at step {steps[chosen.env_id]}, where it went wrong").first.wait_for(timeout=120_000)
        page.get_by_role("tab", name="Camera and maps").first.click()
        browser_support.poll(lambda: page.evaluate(MAPS), lambda m: m and m["step"] == steps[chosen.env_id],
                             "the maps at the step it went wrong", 60)
