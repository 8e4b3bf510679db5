"""Unit tests of the task: metrics and quadrants, instructions and goals, demonstration paths, the expert."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from gsmn.config import ConfigError, DroneConfig, ExpertConfig, TaskConfig, preset
from gsmn.task.demo import DemoPathError, crosses_itself, demonstration_path, path_length
from gsmn.task.expert import Expert
from gsmn.task.instructions import (
    SIDES,
    VOCABULARY,
    InstructionError,
    acceptable,
    instruction_for_env,
    make_instruction,
    sample_instruction,
    tokenize,
)
from gsmn.task.metrics import (
    EpisodeOutcome,
    goal_distance,
    landmark_success,
    record_region_steps,
    region_stop_probability,
    side_of,
    sign_test,
    steps_in_success_region,
    success,
    summarize,
)
from gsmn.task.rollout import task_for_text
from gsmn.task.understand import parse_instruction
from gsmn.world.landmarks import CATALOGUE
from gsmn.world.spec import LandmarkSpec, WorldSpec, start_pose, world_for_env

pytestmark = pytest.mark.unit

_BY_NAME = {m.name: (i, m) for i, m in enumerate(CATALOGUE)}


def landmark(name: str, x: float, y: float, scale: float = 1.0) -> LandmarkSpec:
    i, m = _BY_NAME[name]
    return LandmarkSpec(model=name, noun_phrase=m.noun_phrase, class_id=i, x=x, y=y, yaw=0.0, scale=scale,
                        radius=m.radius * scale)


def make_world(landmarks: list[LandmarkSpec], corner: int = 0, env_id: int = 0) -> WorldSpec:
    x, y, yaw = start_pose(corner, 30.0)
    return WorldSpec(env_id=env_id, field_size=30.0, landmarks=tuple(landmarks), lakes=(), start_corner=corner,
                     start_x=x, start_y=y, start_yaw=yaw)


def _cross(u, v) -> float:
    return float(u[0] * v[1] - u[1] * v[0])


# ---------------------------------------------------------------------------------------------- config


def test_configs_validate():
    TaskConfig()
    ExpertConfig()
    with pytest.raises(ConfigError, match="min_goal_distance"):
        TaskConfig(min_goal_distance=70.0)
    with pytest.raises(ConfigError, match="min_speed"):
        ExpertConfig(min_speed=1.5)
    with pytest.raises(ConfigError, match="waypoint_spacing"):
        ExpertConfig(waypoint_spacing=0.0)


# --------------------------------------------------------------------------------------------- metrics


@pytest.mark.parametrize("point, side", [((12, 0), "back"), ((8, 0), "front"), ((10, 2), "left"),
                                         ((10, -2), "right"), ((13, 1), "back"), ((7, -1), "front")])
def test_side_of_each_quadrant(point, side):
    # Start at the origin looking east at a landmark at (10, 0): north is on the left.
    assert side_of((10, 0), (0, 0), point) == side


def test_side_of_boundaries_at_45_degrees_belong_to_front_and_back():
    assert side_of((10, 0), (0, 0), (11, 1)) == "back"
    assert side_of((10, 0), (0, 0), (11, -1)) == "back"
    assert side_of((10, 0), (0, 0), (9, 1)) == "front"
    assert side_of((10, 0), (0, 0), (9, -1)) == "front"
    assert side_of((10, 0), (0, 0), (11, 1.001)) == "left"
    assert side_of((10, 0), (0, 0), (8.999, -1)) == "front"
    assert side_of((10, 0), (0, 0), (9.001, -1)) == "right"


def test_side_of_from_the_far_corner():
    # Start at (30, 30) looking south-west at (15, 15): the viewer's left is south-east.
    assert side_of((15, 15), (30, 30), (17, 13)) == "left"
    assert side_of((15, 15), (30, 30), (13, 17)) == "right"
    assert side_of((15, 15), (30, 30), (17, 17)) == "front"
    assert side_of((15, 15), (30, 30), (13, 13)) == "back"


def test_success_radius_is_open_at_exactly_6_m():
    lm, start = (10.0, 0.0), (0.0, 0.0)
    assert not landmark_success((16.0, 0.0), lm)  # exactly 6 m: outside ("less than" in the paper)
    assert landmark_success((15.999, 0.0), lm)
    assert success((15.999, 0.0), lm, start, "back")
    assert not success((15.999, 0.0), lm, start, "front")  # right distance, wrong quadrant
    assert not success((16.0, 0.0), lm, start, "back")
    assert landmark_success((16.0, 0.0), lm, radius=6.5)
    assert goal_distance((3, 4), (0, 0)) == 5.0


def test_steps_in_success_region_are_where_a_stop_would_have_succeeded():
    """A flight from the start straight through the landmark at x = 10: in the back quadrant from the centre (which
    counts as back) to 15 m, in the front one from 5 to 9 m, never in the left one; 4 and 16 m are 6 m away."""
    lm, start = (10.0, 0.0), (0.0, 0.0)
    path = [(x, 0.0, 5.0) for x in np.arange(0.0, 20.0, 1.0)]  # (x, y, z) positions, one per step
    assert steps_in_success_region(path, lm, start, "back") == [10, 11, 12, 13, 14, 15]
    assert steps_in_success_region(path, lm, start, "front") == [5, 6, 7, 8, 9]
    assert steps_in_success_region(path, lm, start, "left") == []
    assert steps_in_success_region(path, lm, start, "back", radius=3.0) == [10, 11, 12]
    record = {"trajectory": [(*p, 0.0) for p in path], "landmark_x": 10.0, "landmark_y": 0.0, "start_x": 0.0,
              "start_y": 0.0, "side": "front"}  # as `gsmn eval --json` writes it: (x, y, z, yaw) per step
    assert record_region_steps(record) == [5, 6, 7, 8, 9] and record_region_steps(record, 3.0) == [8, 9]


def test_region_stop_probability_is_the_highest_p_stop_the_policy_acted_on_inside_the_region():
    record = {"stop_probabilities": [0.1, 0.3, 0.2, 0.05, 0.6]}
    assert region_stop_probability(record, [1, 2]) == 0.3 and region_stop_probability(record, [2, 3]) == 0.2
    assert region_stop_probability(record, []) is None  # never entered
    assert region_stop_probability({"stop_probabilities": None}, [1]) is None  # the expert keeps none
    assert region_stop_probability({}, [1]) is None  # a file written before P(stop) was kept
    assert region_stop_probability(record, [4, 5]) is None  # steps it does not have: not a partial answer


def test_sign_test_of_discordant_pairs():
    assert sign_test(0, 0) == 1.0 and sign_test(5, 0) == sign_test(0, 5) == 2 / 32
    assert sign_test(3, 3) == 1.0 and sign_test(9, 2) == sign_test(2, 9) == 2 * (1 + 11 + 55) / 2 ** 11


def _outcome(final, side="back", ambiguous=False) -> EpisodeOutcome:
    return EpisodeOutcome(final_x=final[0], final_y=final[1], landmark_x=10.0, landmark_y=0.0, start_x=0.0,
                          start_y=0.0, side=side, goal_x=13.0, goal_y=0.0, ambiguous=ambiguous)


def test_summarize_hand_made_records():
    records = [
        _outcome((13.0, 0.0)),  # at the goal: success, distance 0
        _outcome((12.0, 0.0), ambiguous=True),  # success, distance 1
        _outcome((10.0, 3.0)),  # at the landmark, left quadrant: landmark success only, distance sqrt(18)
        _outcome((25.0, 0.0)),  # far away: nothing, distance 12
    ]
    s = summarize(records)
    assert s.count == 4 and s.success == 50.0 and s.landmark_success == 75.0
    assert s.mean_distance == pytest.approx((0 + 1 + math.sqrt(18) + 12) / 4)
    assert s.median_distance == pytest.approx((1 + math.sqrt(18)) / 2)
    p = s.pruned
    assert p is not None and p.count == 3 and p.success == pytest.approx(100 / 3)
    assert p.landmark_success == pytest.approx(200 / 3)
    # Plain dicts work too, and give the same numbers.
    assert summarize([r.__dict__ for r in records]) == s
    assert s.to_dict()["pruned"]["count"] == 3


def test_summarize_empty_is_nan():
    s = summarize([])
    assert s.count == 0 and math.isnan(s.success) and math.isnan(s.median_distance)


# ---------------------------------------------------------------------------------------- instructions


@pytest.mark.parametrize("corner", [0, 2])
@pytest.mark.parametrize("side", SIDES)
def test_goal_placement_per_side(corner, side):
    world = make_world([landmark("igloo", 15.0, 14.0, scale=1.2)], corner=corner)
    lm = world.landmarks[0]
    ins = make_instruction(world, 0, side)
    goal, centre, start = ins.goal, lm.position, world.start_position
    assert np.linalg.norm(goal - centre) == pytest.approx(lm.radius)
    assert side_of(centre, start, goal) == side  # on its quadrant's bisector
    d, v = centre - start, goal - centre  # line of sight, landmark to goal
    along, across = float(d @ v) / np.linalg.norm(d), _cross(d, v) / np.linalg.norm(d)
    expected = {"front": (-lm.radius, 0.0), "back": (lm.radius, 0.0), "left": (0.0, lm.radius),
                "right": (0.0, -lm.radius)}[side]
    assert (along, across) == pytest.approx(expected, abs=1e-9)
    assert ins.text == f"go to the {side} side of the igloo"
    assert not ins.ambiguous


def test_left_is_on_the_left_as_seen_from_the_start():
    # Start corner 0 looks north-east at (15, 15): left is north-west of the landmark, right south-east.
    world = make_world([landmark("igloo", 15.0, 15.0)], corner=0)
    r = world.landmarks[0].radius
    assert make_instruction(world, 0, "left").goal == pytest.approx([15 - r / math.sqrt(2), 15 + r / math.sqrt(2)])
    assert make_instruction(world, 0, "right").goal == pytest.approx([15 + r / math.sqrt(2), 15 - r / math.sqrt(2)])
    # From corner 2 (30, 30), looking south-west, left is south-east.
    world = make_world([landmark("igloo", 15.0, 15.0)], corner=2)
    assert make_instruction(world, 0, "left").goal == pytest.approx([15 + r / math.sqrt(2), 15 - r / math.sqrt(2)])


def test_goal_distance_rule():
    # The igloo's front goal is 7.07 - 3.175 = 3.9 m from the start: never drawn; its other sides are.
    world = make_world([landmark("igloo", 5.0, 5.0), landmark("fir_tree", 20.0, 20.0)])
    assert not acceptable(world, make_instruction(world, 0, "front"), TaskConfig())
    assert acceptable(world, make_instruction(world, 0, "left"), TaskConfig())
    drawn = set()
    for seed in range(300):
        ins = sample_instruction(world, np.random.default_rng(seed))
        d = np.linalg.norm(ins.goal - world.start_position)
        assert 6.0 < d < 60.0
        drawn.add((ins.landmark_index, ins.side))
    assert (0, "front") not in drawn and len(drawn) == 7


def test_no_acceptable_instruction_raises():
    world = make_world([landmark("traffic_cone", 3.0, 3.0, scale=0.4)])  # every goal within 6 m of the start
    with pytest.raises(InstructionError, match="no acceptable instruction"):
        sample_instruction(world, np.random.default_rng(0), TaskConfig(instruction_draws=50))


def test_instruction_for_env_is_deterministic_and_in_vocabulary():
    for env_id in range(20):
        world = world_for_env(env_id)
        a, b = instruction_for_env(world), instruction_for_env(world)
        assert a == b
        assert set(tokenize(a.text)) <= set(VOCABULARY)
        assert a.ambiguous == (len(world.landmarks_named(a.noun_phrase)) > 1)
    # A different seed gives a different stream (some instruction differs over 20 worlds).
    worlds = [world_for_env(e) for e in range(20)]
    assert [instruction_for_env(w) for w in worlds] != [instruction_for_env(w, TaskConfig(seed=1)) for w in worlds]


def test_ambiguity_flag():
    world = make_world([landmark("rock_1", 10, 20), landmark("rock_3", 20, 10), landmark("fir_tree", 22, 22)])
    assert make_instruction(world, 0, "left").ambiguous
    assert make_instruction(world, 1, "back").ambiguous
    assert not make_instruction(world, 2, "back").ambiguous


def test_vocabulary_and_tokenize():
    assert tokenize("Go to the LEFT side of the red-barrel!") == ["go", "to", "the", "left", "side", "of", "the",
                                                                   "red", "barrel"]
    assert list(VOCABULARY) == sorted(set(VOCABULARY))
    assert {"go", "to", "the", "side", "of", "left", "right", "front", "back", "christmas", "tree"} <= set(VOCABULARY)


# ---------------------------------------------------------------------------------------- parsing


@pytest.fixture
def barrels_world() -> WorldSpec:
    return make_world([landmark("barrel_1", 10, 20), landmark("red_barrel", 20, 10), landmark("rock_1", 22, 22),
                       landmark("rock_2", 8, 8)])


def test_parse_accepts_free_text(barrels_world):
    ins = parse_instruction("Go to the LEFT side of the red barrel!", barrels_world)
    assert (ins.landmark_index, ins.side, ins.noun_phrase) == (1, "left", "red barrel")
    assert ins == make_instruction(barrels_world, 1, "left")
    # Without "the", and the shorter phrase inside "red barrel" names the other landmark.
    ins = parse_instruction("go to back side of barrel", barrels_world)
    assert (ins.landmark_index, ins.side, ins.noun_phrase) == (0, "back", "barrel")
    ins = parse_instruction("  front ,  rock ", barrels_world)
    assert ins.ambiguous and ins.landmark_index == 2 and ins.side == "front"


def test_parse_rejects_with_clear_messages(barrels_world):
    with pytest.raises(InstructionError, match=r"no landmark named \(not a landmark: quickly, banana\)"):
        parse_instruction("go quickly to the left side of the banana", barrels_world)
    with pytest.raises(InstructionError, match="no side named"):
        parse_instruction("go to the red barrel", barrels_world)
    with pytest.raises(InstructionError, match="several sides named"):
        parse_instruction("go to the left side of the right barrel", barrels_world)
    with pytest.raises(InstructionError,
                       match="there is no igloo in this world; this world has: barrel, red barrel, rock"):
        parse_instruction("go to the left side of the igloo", barrels_world)
    with pytest.raises(InstructionError, match="no landmark named"):
        parse_instruction("go to the left side", barrels_world)
    with pytest.raises(InstructionError, match="several landmarks named"):
        parse_instruction("left side of the rock barrel", barrels_world)
    with pytest.raises(InstructionError, match="empty"):
        parse_instruction(" !? ", barrels_world)


def test_a_typed_instruction_becomes_a_task_with_its_path_or_a_straight_line(barrels_world):
    """gsmn.task.rollout.task_for_text, the one builder of a task from typed text (the dashboard's runner wraps its
    errors): the planner's path to the goal; where there is none, a DemoPathError for the expert, or a straight
    line from the start to the goal for a model; text that names no instruction is an InstructionError."""
    config = preset("tiny")
    task = task_for_text(barrels_world, "go to the left side of the red barrel", config)
    assert task.instruction == make_instruction(barrels_world, 1, "left")
    assert np.array_equal(task.path, demonstration_path(barrels_world, task.instruction.goal, config.expert))
    no_path = dataclasses.replace(config, expert=dataclasses.replace(config.expert, max_demo_steps=2))
    with pytest.raises(DemoPathError, match="did not reach the goal"):
        task_for_text(barrels_world, "go to the left side of the red barrel", no_path)
    straight = task_for_text(barrels_world, "go to the left side of the red barrel", no_path, need_path=False)
    assert straight.instruction == task.instruction
    assert straight.path[0] == pytest.approx(barrels_world.start_position)
    assert straight.path[-1] == pytest.approx(task.instruction.goal)
    assert len(straight.path) > 2 and not np.array_equal(straight.path, task.path)
    directions = np.diff(straight.path, axis=0)
    cross = directions[:, 0] * directions[0, 1] - directions[:, 1] * directions[0, 0]
    assert np.allclose(cross, 0.0, atol=1e-9), "one straight line"
    assert np.all(np.linalg.norm(directions, axis=1) <= config.expert.waypoint_spacing + 1e-9)
    with pytest.raises(InstructionError, match="no side named"):
        task_for_text(barrels_world, "go to the red barrel", config, need_path=False)


# ------------------------------------------------------------------------------------ demonstrations


def _segment_points(path: np.ndarray, per_segment: int = 10) -> np.ndarray:
    t = np.linspace(0, 1, per_segment, endpoint=False)[None, :, None]
    return (path[:-1, None] + t * np.diff(path, axis=0)[:, None]).reshape(-1, 2)


def _check_path(world: WorldSpec, goal: np.ndarray, path: np.ndarray, config: ExpertConfig) -> None:
    assert path[0] == pytest.approx(world.start_position)
    assert path[-1] == pytest.approx(goal)
    steps = np.linalg.norm(np.diff(path, axis=0), axis=1)
    assert np.all(steps <= config.waypoint_spacing + 1e-9)
    assert np.all((path >= 0) & (path <= world.field_size))
    assert not crosses_itself(path)
    # Every landmark's radius is kept, the named one's too: the goal is on its rim and the path reaches it
    # along the rim. Straight chords between waypoints may dip a few centimetres inside.
    points = _segment_points(path)
    for lm in world.landmarks:
        assert np.linalg.norm(points - lm.position, axis=1).min() > lm.radius - 0.1, lm


def test_demonstration_goes_around_a_landmark_in_the_way():
    # The fir tree stands exactly on the line from the start (corner 0, heading 45 deg) to the goal.
    world = make_world([landmark("fir_tree", 12.0, 12.0), landmark("igloo", 22.0, 22.0)])
    goal = make_instruction(world, 1, "front").goal
    config = ExpertConfig()
    path = demonstration_path(world, goal, config)
    _check_path(world, goal, path, config)
    # The take-off is straight along the start heading.
    assert path[2] == pytest.approx(world.start_position + 2.4 * np.array([1, 1]) / math.sqrt(2))
    assert path_length(path) > np.linalg.norm(goal - world.start_position) + 0.5  # a detour


def test_demonstration_goes_the_other_way_when_the_near_side_leaves_the_field():
    # Sliding around the big house toward the goal's side would leave the field at x < 0.
    world = make_world([landmark("house_2", 4.5, 12.0, scale=1.25), landmark("igloo", 3.5, 25.0)])
    goal = make_instruction(world, 1, "back").goal
    path = demonstration_path(world, goal)
    _check_path(world, goal, path, ExpertConfig())
    assert path[:, 0].max() > 4.5 + world.landmarks[0].radius - 0.2  # went around the east side


def test_demonstration_rejected_when_the_goal_is_boxed_in():
    # The back goal sits in the corner behind a landmark wider than its gap to both edges.
    world = make_world([landmark("house_2", 3.8, 26.7, scale=1.12)], corner=1)
    goal = make_instruction(world, 0, "back").goal
    assert 0 <= goal[0] <= 30 and 0 <= goal[1] <= 30
    with pytest.raises(DemoPathError, match="leaves the field"):
        demonstration_path(world, goal)


def test_demonstration_rejected_when_the_goal_is_outside_the_field():
    world = make_world([landmark("igloo", 22.0, 22.0)])
    with pytest.raises(DemoPathError, match="outside the field"):
        demonstration_path(world, np.array([31.0, 20.0]))


def test_demonstration_rejected_after_too_many_steps():
    world = make_world([landmark("igloo", 22.0, 22.0)])
    with pytest.raises(DemoPathError, match="did not reach the goal in 50 steps"):
        demonstration_path(world, make_instruction(world, 0, "back").goal, ExpertConfig(max_demo_steps=50))


def test_crosses_itself():
    assert crosses_itself(np.array([[0, 0], [2, 2], [2, 0], [0, 2.0]]))
    assert not crosses_itself(np.array([[0, 0], [1, 0], [1, 1], [0, 1.0]]))
    # A straight line cut into many collinear pieces (floating-point noise) does not cross itself.
    line = np.stack([np.linspace(30, 14, 20), np.linspace(0, 16.6, 20)], axis=1)
    assert not crosses_itself(line)
    # A path that folds back over itself does.
    assert crosses_itself(np.array([[0, 0], [1, 0], [2, 0], [3, 0], [2.5, 0], [1.5, 0.0]]))


def test_demonstrations_on_sampled_worlds():
    config, rejected = ExpertConfig(), []
    for env_id in range(100):
        world = world_for_env(env_id)
        ins = instruction_for_env(world)
        try:
            path = demonstration_path(world, ins.goal, config)
        except DemoPathError:
            rejected.append(env_id)
            continue
        _check_path(world, ins.goal, path, config)
    print(f"demonstrations rejected: {len(rejected)} of 100 {rejected}")
    assert len(rejected) <= 2, rejected


# ----------------------------------------------------------------------------------------------- expert


def _straight_path(length: float = 24.0) -> np.ndarray:
    return np.stack([np.arange(0, length + 1e-9, 1.2), np.zeros(round(length / 1.2) + 1)], axis=1)


def test_expert_control_law_on_a_straight_path():
    drone = DroneConfig()
    expert = Expert(_straight_path(), ExpertConfig(), drone)
    a = expert.act(np.array([0.0, 0.0]), 0.0)
    assert not a.stop and a.omega_norm == 0.0
    assert a.v_norm == pytest.approx(1 / 3)  # ramp: (progress + 1) / 3
    assert a.forward_velocity == pytest.approx(a.v_norm * drone.max_forward_velocity)
    a = Expert(_straight_path()).act(np.array([0.0, 0.0]), 0.2)  # heading left of the path
    assert a.omega_norm == pytest.approx(-0.1) and a.yaw_rate == pytest.approx(-0.1 * drone.max_yaw_rate)
    a = Expert(_straight_path()).act(np.array([6.0, 1.0]), 0.0)  # left of the path, heading along it
    heading_error = math.atan2(-1.0, 14.4)
    assert a.omega_norm == pytest.approx(0.5 * heading_error - 0.1 * 1.0)
    assert a.v_norm == 1.0  # progress 5 > 3 waypoints
    a = Expert(_straight_path()).act(np.array([0.0, 0.0]), math.pi)  # facing away: turn at full rate
    assert abs(a.omega_norm) == 1.0 and a.v_norm == pytest.approx(1 / 3)


def test_expert_stops_at_the_second_to_last_waypoint():
    path = _straight_path(12.0)  # short enough that the progress window reaches the end from the start
    expert = Expert(path)
    assert not expert.act(path[-2] - [0.05, 0.0], 0.0).stop
    assert expert.act(path[-2], 0.0).stop
    assert Expert(path, ExpertConfig(stop_before_end=0)).act(path[-2], 0.0).stop is False


def test_off_the_path_the_expert_stops_only_near_the_goal():
    """DAgger asks the expert at the learner's states. A learner flying straight past the fir tree, 2 m to the left
    of the back-side goal, while the path curls around the tree's rim: progress alone (the original's rule, an
    infinite stop radius) reaches the stop waypoint 3-4 m from the goal, in the left quadrant. With the stop
    radius the expert says fly on, and flying its own commands from there it stops near the goal, on the back."""
    world = make_world([landmark("fir_tree", 12.0, 12.0), landmark("igloo", 21.0, 21.0),
                        landmark("rock_1", 24.0, 8.0)], corner=0)
    ins = make_instruction(world, 0, "back")
    tree, path, goal = world.landmarks[0], demonstration_path(world, ins.goal), np.array(ins.goal)
    start = np.array(world.start_position)
    heading = (goal - start) / np.linalg.norm(goal - start)
    past = goal + 2.0 * np.array([-heading[1], heading[0]])  # 2 m to the left of the goal
    yaw = math.atan2(heading[1], heading[0])

    def first_stop(expert: Expert):
        for t in np.linspace(0.0, 1.3, 400):
            p = start + t * (past - start)
            if expert.act(p, yaw).stop:
                return p
        return None

    old = first_stop(Expert(path, ExpertConfig(stop_radius=math.inf)))
    assert old is not None and np.linalg.norm(old - goal) > 3.0
    assert side_of(tree.position, world.start_position, old) == "left"  # a wrong STOP label
    expert = Expert(path)
    assert first_stop(expert) is None  # the same states: fly on

    expert.reset()
    p, heading_angle, drone = start.copy(), yaw, DroneConfig()
    for t in np.linspace(0.0, 1.0, 200):  # the learner's states up to where the old rule said STOP
        p = start + t * (old - start)
        expert.act(p, heading_angle)
    for _ in range(60):  # then the expert's own commands, flown as a unicycle at 5 Hz
        a = expert.act(p, heading_angle)
        if a.stop:
            break
        heading_angle += a.yaw_rate / drone.control_hz
        p = p + a.forward_velocity / drone.control_hz * np.array([math.cos(heading_angle), math.sin(heading_angle)])
    assert a.stop and np.linalg.norm(p - goal) <= ExpertConfig().stop_radius
    assert success(p, tree.position, world.start_position, "back")


def test_expert_progress_is_monotone_and_windowed():
    # A U-turn: out along y = 0, back along y = 2. Near the start the return leg is the nearest.
    out = _straight_path(24.0)
    back = out[::-1] + [0.0, 2.0]
    path = np.concatenate([out, back])
    expert = Expert(path)
    assert expert.act(np.array([0.5, 1.8]), 0.0).progress < 1.0  # starts on the outgoing leg
    assert expert.act(np.array([30.0, 1.0]), 0.0).progress <= 1 + 12 + 1e-9  # cannot jump beyond the window
    for x in np.linspace(2.0, 24.0, 30):
        expert.act(np.array([x, 0.0]), 0.0)
    p = expert.progress
    assert p == pytest.approx(20.0)
    assert expert.act(np.array([0.0, 0.0]), 0.0).progress >= p  # never goes back
    expert.reset()
    assert expert.progress == 0.0
    assert expert.distance_to_path(np.array([12.0, 1.0])) == pytest.approx(1.0)


@pytest.mark.parametrize("corner, landmarks, target, side", [
    (0, [("fir_tree", 12.0, 12.0), ("igloo", 21.0, 21.0), ("rock_1", 24.0, 8.0)], 1, "back"),
    (2, [("house_1", 15.0, 17.0), ("rock_2", 8.0, 9.0), ("barrel_1", 24.0, 9.0)], 1, "left"),
])
def test_expert_flies_the_drone_to_the_goal(corner, landmarks, target, side):
    from gsmn.world.env import Action, Env

    world = make_world([landmark(*lm) for lm in landmarks], corner=corner)
    ins = make_instruction(world, target, side)
    config = preset("tiny")
    path = demonstration_path(world, ins.goal)
    expert = Expert(path, ExpertConfig(), config.drone)
    progress, stopped = [], False
    with Env(config) as env:
        obs = env.reset(0, ins.text, world=world)
        for _ in range(150):
            a = expert.act(obs.pose.position[:2], obs.pose.yaw)
            progress.append(a.progress)
            if a.stop:
                stopped = True
                break
            obs = env.step(Action(a.forward_velocity, a.yaw_rate))
    final = obs.pose.position[:2]
    lm = world.landmarks[target]
    assert stopped
    # The second-to-last waypoint is up to one spacing (1.2 m) before the goal.
    assert goal_distance(final, ins.goal) < 1.3
    assert side_of(lm.position, world.start_position, final) == side
    assert success(final, lm.position, world.start_position, side)
    assert np.all(np.diff(progress) >= 0)
