"""End to end in headless Chromium: evaluate a checkpoint from the page, open the failure browser, pick a failure
and replay it in the live view with its maps, launch a tiny DAggerFM run on the failures selected, watch its
progress to the end, switch to its checkpoint, and compare before/after; an evaluation and a run each cancelled
part way and resumed from the page.

Real processes (the evaluation and the run are `gsmn eval` and `gsmn train dagger` children of the server), a
real SQLite record, a real Chromium. Like tests/test_dashboard_browser.py it fails, not skips, without Playwright
or a Chromium.
"""

from __future__ import annotations

import csv
import io
import re
import time
from pathlib import Path

import browser_support
import pytest

from app.browser import field
from app.render.jobs_panels import stage_title
from app.render.panels import region_text, steps_in_region
from gsmn.attribution import PIPELINE, reported_stages

pytestmark = [pytest.mark.browser, pytest.mark.training]

HORIZON = 40


@pytest.fixture(scope="module")
def dashboard(tmp_path_factory):
    with browser_support.dashboard(tmp_path_factory, HORIZON) as d:
        yield d
        for run in d.jobs.db.runs(("queued", "running")):  # no job outlives the test
            d.jobs.cancel_run(run.id)


@pytest.fixture(scope="module")
def page(dashboard):
    with browser_support.page_on(dashboard, 1400, 1000) as page:
        yield page


def wait_js(page, script: str, predicate, timeout: float = 120.0, what: str = ""):
    return browser_support.poll(lambda: page.evaluate(script), predicate, what, timeout, every=0.2)


def evaluate_ids(page, dashboard, ids: str, label: str) -> int:
    """Evaluate these environment ids from the Failures tab; the new evaluation's id once its label shows."""
    box = field(page, "Or env ids")
    box.fill(ids)
    box.press("Enter")
    page.get_by_role("button", name="Evaluate", exact=True).click()
    page.get_by_text(re.compile(label)).first.wait_for()
    return max(e.id for e in dashboard.jobs.db.evaluations())


EVALUATION = """() => { const e = document.querySelector('.gsmn-evaluation');
    return e ? {id: e.dataset.id, status: e.dataset.status, text: e.innerText} : null; }"""
MAPS = """() => { const m = document.querySelector('.gsmn-maps');
    return m ? {episode: m.dataset.episode, step: m.dataset.step === '' ? -1 : +m.dataset.step} : null; }"""
REPLAY = """() => { const e = document.querySelector('.gsmn-episode');
    return e ? {env: e.dataset.env, text: e.innerText} : null; }"""


def test_browse_failures_replay_one_and_fine_tune_on_them(dashboard, page):
    page.get_by_role("tab", name="Failures").click()
    ids = field(page, "Or env ids")
    ids.fill("70,71,72")
    ids.press("Enter")
    page.get_by_role("button", name="Evaluate", exact=True).click()
    page.get_by_text(re.compile(r"Evaluation 1 \(3 chosen environments\)")).first.wait_for()  # its progress
    done = wait_js(page, EVALUATION, lambda v: v and v["status"] == "finished", timeout=180,
                   what="the evaluation to finish in the page")
    assert "3/3 episodes" in done["text"] and "Failures by attribution" in done["text"]
    evaluation = dashboard.jobs.db.evaluation(1)
    assert evaluation.status == "finished" and evaluation.done == 3
    # its results to take away, and how long the form's next evaluation would take here, from this one's pace
    with page.expect_download() as download:
        page.get_by_role("button", name="CSV", exact=True).click()
    exported = list(csv.DictReader(io.StringIO(Path(download.value.path()).read_text())))
    assert [int(r["env_id"]) for r in exported] == [70, 71, 72] and {r["split"] for r in exported} == {"test"}
    page.get_by_text(re.compile(r"^3 episodes take about \d+ (s|min) here")).first.wait_for()  # the ids typed

    rows = dashboard.jobs.db.episodes(1, failed_only=True)
    assert rows, "an untrained model fails"
    first = rows[0]
    page.get_by_text(f"{len(rows)} episode").first.wait_for()
    buttons = page.get_by_role("button", name=re.compile(r"^▶ \d+ "))
    assert buttons.count() == len(rows)
    assert f"{first.side} of the {first.landmark}" in buttons.first.inner_text()

    # a filter: by landmark, then back to all
    def choose(label: str, option: str, count: int) -> None:
        field(page, label).click()
        page.get_by_role("option", name=option, exact=True).click()
        deadline = time.monotonic() + 30
        while buttons.count() != count and time.monotonic() < deadline:
            page.wait_for_timeout(100)
        assert buttons.count() == count, f"{label} = {option}: {buttons.count()} rows shown, expected {count}"

    choose("Landmark", first.landmark, sum(r.landmark == first.landmark for r in rows))
    assert all(first.landmark in buttons.nth(k).inner_text() for k in range(buttons.count()))
    choose("Landmark", "all", len(rows))
    assert all(r.region_steps is not None for r in rows), "the evaluation's progress lines carry the region"
    choose("Success region", "never entered", sum(not r.region_steps for r in rows))
    choose("Success region", "flew through it", sum(bool(r.region_steps) for r in rows))
    choose("Success region", "all", len(rows))
    # the stage filter offers the stages the bars show: for a full GSMN the four of the pipeline, none merged
    field(page, "Attributed to").click()
    offered = page.get_by_role("option").all_inner_texts()
    page.keyboard.press("Escape")
    shown = reported_stages(dashboard.jobs.db.stage_counts(1))
    assert offered == ["all", *map(stage_title, shown)] == ["all", *map(stage_title, PIPELINE)], offered
    choose("Attributed to", stage_title(first.stage), sum(r.stage == first.stage for r in rows))
    choose("Attributed to", "all", len(rows))

    # pick a failure: it flies again in the live view, with its maps, and its attribution shows
    before = dashboard.runner.episodes.all()
    page.get_by_role("button", name=re.compile(rf"^▶ {first.env_id} ")).click()
    detail = wait_js(page, REPLAY, lambda v: v and v["env"] == str(first.env_id), what="the episode's details")
    assert first.attribution["reason"] in detail["text"]
    replayed = wait_js(page, REPLAY, lambda v: "Replayed as episode" in v["text"], timeout=120,
                       what="the replay to end")
    assert "reproduces the evaluation" in replayed["text"], replayed["text"]
    episode = next(e for e in dashboard.runner.episodes.all() if e not in before)
    assert episode.env_id == first.env_id and episode.result.steps == first.steps
    # the steps inside the success region the evaluation's process recorded are the live replay's, and shown
    assert first.region_steps == steps_in_region(episode, dashboard.runner.config.task.success_radius)
    assert f"success region\t{region_text(first.region_steps, first.region_stop_p, ('', ''))}" in replayed["text"]
    assert "Success region:" in wait_js(page, EVALUATION, lambda v: v is not None)["text"]
    page.get_by_role("tab", name="Camera and maps").click()
    maps = wait_js(page, MAPS, lambda v: v and v["episode"] == str(episode.id), what="the replay's maps")
    assert maps["step"] >= 0
    assert page.locator('.gsmn-maps img[data-layer="goal"]').count() == 1

    # fine-tune on the failures selected in the browser
    page.get_by_role("tab", name="Fine-tune").click()
    assert field(page, "Environments").input_value() == f"failures selected in the browser ({len(rows)})"
    page.get_by_role("button", name="Launch", exact=True).click()
    progress = wait_js(page, "() => document.body.innerText",
                       lambda t: re.search(r"Run 1\*?\*? \(running\): iteration \d of 2", t) is not None,
                       timeout=180, what="the run's progress in the page")
    assert "iteration" in progress
    run = dashboard.jobs.db.run(1)
    assert run.env_ids == sorted(r.env_id for r in rows) and run.source_evaluation_id == 1
    wait_js(page, "() => document.body.innerText", lambda t: "checkpoint run-1" in t or "Run 1 failed" in t,
            timeout=300, what="the run to finish")
    assert dashboard.jobs.db.run(1).status == "finished", dashboard.jobs.db.run(1).error
    assert page.locator("table.gsmn-runs tr[data-run='1'][data-status='finished']").count() == 1

    # its checkpoint to switch to, and before/after on the same episodes
    page.get_by_role("button", name="Fly with it", exact=True).click()
    page.get_by_text("policy is now").first.wait_for()
    assert dashboard.viewer.policy.value == "Model: run-1"
    page.get_by_role("button", name="Before/after", exact=True).click()
    compare = wait_js(page, """() => { const c = document.querySelector('.gsmn-compare');
        return c ? {after: c.dataset.after, text: c.innerText} : null; }""", lambda v: v is not None, timeout=180,
                      what="the before/after table")
    after = dashboard.jobs.db.evaluation(int(compare["after"]))
    assert after.status == "finished" and after.baseline_id == 1 and after.run_id == 1
    assert "Evaluation 1 → 2" in compare["text"] and str(first.env_id) in compare["text"]

    # an evaluation flown as a mirror ensemble, from the same form
    page.get_by_role("tab", name="Failures").click()
    field(page, "As mirror ensemble").check(force=True)
    mirrored = evaluate_ids(page, dashboard, "70", r"1 chosen environments, mirror ensemble")
    wait_js(page, EVALUATION, lambda v: v and v["id"] == str(mirrored) and v["status"] == "finished", timeout=180,
            what="the mirror-ensemble evaluation to finish in the page")
    e = dashboard.jobs.db.evaluation(mirrored)
    assert e.mirror_ensemble and e.env_ids == [70] and "--mirror-ensemble" in e.command

    # cancelled part way, then resumed from the page: the episodes it had finished are kept, the rest fly
    field(page, "As mirror ensemble").uncheck(force=True)
    long = evaluate_ids(page, dashboard, "70:78", r"8 chosen environments")
    wait_js(page, EVALUATION, lambda v: v and v["id"] == str(long) and re.search(r"\b[2-7]/8\b", v["text"]),
            timeout=180, what="two episodes of eight in the page")
    page.get_by_role("button", name="Cancel", exact=True).click()
    stopped = wait_js(page, EVALUATION, lambda v: v and v["id"] == str(long) and v["status"] == "cancelled",
                      timeout=60, what="the cancelled evaluation in the page")
    kept = dashboard.jobs.db.episodes(long)
    assert f"Stopped at {len(kept)} of 8 episodes" in stopped["text"] and 2 <= len(kept) < 8
    page.get_by_text(f"Evaluation {long} cancelled at {len(kept)} of 8 episodes").first.wait_for()
    page.get_by_role("button", name="Resume", exact=True).click()
    page.get_by_text(re.compile(rf"Evaluation {long} \(8 chosen environments\): \d+ of 8")).first.wait_for()
    done = wait_js(page, EVALUATION, lambda v: v and v["id"] == str(long) and v["status"] == "finished",
                   timeout=300, what="the resumed evaluation to finish in the page")
    assert "8/8 episodes" in done["text"] and "Stopped at" not in done["text"]
    after = {r.env_id: r for r in dashboard.jobs.db.episodes(long)}
    assert sorted(after) == list(range(70, 78)) and all(after[r.env_id] == r for r in kept)
    log = (Path(dashboard.jobs.db.evaluation(long).folder) / "output.log").read_text()
    m = re.search(r"resuming: (\d+) of 8 episodes kept", log)  # none of those flew again
    assert m and int(m.group(1)) >= len(kept), log[-2000:]

    # a fine-tuning run cancelled after its first iteration, then resumed from the page where it stopped
    page.get_by_role("tab", name="Fine-tune").click()
    field(page, "Environments").click()
    page.get_by_role("option", name="train split", exact=True).click()
    iterations = field(page, "Iterations")
    iterations.fill("2")
    iterations.press("Enter")
    known = {r.id for r in dashboard.jobs.db.runs()}
    page.get_by_role("button", name="Launch", exact=True).click()
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline and not any(
            r.id not in known and len(r.metrics) >= 1 for r in dashboard.jobs.db.runs()):
        page.wait_for_timeout(200)
    rid = max(r.id for r in dashboard.jobs.db.runs())
    assert rid not in known and dashboard.jobs.db.run(rid).settings["iterations"] == 2
    page.get_by_role("button", name="Cancel", exact=True).click()
    text = wait_js(page, "() => document.body.innerText", lambda t: f"Run {rid} cancelled." in t, timeout=60,
                   what="the cancelled run in the page")
    saved = dashboard.jobs.db.run(rid).metrics
    assert len(saved) == 1 and "Resume continues it from iteration 2 of 2" in text
    page.get_by_role("button", name="Resume", exact=True).click()
    wait_js(page, "() => document.body.innerText", lambda t: f"checkpoint run-{rid}" in t or f"Run {rid} failed" in t,
            timeout=300, what="the resumed run to finish")
    run = dashboard.jobs.db.run(rid)
    assert run.status == "finished" and [m["iteration"] for m in run.metrics] == [1, 2], run.error
    assert run.metrics[:len(saved)] == saved
