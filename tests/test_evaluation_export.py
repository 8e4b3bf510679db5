"""An evaluation's results taken away as CSV or JSON (app.jobs.evaluation_export), and how long jobs take, said
before and while they run (app.render.estimates): issue 77, "also expected and missing"."""

from __future__ import annotations

import csv
import io
import json

import pytest
from test_jobs_units import episode

from app.jobs.db import Database
from app.jobs.evaluation_export import COLUMNS, export_evaluation, export_name
from app.render.estimates import (
    duration_words,
    evaluation_estimate,
    evaluation_remaining,
    remaining,
    run_estimate,
    run_remaining,
)

pytestmark = pytest.mark.unit


def _evaluation(db: Database, status: str = "finished", env_ids=(70, 5, 90), **kw) -> int:
    eid = db.add_evaluation(system="gsmn", checkpoint="/ck/gsmn", env_ids=list(env_ids), label="three",
                            status=status, **kw)
    db.update_evaluation(eid, done=len(env_ids))
    return eid


def test_csv_and_json_say_what_flew_each_episode_where_and_why_it_failed(tmp_path):
    db = Database(tmp_path / "gsmn.sqlite")
    eid = _evaluation(db)
    db.add_episode(episode(eid, 0, 70, stage="goal_or_control", attribution={"reason": "the goal map was wrong"}))
    db.add_episode(episode(eid, 1, 5, success=True, landmark_success=True, stage=None, attribution=None,
                           goal_distance=2.5))
    db.add_episode(episode(eid, 2, 90, region_steps=[30, 31]))
    e = db.evaluation(eid)

    rows = list(csv.DictReader(io.StringIO(export_evaluation(db, e, "csv").decode())))
    assert tuple(rows[0]) == COLUMNS and len(rows) == 3
    assert [r["split"] for r in rows] == ["test", "train", "dev"]
    assert {r["checkpoint"] for r in rows} == {"/ck/gsmn"} and {r["system"] for r in rows} == {"gsmn"}
    assert rows[0]["attributed_to"] == "goal or control" and rows[0]["reason"] == "the goal map was wrong"
    assert rows[1]["success"] == "True" and rows[1]["attributed_to"] == ""
    assert rows[2]["goal_distance_m"] == "10.0" and rows[2]["region_steps"] == "2"

    record = json.loads(export_evaluation(db, e, "json"))
    assert record["evaluation"]["id"] == eid and record["note"] is None
    assert record["splits"] == {"test": 1, "train": 1, "dev": 1}
    assert record["summary"]["success"] == pytest.approx(1 / 3)
    assert record["summary"]["failures_by_stage"] == {"goal_or_control": 1, "perception": 1}
    assert export_name(e, "csv") == f"evaluation-{eid}.csv"
    with pytest.raises(ValueError, match="unknown format"):
        export_evaluation(db, e, "xlsx")


def test_an_unfinished_evaluation_says_how_many_episodes_its_export_holds(tmp_path):
    db = Database(tmp_path / "gsmn.sqlite")
    eid = _evaluation(db, status="cancelled", env_ids=(70, 71, 72, 73))
    db.add_episode(episode(eid, 0, 70))
    record = json.loads(export_evaluation(db, db.evaluation(eid), "json"))
    assert record["note"] == "incomplete: cancelled, 1 of 4 episodes flown; the figures are of those only"
    assert record["evaluation"]["episodes_held"] == 1 and record["evaluation"]["episodes_asked"] == 4


def test_estimates_come_from_the_record_or_the_jobs_own_pace_and_never_from_a_guess(tmp_path):
    assert [duration_words(s) for s in (3, 42, 400, 6000)] == ["about 5 s", "about 40 s", "about 7 min",
                                                                "about 1 h 40 min"]
    db = Database(tmp_path / "gsmn.sqlite")
    assert evaluation_estimate(30, db.evaluations()).startswith("No evaluation has finished on this server yet")
    for seconds in (20.0, 40.0, 30.0):  # 10 episodes each: 2, 4 and 3 s an episode
        eid = _evaluation(db, env_ids=range(70, 80))
        db.update_evaluation(eid, started=1000.0, finished=1000.0 + seconds)
    imported = _evaluation(db, env_ids=range(70, 80), source="import")
    db.update_evaluation(imported, started=1000.0, finished=1000.5)  # not flown here: no pace
    assert evaluation_estimate(30, db.evaluations()) == \
        "30 episodes take about 2 min here (3.0 s an episode in the last evaluations)."
    running = _evaluation(db, status="running", env_ids=range(70, 80))
    db.update_evaluation(running, started=2000.0, done=0)
    assert evaluation_remaining(db.evaluation(running), 2001.0, db.evaluations()) == \
        "about 30 s in all at the last evaluations' pace"
    db.update_evaluation(running, done=4)
    assert evaluation_remaining(db.evaluation(running), 2020.0, db.evaluations()) == "about 30 s left"
    assert remaining(0, 10, 50.0) == "" and remaining(10, 10, 50.0) == ""

    settings = {"preset": "tiny", "iterations": 2, "rollouts_per_iteration": 2}
    assert run_estimate(settings, db.runs()).startswith("No run with these settings has finished")
    rid = db.add_run(settings={**settings, "iterations": 4}, env_ids=None, init_checkpoint="/c", folder="/f",
                     status="finished")
    db.update_run(rid, started=100.0, finished=340.0)  # 60 s an iteration
    other = db.add_run(settings={**settings, "rollouts_per_iteration": 8}, env_ids=None, init_checkpoint="/c",
                       folder="/g", status="finished")
    db.update_run(other, started=100.0, finished=5000.0)  # other settings: not this form's pace
    assert run_estimate({**settings, "iterations": 3}, db.runs()) == \
        "3 iterations take about 3 min here (60 s an iteration in runs with these settings)."
    going = db.add_run(settings=settings, env_ids=None, init_checkpoint="/c", folder="/h", status="running")
    db.update_run(going, started=1000.0, progress={"fraction": 0.25})
    assert run_remaining(db.run(going), 1100.0) == "about 5 min left"
