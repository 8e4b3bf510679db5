"""An evaluation's analysis from the dashboard's record (app/jobs/analysis.py): the episodes' facts kept in the record
and computed once for an evaluation recorded without them, the shipped evaluations imported once, and the faults of
the new table: a full disk, a server killed mid-import (kill -9), damaged bytes, an older record."""

from __future__ import annotations

import json
import sqlite3
import subprocess
import sys
from pathlib import Path

import pytest
from support import compact_evaluation, in_private_mounts

from app.jobs.analysis import Analyses, facts_of
from app.jobs.db import Database, EpisodeRow
from app.live.commands import NotFound, RunnerError
from gsmn.config import preset

pytestmark = pytest.mark.unit

ENVS = (85, 86, 87, 88, 89, 90)  # dev environments: no warning about test environments


def ship(root: Path) -> Path:
    """A checkpoints folder with two shipped Table 2 evaluations of the same environments."""
    for name, won in (("gsmn", lambda e: e != 86), ("no-percept", lambda e: e in (85, 87))):
        (root / "table2" / name).mkdir(parents=True)
        (root / "table2" / name / "evaluation.json").write_text(json.dumps(compact_evaluation(ENVS, won, name)))
    return root


def test_the_shipped_gsmns_rescue_flights_come_with_its_evaluation(tmp_path):
    """checkpoints/gsmn/rescue/truth-*.json (`gsmn analyze rescue --write-compact`) are imported with the shipped
    GSMN's test evaluation, as evaluations of its failures with their intervention: the Failures tab's rescue table
    reads them; a rescue file that went missing the first time is imported when the evaluation is asked for again."""
    from app.jobs.results import rescue_of

    root = tmp_path / "checkpoints"
    (root / "gsmn" / "rescue").mkdir(parents=True)
    (root / "gsmn" / "table1.json").write_text(json.dumps(compact_evaluation(ENVS, lambda e: e > 87)))
    goal = compact_evaluation((85, 86, 87), lambda e: e != 87) | {"intervention": {"map": "goal", "with": "truth"}}
    (root / "gsmn" / "rescue" / "truth-goal.json").write_text(json.dumps(goal))
    db = Database(tmp_path / "gsmn.sqlite")
    analyses = Analyses(db, preset("tiny"), root)
    e = analyses.import_shipped("gsmn/test")
    table = rescue_of(db, e)
    assert table["failures"] == 3 and table["stages"] == {"control": 3}
    assert table["interventions"]["truth-goal"]["all"] | {"low": 0, "high": 0} == {
        "rescued": 2, "of": 3, "rate": 2 / 3, "low": 0, "high": 0}
    (rescue,) = [x for x in db.evaluations() if x.intervention]
    assert rescue.baseline_id == e.id and "perfect goal (shipped)" in rescue.label
    semantic = compact_evaluation((85, 86, 87), lambda e: False) | {"intervention": {"map": "semantic"}}
    (root / "gsmn" / "rescue" / "truth-semantic.json").write_text(json.dumps(semantic))
    assert analyses.import_shipped("gsmn/test").id == e.id
    assert set(rescue_of(db, e)["interventions"]) == {"truth-semantic", "truth-goal"}
    assert len(db.evaluations()) == 3, "each imported once"
    db.close()


def recorded(db: Database, evaluation: dict, facts: bool) -> int:
    """`evaluation`'s episodes written as the dashboard records an evaluation's (with or without their facts)."""
    eid = db.add_evaluation(system="gsmn", checkpoint="/c", env_ids=[e["env_id"] for e in evaluation["episodes"]],
                            label="flown", status="finished")
    for position, ep in enumerate(evaluation["episodes"]):
        db.add_episode(EpisodeRow(
            evaluation_id=eid, position=position, env_id=ep["env_id"], instruction=ep["instruction"],
            landmark=ep["noun_phrase"], side=ep["side"], ambiguous=ep["ambiguous"], success=ep["success"],
            landmark_success=True, goal_distance=0.0, steps=30, stopped=True, final_x=ep["final_x"],
            final_y=ep["final_y"], stage=ep["stage"], attribution=None, recording=None))
        if facts:
            db.set_facts(eid, {ep["env_id"]: facts_of(ep, preset("tiny"), None)})
    return eid


def test_a_shipped_evaluation_is_imported_once_and_analysed_against_another(tmp_path):
    db = Database(tmp_path / "gsmn.sqlite")
    analyses = Analyses(db, preset("tiny"), ship(tmp_path / "checkpoints"))
    offered = analyses.shipped()
    assert [s["key"] for s in offered] == ["table2/gsmn/dev", "table2/no-percept/dev"]
    assert all(s["evaluation_id"] is None for s in offered) and "without J_percept" in offered[1]["label"]
    control = analyses.import_shipped("table2/gsmn/dev")
    assert analyses.import_shipped("table2/gsmn/dev").id == control.id, "imported once"
    assert (control.status, control.total, control.done, control.source) == ("finished", 6, 6, "import")
    assert control.checkpoint == str(tmp_path / "checkpoints" / "table2" / "gsmn")
    ablation = analyses.import_shipped("table2/no-percept/dev")
    assert analyses.shipped()[1]["evaluation_id"] == ablation.id
    assert len(db.facts(control.id)) == 6 and [e.stage for e in db.episodes(control.id)].count("control") == 1
    found = analyses.analysis(ablation.id, control.id)
    assert found["n"] == 6 and found["successes"] == 2
    assert found["versus_summary"]["overall"] | {"p": None} == {"n": 6, "rate": 33.33, "rate_versus": 83.33,
                                                              "fixed": 0, "broken": 3, "p": None}
    assert found["evaluation"]["id"] == ablation.id and found["versus_evaluation"]["id"] == control.id
    assert found["warnings"] == []
    assert analyses.analysis(ablation.id, control.id) is found, "a finished evaluation's analysis is kept"
    landmark = db.episodes(control.id)[1].landmark
    chosen = analyses.episodes(ablation.id, {"landmark": landmark})
    assert chosen and all(e.landmark == landmark and e.evaluation_id == ablation.id for e in chosen)
    with pytest.raises(NotFound, match="no shipped evaluation 'table2/nothing/dev'"):
        analyses.import_shipped("table2/nothing/dev")
    with pytest.raises(RunnerError, match="no attribute 'colour'"):
        analyses.episodes(control.id, {"colour": "red"})
    with pytest.raises(NotFound, match="no evaluation 99"):
        analyses.analysis(99)
    db.close()


def test_an_evaluation_recorded_without_facts_gets_them_once_and_damaged_ones_again(tmp_path):
    db = Database(tmp_path / "gsmn.sqlite")
    evaluation = compact_evaluation(ENVS, lambda e: e % 2 == 0)
    eid = recorded(db, evaluation, facts=False)
    assert db.facts(eid) == {}
    first = Analyses(db, preset("tiny"), tmp_path).analysis(eid)
    kept = db.facts(eid)
    assert sorted(kept) == list(ENVS) and first["slices"]["landmarks"] != {"not read": first["slices"]["landmarks"]}
    assert kept == {ep["env_id"]: facts_of(ep, preset("tiny"), None) for ep in evaluation["episodes"]}
    # the computed facts are those the evaluation would have kept as it ran
    raw = sqlite3.connect(tmp_path / "gsmn.sqlite")
    raw.execute("UPDATE episode_facts SET facts = 'not json {' WHERE env_id = 86")
    raw.execute("UPDATE episode_facts SET facts = '[1, 2]' WHERE env_id = 87")
    raw.commit()
    raw.close()
    assert sorted(db.facts(eid)) == [85, 88, 89, 90], "damaged facts are left out"
    again = Analyses(db, preset("tiny"), tmp_path).analysis(eid)
    assert again["slices"] == first["slices"] and db.facts(eid) == kept, "and computed again"
    db.close()


FULL_DISK = """
import json, logging, os, sys
from pathlib import Path
sys.path.insert(0, sys.argv[2])
from support import compact_evaluation, in_private_mounts
from test_analysis_record import recorded
from app.jobs.analysis import Analyses
from app.jobs.db import Database
from gsmn.config import preset
root = Path(sys.argv[1])
logging.basicConfig(level=logging.WARNING, stream=sys.stderr)
db = Database(root / "gsmn.sqlite")
eid = recorded(db, compact_evaluation((70, 71, 72, 73, 74, 75), lambda e: True), facts=False)
fd = os.open(root / "filler", os.O_WRONLY | os.O_CREAT)  # fill the tmpfs
try:
    while True:
        os.write(fd, bytes(4096))
except OSError:
    os.close(fd)
found = Analyses(db, preset("tiny"), root).analysis(eid)
kept_while_full = db.facts(eid)
(root / "filler").unlink()
print(json.dumps({"eid": eid, "n": found["n"], "landmarks": found["slices"]["landmarks"], "kept": len(kept_while_full),
                  "warnings": found["warnings"]}))
"""


def test_on_a_full_disk_the_analysis_still_answers_and_keeps_nothing(tmp_path):
    """The facts of an evaluation recorded without them cannot be kept on a full disk (a 2 MB tmpfs): the analysis
    answers all the same, says so in the log, and keeps none of them (all or nothing)."""
    script = tmp_path / "full.py"
    script.write_text(FULL_DISK)
    root = tmp_path / "small"
    root.mkdir()
    tests = Path(__file__).parent
    command = in_private_mounts(f"mount -t tmpfs -o size=2m tmpfs {root} && {sys.executable} {script} {root} {tests}")
    done = subprocess.run(command, capture_output=True, text=True, timeout=240, cwd=tests.parent)
    assert done.returncode == 0, done.stdout + done.stderr
    out = json.loads(done.stdout.strip().splitlines()[-1])
    assert out["n"] == 6 and sum(v["n"] for v in out["landmarks"].values()) == 6 and "not read" not in out["landmarks"]
    assert "facts of evaluation" in done.stderr and "not kept" in done.stderr and "full" in done.stderr
    assert out["kept"] == 0
    assert out["warnings"] == [f"Evaluation {out['eid']} flew test environments: choosing a model by these numbers "
                               "spends the test set."]


KILLED_IMPORT = """
import os, sys
from app.jobs.analysis import Analyses
from app.jobs.db import Database
from gsmn.config import preset
db = Database(sys.argv[1])
class Dying:  # the connection, killed (-9) while it inserts the episodes
    def __getattr__(self, name):
        return getattr(db._db_real, name)
    def executemany(self, sql, rows):
        if "INSERT INTO episode_facts" in sql:
            os.kill(os.getpid(), 9)
        return db._db_real.executemany(sql, rows)
db._db_real, db._db = db._db, Dying()
Analyses(db, preset("tiny"), __import__("pathlib").Path(sys.argv[2])).import_shipped("table2/gsmn/dev")
"""


def test_a_server_killed_mid_import_leaves_the_record_as_before(tmp_path):
    """kill -9 after the evaluation's row and its episodes are written, before their facts: the record is as before
    the import (one transaction), and asking again imports it whole."""
    root = ship(tmp_path / "checkpoints")
    done = subprocess.run([sys.executable, "-c", KILLED_IMPORT, str(tmp_path / "gsmn.sqlite"), str(root)],
                          capture_output=True, text=True)
    assert done.returncode == -9, done.stderr
    from app.jobs.manager import JobManager

    jobs = JobManager(tmp_path, preset("tiny"), lambda ref: Path("/nonexistent"), checkpoints_root=root)
    try:
        assert jobs.db.evaluations() == [] and jobs.analyses.shipped()[0]["evaluation_id"] is None
        whole = jobs.analyses.import_shipped("table2/gsmn/dev")
        assert whole.status == "finished" and len(jobs.db.episodes(whole.id)) == 6 and len(jobs.db.facts(whole.id)) == 6
    finally:
        jobs.close()


def test_an_older_record_gains_the_facts_table(tmp_path):
    path = tmp_path / "gsmn.sqlite"
    db = Database(path)
    eid = recorded(db, compact_evaluation(ENVS, lambda e: True), facts=False)
    db.close()
    raw = sqlite3.connect(path)  # as schema 4 left it
    raw.executescript("DROP TABLE episode_facts; PRAGMA user_version=4;")
    raw.close()
    db = Database(path)
    assert db.facts(eid) == {} and len(db.episodes(eid)) == 6
    assert sqlite3.connect(path).execute("PRAGMA user_version").fetchone()[0] == 6
    db.close()


def test_an_episode_recorded_as_an_evaluation_flies_keeps_its_facts(tmp_path):
    """The monitor records each progress line (`EpisodeRecorder.record`): the episode's facts are kept with it, the
    same as computed later from its row, so an evaluation flown from the page is analysed without computing them."""
    from app.jobs.results import EpisodeRecorder

    db = Database(tmp_path / "gsmn.sqlite")
    evaluation = compact_evaluation(ENVS[:3], lambda e: e != 86)
    eid = db.add_evaluation(system="oracle", checkpoint=None, env_ids=list(ENVS[:3]), label="flown")
    recorder = EpisodeRecorder(db)
    for position, ep in enumerate(evaluation["episodes"]):
        recorder.record(eid, position, {**ep, "trajectory": [[ep["final_x"], ep["final_y"], 2.0, 0.0]]},
                        preset("tiny"), None, None)
    kept = db.facts(eid)
    assert sorted(kept) == list(ENVS[:3])
    assert kept[86] == facts_of(evaluation["episodes"][1], preset("tiny"), None)
    assert kept[86]["stopped_at"] == evaluation["episodes"][1]["noun_phrase"] and kept[86]["grounded"] is None
    from app.jobs.analysis import row_facts

    assert row_facts(db.episode(eid, 86), preset("tiny")) == kept[86], "the same as from the row"
    db.close()


def test_a_record_without_what_the_facts_need_is_recorded_and_analysed_from_its_row(tmp_path):
    """A progress line or an imported file without the instruction's landmark index and goal (an older writer's):
    the episode is recorded all the same, without facts, and the analysis computes them from its row."""
    from app.jobs.results import EpisodeRecorder

    db = Database(tmp_path / "gsmn.sqlite")
    (ep,) = compact_evaluation((85,), lambda e: True)["episodes"]
    eid = db.add_evaluation(system="oracle", checkpoint=None, env_ids=[85], label="old file", status="finished")
    bare = {k: v for k, v in ep.items() if k not in ("landmark_index", "goal_x", "goal_y")}
    EpisodeRecorder(db).record(eid, 0, bare, preset("tiny"), None, None)
    assert len(db.episodes(eid)) == 1 and db.facts(eid) == {}
    found = Analyses(db, preset("tiny"), tmp_path).analysis(eid)
    assert found["n"] == 1 and db.facts(eid)[85] == facts_of(ep, preset("tiny"), None)
    db.close()
