"""Mirror augmentation (gsmn/training/augment.py), checked against the real simulator and renderer: a mirrored
episode must be what flying the mirrored world would have recorded."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from gsmn.config import preset, with_overrides
from gsmn.model.batch import collate
from gsmn.model.labels import project_landmarks
from gsmn.model.vocabulary import Vocabulary
from gsmn.task.demo import demonstration_path
from gsmn.task.instructions import SIDES, goal_position
from gsmn.task.metrics import side_of
from gsmn.task.mirror import mirror_instruction, mirror_world
from gsmn.task.rollout import Task, task_for_env
from gsmn.training.augment import maybe_mirror, mirror_episode
from gsmn.training.collect import MixturePolicy, record_episode
from gsmn.training.run import RunError, RunFolder
from gsmn.world.env import Env
from gsmn.world.spec import world_for_env

pytestmark = pytest.mark.unit

TINY = preset("tiny")


@pytest.fixture(scope="module")
def flown():
    """An expert episode of environment 70 and the expert's episode in the mirrored world."""
    task = task_for_env(70, TINY)
    world = mirror_world(task.world)
    instruction = mirror_instruction(task.instruction, world.field_size)
    mirrored_task = Task(world, instruction, demonstration_path(world, instruction.goal, TINY.expert))
    with Env(TINY) as env:
        sample = record_episode(env, MixturePolicy(TINY), task, TINY.task.horizon)
        in_mirror = record_episode(env, MixturePolicy(TINY), mirrored_task, TINY.task.horizon)
    return sample, in_mirror


@pytest.mark.parametrize("env_id", [70, 85, 1234])
def test_mirrored_goal_is_the_swapped_side_of_the_mirrored_world(env_id):
    world = world_for_env(env_id, TINY.world)
    mirrored = mirror_world(world)
    F = world.field_size
    swap = {"left": "right", "right": "left", "front": "front", "back": "back"}
    for index in range(len(world.landmarks)):
        for side in SIDES:
            goal = goal_position(world, index, side)
            assert np.allclose(goal_position(mirrored, index, swap[side]), (F - goal[0], goal[1]), atol=1e-9)
            # the metric's quadrants agree: a point on `side` is on the swapped side in the mirror
            lm = world.landmarks[index]
            assert side_of((F - lm.x, lm.y), mirrored.start_position, (F - goal[0], goal[1])) == swap[side]
    back = mirror_world(mirrored)  # the reflection is its own inverse
    assert back.start_corner == world.start_corner and np.isclose(back.start_x, world.start_x)
    for a, b in zip(back.landmarks, world.landmarks, strict=True):
        assert np.isclose(a.x, b.x) and np.isclose(a.y, b.y) and np.isclose(np.cos(a.yaw - b.yaw), 1.0)


def test_mirrored_instruction_swaps_left_and_right_only():
    task = task_for_env(70, TINY)
    for side, other in (("left", "right"), ("right", "left"), ("front", "front"), ("back", "back")):
        instruction = mirror_instruction(task.instruction.__class__(
            text=f"Go to the {side} side of the barrel.", landmark_index=0, noun_phrase="barrel", side=side,
            goal_x=10.0, goal_y=4.0, ambiguous=False), 30.0)
        assert instruction.side == other and instruction.text == f"go to the {other} side of the barrel"
        assert (instruction.goal_x, instruction.goal_y) == (20.0, 4.0)


@pytest.mark.slow
def test_mirrored_episode_is_what_the_mirrored_world_shows(flown):
    """At the start both flights are at mirrored poses: the real render of the mirrored world is the flipped image
    (up to the landmark meshes, which are rotated, not reflected), far closer than the unflipped one."""
    sample, in_mirror = flown
    mirrored = mirror_episode(sample)
    assert np.allclose(mirrored.poses[0], in_mirror.poses[0], atol=1e-4)
    assert np.allclose(mirrored.T_world_camera[0], in_mirror.T_world_camera[0], atol=1e-4)
    rendered = in_mirror.images[0].astype(np.float32)
    flipped_error = np.abs(mirrored.images[0].astype(np.float32) - rendered).mean()
    unflipped_error = np.abs(sample.images[0].astype(np.float32) - rendered).mean()
    assert flipped_error < 0.5 * unflipped_error, (flipped_error, unflipped_error)
    # the simulator and the expert are symmetric: the mirrored world's flight is the mirror of the flight, step by
    # step (same speeds, opposite turns, same STOP)
    assert in_mirror.length == sample.length and np.abs(sample.actions[:, 1]).max() > 0.1
    assert np.allclose(mirrored.actions, in_mirror.actions, atol=1e-3)
    assert np.allclose(mirrored.poses[:, :2], in_mirror.poses[:, :2], atol=1e-3)
    assert np.allclose(np.cos(mirrored.poses[:, 2] - in_mirror.poses[:, 2]), 1.0, atol=1e-6)
    assert np.allclose(mirrored.T_world_camera, in_mirror.T_world_camera, atol=1e-3)


@pytest.mark.slow
def test_landmarks_project_to_the_flipped_pixels(flown):
    sample, _ = flown
    vocabulary = Vocabulary.default()
    W = sample.images.shape[2]
    uv, depth = project_landmarks(collate([sample], vocabulary))
    uv_m, depth_m = project_landmarks(collate([mirror_episode(sample)], vocabulary))
    assert torch.allclose(depth_m, depth, atol=1e-3)
    front = depth > 0.5
    assert front.any()
    assert torch.allclose(uv_m[..., 0][front], W - uv[..., 0][front], atol=1e-2)
    assert torch.allclose(uv_m[..., 1][front], uv[..., 1][front], atol=1e-2)


def test_mirroring_twice_gives_the_episode_back(flown):
    sample, _ = flown
    back = mirror_episode(mirror_episode(sample))
    assert np.array_equal(back.images, sample.images) and back.instruction.side == sample.instruction.side
    assert np.allclose(back.T_world_camera, sample.T_world_camera, atol=1e-5)
    assert np.allclose(back.poses[:, :2], sample.poses[:, :2], atol=1e-5)
    assert np.allclose(np.cos(back.poses[:, 2]), np.cos(sample.poses[:, 2]), atol=1e-5)
    assert np.array_equal(back.actions, sample.actions)


@pytest.mark.slow
def test_maybe_mirror_is_seeded_and_follows_its_probability(flown):
    sample, _ = flown
    samples = [sample] * 40
    assert maybe_mirror(samples, 0.0, seed=3) is samples
    assert all(s.instruction.goal_x != sample.instruction.goal_x for s in maybe_mirror(samples, 1.0, seed=3))
    half = [s.poses[0, 0] != sample.poses[0, 0] for s in maybe_mirror(samples, 0.5, seed=3)]
    assert 8 <= sum(half) <= 32
    assert half == [s.poses[0, 0] != sample.poses[0, 0] for s in maybe_mirror(samples, 0.5, seed=3)]
    assert half != [s.poses[0, 0] != sample.poses[0, 0] for s in maybe_mirror(samples, 0.5, seed=4)]


def test_a_run_resumes_with_the_mirror_switched_on_and_from_an_older_config(tmp_path):
    run = RunFolder(tmp_path / "run")
    run.start(TINY)
    run.start(with_overrides(TINY, {"train.mirror": "0.5"}))  # switched on when resuming
    assert json.loads((run.root / "config.json").read_text())["train"]["mirror"] == 0.5
    older = json.loads(TINY.to_json())
    del older["train"]["mirror"]  # written before the field existed
    (run.root / "config.json").write_text(json.dumps(older))
    run.start(TINY)
    with pytest.raises(RunError):
        run.start(with_overrides(TINY, {"train.learning_rate": "0.5"}))
    with pytest.raises(ValueError):
        with_overrides(TINY, {"train.mirror": "1.5"})
