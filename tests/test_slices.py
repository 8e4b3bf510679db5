"""Failures across a whole evaluation (gsmn/analysis/slices.py, `gsmn analyze slices`): counts on hand-made episode
records, the intervals and sign tests on known cases, the map readings on hand-made maps (those of
tests/test_attribution.py, whose readings are known), the confusion cells and the versus table."""

from __future__ import annotations

import json
import math
import subprocess
import sys

import numpy as np
import pytest
from support import compact_evaluation
from test_attribution import INSTRUCTION, TARGET, WORLD, maps_where, run

from gsmn.analysis import slices
from gsmn.task.metrics import sign_test

pytestmark = pytest.mark.unit


def row(env_id: int, landmark: str, side: str, success: bool, ambiguous: bool = False, stage: str | None = None,
        **facts) -> dict:
    base = {"landmarks": 6, "distance": 12.0, "demonstration": 14.0, "stopped_at": landmark,
            "stopped_side": side if success else "front", "reached_side": side if success else "front",
            "grounded": landmark, "goal_at": landmark, "goal_side": side, "went_wrong": None}
    return {"env_id": env_id, "landmark": landmark, "side": side, "ambiguous": ambiguous, "success": success,
            "landmark_success": success, "stopped": True, "steps": 40, "stage": None if success else stage,
            "facts": base | facts}


ROWS = [row(1, "tank", "left", True), row(2, "tank", "left", False, stage="grounding", grounded="box",
                                               stopped_at="box", went_wrong=12),
        row(3, "tank", "back", False, stage="goal", goal_side="front", went_wrong=45), row(4, "box", "back", True),
        row(5, "box", "left", True, ambiguous=True), row(6, "box", "front", False, ambiguous=True,
                                                          stage="control", grounded="tank", stopped_at="no landmark"),
        row(7, "cone", "right", True, landmarks=9, distance=31.0), row(8, "cone", "right", True, distance=25.0)]


def test_the_slices_count_every_episode_once_and_list_the_worst_first():
    found = slices.analyze(ROWS)
    assert (found["n"], found["successes"]) == (8, 5)
    for attribute, values in found["slices"].items():
        assert sum(v["n"] for v in values.values()) == 8, attribute
        assert sum(v["successes"] for v in values.values()) == 5, attribute
        rates = [v["successes"] / v["n"] for v in values.values()]
        assert rates == sorted(rates), attribute  # worst first
    landmark = found["slices"]["landmark"]
    assert list(landmark) == ["tank", "box", "cone"]
    assert landmark["tank"] | {"interval": None} == {"n": 3, "successes": 1, "rate": 33.33, "interval": None}
    assert found["slices"]["stage"]["grounding"]["n"] == 1 and found["slices"]["stage"]["success"]["n"] == 5
    assert found["slices"]["went_wrong"] == {"under 20": slices.rate_of(0, 1), "40-60": slices.rate_of(0, 1),
                                             slices.NOT_READ: slices.rate_of(0, 1), "success": slices.rate_of(5, 5)}
    assert found["slices"]["grounding"]["another landmark"]["n"] == 2
    assert found["slices"]["goal"]["the named landmark, another side"]["n"] == 1
    assert found["slices"]["stopped"]["no landmark"]["n"] == 1
    assert found["slices"]["landmarks"]["9"]["n"] == 1 and found["slices"]["distance"]["30 m or more"]["n"] == 1
    crossed = found["crossed"]["landmark x side"]
    assert crossed["tank"]["left"]["n"] == 2 and crossed["tank"]["left"]["successes"] == 1
    assert sum(c["n"] for sides in crossed.values() for c in sides.values()) == 8


def test_the_intervals_and_sign_tests_on_known_cases():
    assert slices.wilson(0, 10) == pytest.approx((0.0, 0.27753), abs=1e-5)
    assert slices.wilson(5, 10) == pytest.approx((0.23659, 0.76341), abs=1e-5)
    assert slices.wilson(10, 10) == pytest.approx((0.72247, 1.0), abs=1e-5)
    assert slices.wilson(0, 0) == (0.0, 1.0)
    assert sign_test(0, 6) == pytest.approx(2 / 64) and sign_test(6, 0) == sign_test(0, 6)
    assert sign_test(3, 3) == 1.0 and sign_test(0, 0) == 1.0
    assert sign_test(1, 9) == pytest.approx(2 * (1 + 10) / 1024)


def test_the_confusions_count_named_to_read_and_keep_the_ambiguous_apart():
    found = slices.analyze(ROWS)
    assert found["confusion"]["grounded"] == {"box": {"box": 1}, "cone": {"cone": 2}, "tank": {"tank": 2, "box": 1}}
    assert found["confusion"]["stopped_at"]["tank"] == {"tank": 2, "box": 1}
    assert found["confusion"]["side"]["left"] == {"left": 1, "front": 1}
    assert found["confusion_ambiguous"]["grounded"] == {"box": {"box": 1, "tank": 1}}
    assert found["confusion_ambiguous"]["stopped_at"] == {"box": {"box": 1, "no landmark": 1}}
    # every cell opens exactly its episodes
    assert slices.select(ROWS, cell=("grounded", "tank", "box"), ambiguous=False) == [2]
    assert slices.select(ROWS, cell=("grounded", "box", "tank"), ambiguous=True) == [6]
    assert slices.select(ROWS, cell=("side", "left", "front")) == [2]
    assert slices.select(ROWS, {"landmark": "tank", "side": "left"}) == [1, 2]
    assert slices.select(ROWS, {"stage": "success"}) == [1, 4, 5, 7, 8]


def test_two_evaluations_compared_slice_by_slice_pair_by_environment():
    other = [dict(r, success=not r["success"] if r["landmark"] == "tank" else r["success"]) for r in ROWS]
    other.append(row(99, "tank", "left", True))  # flown by only one of them: left out
    many = [row(i, "tank", "left", True) for i in range(10, 17)]
    broken = [dict(r, success=False) for r in many]
    found = slices.versus(ROWS + many, other + broken)
    assert found["n"] == 15
    assert found["overall"] | {"p": None} == {"n": 15, "rate": 80.0, "rate_versus": 40.0, "fixed": 8, "broken": 2,
                                              "p": None}
    tank = found["slices"]["landmark"]["tank"]
    assert (tank["n"], tank["fixed"], tank["broken"]) == (10, 8, 2)  # env 1 and the seven won, envs 2 and 3 lost
    assert tank["p"] == pytest.approx(sign_test(8, 2))
    assert found["slices"]["landmark"]["cone"] == {"n": 2, "rate": 100.0, "rate_versus": 100.0, "fixed": 0,
                                                   "broken": 0, "p": 1.0}
    largest = found["largest"]
    assert largest[0]["p"] < 0.05 and all(s["n"] >= slices.MIN_SLICE for s in largest)
    assert [s["p_adjusted"] < 0.05 for s in largest] == sorted((s["p_adjusted"] < 0.05 for s in largest), reverse=True)
    assert all(s["p_adjusted"] >= s["p"] for s in largest) and found["tested"] >= len(largest)
    assert any(s["slice"] == {"landmark": "tank", "side": "left"} and (s["fixed"], s["broken"]) == (8, 1)
               for s in largest)
    assert all(len(s["slice"]) <= 2 for s in largest)
    assert set(slices.analyze(ROWS, other)["versus"]) == set(slices.ENVIRONMENT)


def test_the_map_readings_on_hand_made_maps():
    """The relevance map singles out the globe, the goal map peaks in front of the pumpkin, the drone stops behind
    the pumpkin: the readings name each, and the step the stage went wrong comes from the attribution."""
    front = (TARGET.x + 3.0, TARGET.y - 3.0)  # between the start (30, 0) and the pumpkin
    episode = {"landmark_index": INSTRUCTION.landmark_index, "goal_x": INSTRUCTION.goal_x,
               "goal_y": INSTRUCTION.goal_y, "final_x": INSTRUCTION.goal_x, "final_y": INSTRUCTION.goal_y}
    a = run(maps_where(relevance={"pumpkin": 1.0, "globe": 2.5}, goal_xy=front)).to_dict()
    a["failed_from"] = {"perception": None, "grounding": 7, "goal": 3}
    facts = slices.episode_facts(episode, WORLD, a, demonstration=20.0)
    assert facts["grounded"] == "globe" and a["stage"] == "grounding"
    assert (facts["goal_at"], facts["goal_side"]) == ("pumpkin", "front")
    assert (facts["stopped_at"], facts["stopped_side"], facts["reached_side"]) == ("pumpkin", "back", "back")
    assert facts["went_wrong"] == 7 and facts["landmarks"] == len(WORLD.landmarks)
    assert facts["distance"] == round(math.dist((WORLD.start_x, WORLD.start_y), INSTRUCTION.goal), 2)
    grounded = slices.episode_facts(episode, WORLD, run(maps_where()).to_dict(), demonstration=20.0)
    assert grounded["grounded"] == "pumpkin" and grounded["went_wrong"] is None
    # a head trained without its objective reads nothing; an episode without maps has only its world's facts
    untrained = dict(a, grounded=None, goal_right=None)
    assert slices.episode_facts(episode, WORLD, untrained, demonstration=20.0)["grounded"] is None
    bare = slices.episode_facts(episode, WORLD, None)
    assert bare["grounded"] is None and bare["goal_at"] is None and bare["demonstration"] > facts["distance"] - 1
    far = slices.episode_facts(dict(episode, final_x=29.5, final_y=29.5), WORLD, None, demonstration=1.0)
    assert far["stopped_at"] == slices.NO_LANDMARK and far["stopped_side"] is None


def test_the_command_line_writes_the_json_the_issue_names(tmp_path):
    """`gsmn analyze slices` on a compact evaluation and another of the same environments: the JSON's keys, the
    facts kept with --keep-facts, and a clear message for a file that is not an evaluation."""
    a, b = tmp_path / "a" / "evaluation.json", tmp_path / "b" / "evaluation.json"
    for path, won in ((a, lambda e: e != 71), (b, lambda e: e in (70, 72))):
        path.parent.mkdir()
        path.write_text(json.dumps(compact_evaluation((70, 71, 72, 73), won)))
    out = tmp_path / "out.json"
    done = subprocess.run([sys.executable, "-m", "gsmn.cli", "analyze", "slices", str(a), "--versus", str(b),
                           "--json", str(out), "--markdown", "--keep-facts"], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    found = json.loads(out.read_text())
    assert found["n"] == 4 and {"landmark", "side", "ambiguous", "stage"} <= set(found["slices"])
    assert set(found["confusion"]) == {"grounded", "stopped_at", "side"}
    assert {"fixed", "broken", "p"} <= set(next(iter(found["versus"]["landmark"].values())))
    assert found["versus_summary"]["overall"]["fixed"] == 1 and found["versus_summary"]["overall"]["broken"] == 0
    assert "a against b on the 4 environments both flew: 75.0 % against 50.0 %" in done.stdout
    kept = json.loads(a.read_text())["episodes"]
    assert all(e["facts"]["landmarks"] >= 6 for e in kept) and "facts" not in json.loads(b.read_text())["episodes"][0]
    bad = tmp_path / "bad.json"
    bad.write_text("{}")
    done = subprocess.run([sys.executable, "-m", "gsmn.cli", "analyze", "slices", str(bad)], capture_output=True,
                          text=True)
    assert done.returncode == 2 and "not an evaluation" in done.stderr


def test_holm_corrects_for_every_slice_tested():
    assert slices.holm([0.01, 0.04, 0.03, 0.5]) == pytest.approx([0.04, 0.09, 0.09, 0.5])
    assert slices.holm([]) == [] and slices.holm([0.2]) == [0.2]


def test_the_landmark_ended_at_is_the_named_one_first_and_a_twin_is_told_apart():
    """Ending inside the named landmark's region reads as the named landmark even nearer another; ending at another
    landmark of the same name (an ambiguous instruction) is "another landmark of the same name", never a success's
    reading, and the matrix reads it as "another pumpkin"."""
    import dataclasses

    episode = {"landmark_index": INSTRUCTION.landmark_index, "goal_x": INSTRUCTION.goal_x,
               "goal_y": INSTRUCTION.goal_y}
    others = [lm for lm in WORLD.landmarks if lm is not TARGET]
    near = min(others, key=lambda lm: math.dist((lm.x, lm.y), (TARGET.x, TARGET.y)))
    # a point inside the pumpkin's 6 m region, nearer the landmark closest to it
    t = next(t for t in np.linspace(0, 1, 201) if math.dist(
        p := (TARGET.x + t * (near.x - TARGET.x), TARGET.y + t * (near.y - TARGET.y)), (near.x, near.y))
        < math.dist(p, (TARGET.x, TARGET.y)) < 6.0)
    point = (TARGET.x + t * (near.x - TARGET.x), TARGET.y + t * (near.y - TARGET.y))
    facts = slices.episode_facts(dict(episode, final_x=point[0], final_y=point[1]), WORLD, None, demonstration=1.0)
    assert (facts["stopped_at"], facts["stopped_which"]) == ("pumpkin", "named")
    twin = dataclasses.replace(near, noun_phrase="pumpkin", class_id=TARGET.class_id)
    world = dataclasses.replace(WORLD, landmarks=tuple(twin if lm is near else lm for lm in WORLD.landmarks))
    at_twin = slices.episode_facts(dict(episode, final_x=twin.x + 1.0, final_y=twin.y), world, None,
                                   demonstration=1.0)
    assert (at_twin["stopped_at"], at_twin["stopped_which"]) == ("pumpkin", "same name")
    row = {"env_id": 1, "landmark": "pumpkin", "side": "back", "ambiguous": True, "success": False,
           "landmark_success": False, "stopped": True, "steps": 9, "stage": "goal",
           "facts": at_twin | {"version": slices.FACTS_VERSION}}
    assert slices.attribute_values(row)["stopped"] == "another landmark of the same name"
    assert slices.confusion([row])["stopped_at"] == {"pumpkin": {"another pumpkin": 1}}
    assert slices.select([row], cell=("stopped_at", "pumpkin", "another pumpkin")) == [1]
    assert slices.valid_facts(facts) and not slices.valid_facts(facts | {"went_wrong": "x"})
    assert not slices.valid_facts({k: v for k, v in facts.items() if k != "version"})


def test_an_evaluation_without_its_config_reads_with_the_look_it_flew():
    """A compact Table 2 evaluation keeps its recipe, not its config: one saved before recipes named their look flew
    MuJoCo's shadow passes, whatever the default look is now."""
    from gsmn.config import RunConfig

    config_of = slices.config_of
    assert config_of({"recipe": {"preset": "paper"}}).camera.shadow_method == "mujoco"
    assert config_of({"recipe": {"preset": "paper", "shadow_method": "baked"}}).camera.shadow_method == "baked"
    assert config_of({}).camera.shadow_method == "mujoco"
    assert config_of({"config": RunConfig().to_dict()}).camera.shadow_method == "baked"
