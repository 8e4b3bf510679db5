"""Map interventions (gsmn/analysis/intervention.py): requests checked with a message; the shipped GSMN's heads read
each substituted truth map as the truth; the model flies on with the substitute (held, or written once into the map
it integrates); map codes from real calibration flights, refused for other weights, and a damaged or half-written
codes file is reported, never read; rescue tables count what they say."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from gsmn.analysis.intervention import (
    CODES_FILE,
    Intervention,
    InterventionError,
    InterventionMaker,
    MapCodes,
    Substitute,
    codes_for,
    intervention_from_flag,
    paint_from_text,
    parse_intervention,
    truth_map,
)
from gsmn.analysis.truth import agreement, truth_maps
from gsmn.attribution import goal_peak
from gsmn.config import preset, with_overrides
from gsmn.model.checkpoint import load_checkpoint
from gsmn.model.grid import cell_of
from gsmn.model.readout import Heads
from gsmn.task.rollout import EpisodeRecord, rollout, task_for_env
from gsmn.world.env import Env

pytestmark = pytest.mark.unit

SHIPPED = Path(__file__).resolve().parents[1] / "checkpoints" / "gsmn"


def test_requests_are_checked_with_a_message():
    assert parse_intervention({"map": "goal", "with": "truth", "hold": True}) == Intervention("goal")
    painted = parse_intervention({"map": "relevance", "with": "painted", "paint": [{"op": "peak", "x": 12, "y": 20}]})
    assert painted.paint[0].x == 12.0 and painted.paint[0].radius == 1.5
    assert intervention_from_flag("truth-semantic") == Intervention("semantic")
    for bad, words in [({"map": "elevation"}, "map must be one of"), ({"map": "goal", "with": "oracle"}, "with must"),
                       ({"map": "goal", "hold": False}, "only the true semantic map can be written once"),
                       ({"map": "semantic", "with": "painted", "paint": [{"op": "peak", "x": 1, "y": 1}]},
                        "paint the relevance or goal map"),
                       ({"map": "goal", "with": "painted"}, "needs a non-empty paint list"),
                       ({"map": "goal", "with": "painted", "paint": [{"op": "peak", "x": 40, "y": 1}]},
                        "off the field"),
                       ({"map": "goal", "colour": "red"}, "unknown intervention field"), ("goal", "is an object")]:
        with pytest.raises(InterventionError, match=words):
            parse_intervention(bad)
    with pytest.raises(InterventionError, match="cannot read the paint 'dab 1 2'"):
        paint_from_text("peak 1 2; dab 1 2")
    with pytest.raises(InterventionError, match="--intervene takes one of"):
        intervention_from_flag("truth-camera")
    described = parse_intervention({"map": "semantic", "hold": False}).describe()
    assert described == "perfect perception: the true semantic map, written once into the semantic map"


def test_the_shipped_heads_read_each_substituted_truth_map_as_the_truth():
    """On test environments the calibration never flew, the perception head names the landmarks' footprints from the
    true semantic map, the grounding head ranks the named footprint above every other cell of the true relevance
    map, and the goal head peaks on the goal's cell of the true goal map and puts as much of P(goal) in the success
    region as the model's successes end with (4 to 7 times the region's share of the field, what an even spread
    puts there)."""
    codes = codes_for(SHIPPED)
    assert codes.meta["classes_seen"] >= 50 and codes.meta["successes"] > 0
    model, config, *_ = load_checkpoint(SHIPPED)
    heads = Heads.of(model)
    for env_id in (70, 72, 76):
        task = task_for_env(env_id, config)
        truth = truth_maps(task.world, task.instruction, config.model.map_size, config.task.success_radius)
        maps = {name: truth_map(name, truth, codes) for name in ("semantic", "relevance", "goal")}
        figures = agreement(maps["semantic"], maps["relevance"], maps["goal"], truth, heads)
        assert figures.perception >= 0.9, (env_id, figures)
        assert figures.relevance >= 0.99, (env_id, figures)
        assert figures.goal >= 4 * figures.region_share, (env_id, figures)  # as its successes end (4-7 times)
        row, col, _ = goal_peak(maps["goal"], heads)
        assert (row, col) == truth.goal_cell


def test_the_model_flies_on_with_the_substitute_held_or_written_once(untrained_checkpoint):
    """The untrained tiny GSMN with made-up codes: a held goal map is what the step reports and what the controller
    reads in the drone's frame (background beyond the field); a semantic map written once becomes the state, and the
    next step integrates the camera into it."""
    model, config, vocabulary, _ = load_checkpoint(untrained_checkpoint)
    from gsmn.model.policy import ModelPolicy

    n, C = config.model.map_size, config.model.feature_channels
    rng = np.random.default_rng(0)
    codes = MapCodes(rng.normal(size=(63, C)).astype(np.float32), np.ones(63, bool),
                     rng.normal(size=C).astype(np.float32), *(rng.normal(size=3).astype(np.float32) for _ in range(3)),
                     rng.normal(size=(2, 9, 9)).astype(np.float32), np.array([0.5, -0.25], np.float32))
    config = with_overrides(config, {"task.horizon": "3"})
    task = task_for_env(70, config)
    truth = truth_maps(task.world, task.instruction, n, config.task.success_radius)
    env = Env(config, render=True)
    try:
        policy = ModelPolicy(model, vocabulary, config)
        policy.intervene(InterventionMaker(Intervention("goal"), codes, n, config.task.success_radius))
        rollout(env, policy, task, 3)
        goal = truth_map("goal", truth, codes)
        out = policy.last_outputs
        assert torch.equal(out.goal_map_w[0, 0], torch.from_numpy(goal))
        corner = out.goal_map_r[0, 0, :, 0, 0]  # the drone map's corner lies beyond the field from anywhere near it
        assert torch.allclose(corner, torch.tensor([0.5, -0.25]))
        plain = ModelPolicy(model, vocabulary, config)
        rollout(env, plain, task, 3)
        assert not torch.equal(plain.last_outputs.goal_map_w, out.goal_map_w)

        once = ModelPolicy(model, vocabulary, config)
        once.intervene(InterventionMaker(Intervention("semantic", hold=False), codes, n, config.task.success_radius))
        states = []

        class Spy:  # the state the policy carries after each step
            needs_images, name = True, "gsmn"

            def reset(self, t):
                once.reset(t)

            def act(self, obs):
                action = once.act(obs)
                states.append(once.state[0].clone())
                return action

        rollout(env, Spy(), task, 2)
        semantic = torch.from_numpy(truth_map("semantic", truth, codes))
        assert torch.equal(states[0], semantic)
        assert not torch.equal(states[1], semantic)  # the camera's view integrated into the written map
        assert float((states[1] - semantic).abs().mean()) < float(semantic.abs().mean())
    finally:
        env.close()


def test_painted_edits_touch_only_their_cells():
    n, field = 32, 30.0
    codes = MapCodes(np.zeros((63, 4), np.float32), np.ones(63, bool), np.zeros(4, np.float32),
                     np.array([3, 0, 0], np.float32), np.array([1, 0, 0], np.float32), np.array([-1, 0, 0], np.float32),
                     np.full((2, 9, 9), 7, np.float32), np.zeros(2, np.float32))
    task = task_for_env(70, preset("tiny"))
    truth = truth_maps(task.world, task.instruction, n)
    paint = paint_from_text("peak 10 10 2; erase 25 25")
    iv = parse_intervention({"map": "relevance", "with": "painted", "paint": paint})
    fresh = torch.full((1, 3, n, n), 0.25)
    out = Substitute(iv, codes, truth, field)("relevance_map_w", fresh)
    r, c = cell_of(10, 10, field, n)
    er, ec = cell_of(25, 25, field, n)
    assert out[0, 0, r, c] == 3 and out[0, 0, er, ec] == -1 and out[0, 0, 0, 0] == 0.25
    assert 4 <= int((out[0, 0] == 3).sum()) <= 20  # a 2 m disk at 0.94 m cells
    assert Substitute(iv, codes, truth, field)("goal_map_w", fresh) is fresh  # another map passes through


def test_codes_come_from_real_calibration_flights_and_belong_to_their_weights(untrained_checkpoint, tmp_path):
    from gsmn.analysis.rescue import calibrate, save_codes

    folder = tmp_path / "gsmn"
    shutil.copytree(untrained_checkpoint, folder, copy_function=shutil.copyfile)
    with pytest.raises(InterventionError, match="gsmn map-codes --checkpoint"):
        codes_for(folder)
    config = with_overrides(preset("tiny"), {"task.horizon": "12"})
    codes = calibrate(folder, [85, 86], config)
    assert codes.meta["episodes"] == 2 and codes.meta["classes_seen"] >= 1
    assert codes.semantic_class.shape == (63, config.model.feature_channels) and np.isfinite(codes.semantic_class).all()
    save_codes(folder, codes)
    again = codes_for(folder)
    assert np.array_equal(again.goal_template, codes.goal_template) and again.meta == codes.meta
    weights = (folder / "weights.safetensors").read_bytes()
    (folder / "weights.safetensors").write_bytes(weights[:-4] + bytes(4))  # other weights
    with pytest.raises(InterventionError, match="derived for other weights"):
        codes_for(folder)


def test_a_damaged_or_half_written_codes_file_is_reported_and_the_old_one_kept(tmp_path, monkeypatch):
    codes = MapCodes(np.ones((63, 4), np.float32), np.ones(63, bool), np.zeros(4, np.float32),
                     *(np.ones(3, np.float32) for _ in range(3)), np.ones((2, 9, 9), np.float32),
                     np.zeros(2, np.float32), {"weights_sha256": "x"})
    path = tmp_path / CODES_FILE
    codes.save(path)
    good = path.read_bytes()

    import safetensors.numpy

    def full_disk(arrays, filename, metadata=None):
        Path(filename).write_bytes(b"\0" * 100)
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(safetensors.numpy, "save_file", full_disk)
    with pytest.raises(OSError, match="No space"):
        codes.save(path)
    assert path.read_bytes() == good and sorted(p.name for p in tmp_path.iterdir()) == [CODES_FILE]
    path.write_bytes(good[: len(good) // 2])
    with pytest.raises(InterventionError, match="cannot be read.*derive them again"):
        MapCodes.load(path)


def test_a_rescue_table_counts_failures_saved_per_stage():
    from gsmn.analysis.rescue import rescue_markdown, rescue_table

    def record(env_id: int, success: bool) -> EpisodeRecord:
        return EpisodeRecord(system="gsmn", env_id=env_id, instruction="", landmark_index=0, noun_phrase="box",
                             side="left", ambiguous=False, goal_x=0, goal_y=0, landmark_x=0, landmark_y=0, start_x=0,
                             start_y=0, final_x=0, final_y=0, steps=1, stopped=True, success=success,
                             landmark_success=success, goal_distance=0.0, trajectory=(), actions=())

    stages = {1: "grounding", 2: "grounding", 3: "perception", 4: "goal"}
    flown = {"truth-relevance": [record(1, True), record(2, True), record(3, False), record(4, False)],
             "truth-goal": [record(1, False), record(2, True), record(3, True), record(4, True)]}
    table = rescue_table(stages, {f: [(r.env_id, r.success) for r in rs] for f, rs in flown.items()}, replayed=[9])
    assert table["failures"] == 4 and table["stages"] == {"goal": 1, "grounding": 2, "perception": 1}
    assert table["interventions"]["truth-relevance"]["per_stage"]["grounding"]["rescued"] == 2
    assert table["interventions"]["truth-goal"]["all"]["rescued"] == 3
    text = rescue_markdown(table)
    assert "| grounding | 2 | 2 (100 %" in text and "succeeded when flown again" in text


def test_the_episodes_list_says_what_was_changed():
    from app.page.episodes_view import relation

    assert relation({"fork_of": 3, "fork_step": 12, "intervention": {"map": "goal", "with": "truth", "hold": True}}) \
        == ["fork of #3 at step 12", "perfect goal"]
    edited = {"world_edits": [{"op": "remove", "landmark": 4}], "intervention": {"map": "relevance", "with": "painted"}}
    assert relation(edited) == ["edited world", "painted relevance map"]
    assert relation({"world_edits": [], "intervention": None}) == []


def test_a_kept_episode_reads_its_intervention_back_and_a_damaged_one_as_none():
    from app.jobs.kept_store import _intervention

    assert _intervention({"map": "goal", "with": "truth", "hold": True}) == Intervention("goal")
    assert _intervention(None) is None
    assert _intervention({"map": "elevation"}) is None and _intervention("goal") is None  # damaged: left out


def test_an_exports_result_line_says_what_was_changed():
    import types

    from app.live.recording import FINISHED
    from app.render.export import result_line

    r = types.SimpleNamespace(success=True, stopped=True, steps=37, goal_distance=0.93, final_side="back")
    episode = types.SimpleNamespace(status=FINISHED, result=r, steps=[], world_edits=(), intervention=None,
                                    task=types.SimpleNamespace(instruction=types.SimpleNamespace(side="back")))
    plain = result_line(episode)
    assert plain == "Success: said STOP after 37 steps, 0.9 m from the goal, back side (asked back)"
    episode.world_edits, episode.intervention = ("an edit",), Intervention("goal", "painted")
    assert result_line(episode) == plain + "; in an edited world, with a painted goal map"
