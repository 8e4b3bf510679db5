"""World edits (gsmn/task/edits.py): a moved landmark takes the goal, the demonstration and the expert with it in the
real simulator; a removed named landmark refuses the instruction; every edit that cannot stand is refused saying
why; indices and ambiguity follow the edits."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gsmn.config import preset
from gsmn.task.baselines import ExpertPolicy
from gsmn.task.edits import EditError, WorldEdit, edit_world, edited_task, edits_from_text, parse_edits
from gsmn.task.instructions import goal_position
from gsmn.task.metrics import side_of
from gsmn.task.rollout import rollout, task_for_env
from gsmn.world.env import Env

pytestmark = pytest.mark.unit

CONFIG = preset("tiny")
TASK = task_for_env(70, CONFIG)  # "go to the back side of the pumpkin", start (30, 0); 8 landmarks
NAMED = TASK.instruction.landmark_index


def free_spot(avoid=(), radius: float = 3.0) -> tuple[float, float]:
    """A place where a landmark of `radius` may stand (clear of the start and of the landmarks but those `avoid`ed)."""
    c = CONFIG.world
    for x in np.arange(4.0, 26.5, 0.5):
        for y in np.arange(4.0, 26.5, 0.5):
            far = all(math.dist((x, y), (lm.x, lm.y)) > lm.radius + radius + c.landmark_gap
                      for k, lm in enumerate(TASK.world.landmarks) if k not in avoid)
            clear = math.dist((x, y), (TASK.world.start_x, TASK.world.start_y)) > radius + c.start_clearance + 1
            if far and clear:
                return float(x), float(y)
    raise AssertionError("no free spot")


def test_a_moved_landmark_takes_the_goal_the_demonstration_and_the_expert_with_it():
    box = next(k for k, lm in enumerate(TASK.world.landmarks) if lm.noun_phrase == "box")  # mid-field, 14 m away
    x, y = TASK.world.landmarks[box].x, TASK.world.landmarks[box].y  # the field has no room otherwise
    task = edited_task(TASK, parse_edits([{"op": "remove", "landmark": box},
                                          {"op": "move", "landmark": NAMED, "x": x, "y": y}]), CONFIG)
    moved = task.world.landmarks[task.instruction.landmark_index]
    assert (moved.noun_phrase, moved.x, moved.y) == (TASK.instruction.noun_phrase, x, y)
    assert task.instruction.text == TASK.instruction.text
    assert np.allclose(task.instruction.goal, goal_position(task.world, task.instruction.landmark_index, "back"))
    assert side_of((x, y), task.world.start_position, task.instruction.goal) == "back"
    assert np.allclose(task.path[-1], task.instruction.goal) and not np.allclose(task.path[-1], TASK.path[-1])
    record = rollout(Env(CONFIG), ExpertPolicy(CONFIG), task, CONFIG.task.horizon)  # the real simulator
    assert record.success and record.stopped
    assert math.dist((record.final_x, record.final_y), task.instruction.goal) < 2.0
    assert (record.landmark_x, record.landmark_y) == (x, y)
    assert math.dist((record.final_x, record.final_y), TASK.instruction.goal) > 6.0, "not where it used to be"


def test_a_removed_named_landmark_refuses_the_instruction_and_another_keeps_it():
    with pytest.raises(EditError, match=r"names the pumpkin \(landmark \d\), which the edits remove"):
        edited_task(TASK, parse_edits([{"op": "remove", "landmark": NAMED}]), CONFIG)
    other = 0 if NAMED != 0 else 1
    task = edited_task(TASK, parse_edits([{"op": "remove", "landmark": other}]), CONFIG)
    assert len(task.world.landmarks) == len(TASK.world.landmarks) - 1
    assert task.world.landmarks[task.instruction.landmark_index] == TASK.world.landmarks[NAMED]
    assert task.instruction.landmark_index == NAMED - (other < NAMED)
    assert np.allclose(task.instruction.goal, TASK.instruction.goal)


def test_an_added_landmark_of_the_same_name_makes_the_instruction_ambiguous():
    """A second pumpkin where the largest other landmark stood (removed first: the field has no room otherwise)."""
    others = [k for k in range(len(TASK.world.landmarks)) if k != NAMED]
    gone = max(others, key=lambda k: TASK.world.landmarks[k].radius)
    spot = TASK.world.landmarks[gone]
    assert not TASK.instruction.ambiguous
    task = edited_task(TASK, parse_edits([{"op": "remove", "landmark": gone},
                                          {"op": "add", "noun_phrase": "pumpkin", "x": spot.x, "y": spot.y}]), CONFIG)
    assert task.instruction.ambiguous and len(task.world.landmarks_named("pumpkin")) == 2
    added = task.world.landmarks[-1]
    assert added.noun_phrase == "pumpkin" and (added.x, added.y) == (spot.x, spot.y)
    assert task.world.landmarks[task.instruction.landmark_index] == TASK.world.landmarks[NAMED]


def test_edits_that_cannot_stand_are_refused_saying_why():
    lm = TASK.world.landmarks[NAMED]
    other = TASK.world.landmarks[0 if NAMED != 0 else 1]
    cases = {
        "off the field": [{"op": "move", "landmark": NAMED, "x": 1.0, "y": 15.0}],
        "stand on the drone": [{"op": "move", "landmark": NAMED, "x": 27.0, "y": 3.0}],
        "overlap the": [{"op": "move", "landmark": NAMED, "x": other.x + 0.5, "y": other.y}],
        "is not one of this world's 8": [{"op": "remove", "landmark": 8}],
        "was removed by an earlier edit": [{"op": "remove", "landmark": 0}, {"op": "move", "landmark": 0, "x": 9.0,
                                                                             "y": 9.0}],
        "no landmark called 'unicorn'": [{"op": "add", "noun_phrase": "unicorn", "x": 9.0, "y": 9.0}],
    }
    for message, edits in cases.items():
        with pytest.raises(EditError, match=message):
            edited_task(TASK, parse_edits(edits), CONFIG)
    # at a fork the drone is where it flew to: a landmark may not be put there, and may stand at the start
    with pytest.raises(EditError, match=r"would stand on the drone at \(15.0, 15.5\)"):
        edit_world(TASK.world, [WorldEdit("move", NAMED, 15.0, 15.0)], CONFIG, drone_xy=(15.0, 15.5))
    spot = free_spot(avoid=(NAMED,), radius=lm.radius)
    assert edit_world(TASK.world, [WorldEdit("move", NAMED, *spot)], CONFIG)[0].landmarks[NAMED] != lm


@pytest.mark.parametrize(("items", "message"), [
    ([{"op": "paint"}], "op must be one of move, remove, add, got 'paint'"),
    ([{"op": "move", "landmark": 1}], r"world edit 1 \(move\): needs x, y"),
    ([{"op": "remove", "landmark": 1, "x": 3.0}], "takes no x"),
    ([{"op": "move", "landmark": True, "x": 1.0, "y": 2.0}], "landmark must be an index"),
    ([{"op": "move", "landmark": -1, "x": 1.0, "y": 2.0}], "landmark must be an index"),
    ([{"op": "add", "noun_phrase": "tank", "x": float("nan"), "y": 2.0}], "x must be a finite number"),
    ([{"op": "add", "noun_phrase": "tank", "x": "3", "y": 2.0}], "x must be a finite number"),
    ([{"op": "remove", "landmark": 0}] * 33, "at most 32 world edits"),
])
def test_malformed_edits_are_refused_naming_the_edit(items, message):
    with pytest.raises(EditError, match=message):
        parse_edits(items)


def test_no_edits_is_the_task_itself_and_edits_round_trip():
    assert edited_task(TASK, (), CONFIG) is TASK
    items = [{"op": "move", "landmark": 3, "x": 12.0, "y": 20.5}, {"op": "remove", "landmark": 5},
             {"op": "add", "noun_phrase": "tank", "x": 4.0, "y": 9.0}]
    assert [e.to_dict() for e in parse_edits(items)] == items


def test_a_kept_episode_reads_back_its_edited_world(tmp_path):
    """The record keeps the edits with the episode (its task JSON) and makes them again on reading it back, so a
    kept episode, its link and its export show the world it flew."""
    from app.jobs.db import Database
    from app.jobs.kept import row_summary
    from app.jobs.kept_store import KeptStore, kept_row
    from app.live.recording import Episode

    edits = parse_edits([{"op": "remove", "landmark": 0 if NAMED != 0 else 1}])
    task = edited_task(TASK, edits, CONFIG)
    db = Database(tmp_path / "gsmn.sqlite")
    db.add_kept(kept_row(Episode(id=1, task=task, policy="expert", system="oracle", checkpoint=None, horizon=20,
                                 world_edits=edits), CONFIG.world))
    back = KeptStore(db, CONFIG, 4).load(1)
    assert back.task.world == task.world and back.world_edits == edits
    assert back.task.instruction == task.instruction
    assert row_summary(db.kept(1))["world_edits"] == [e.to_dict() for e in edits]
    db.close()


def test_edits_typed_in_a_few_words():
    box = next(k for k, lm in enumerate(TASK.world.landmarks) if lm.noun_phrase == "box")
    edits = edits_from_text("move pumpkin to 12 20.5; remove box; add tank at 4, 9", TASK.world)
    assert [e.to_dict() for e in edits] == [{"op": "move", "landmark": NAMED, "x": 12.0, "y": 20.5},
                                            {"op": "remove", "landmark": box},
                                            {"op": "add", "noun_phrase": "tank", "x": 4.0, "y": 9.0}]
    assert edits_from_text("remove 3", TASK.world)[0].landmark == 3 and edits_from_text("  ", TASK.world) == ()
    for text, message in (("move anvil to 3 4", "no anvil in this world"), ("fly pumpkin", "write 'move NAME"),
                          ("move pumpkin to x 4", "could not convert"), ("add tank 4 9", "write 'move NAME")):
        with pytest.raises(EditError, match=message):
            edits_from_text(text, TASK.world)


def test_the_result_panel_says_what_was_changed():
    from app.live.recording import Episode
    from app.render.panels import edits_text

    edits = edits_from_text("remove box; add tank at 4 9", TASK.world)
    episode = Episode(id=1, task=TASK, policy="expert", system="oracle", checkpoint=None, horizon=20,
                      world_edits=edits)
    box = next(k for k, lm in enumerate(TASK.world.landmarks) if lm.noun_phrase == "box")
    assert edits_text(episode) == f"removed landmark {box}; added a tank at (4.0, 9.0)"


def test_an_added_landmark_is_simulated_and_seen_by_the_camera():
    """A mailbox added 10 m ahead of the drone at the start (the fir tree and the car, in the way, removed first): the
    simulator builds a body for it and the first camera image shows it (pixels change, in the middle of the picture);
    the world without it renders as before."""
    w = TASK.world
    ahead = (w.start_x + 10.0 * math.cos(w.start_yaw), w.start_y + 10.0 * math.sin(w.start_yaw))
    w, _ = edit_world(w, edits_from_text("remove fir tree; remove car", w), CONFIG)  # in the way: removed first
    edits = parse_edits([{"op": "add", "noun_phrase": "mailbox", "x": ahead[0], "y": ahead[1]}])
    edited, _ = edit_world(w, edits, CONFIG)
    env = Env(CONFIG)
    before = env.reset(70, None, w).image.astype(int)
    bodies = env.sim.model.nbody
    after = env.reset(70, None, edited).image.astype(int)
    assert env.sim.model.nbody == bodies + 1, "a body for the mailbox"
    changed = np.abs(after - before).max(axis=2) > 24
    h, width = changed.shape
    assert changed.mean() > 0.003, f"only {changed.mean():.3%} of the pixels changed"  # a mailbox 10 m away
    ys, xs = np.nonzero(changed)
    assert width / 3 < xs.mean() < 2 * width / 3 and h / 4 < ys.mean() < 3 * h / 4, "straight ahead"
    again = env.reset(70, None, w).image.astype(int)
    assert np.array_equal(again, before)
