"""What the Episodes list says of a kept episode (issue 77, item 5), without a browser: a fork and a comparison's side
kept in the record's task JSON and given back in the API's summary (an older row has none), the search by checkpoint
and the policies flown, and a row's words: who flew it, how it ended in its result line's number, its colour, and a
list note that counts as the storage line does. The browser's view of them: tests/test_episodes_list_browser.py."""

from __future__ import annotations

import json
import types

import pytest

from app.api.models import EpisodeSummary, summary
from app.jobs.db import Database
from app.jobs.kept import policies_flown, row_summary, search
from app.jobs.kept_store import kept_row
from app.live.recording import Episode, EpisodeResult
from app.page.episodes_view import ending, flier, list_note, row_color, row_label
from gsmn.config import preset
from gsmn.task.rollout import task_for_env

pytestmark = pytest.mark.unit
CONFIG = preset("tiny")
NAMES = {"/ck/gsmn": "gsmn", "/ck/table2/no-plan": "table2/no-plan"}  # resolved folder -> the name offered


def episode(episode_id: int, policy: str = "model", checkpoint: str | None = "/ck/gsmn", **fields) -> Episode:
    return Episode(id=episode_id, task=task_for_env(217, CONFIG), policy=policy, system="gsmn",
                   checkpoint=checkpoint, horizon=70, **fields)


def result(steps: int, stopped: bool, success: bool) -> EpisodeResult:
    return EpisodeResult(success=success, landmark_success=success, goal_distance=1.5, landmark_distance=2.0,
                         final_side="left", steps=steps, stopped=stopped, final_x=1.0, final_y=2.0,
                         stop_probability=0.9)


def kept(tmp_path, *episodes: Episode) -> Database:
    db = Database(tmp_path / "gsmn.sqlite")
    for e in episodes:
        db.add_kept(kept_row(e, CONFIG.world))
    return db


def test_a_fork_and_a_comparison_are_kept_and_summarised(tmp_path):
    fork = episode(5, fork=types.SimpleNamespace(episode_id=2, step=30))  # app.live.compare.ForkPoint's fields
    first = episode(6, policy="expert", comparison=3, compared_with=7)
    second = episode(7, policy="mirror", comparison=3, compared_with=6)
    plain = episode(8)
    db = kept(tmp_path, fork, first, second, plain)
    rows = {e.id: row_summary(db.kept(e.id)) for e in (fork, first, second, plain)}
    assert (rows[5]["fork_of"], rows[5]["fork_step"], rows[5]["comparison"]) == (2, 30, None)
    assert (rows[6]["comparison"], rows[6]["comparison_side"], rows[6]["compared_with"]) == (3, 1, 7)
    assert (rows[7]["comparison"], rows[7]["comparison_side"], rows[7]["compared_with"]) == (3, 2, 6)
    assert all(rows[8][k] is None for k in ("fork_of", "fork_step", "comparison", "comparison_side", "compared_with"))
    for e in (fork, first, second, plain):  # the API says the same of an episode in memory and of its row
        fields = ("fork_of", "fork_step", "comparison", "comparison_side", "compared_with")
        assert {k: getattr(summary(e), k) for k in fields} == {k: rows[e.id][k] for k in fields}
        EpisodeSummary(**rows[e.id])
    # a row written before these were kept reads as related to nothing
    task = json.loads(db.kept(5)["task"])
    del task["fork"]
    db.update_kept(5, task=json.dumps(task))
    assert row_summary(db.kept(5))["fork_of"] is None
    db.close()


def test_search_by_checkpoint_and_the_policies_flown(tmp_path):
    db = kept(tmp_path, episode(1), episode(2, checkpoint="/ck/table2/no-plan"), episode(3, policy="mirror"),
              episode(4, policy="expert"), episode(5, policy="expert", checkpoint="/ck/table2/no-plan"))
    assert [int(r["id"]) for r in search(db, checkpoint="/ck/gsmn")] == [4, 3, 1]
    assert [int(r["id"]) for r in search(db, policy="model", checkpoint="/ck/gsmn")] == [1]
    assert len(search(db, columns="id")) == 5
    # newest first; the expert once, whoever watched
    assert policies_flown(db) == [("expert", None), ("mirror", "/ck/gsmn"), ("model", "/ck/table2/no-plan"),
                                  ("model", "/ck/gsmn")]
    db.close()


def test_a_row_names_who_flew_it_and_ends_as_its_result_line(tmp_path):
    assert flier("model", "/ck/table2/no-plan", NAMES) == "model table2/no-plan"
    assert flier("mirror", "/ck/gsmn", NAMES) == "model gsmn, mirror ensemble"
    assert flier("model", "/elsewhere/run/checkpoint", NAMES) == "model checkpoint"  # offered by no name
    assert flier("expert", "/ck/gsmn", NAMES) == "expert"
    stopped = episode(1, status="finished", result=result(99, stopped=True, success=True))
    horizon = episode(2, status="finished", result=result(70, stopped=False, success=False))
    cancelled = episode(3, status="cancelled")
    fork = episode(4, status="finished", result=result(40, True, False), fork=types.SimpleNamespace(episode_id=2,
                                                                                                    step=12))
    db = kept(tmp_path, stopped, horizon, cancelled, fork)
    for e in (stopped, horizon, fork):
        db.update_kept(e.id, status="finished", result=json.dumps(e.result.__dict__), success=int(e.result.success),
                       steps=e.result.steps + 1)  # the steps recorded count the start too
    db.update_kept(3, steps=42)
    rows = {i: row_summary(db.kept(i)) for i in (1, 2, 3, 4)}
    assert ending(rows[1]) == "said STOP after 99 steps"  # the result line: "said STOP after **99** steps"
    assert ending(rows[2]) == "ran out of steps after 70 steps"  # "ran out of steps (horizon 70) after **70** steps"
    assert ending(rows[3]) == "at step 41"  # "cancelled at step 41, the timeline's last"
    label = row_label(rows[4], NAMES)
    assert label.startswith("#4 · failure · go to the right side of the rock · env 217 · model gsmn · fork of #2 "
                            "at step 12 · said STOP after 40 steps · ")
    assert [row_color(rows[i]) for i in (1, 2, 3)] == ["green", "red", "gray"]
    db.close()


def test_the_list_note_counts_as_the_storage_line():
    assert list_note(12, 14, 14, filtered=False) == ("12 of 14 kept episodes shown, the newest first (narrow the "
                                                     "search for older ones). Click one to replay it.")
    assert list_note(3, 3, 3, filtered=False) == "3 of 3 kept episodes shown. Click one to replay it."
    assert list_note(1, 1, 6, filtered=True) == "1 of 6 kept episodes shown: 1 matches the search. Click one to " \
                                                "replay it."
    assert list_note(0, 0, 6, filtered=True) == "No kept episode matches the search."
    assert list_note(0, 0, 0, filtered=False) == "No episode kept yet: run one."
