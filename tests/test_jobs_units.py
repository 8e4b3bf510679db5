"""The pieces of the dashboard's jobs that need no process: the SQLite record, run settings, the command-line flags
that carry the server's configuration to a job, summaries, a run folder's progress, and the page's text."""

from __future__ import annotations

import dataclasses
import json
import math
import os
import sqlite3

import numpy as np
import pytest

from app.jobs.db import Database, EpisodeRow
from app.jobs.manager import JobManager, evaluation_system
from app.jobs.results import region_steps_of, region_stop_p_of, summarize_rows
from app.jobs.runs import run_progress
from app.jobs.settings import RUN_PRESETS, run_config, run_settings
from app.jobs.supervisor import pid_runs
from app.live.commands import RunnerError
from app.render.jobs_panels import (
    compare_html,
    curve_data,
    curve_scales,
    episode_html,
    episode_label,
    error_summary,
    resume_hint,
    run_resume_hint,
    summary_html,
)
from gsmn.attribution import STAGE_COLOURS
from gsmn.config import preset, with_overrides
from gsmn.task.metrics import summarize

pytestmark = pytest.mark.unit


def episode(evaluation_id: int, position: int, env_id: int, **kw) -> EpisodeRow:
    values = dict(evaluation_id=evaluation_id, position=position, env_id=env_id, instruction="go to the left side of "
                  "the box", landmark="box", side="left", ambiguous=False, success=False, landmark_success=False,
                  goal_distance=10.0, steps=40, stopped=False, final_x=1.0, final_y=2.0, stage="perception",
                  attribution={"stage": "perception", "reason": "never seen"}, recording=None)
    values.update(kw)
    return EpisodeRow(**values)


def test_the_record_keeps_evaluations_episodes_and_runs_across_reopening(tmp_path):
    db = Database(tmp_path / "gsmn.sqlite")
    eid = db.add_evaluation(system="gsmn", checkpoint="/c", env_ids=[70, 71, 72], label="three")
    db.update_evaluation(eid, status="running", pid=123, command=["gsmn", "eval"], summary={"success": 50.0})
    db.add_episode(episode(eid, 0, 70))
    db.add_episode(episode(eid, 1, 71, landmark="car", side="back", ambiguous=True, stage="goal"))
    db.add_episode(episode(eid, 2, 72, success=True, stage=None, attribution=None))
    db.add_episode(episode(eid, 0, 70, goal_distance=3.0))  # written again (a monitor re-reading): replaced
    rid = db.add_run(settings={"iterations": 2}, env_ids=[70, 71], init_checkpoint="/c", folder="/f",
                     source_evaluation_id=eid)
    db.update_run(rid, metrics=[{"iteration": 1}], cancel_requested=True)
    with pytest.raises(ValueError, match="no such runs column"):
        db.update_run(rid, colour="red")
    db.close()

    db = Database(tmp_path / "gsmn.sqlite")
    e = db.evaluation(eid)
    assert (e.status, e.pid, e.command, e.summary, e.env_ids, e.total) == ("running", 123, ["gsmn", "eval"],
                                                                           {"success": 50.0}, [70, 71, 72], 3)
    assert [x.env_id for x in db.episodes(eid)] == [70, 71, 72] and db.episode(eid, 70).goal_distance == 3.0
    assert [x.env_id for x in db.episodes(eid, failed_only=True)] == [70, 71]
    assert [x.env_id for x in db.episodes(eid, landmark="car")] == [71]
    assert [x.env_id for x in db.episodes(eid, side="left", failed_only=True)] == [70]
    assert [x.env_id for x in db.episodes(eid, ambiguous=False)] == [70, 72]
    assert [x.env_id for x in db.episodes(eid, stage="goal")] == [71]
    assert db.episode(eid, 71).ambiguous is True and db.episode(eid, 70).attribution["reason"] == "never seen"
    assert db.stage_counts(eid) == {"perception": 1, "goal": 1}
    r = db.run(rid)
    assert r.metrics == [{"iteration": 1}] and r.cancel_requested is True and r.env_ids == [70, 71]
    assert [x.id for x in db.runs(("queued",))] == [rid] and db.runs(("finished",)) == []
    assert db.evaluation(999) is None and db.run(999) is None
    db.close()
    with sqlite3.connect(tmp_path / "gsmn.sqlite") as raw:
        assert raw.execute("PRAGMA journal_mode").fetchone()[0] == "wal"


def old_schema(version: int) -> str:
    """The schema a record of an earlier version was written with: today's without the columns added since."""
    import app.jobs.db

    schema = app.jobs.db.SCHEMA
    region = [x for x in schema.splitlines() if x.strip().startswith(("region_steps", "region_stop_p"))]
    assert len(region) == 2
    for line in region:
        schema = schema.replace(line + "\n", "", 1)
    intervention = [x for x in schema.splitlines() if x.strip().startswith("intervention")]
    assert len(intervention) == 1
    schema = schema.replace(intervention[0] + "\n", "", 1).replace(
        "mirror_ensemble INTEGER NOT NULL DEFAULT 0,", "mirror_ensemble INTEGER NOT NULL DEFAULT 0", 1)
    if version == 1:
        line = [x for x in schema.splitlines() if x.strip().startswith("mirror_ensemble")]
        assert len(line) == 1
        schema = schema.replace("cancel_requested INTEGER NOT NULL DEFAULT 0,\n" + line[0] + "\n",
                                "cancel_requested INTEGER NOT NULL DEFAULT 0\n", 1)
        assert "mirror_ensemble" not in schema
    assert "region_" not in schema and "intervention" not in schema
    return schema


def test_a_record_of_schema_version_1_gains_the_mirror_column_and_keeps_its_rows(tmp_path):
    """A record written before evaluations had `mirror_ensemble` (schema 1) opens with every row as it was, marked
    as flown plainly, and takes mirror-ensemble evaluations from then on."""
    import app.jobs.db

    path = tmp_path / "old.sqlite"
    with sqlite3.connect(path) as old:
        old.executescript(old_schema(1))
        old.execute("INSERT INTO evaluations (status, created, system, checkpoint, env_ids, label, source, total) "
                    "VALUES ('finished', 1.0, 'gsmn', '/c', '[70, 71]', 'before the column', 'dashboard', 2)")
        old.execute("PRAGMA user_version=1")
    old.close()
    db = Database(path)
    (e,) = db.evaluations()
    assert (e.label, e.env_ids, e.status, e.mirror_ensemble) == ("before the column", [70, 71], "finished", False)
    new = db.add_evaluation(system="gsmn", checkpoint="/c", env_ids=[72], label="mirrored", mirror_ensemble=True)
    db.close()
    db = Database(path)
    assert db.evaluation(new).mirror_ensemble is True and db.evaluation(e.id).mirror_ensemble is False
    assert sqlite3.connect(path).execute("PRAGMA user_version").fetchone()[0] == app.jobs.db.SCHEMA_VERSION == 6
    assert db.evaluation(e.id).intervention is None
    db.close()


def test_a_record_of_schema_version_2_gains_the_region_columns_as_not_known(tmp_path):
    """Episodes recorded before the success region was (schema 2) keep every value, show no region row, are left
    out of both choices of the region filter and are counted apart; episodes recorded after carry it."""
    path = tmp_path / "old.sqlite"
    with sqlite3.connect(path) as old:
        old.executescript(old_schema(2))
        old.execute("INSERT INTO evaluations (status, created, system, checkpoint, env_ids, label, source, total, "
                    "mirror_ensemble) VALUES ('finished', 1.0, 'gsmn', '/c', '[70, 71]', 'old', 'dashboard', 2, 0)")
        old.execute("INSERT INTO episodes (evaluation_id, position, env_id, instruction, landmark, side, ambiguous, "
                    "success, landmark_success, goal_distance, steps, stopped, final_x, final_y) VALUES "
                    "(1, 0, 70, 'go to the left side of the box', 'box', 'left', 0, 0, 1, 4.5, 60, 1, 3.0, 4.0)")
        old.execute("PRAGMA user_version=2")
    old.close()
    db = Database(path)
    (row,) = db.episodes(1)
    assert (row.env_id, row.goal_distance, row.steps, row.region_steps, row.region_stop_p) == (70, 4.5, 60, None, None)
    assert db.episodes(1, entered_region=True) == [] and db.episodes(1, entered_region=False) == []
    assert db.region_counts(1) == {"entered": 0, "never": 0, "unknown": 1}
    assert "success region" not in episode_html(row, "")
    db.add_episode(episode(1, 1, 71, region_steps=[30, 31, 32], region_stop_p=0.25))
    db.close()
    db = Database(path)
    assert db.episode(1, 71).region_steps == [30, 31, 32] and db.episode(1, 71).region_stop_p == 0.25
    assert [r.env_id for r in db.episodes(1, entered_region=True)] == [71]
    db.close()


def test_a_record_of_schema_version_5_gains_the_intervention_column_as_none(tmp_path):
    """Evaluations recorded before map interventions (schema 5) read back as flown with the model's own maps; an
    intervened evaluation recorded after keeps its intervention across a reopening."""
    path = tmp_path / "old.sqlite"
    with sqlite3.connect(path) as old:
        old.executescript(old_schema(5).replace("CREATE TABLE IF NOT EXISTS episodes (",
                                                "CREATE TABLE IF NOT EXISTS episodes (\n    region_steps TEXT,\n"
                                                "    region_stop_p REAL,", 1))
        old.execute("INSERT INTO evaluations (status, created, system, checkpoint, env_ids, label, source, total, "
                    "mirror_ensemble) VALUES ('finished', 1.0, 'gsmn', '/c', '[70]', 'old', 'dashboard', 1, 0)")
        old.execute("PRAGMA user_version=5")
    old.close()
    db = Database(path)
    assert db.evaluation(1).intervention is None
    new = db.add_evaluation(system="gsmn", checkpoint="/c", env_ids=[70], label="rescue", baseline_id=1,
                            intervention="truth-goal")
    db.close()
    db = Database(path)
    assert db.evaluation(new).intervention == "truth-goal" and db.evaluation(1).intervention is None
    db.close()


def test_failures_are_told_apart_by_whether_they_flew_through_the_success_region(tmp_path):
    """The record keeps the steps inside the success region; the browser filters on them, counts them under the
    attribution bars and names them in an episode's details, the way the live view's result does."""
    db = Database(tmp_path / "gsmn.sqlite")
    eid = db.add_evaluation(system="gsmn", checkpoint="/c", env_ids=[70, 71, 72, 73], label="four")
    plain = {"stage": None, "attribution": None}
    db.add_episode(episode(eid, 0, 70, region_steps=[], **plain))
    db.add_episode(episode(eid, 1, 71, region_steps=[12, 13, 14, 20], region_stop_p=0.31, **plain))
    db.add_episode(episode(eid, 2, 72, success=True, region_steps=[40, 41], **plain))
    db.add_episode(episode(eid, 3, 73, region_steps=[5], **plain))  # a baseline's: no recorded P(stop)
    assert [r.env_id for r in db.episodes(eid, entered_region=True)] == [71, 72, 73]
    assert [r.env_id for r in db.episodes(eid, failed_only=True, entered_region=True)] == [71, 73]
    assert [r.env_id for r in db.episodes(eid, entered_region=False)] == [70]
    assert db.region_counts(eid) == {"entered": 2, "never": 1}
    passed = episode_html(db.episode(eid, 71), "")
    assert "success region" in passed and "flew through it at steps 12-14, 20 without a STOP there" in passed
    assert "highest P(stop) there <b>0.31</b>" in passed
    assert "flew through it at step 5 without a STOP there</td>" in episode_html(db.episode(eid, 73), "")
    assert "never entered" in episode_html(db.episode(eid, 70), "")
    assert "success region" not in episode_html(db.episode(eid, 72), "")  # a success needs no such row
    ev = db.evaluation(eid)
    line = summary_html(ev, db.stage_counts(eid), db.region_counts(eid))
    assert "<b>2</b> flew through it without a STOP there, <b>1</b> never entered it" in line
    assert "recorded without" not in line and "gsmn-regions" not in summary_html(ev, db.stage_counts(eid))
    assert "1 recorded without it" in summary_html(ev, {}, {"entered": 1, "never": 0, "unknown": 1})
    # an ablation's merged stages get bars of their own, named and coloured like the filter and the figures
    ablation = summary_html(ev, {"goal": 2, "perception_or_grounding": 3, "grounding_or_goal_or_control": 1})
    assert 'data-stage="perception_or_grounding"' in ablation and "perception or grounding" in ablation
    assert STAGE_COLOURS["perception_or_grounding"] in ablation and "grounding or goal or control" in ablation
    assert 'data-stage="goal_or_control"' not in ablation and "Failures by attribution (6)" in ablation
    db.close()


def test_the_region_steps_come_from_a_progress_line_or_a_trajectory():
    """A progress line carries them (gsmn eval --progress); a `gsmn eval --json` record is measured from its
    trajectory with the metric's own function; an older progress line has neither."""
    from gsmn.task.metrics import steps_in_success_region

    record = {"landmark_x": 10.0, "landmark_y": 10.0, "start_x": 0.0, "start_y": 0.0, "side": "front",
              "trajectory": [[x, x, 1.0, 0.0] for x in (0.0, 4.0, 6.0, 7.0, 9.0, 12.0)]}
    expected = steps_in_success_region([p[:2] for p in record["trajectory"]], (10, 10), (0, 0), "front", 6.0)
    assert expected == [2, 3, 4] and region_steps_of(record, 6.0) == expected  # front: not (12, 12), beyond it
    assert region_steps_of(record, 2.0) == [4]
    assert region_steps_of({"region_steps": [3, 4]}, 6.0) == [3, 4]
    assert region_steps_of({"env_id": 70}, 6.0) is None


def test_an_evaluation_flies_the_checkpoints_own_kind_unless_asked_for_another(tmp_path):
    """A checkpoint named without a system flies as what it holds (a GS-FPV checkpoint as gs-fpv); a system asked
    for must match it, except 'gsmn' with the server's default checkpoint."""
    ckpt = tmp_path / "gs-fpv"
    assert evaluation_system(None, True, "gs-fpv", ckpt) == "gs-fpv"
    assert evaluation_system("gs-fpv", True, "gs-fpv", ckpt) == "gs-fpv"
    assert evaluation_system("gsmn", False, "gs-fpv", ckpt) == "gs-fpv"
    assert evaluation_system(None, False, "gsmn", ckpt) == "gsmn"
    with pytest.raises(RunnerError, match="holds a 'gs-fpv' model, not 'gsmn'"):
        evaluation_system("gsmn", True, "gs-fpv", ckpt)
    with pytest.raises(RunnerError, match="not 'gs-fpv-mem'"):
        evaluation_system("gs-fpv-mem", False, "gs-fpv", ckpt)


def test_a_checkpoint_of_unknown_kind_is_refused_before_anything_starts(tmp_path):
    folder = tmp_path / "odd"
    folder.mkdir()
    (folder / "meta.json").write_text(json.dumps({"kind": "resnet50"}))
    jobs = JobManager(tmp_path / "data", preset("tiny"), lambda ref: folder)
    try:
        for launch in (lambda: jobs.start_run(run_settings("tiny"), checkpoint="odd"),
                       lambda: jobs.start_evaluation("odd", split="dev", episodes=1)):
            with pytest.raises(RunnerError, match="names kind 'resnet50'"):
                launch()
        assert jobs.db.runs() == [] and jobs.db.evaluations() == []
    finally:
        jobs.close()


def test_expert_data_must_be_a_store_inside_the_data_folder_and_the_refusal_tells_nothing_of_the_outside(
        tmp_path, untrained_checkpoint):
    """A run cleans and links files in its expert store, so `expert_data` is confined to the data folder; outside
    it, an existing folder and a missing one are refused in the same words."""
    folder = untrained_checkpoint
    jobs = JobManager(tmp_path / "data", preset("tiny"), lambda ref: folder)
    outside = tmp_path / "elsewhere"
    outside.mkdir()
    try:
        answers = []
        for name in ("/etc", str(outside), str(tmp_path / "missing"), "../elsewhere", "", "missing", ".",
                     str(tmp_path / "data")):
            with pytest.raises(RunnerError) as refused:
                jobs.start_run(dataclasses.replace(run_settings("tiny"), expert_data=name))
            answers.append(str(refused.value).replace(repr(name), "NAME"))
        assert len(set(answers)) == 1 and "inside the data folder" in answers[0], answers
        assert jobs.db.runs() == []
        (tmp_path / "data" / "mine").mkdir()
        assert jobs._expert_store("mine") == (tmp_path / "data" / "mine").resolve()
        assert jobs._expert_store(str(tmp_path / "data" / "mine")) == (tmp_path / "data" / "mine").resolve()
    finally:
        jobs.close()


def test_run_settings_come_from_a_preset_with_overrides_and_are_checked():
    assert run_settings("tiny") == RUN_PRESETS["tiny"]
    s = run_settings("paper", iterations=3, learning_rate=1e-4, beta0=None)
    assert (s.iterations, s.learning_rate, s.beta0, s.dataset_size) == (3, 1e-4, 0.92, 500)
    # the values are checked by the configuration they make (DaggerConfig, TrainConfig), as the request's error
    for kwargs, words in (({"rollouts_per_iteration": 5, "dataset_size": 4}, "cannot exceed M"),
                          ({"iterations": 0}, "iterations must be at least 1"), ({"beta0": 1.5}, "beta0"),
                          ({"learning_rate": 0.0}, "learning_rate"), ({"colour": 1}, "unknown run setting"),
                          ({"mirror": 1.5}, "mirror"), ({"horizon": 0}, "horizon")):
        with pytest.raises(RunnerError, match=words):
            run_config(preset("tiny"), run_settings("tiny", **kwargs))
    with pytest.raises(RunnerError, match="unknown run preset"):
        run_settings("huge")
    config = run_config(with_overrides(preset("tiny"), {"task.horizon": "60"}), run_settings("tiny", beta0=0.3))
    assert (config.dagger.iterations, config.dagger.beta0, config.task.horizon, config.train.threads) == (2, 0.3, 30, 1)
    assert config.train.mirror == 0.0
    assert run_config(preset("tiny"), run_settings("tiny", mirror=0.5)).train.mirror == 0.5
    assert not config.camera.shadows


def test_the_config_file_a_job_gets_rebuilds_the_servers_configuration_exactly(tmp_path):
    from gsmn.cli import build_parser, config_from_args
    from gsmn.config import ConfigError

    config = with_overrides(preset("tiny"), {"task.horizon": "37", "train.learning_rate": "0.000123",
                                             "dagger.beta0": "0.5", "model.channels_last": "false"})
    path = tmp_path / "config.json"
    path.write_text(config.to_json() + "\n")
    parse = build_parser().parse_args
    for verb in (["eval", "--system", "oracle", "--split", "test"], ["collect", "--out", "x"],
                 ["train", "dagger", "--init", "c", "--data", "d", "--run", "r"],
                 ["train", "supervised", "--data", "d", "--run", "r"]):
        assert config_from_args(parse([*verb, "--config", str(path)])) == config
    # flags still override the file; a preset and a file at once, or a file that is no RunConfig, are refused
    assert config_from_args(parse(["collect", "--out", "x", "--config", str(path), "--task.horizon", "12"])) == \
        with_overrides(config, {"task.horizon": "12"})
    assert config_from_args(parse(["collect", "--out", "x"])) == preset("paper")
    with pytest.raises(ConfigError, match="not both"):
        config_from_args(parse(["collect", "--out", "x", "--config", str(path), "--preset", "tiny"]))
    (tmp_path / "odd.json").write_text(json.dumps({"colour": 1}))
    with pytest.raises(ConfigError, match="colour"):
        config_from_args(parse(["collect", "--out", "x", "--config", str(tmp_path / "odd.json")]))
    with pytest.raises(ConfigError, match="cannot read"):
        config_from_args(parse(["collect", "--out", "x", "--config", str(tmp_path / "none.json")]))


def test_summaries_of_recorded_outcomes_match_the_papers_metrics():
    rng = np.random.default_rng(0)
    records = []
    for k in range(9):
        records.append({"final_x": float(rng.uniform(0, 30)), "final_y": float(rng.uniform(0, 30)), "landmark_x": 15.0,
                        "landmark_y": 15.0, "start_x": 0.0, "start_y": 0.0, "side": ["left", "back", "front"][k % 3],
                        "goal_x": 15.0, "goal_y": 19.0, "ambiguous": k % 4 == 0})
    records[0].update(final_x=15.0, final_y=18.0, side="back")  # one success at least
    from gsmn.task.metrics import goal_distance, landmark_success, success

    rows = [{"success": success((r["final_x"], r["final_y"]), (15, 15), (0, 0), r["side"]),
             "landmark_success": landmark_success((r["final_x"], r["final_y"]), (15, 15)),
             "goal_distance": goal_distance((r["final_x"], r["final_y"]), (15, 19)), "ambiguous": r["ambiguous"]}
            for r in records]
    ours, theirs = summarize_rows(rows), summarize(records).to_dict()
    for key in ("count", "success", "landmark_success", "mean_distance", "median_distance"):
        assert ours[key] == pytest.approx(theirs[key]) and ours["pruned"][key] == pytest.approx(theirs["pruned"][key])
    assert math.isnan(summarize_rows([])["success"])


def test_a_run_folder_says_where_the_run_is(tmp_path):
    from app.jobs.db import Run

    row = Run(id=1, status="running", created=0, started=0, finished=None, settings={"iterations": 4}, env_ids=None,
              source_evaluation_id=None, init_checkpoint="/c", folder=str(tmp_path), pid=None, command=None,
              progress=None, metrics=[], checkpoint=None, error=None, cancel_requested=False)
    p, metrics = run_progress(tmp_path, row)
    assert p["phase"] == "expert data" and p["fraction"] == 0 and metrics == []
    assert run_resume_hint(row) == ""  # running
    stopped = dataclasses.replace(row, status="cancelled", command=["sh", "-c", "x"])
    assert "starts it again" in run_resume_hint(stopped)
    assert "from iteration 2 of 4" in run_resume_hint(dataclasses.replace(stopped, metrics=[{"iteration": 1}]))
    # the chart's x axis spans the planned iterations from the first point on (uPlot alone gives 0-100)
    # before any run, the empty chart spans the form's planned iterations, not uPlot's 0-100 (item 18 of issue 51)
    assert curve_scales(None, 2)["x"]["range"] == (1.0, 2.0) and curve_scales(None, 5)["x"]["range"] == (1.0, 5.0)
    assert curve_scales(None, 2)["share"]["range"][0] == 0.0  # the shares have their own 0-1 axis
    assert curve_scales(dataclasses.replace(row, metrics=[{"iteration": 1}]))["x"]["range"] == (1.0, 4.0)
    assert curve_scales(dataclasses.replace(row, settings={"iterations": 1}))["x"]["range"] == (1.0, 2.0)
    assert curve_scales(dataclasses.replace(row, settings={}, metrics=[{"iteration": 7}]))["x"]["range"] == (1.0, 7.0)
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.json").write_text("{}")
    (run / "log.jsonl").write_text(json.dumps({"iteration": 1, "train": {"loss": 1.5}}) + "\n")
    (run / "progress.json").write_text(json.dumps({"phase": "collect", "iteration": 2, "rollouts": 4, "done": 2,
                                                   "beta": 0.8}))
    p, metrics = run_progress(tmp_path, row)
    assert p["phase"] == "collect" and p["fraction"] == pytest.approx((1 + 0.25) / 4, abs=1e-4)
    assert "rollouts 2/4" in p["text"]
    assert p["loss"] == 1.5 and len(metrics) == 1
    (run / "progress.json").write_text(json.dumps({"phase": "train", "batch": 3, "batches": 4, "loss": 0.9}))
    p, _ = run_progress(tmp_path, row)
    assert p["fraction"] == pytest.approx((1 + 0.5 + 0.5 * 0.75) / 4, abs=1e-4) and "batch 3/4, loss 0.900" in p["text"]
    (run / "progress.json").write_text(json.dumps({"phase": "validate", "iteration": 2}))
    p, _ = run_progress(tmp_path, row)
    assert p["fraction"] == pytest.approx((1 + 0.95) / 4, abs=1e-4)
    # Iteration 2's log line is written before the next progress report: the fraction must not run ahead of it
    # (it read 2.95 / 4 here, then fell back to 2 / 4 once iteration 3's rollouts began).
    with (run / "log.jsonl").open("a") as f:
        f.write(json.dumps({"iteration": 2, "train": {"loss": 1.2}}) + "\n")
    p, _ = run_progress(tmp_path, row)
    assert p["fraction"] == pytest.approx(2 / 4, abs=1e-4)


def test_a_pid_counts_as_the_job_only_when_its_command_line_names_the_job():
    assert pid_runs(os.getpid(), "python") or pid_runs(os.getpid(), "pytest")
    assert not pid_runs(os.getpid(), "/no/such/job/folder")
    assert not pid_runs(None, "x") and not pid_runs(2**22 + 12345, "x")


def test_the_pages_text():
    e = episode(1, 0, 73, success=False, goal_distance=14.25, stage="grounding", side="left", landmark="pumpkin")
    assert episode_label(e) == "▶ 73 ✗ not grounded · left of the pumpkin · 14.2 m"
    assert error_summary("its process exited with status 1; its output ends:\nTraceback\n  File x\nValueError: bad") \
        == "its process exited with status 1: ValueError: bad"
    assert error_summary(None) == "" and error_summary("cancelled") == "cancelled"
    from app.jobs.db import Evaluation

    ev = Evaluation(id=2, status="finished", created=0, started=0, finished=0, system="gsmn", checkpoint="/c",
                    env_ids=[1, 2], label="x", baseline_id=None, run_id=None, source="dashboard", folder=None,
                    pid=None, command=None, done=2, total=2, summary={"success": 50.0, "landmark_success": 50.0,
                                                                      "mean_distance": 3.0}, error=None,
                    cancel_requested=False)
    html = summary_html(ev, {"perception": 1, "goal": 2})
    assert "2/2" in html and "50 %" in html and 'data-stage="goal"' in html and "Failures by attribution (3)" in html
    assert "gsmn-resumable" not in html and resume_hint(ev) == ""  # finished: nothing to resume
    stopped = dataclasses.replace(ev, status="cancelled", done=1, command=["gsmn", "eval"])
    assert "Stopped at 1 of 2 episodes" in resume_hint(stopped) and "the other 1" in resume_hint(stopped)
    assert "gsmn-resumable" in summary_html(stopped, {})
    assert resume_hint(dataclasses.replace(stopped, source="import", command=None)) == ""
    assert "flies all 2" in resume_hint(dataclasses.replace(stopped, status="failed", done=0))
    it, loss, action, learner, succeeded = curve_data([
        {"iteration": 1, "train": {"loss": 2.0, "loss_action": 0.5}, "learner_step_fraction": 0.1},
        {"iteration": 2, "train": {"loss": 1.0}, "learner_step_fraction": 0.3, "rollout_success": 0.25}])
    assert list(it) == [1, 2] and list(loss) == [2.0, 1.0] and math.isnan(action[1])
    assert list(learner) == [0.1, 0.3] and math.isnan(succeeded[0]) and succeeded[1] == 0.25
    assert len(curve_data([])) == 5
    brief = {"success": False, "goal_distance": 5.0, "stage": "goal", "landmark_success": False, "steps": 3,
             "stopped": True}
    c = {"before": 1, "after": 2, "episodes": [{"env_id": 7, "instruction": "i", "before": brief,
                                                "after": {**brief, "success": True, "stage": None}}],
         "fixed": 1, "broken": 0, "before_success": 0.0, "after_success": 100.0, "before_mean_distance": 5.0,
         "after_mean_distance": 5.0}
    assert "0 % → 100 %" in compare_html(c, None) and "1 fixed" in compare_html(c, None)


def test_the_p_stop_in_the_region_is_the_one_the_policy_acted_on_when_the_file_keeps_it():
    recorded = [0.1, 0.2, 0.9, 0.3]  # a recording's (for a mirror ensemble: the unmirrored copy's)
    acted = {"stop_probabilities": [0.1, 0.4, 0.45, 0.2]}  # a `gsmn eval --json` record keeps the mean acted on
    assert region_stop_p_of(acted, [1, 2], recorded) == 0.45
    assert region_stop_p_of({"region_stop_p": 0.33}, [1, 2], recorded) == 0.33  # a progress line's
    assert region_stop_p_of({}, [1, 2], recorded) == 0.9  # an older file: the recording's
    assert region_stop_p_of({}, [1, 2]) is None  # a baseline's older file: not known
    assert region_stop_p_of(acted, [], recorded) is None and region_stop_p_of(acted, None) is None  # never entered
    assert region_stop_p_of({}, [3, 4], recorded) is None  # steps the recording does not have


def test_the_failure_browser_and_fine_tune_tab_read_plainly():
    """Issue 51, items 10, 17 and 18: successes and failures told apart, sorting, the stage filter named as the bars
    are, a failure whose attribution and region passage differ saying why, and before/after saying which episodes
    were trained on."""
    from app.jobs.db import Run
    from app.render.jobs_panels import both_readings, episode_colour, sort_rows, stage_title, trained_on_note

    ok = episode(1, 0, 70, success=True, goal_distance=1.0, stage=None, attribution=None)
    far = episode(1, 1, 71, goal_distance=17.9, stage="goal_or_control")
    near = episode(1, 2, 72, goal_distance=4.0)
    assert "✓ success" in episode_label(ok) and "✗ goal or control" in episode_label(far)
    assert episode_colour(ok) != episode_colour(far)
    assert "goal or control" in episode_label(far) and stage_title("goal_or_control") == "goal or control"
    assert [r.env_id for r in sort_rows([ok, far, near], "distance to goal, far first")] == [71, 72, 70]
    assert [r.env_id for r in sort_rows([near, ok, far], "environment id")] == [70, 71, 72]
    assert [r.env_id for r in sort_rows([near, ok], "flown order")] == [72, 70]
    # environment 72's kind: the goal map at the end is wrong, yet it flew through the region at steps 32-50
    goal = episode(1, 3, 72, stage="goal", region_steps=list(range(32, 51)),
                   attribution={"stage": "goal", "reason": "r", "goal_peak_error": 9.5, "perceived": True,
                                "observed": True, "top_class": "tower", "landmark_class_rank": 1, "grounded": True,
                                "p_named": 0.7, "goal_right": False, "goal_peak_p": 0.4})
    both = both_readings(goal)
    assert "Both readings hold" in both and "9.5 m" in both
    assert "Both readings hold" in episode_html(goal, "")
    assert both_readings(dataclasses.replace(goal, region_steps=[])) == ""
    assert both_readings(dataclasses.replace(goal, stage="control")) == ""  # control: the two already agree
    run = Run(id=3, status="finished", created=0, started=0, finished=0, settings={"iterations": 2},
              env_ids=[7, 8], source_evaluation_id=1, init_checkpoint="/c", folder="/f", pid=None, command=None,
              progress=None, metrics=[], checkpoint="/c3", error=None, cancel_requested=False)
    c = {"episodes": [{"env_id": 7}, {"env_id": 8}]}
    assert "trained on: the figures are on its training episodes" in trained_on_note(c, run)
    assert "1 of these 2" in trained_on_note({"episodes": [{"env_id": 7}, {"env_id": 90}]}, run)
    assert "held out" in trained_on_note({"episodes": [{"env_id": 75}]}, dataclasses.replace(run, env_ids=None))


def test_a_failure_card_says_from_which_step_each_stage_went_wrong():
    from gsmn.attribution import Attribution

    a = Attribution(stage="goal", reason="Grounded, but the goal map peaks 9.0 m from the true goal.", landmark_row=3,
                    landmark_col=4, observed=True, perceived=True, top_class="box", p_landmark_class=0.6,
                    landmark_class_rank=1, grounded=True, p_named=0.7, p_named_other=0.2, other_landmark="tank",
                    goal_right=False, goal_peak_x=1.0, goal_peak_y=2.0, goal_peak_p=0.4, goal_peak_error=9.0,
                    stopped=True, final_to_peak=0.5, failed_from={"perception": None, "grounding": None, "goal": 41})
    card = episode_html(episode(1, 0, 70, stage="goal", attribution=a.to_dict()), "")
    assert "whole maps vs truth" in card and "goal mass: at chance from step <b>41</b>" in card
    assert "landmarks read: above chance to the end" in card
    older = {k: v for k, v in a.to_dict().items() if k != "failed_from"}  # recorded before the figures were
    assert "whole maps vs truth" not in episode_html(episode(1, 0, 70, stage="goal", attribution=older), "")


def test_a_failure_card_of_an_ablation_says_which_heads_have_no_trained_reading():
    from gsmn.attribution import Attribution

    a = Attribution(stage="grounding_or_goal", reason="Perceived, but the goal map peaks 9.0 m from the true goal.",
                    landmark_row=3, landmark_col=4, observed=True, perceived=True, top_class="box",
                    p_landmark_class=0.6, landmark_class_rank=1, grounded=None, p_named=0.5, p_named_other=0.5,
                    other_landmark="tank", goal_right=False, goal_peak_x=1.0, goal_peak_y=2.0, goal_peak_p=0.4,
                    goal_peak_error=9.0, stopped=True, final_to_peak=0.5)
    card = episode_html(episode(1, 0, 70, stage=a.stage, attribution=a.to_dict()), "")
    assert "grounding or goal" in card and "no trained reading (trained without J_ground)" in card
    assert "perceived</td><td>yes (read as box" in card
    b = dataclasses.replace(a, stage="perception_or_grounding", perceived=None, grounded=False)
    card = episode_html(episode(1, 0, 70, stage=b.stage, attribution=b.to_dict()), "")
    assert "perception or grounding" in card and "seen; no trained reading (trained without J_percept)" in card
    assert "grounded</td><td>no (P(named) 0.50" in card
