"""What the page says must be honest about what it compares (issue: the page's trust defects): a before/after names
both checkpoints and never credits a change of checkpoint to a fine-tune, warns when the run trained on test or dev
environments; a comparison names who flew each side and at which step each view is."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from test_job_faults import fake_eval
from test_jobs_units import episode

from app.jobs.db import Database
from app.jobs.manager import JobManager
from app.jobs.results import before_for_run, compare, evaluation_config, look_words, same_checkpoint
from app.jobs.settings import run_settings
from app.live.commands import RunnerError
from app.page.compare_view import cameras_html, step_words, who_flew
from app.render.jobs_panels import compare_html
from gsmn.config import RunConfig, preset
from gsmn.evaluation import evaluate, results_dict

pytestmark = pytest.mark.unit

ROOT = Path(__file__).resolve().parents[1]


def _record(tmp_path, start: str, failures_of: str, env_ids=(70, 71), trained=(70, 71)):
    """An evaluation of `failures_of`, a run from `start` on its failures, and that run's rerun."""
    tmp_path.mkdir(parents=True, exist_ok=True)
    db = Database(tmp_path / "gsmn.sqlite")
    source = db.add_evaluation(system="gsmn", checkpoint=failures_of, env_ids=list(env_ids), label="source",
                               status="finished")
    for k, e in enumerate(env_ids):
        db.add_episode(episode(source, k, e))
    rid = db.add_run(settings={}, env_ids=list(trained), init_checkpoint=start, folder=str(tmp_path / "run"),
                     source_evaluation_id=source, status="finished")
    db.update_run(rid, checkpoint=str(tmp_path / "run" / "checkpoint"))
    return db, db.evaluation(source), db.run(rid)


def test_before_is_the_checkpoint_the_run_started_from(tmp_path):
    a, b = str(tmp_path / "a"), str(tmp_path / "b")
    db, source, run = _record(tmp_path, start=b, failures_of=a)
    assert not same_checkpoint(a, b) and same_checkpoint(a, str(tmp_path / "a" / ".." / "a"))
    assert before_for_run(db, run, source) is None, "another checkpoint's evaluation is no 'before'"
    mirrored = db.add_evaluation(system="gsmn", checkpoint=b, env_ids=[71, 70], label="b, mirrored",
                                 status="finished", mirror_ensemble=True)
    running = db.add_evaluation(system="gsmn", checkpoint=b, env_ids=[70, 71], label="b, running", status="running")
    assert before_for_run(db, run, source) is None, (mirrored, running)
    fair = db.add_evaluation(system="gsmn", checkpoint=b, env_ids=[71, 70], label="b", status="finished")
    assert before_for_run(db, run, source).id == fair
    db2, source2, run2 = _record(tmp_path / "x", start=a, failures_of=a)
    assert before_for_run(db2, run2, source2).id == source2.id


def test_before_after_names_both_checkpoints_and_warns_when_they_are_not_start_and_fine_tune(tmp_path):
    a, b = str(tmp_path / "a"), str(tmp_path / "b")
    db, source, run = _record(tmp_path, start=b, failures_of=a)
    after = db.add_evaluation(system="gsmn", checkpoint=run.checkpoint, env_ids=[70, 71], label="after",
                              baseline_id=source.id, run_id=run.id, status="finished")
    for k, e in enumerate((70, 71)):
        db.add_episode(episode(after, k, e, success=True, stage=None, attribution=None))
    page = compare_html(compare(db, source, db.evaluation(after)), db.evaluation(after), run)
    assert "<b>Before</b>: evaluation" in page and f"run-{run.id}, fine-tuned from" in page
    assert "gsmn-unfair" in page and "mixes the change of checkpoint with the fine-tune" in page
    fair = db.add_evaluation(system="gsmn", checkpoint=b, env_ids=[70, 71], label="b", status="finished")
    for k, e in enumerate((70, 71)):
        db.add_episode(episode(fair, k, e))
    page = compare_html(compare(db, db.evaluation(fair), db.evaluation(after)), db.evaluation(after), run)
    assert "gsmn-unfair" not in page


def test_before_after_warns_when_the_run_trained_on_test_environments(tmp_path):
    a = str(tmp_path / "a")
    db, source, run = _record(tmp_path, start=a, failures_of=a, env_ids=(70, 71, 5), trained=(70, 71, 5))
    after = db.add_evaluation(system="gsmn", checkpoint=run.checkpoint, env_ids=[70, 71, 5], label="after",
                              baseline_id=source.id, run_id=run.id, status="finished")
    for k, e in enumerate((70, 71, 5)):
        db.add_episode(episode(after, k, e))
    page = compare_html(compare(db, source, db.evaluation(after)), db.evaluation(after), run)
    assert "gsmn-test-trained" in page and "trained on 2 test environments" in page
    assert "no longer held out" in page
    db2, source2, run2 = _record(tmp_path / "t", start=a, failures_of=a, env_ids=(5, 6), trained=(5, 6))
    assert "gsmn-test-trained" not in compare_html(compare(db2, source2, source2), source2, run2)


class _Episode:
    def __init__(self, policy, checkpoint):
        self.policy, self.checkpoint = policy, checkpoint


class _Model:
    name = "table2/no-ground"


def test_a_comparison_says_who_flew_each_side_and_at_which_step():
    models = {"/ck/no-ground": _Model()}
    assert who_flew(_Episode("expert", None), models) == "expert"
    assert who_flew(_Episode("model", "/ck/no-ground"), models) == "model table2/no-ground"
    assert who_flew(_Episode("mirror", "/ck/no-ground"), models) == "model table2/no-ground, mirror ensemble"
    assert who_flew(_Episode("model", "/elsewhere/gsmn"), models) == "model gsmn"
    assert step_words(12, 12) == "step 12"
    assert step_words(40, 31) == "step 31, its last (it ended before step 40)"
    page = cameras_html(b"\xff\xd8", b"\xff\xd8", 3, 3, "blue: episode 1, model gsmn, step 3",
                        "magenta: episode 2, expert, step 3")
    assert "gsmn-camera-a-caption" in page and "magenta: episode 2, expert, step 3" in page


def test_the_failure_card_never_says_right_and_wrong_of_one_thing():
    """The attribution reads the named landmark ("read as street lamp"); the truth figures read whole maps. A card
    with both says which is which, and a success's card lists no stage as gone wrong."""
    from app.render.jobs_panels import episode_html
    from app.render.truth import went_wrong_text
    from gsmn.attribution import Attribution

    a = Attribution(stage="perception", reason="The named landmark was seen but read as a street lamp.",
                    landmark_row=3, landmark_col=4, observed=True, perceived=False, top_class="street lamp",
                    p_landmark_class=0.1, landmark_class_rank=4, grounded=None, p_named=0.1, p_named_other=None,
                    other_landmark=None, goal_right=False, goal_peak_x=1.0, goal_peak_y=2.0, goal_peak_p=0.4,
                    goal_peak_error=9.0, stopped=True, final_to_peak=0.5,
                    failed_from={"perception": None, "grounding": None, "goal": None})
    card = episode_html(episode(1, 0, 70, stage="perception", attribution=a.to_dict()), "")
    assert "named landmark perceived" in card and "read as street lamp" in card
    assert "whole maps vs truth" in card and "every figure above chance to the end" in card
    for contradiction in ("perceived: right", "went wrong", "right at the end"):
        assert contradiction not in card
    assert went_wrong_text({"perception": None, "goal": 12}) == \
        "landmarks read: above chance to the end · goal mass: at chance from step **12**"


def test_failure_rows_before_after_and_a_stopped_result_read_as_words():
    """Issue 77, item 8: a failure row leads with its verdict and stage (a narrow button loses the distance, not the
    attribution) and says it all in its hint; before/after names stages as the bars do, never by their keys; the
    truth rows of an episode stopped early sit in a table of their own, not as raw pipes."""
    import re

    from test_dashboard_units import _episode_with_steps, _heads

    from app.jobs.results import compare
    from app.render.jobs_panels import episode_hint, episode_label
    from app.render.panels import result_markdown
    from app.render.truth import result_rows

    row = episode(1, 0, 303, goal_distance=27.1, stage="perception_or_grounding", side="right",
                  landmark="christmas tree")
    label = episode_label(row)
    assert label.startswith("▶ 303 ✗ perception or grounding · ") and label.endswith("27.1 m")
    assert "failure, attributed to: perception or grounding" in episode_hint(row) and "27.1 m" in episode_hint(row)

    db = Database(":memory:")
    before = db.add_evaluation(system="gsmn", checkpoint="a", env_ids=[70], label="a", status="finished")
    after = db.add_evaluation(system="gsmn", checkpoint="b", env_ids=[70], label="b", status="finished")
    db.add_episode(episode(before, 0, 70, stage="goal_or_control"))
    db.add_episode(episode(after, 0, 70, stage="goal_or_control"))
    page = compare_html(compare(db, db.evaluation(before), db.evaluation(after)), db.evaluation(after))
    assert "goal or control" in page and "goal_or_control" not in page

    e = _episode_with_steps()
    e.status, e.result = "cancelled", None
    text = result_markdown(e) + result_rows(e, _heads())
    lines = text.splitlines()
    first_row = next(i for i, line in enumerate(lines) if line.startswith("| truth at the end"))
    assert re.fullmatch(r"\|-+\|-+\|", lines[first_row - 1]), text  # under a table's header, not loose pipes
    rows = result_rows(_episode_with_steps(), _heads())
    assert rows.startswith("| truth at the end"), rows  # a finished one's rows join its result table


def test_the_parted_label_leaves_room_for_the_timelines_numbers():
    """Issue 77, item 10: "parted" near the start or the end of the timeline takes that end's number away (its tick
    stays); any other mark within a quarter of the timeline goes."""
    from app.page.compare_view import clear_of

    marks = ((0, "0"), (10, "STOP"), (60, "entered"), (99, "99"))
    assert clear_of(marks, 5, 100) == ((60, "entered"), (99, "99"), (0, ""))
    assert clear_of(marks, 50, 100) == ((0, "0"), (10, "STOP"), (99, "99"))
    assert clear_of(marks, 95, 100) == ((0, "0"), (10, "STOP"), (60, "entered"), (99, ""))


def test_a_map_cell_names_each_class_once_and_a_map_click_reads_its_cell():
    """Issue 77, item 6: the perception head's several models of one class ("bush", "tower") read as that class once,
    at its likeliest model's probability (as the failure attribution reads the head); a world map's click script
    types "row,col#time", read back into the cell or refused."""
    import numpy as np
    from test_dashboard_units import _episode_with_steps, _heads

    from app.render.layers import inspect_cell, map_layers
    from app.render.panels import CELL_CLICK, CELL_FIELD, maps_html, parse_cell_click
    from gsmn.config import preset
    from gsmn.model.heads import softmax
    from gsmn.world.spec import world_for_env

    heads = _heads()
    probs = softmax(heads.perception_w @ np.full(32, 0.1, np.float32) + heads.perception_b)
    order = np.argsort(-probs)
    names = list(heads.class_names)
    names[order[0]] = names[order[1]] = "bush"  # the two likeliest models: one class
    heads = type(heads)(**{**heads.__dict__, "class_names": tuple(names)})
    world = world_for_env(70, preset("tiny").world)
    report = inspect_cell(10.0, 10.0, np.full((32, 32, 32), 0.1, np.float16), np.zeros((3, 32, 32), np.float32),
                          np.zeros((2, 32, 32), np.float32), heads, world)
    listed = [name for name, _ in report.classes]
    assert listed[0] == "bush" and listed.count("bush") == 1 and len(set(listed)) == 3, listed
    for name, p in report.classes:  # a class at its likeliest model's probability, as the attribution reads it
        assert p == pytest.approx(max(probs[k] for k in range(63) if names[k] == name), rel=1e-3)

    assert parse_cell_click("12,30#1712345678", 32) == (12, 30)
    for bad in ("", "12", "a,b#1", "40,2#1", "-1,3#1"):
        assert parse_cell_click(bad, 32) is None
    assert CELL_FIELD in CELL_CLICK
    e = _episode_with_steps()
    layers = map_layers(e.steps[0].maps.maps, _heads())
    page = maps_html(e, 0, layers, None, lambda x, y: (0, 0))
    assert page.count(f'onclick="{CELL_CLICK}"') == sum(layer.frame == "world" for layer in layers.values()) >= 3


def test_terms_of_art_carry_a_plain_gloss():
    """Issue 77, item 16: P(stop), relevance AUC, goal mass, J_plan, N_D, beta0 ... each glossed where a panel uses
    it (a tooltip) and all of them listed with their glosses; the page's own words stay as they are."""
    from app.render.glossary import GLOSSARY, glossary_markdown, glossed

    text = glossed("P(stop) 0.70 · relevance AUC 0.52 · goal mass 0.1 · trained without J_plan · N_D and beta0")
    for term in ("P(stop)", "relevance AUC", "goal mass", "J_plan", "N_D", "beta0"):
        assert f'">{term}</span>' in text and GLOSSARY[term].replace("'", "&#x27;") in text, term
    assert glossed("| success region | never entered |") == "| success region | never entered |"
    assert glossed("P(stop)").count("<span") == 1  # one pass: a gloss is never glossed again
    assert all(f"**{term}**" in glossary_markdown() for term in GLOSSARY)


def _folder_with_config(folder, config: dict):
    folder.mkdir(parents=True)
    (folder / "config.json").write_text(json.dumps(config))
    return str(folder)


def test_a_before_and_a_rerun_draw_their_images_as_the_evaluation_they_stand_beside(tmp_path):
    """Baked shadows became the default after evaluations had flown with MuJoCo's shadow passes (their folders' config
    carries no shadow_method): a rerun flies the look of the evaluation it reruns, an imported evaluation keeps the
    look its file names, a fine-tuning run on an evaluation's failures trains under its look, and a 'before' of
    another look is no before."""
    a, b = str(tmp_path / "a"), str(tmp_path / "b")
    db, source, run = _record(tmp_path / "rec", start=b, failures_of=a)
    old = RunConfig().to_dict()
    del old["camera"]["shadow_method"]  # written before the field existed
    db.update_evaluation(source.id, folder=_folder_with_config(tmp_path / "source", old))
    source = db.evaluation(source.id)
    assert evaluation_config(source, RunConfig()).camera.shadow_method == "mujoco"
    assert evaluation_config(db.evaluation(source.id), None) is not None
    baked = db.add_evaluation(system="gsmn", checkpoint=b, env_ids=[70, 71], label="b, baked", status="finished")
    db.update_evaluation(baked, folder=_folder_with_config(tmp_path / "baked", RunConfig().to_dict()))
    assert before_for_run(db, run, source) is None, "another look's evaluation is no 'before'"
    unknown = db.add_evaluation(system="gsmn", checkpoint=b, env_ids=[70, 71], label="b, imported", status="finished")
    assert before_for_run(db, run, source).id == unknown  # an import's look is not known: not refused
    assert look_words(RunConfig().camera) == "baked shadows"
    assert look_words(evaluation_config(source, None).camera) == "MuJoCo's shadow passes"

    jobs = JobManager(tmp_path / "data", RunConfig(), lambda ref: ROOT / "checkpoints" / "gsmn",
                      python=fake_eval(tmp_path), poll_seconds=0.1, max_evaluations=4)
    try:
        base = jobs.db.add_evaluation(system="oracle", checkpoint=None, env_ids=[70, 71], label="old",
                                      status="finished")
        jobs.db.update_evaluation(base, folder=source.folder)
        rerun = jobs.start_evaluation(system="oracle", baseline_id=base)  # reruns the old evaluation
        fresh = jobs.start_evaluation(system="oracle", env_ids=[72])
        like = jobs.start_evaluation(system="oracle", env_ids=[73], like=source)  # a 'before' on its episodes
        flown = {e.id: json.loads((Path(e.folder) / "config.json").read_text())["camera"]["shadow_method"]
                 for e in (rerun, fresh, like)}
        assert flown == {rerun.id: "mujoco", fresh.id: "baked", like.id: "mujoco"}
        run = jobs.start_run(run_settings("tiny"), checkpoint="shipped", env_ids=[70], evaluation_id=base)
        assert json.loads((Path(run.folder) / "config.json").read_text())["camera"]["shadow_method"] == "mujoco"
        # an evaluation file imported: its settings as read are kept beside it, for its reruns
        results = results_dict("oracle", None, evaluate("oracle", [70], preset("tiny")), RunConfig(), 1.0, 1)
        results["config"] = old
        (tmp_path / "data" / "old.json").write_text(json.dumps(results))
        imported = jobs.import_evaluation("old.json")
        assert evaluation_config(imported, RunConfig()).camera.shadow_method == "mujoco"
        (Path(imported.folder) / "config.json").write_text("{")  # damaged: refused, naming it, not flown otherwise
        with pytest.raises(RunnerError, match="cannot read the settings"):
            jobs.start_evaluation(system="oracle", baseline_id=imported.id)
    finally:
        jobs.close()
