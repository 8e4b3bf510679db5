"""Failure attribution (gsmn/attribution.py): each stage on hand-made maps and heads whose readings are known, then
on a real episode flown by a (untrained) GSMN through `evaluate(..., record_dir=...)`, checked against the
dashboard's own reading of the same maps."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest

from gsmn.attribution import (
    STAGE_COLOURS,
    STAGE_TITLES,
    STAGES,
    Attribution,
    FinalMaps,
    Heads,
    attribute,
    attribute_record,
    cell_centre,
    cell_of,
    count_stages,
    load_trace,
    merged_stage,
    reported_stages,
    save_trace,
    trace_path,
    trained_heads,
)
from gsmn.config import preset, with_overrides
from gsmn.task.rollout import task_for_env
from gsmn.world.landmarks import CATALOGUE

pytestmark = pytest.mark.unit

N = 32
K = len(CATALOGUE)
TASK = task_for_env(70, preset("tiny"))  # "go to the back side of the pumpkin", start (30, 0)
WORLD, INSTRUCTION = TASK.world, TASK.instruction
TARGET = WORLD.landmarks[INSTRUCTION.landmark_index]


def heads() -> Heads:
    """Perception: the semantic map's channel k votes for class k. Grounding: P(named) = sigmoid(relevance
    channel 0). Goal: P(goal) = sigmoid(goal channel 0)."""
    return Heads(perception_w=10 * np.eye(K, dtype=np.float32), perception_b=np.zeros(K, np.float32),
                 grounding_w=np.array([[0, 0, 0], [1, 0, 0]], np.float32), grounding_b=np.zeros(2, np.float32),
                 goal_w=np.array([[0, 0], [1, 0]], np.float32), goal_b=np.zeros(2, np.float32))


def cell(x: float, y: float) -> tuple[int, int]:
    return cell_of(x, y, WORLD.field_size, N)


def maps_where(perceive: str | None = "pumpkin", relevance: dict[str, float] | None = None,
               goal_xy: tuple[float, float] | None = None) -> FinalMaps:
    """Every landmark's cell observed and read as itself, except the target, read as `perceive` (None: never
    observed). Relevance -4 everywhere but the given landmarks; goal map peaked at goal_xy (default: the goal)."""
    semantic = np.zeros((K, N, N), np.float32)
    for lm in WORLD.landmarks:
        semantic[lm.class_id][cell(lm.x, lm.y)] = 1.0
    r, c = cell(TARGET.x, TARGET.y)
    semantic[:, r, c] = 0.0
    if perceive is not None:
        semantic[next(k for k, m in enumerate(CATALOGUE) if m.noun_phrase == perceive), r, c] = 1.0
    rel = np.full((3, N, N), -4.0, np.float32)
    for name, value in (relevance if relevance is not None else {"pumpkin": 3.0}).items():
        lm = next(lm for lm in WORLD.landmarks if lm.noun_phrase == name)
        rel[0][cell(lm.x, lm.y)] = value
    goal = np.full((2, N, N), -5.0, np.float32)
    goal[0][cell(*(goal_xy or INSTRUCTION.goal))] = 4.0
    return FinalMaps(semantic, rel, goal)


def run(maps: FinalMaps, final=(20.0, 5.0), stopped=True, success=False, world=WORLD, instruction=INSTRUCTION):
    return attribute(maps, heads(), world, instruction, final, stopped, success)


def test_a_landmark_never_seen_is_a_perception_failure():
    a = run(maps_where(perceive=None))
    assert a.stage == "perception" and not a.observed and not a.perceived and a.top_class is None
    assert "never" in a.reason
    assert (a.landmark_row, a.landmark_col) == cell(TARGET.x, TARGET.y)


def test_a_landmark_seen_as_another_is_a_perception_failure():
    a = run(maps_where(perceive="car"))
    assert a.stage == "perception" and a.observed and not a.perceived and a.top_class == "car"
    assert a.landmark_class_rank > 1 and "car" in a.reason


def test_a_model_of_the_same_name_counts_as_perceived():
    world = dataclasses.replace(WORLD, landmarks=tuple(
        dataclasses.replace(lm, noun_phrase="palm tree", class_id=3) if i == INSTRUCTION.landmark_index else lm
        for i, lm in enumerate(WORLD.landmarks)))
    instruction = dataclasses.replace(INSTRUCTION, noun_phrase="palm tree",
                                      text="go to the back side of the palm tree")
    semantic = maps_where(perceive=None).semantic_map_w.copy()
    semantic[4][cell(TARGET.x, TARGET.y)] = 1.0  # read as palm_tree_2, the target is palm_tree_1
    maps = FinalMaps(semantic, maps_where().relevance_map_w, maps_where().goal_map_w)
    a = run(maps, world=world, instruction=instruction)
    assert a.perceived and a.top_class == "palm tree" and a.landmark_class_rank == 2


def test_relevance_higher_at_another_landmark_is_a_grounding_failure():
    a = run(maps_where(relevance={"pumpkin": 1.0, "globe": 2.5}))
    assert a.stage == "grounding" and a.perceived and not a.grounded
    assert a.other_landmark == "globe" and a.p_named_other > a.p_named
    assert a.p_named == pytest.approx(1 / (1 + np.exp(-1.0)), abs=1e-5)
    assert "globe" in a.reason


def test_landmarks_sharing_the_name_do_not_compete_in_grounding():
    twin = dataclasses.replace(WORLD.landmarks[7], noun_phrase="pumpkin", class_id=TARGET.class_id)  # the globe
    world = dataclasses.replace(WORLD, landmarks=WORLD.landmarks[:7] + (twin,))
    a = run(maps_where(relevance={"pumpkin": 1.0, "globe": 2.5}), world=world,
            instruction=dataclasses.replace(INSTRUCTION, ambiguous=True))
    assert a.grounded and a.other_landmark != "pumpkin"


def test_a_goal_map_peaking_on_the_wrong_side_is_a_goal_failure():
    front = (TARGET.x + 3.0, TARGET.y - 3.0)  # between the start (30, 0) and the pumpkin
    a = run(maps_where(goal_xy=front))
    assert a.stage == "goal" and a.perceived and a.grounded and not a.goal_right
    px, py = cell_centre(*cell(*front), WORLD.field_size, N)
    assert (a.goal_peak_x, a.goal_peak_y) == (px, py)
    assert a.goal_peak_error == pytest.approx(np.hypot(px - INSTRUCTION.goal_x, py - INSTRUCTION.goal_y))


def test_a_right_goal_map_and_a_wrong_end_is_a_control_failure():
    a = run(maps_where(), final=(25.0, 5.0), stopped=True)
    assert a.stage == "control" and a.goal_right and a.goal_peak_error < 1.0
    assert a.final_to_peak > 15 and "stopped" in a.reason
    b = run(maps_where(), final=(25.0, 5.0), stopped=False)
    assert b.stage == "control" and "never said STOP" in b.reason


def test_a_control_failure_says_which_way_the_drone_missed_the_peak():
    """With the final heading, a control failure reads as stopped short, overshot or beside the goal peak."""
    gx, gy = INSTRUCTION.goal
    east, north = 0.0, np.pi / 2
    cases = {"ahead": ((gx - 3.0, gy), east), "behind": ((gx + 3.0, gy), east),
             "left": ((gx, gy - 3.0), east), "right": ((gx, gy + 3.0), east),
             "behind ": ((gx, gy + 3.0), north)}  # the same place, facing north: the peak is behind
    for want, (final, yaw) in cases.items():
        a = attribute(maps_where(), heads(), WORLD, INSTRUCTION, final, True, False, final_yaw=yaw)
        assert a.stage == "control" and a.peak_bearing == want.strip(), want
        assert {"ahead": "short", "behind": "overshot", "left": "to its left",
                "right": "to its right"}[want.strip()] in a.reason
    assert run(maps_where(), final=(gx - 3.0, gy)).peak_bearing is None  # no heading, no direction
    never = attribute(maps_where(), heads(), WORLD, INSTRUCTION, (gx - 3.0, gy), False, False, final_yaw=east)
    assert "never said STOP" in never.reason and never.peak_bearing == "ahead"
    old = {k: v for k, v in never.to_dict().items() if k != "peak_bearing"}  # saved before the field existed
    assert Attribution.from_dict(old).peak_bearing is None


def test_without_a_trained_goal_head_goal_and_control_are_one_stage():
    """A model trained without J_plan has an untrained goal head: its P(goal) must not decide the stage."""
    untrained = dataclasses.replace(heads(), goal_trained=False)
    wrong_side = (TARGET.x + 3.0, TARGET.y - 3.0)
    for goal_xy in (None, wrong_side):  # "control" and "goal" with a trained head
        a = attribute(maps_where(goal_xy=goal_xy), untrained, WORLD, INSTRUCTION, (25.0, 5.0), True, False)
        assert a.stage == "goal_or_control" and a.goal_right is None and "J_plan" in a.reason
    assert run(maps_where(relevance={"pumpkin": 1.0, "globe": 2.5})).stage == "grounding"  # earlier stages stay
    ok = attribute(maps_where(), untrained, WORLD, INSTRUCTION, tuple(INSTRUCTION.goal), True, True)
    assert ok.stage is None
    gsmn_counts = dict.fromkeys(STAGES, 0) | dict.fromkeys(("perception", "grounding", "goal", "control"), 1)
    assert reported_stages(gsmn_counts) == ("perception", "grounding", "goal", "control")  # tables keep 4 rows
    assert reported_stages(gsmn_counts, {"goal_or_control": 3})[-1] == "goal_or_control"


def test_an_untrained_head_merges_its_stage_with_the_next_judged_one():
    """Without J_percept a seen landmark's recognition is not judged and the grounding head's verdict covers it;
    without J_ground grounding is not judged and the goal head's verdict covers it. "Never seen" needs no head."""
    no_percept = dataclasses.replace(heads(), perception_trained=False)
    seen_as_car = attribute(maps_where(perceive="car"), no_percept, WORLD, INSTRUCTION, (20.0, 5.0), True, False)
    assert seen_as_car.perceived is None and seen_as_car.stage == "control"  # grounded and goal right after all
    not_grounded = attribute(maps_where(perceive="car", relevance={"pumpkin": 1.0, "globe": 2.5}), no_percept,
                             WORLD, INSTRUCTION, (20.0, 5.0), True, False)
    assert not_grounded.stage == "perception_or_grounding" and not_grounded.reason.startswith("Seen but not grounded")
    assert "J_percept" in not_grounded.reason
    never = attribute(maps_where(perceive=None), no_percept, WORLD, INSTRUCTION, (20.0, 5.0), True, False)
    assert never.stage == "perception" and never.perceived is False and "J_percept" not in never.reason

    no_ground = dataclasses.replace(heads(), grounding_trained=False)
    wrong_side = (TARGET.x + 3.0, TARGET.y - 3.0)
    for relevance in ({"pumpkin": 3.0}, {"pumpkin": 1.0, "globe": 2.5}):  # grounded or not: not read
        a = attribute(maps_where(relevance=relevance, goal_xy=wrong_side), no_ground, WORLD, INSTRUCTION,
                      (20.0, 5.0), True, False)
        assert a.grounded is None and a.stage == "grounding_or_goal" and "J_ground" in a.reason
        assert a.reason.startswith("Perceived, but the goal map peaks")
    right_goal = attribute(maps_where(relevance={"pumpkin": 1.0, "globe": 2.5}), no_ground, WORLD, INSTRUCTION,
                           (25.0, 5.0), True, False)
    assert right_goal.stage == "control" and "J_ground" not in right_goal.reason
    assert attribute(maps_where(perceive="car"), no_ground, WORLD, INSTRUCTION, (20.0, 5.0), True,
                     False).stage == "perception"  # a trained perception head still judges its stage
    assert merged_stage("control", ("grounding", "goal")) == "grounding_or_goal_or_control"
    assert count_stages([dataclasses.replace(right_goal, stage="grounding_or_goal_or_control")])[
        "grounding_or_goal_or_control"] == 1
    counts = dict.fromkeys(STAGES, 1) | {"goal_or_control": 0, "grounding_or_goal": 0}
    assert reported_stages(counts) == ("perception", "grounding", "goal", "control", "perception_or_grounding")
    assert reported_stages(counts, {"grounding_or_goal_or_control": 2})[-1] == "grounding_or_goal_or_control"
    assert set(STAGE_TITLES) == set(STAGES) == set(STAGE_COLOURS)


def test_which_heads_a_model_trained_is_read_from_its_configuration():
    from gsmn.config import LossConfig, RunConfig
    from gsmn.model import build_model

    def trained(kind: str = "gsmn", **loss) -> dict[str, bool]:
        config = dataclasses.replace(preset("tiny"), loss=dataclasses.replace(LossConfig(), **loss))
        assert isinstance(config, RunConfig)
        model = build_model(kind, config)
        h = Heads.of(model)
        assert (h.perception_trained, h.grounding_trained, h.goal_trained) == tuple(trained_heads(model).values())
        return trained_heads(model)

    assert trained() == {"perception": True, "grounding": True, "goal": True}
    assert trained("gsmn-no-plan") == {"perception": True, "grounding": True, "goal": False}
    assert trained(grounding=False) == {"perception": True, "grounding": False, "goal": True}
    assert trained(perception=False) == {"perception": False, "grounding": True, "goal": True}
    assert trained(goal=False)["goal"] is False and trained(language=False) == trained()
    assert trained(grounding_weight=0.0)["grounding"] is False


def test_a_success_has_no_stage_but_keeps_its_evidence_and_counts_add_up():
    ok = run(maps_where(), final=tuple(INSTRUCTION.goal), success=True)
    assert ok.stage is None and ok.goal_right and ok.final_to_peak < 1.0
    stages = [run(maps_where(perceive=None)), run(maps_where(relevance={"pumpkin": 1.0, "globe": 2.5})),
              run(maps_where()), ok, None]
    assert count_stages(stages) == dict.fromkeys(STAGES, 0) | {"perception": 1, "grounding": 1, "control": 1}
    assert type(ok).from_dict(json.loads(json.dumps(ok.to_dict()))) == ok


@pytest.mark.slow
def test_a_real_episode_trace_and_its_attribution(tmp_path, untrained_checkpoint):
    """An untrained GSMN flies env 70 through evaluate(); its recorded trace is what the model held, and the
    attribution reads the maps as the dashboard's layers do."""
    from app.live.models import MapHeads
    from app.render.layers import inspect_cell
    from gsmn.evaluation import evaluate, results_dict
    from gsmn.model.checkpoint import load_checkpoint

    config = with_overrides(preset("tiny"), {"task.horizon": "25"})
    folder = untrained_checkpoint
    [record] = evaluate("gsmn", [70], config, folder, record_dir=tmp_path / "rec")
    trace = load_trace(trace_path(tmp_path / "rec", 70))
    T = record.steps + 1  # observations, the last one included
    assert trace.stop_probability.shape == (T,) and trace.goal_peak_rc.shape == (T, 2)
    assert trace.maps.semantic_map_w.shape == (32, 32, 32) and trace.maps.semantic_map_w.dtype == np.float16
    assert np.allclose(trace.v, [a[0] for a in record.actions], atol=1e-4)  # the model flew: its actions

    model, *_ = load_checkpoint(folder)
    a = attribute(trace.maps, Heads.of(model), WORLD, INSTRUCTION, (record.final_x, record.final_y),
                  record.stopped, record.success, final_yaw=record.trajectory[-1][3])
    assert record.success is False and a.stage in STAGES
    assert a.p_named == pytest.approx(float(trace.p_named[-1]), abs=2e-3)  # float16 maps vs float32 steps
    assert (cell(a.goal_peak_x, a.goal_peak_y) == tuple(trace.goal_peak_rc[-1])) or \
        a.goal_peak_p == pytest.approx(float(trace.goal_peak_p[-1]), abs=2e-3)  # a tie may pick another cell
    report = inspect_cell(TARGET.x, TARGET.y, trace.maps.semantic_map_w, trace.maps.relevance_map_w,
                          trace.maps.goal_map_w, MapHeads.of(model), WORLD)
    assert report.p_named == pytest.approx(a.p_named, abs=1e-5) and report.observed == a.observed
    if a.observed:
        assert report.classes[0][0] == a.top_class

    # The same from the episode as `gsmn eval --json` writes it, and over a whole result file.
    from_record = attribute_record(json.loads(json.dumps(record.to_dict())), trace, Heads.of(model), config)
    assert replace(from_record, failed_from=None) == a
    # and when each stage went wrong for good, from the per-step agreement with the ground truth (gsmn.analysis.truth)
    assert trace.truth.shape == (T, 4) and set(from_record.failed_from) == {"perception", "grounding", "goal"}
    assert all(v is None or 0 <= v < T for v in from_record.failed_from.values())
    results = tmp_path / "eval.json"
    results.write_text(json.dumps(results_dict("gsmn", str(folder), [record], config, 1.0, 1)))
    script = [sys.executable, "-m", "gsmn.cli", "attribute"]
    counts = subprocess.run([*script, str(results), str(tmp_path / "rec")], capture_output=True, text=True)
    assert counts.returncode == 0, counts.stderr
    assert counts.stdout.startswith("1 failures of 1 episodes") and f"{STAGE_TITLES[a.stage]:<15} 1" in counts.stdout
    n_ambiguous = 1 if record.ambiguous else 0
    assert f"{STAGE_TITLES[a.stage]:<15} 1  ({n_ambiguous} with an ambiguous instruction)" in counts.stdout
    flipped = json.loads(results.read_text())  # the same failure with the other ambiguity is counted the other way
    flipped["episodes"][0]["ambiguous"] = not record.ambiguous
    (tmp_path / "flipped.json").write_text(json.dumps(flipped))
    again_counts = subprocess.run([*script, str(tmp_path / "flipped.json"), str(tmp_path / "rec")],
                                  capture_output=True, text=True)
    assert f"({1 - n_ambiguous} with an ambiguous instruction)" in again_counts.stdout, again_counts.stderr
    inside = all(0 <= v <= config.world.field_size for v in (record.final_x, record.final_y))
    assert f"ended outside the field in {0 if inside else 1} episodes" in counts.stdout

    save_trace(tmp_path / "copy.npz", trace)
    again = load_trace(tmp_path / "copy.npz")
    assert np.array_equal(again.maps.goal_map_w, trace.maps.goal_map_w) and np.array_equal(again.v, trace.v)


def test_ambiguous_episodes_are_told_apart_by_where_they_ended():
    """gsmn.analysis.failures.ambiguous_endings (`gsmn attribute`): an ambiguous episode that ended at the named
    landmark, at another of the same name, or at neither is counted so; unambiguous episodes are not counted."""
    from gsmn.analysis.failures import ambiguous_endings
    from gsmn.world.spec import world_for_env

    config = preset("paper")
    world = next(w for w in (world_for_env(i, config.world) for i in range(70, 400))
                 if any(len(w.landmarks_named(lm.noun_phrase)) > 1 for lm in w.landmarks))
    named = next(i for i, lm in enumerate(world.landmarks) if len(world.landmarks_named(lm.noun_phrase)) > 1)
    other = next(lm for i, lm in enumerate(world.landmarks)
                 if i != named and lm.noun_phrase == world.landmarks[named].noun_phrase)
    lm = world.landmarks[named]

    def episode(final_x: float, final_y: float, ambiguous: bool = True) -> dict:
        return {"env_id": world.env_id, "ambiguous": ambiguous, "landmark_index": named,
                "noun_phrase": lm.noun_phrase, "landmark_x": lm.x, "landmark_y": lm.y,
                "final_x": final_x, "final_y": final_y, "success": False}

    far = next((x, y) for x in range(-40, 80, 4) for y in range(-40, 80, 4)
               if all(np.hypot(x - m.x, y - m.y) > 8 for m in world.landmarks))
    results = {"config": config.to_dict(),
               "episodes": [episode(lm.x + 1, lm.y), episode(other.x, other.y + 1), episode(other.x + 0.5, other.y),
                            episode(*far), episode(other.x, other.y, ambiguous=False)]}
    assert ambiguous_endings(results) == {"the named one": 1, "another of that name": 2, "neither": 1}
