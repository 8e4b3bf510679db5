"""The test-time ensembles (gsmn/model/policy.py Ensemble, MirrorEnsemble) and the mirrored observation they fly
(gsmn/task/mirror.py), checked with the real simulator, renderer and shipped GSMN checkpoint."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
import torch

from gsmn.config import preset
from gsmn.evaluation import REPO_ROOT, make_policy, merge_results, results_dict
from gsmn.model.checkpoint import load_policy, save_checkpoint
from gsmn.model.policy import Ensemble, MirrorEnsemble
from gsmn.task.baselines import ExpertPolicy
from gsmn.task.demo import demonstration_path
from gsmn.task.mirror import mirror_instruction, mirror_observation, mirror_task, mirror_world
from gsmn.task.rollout import Task, task_for_env
from gsmn.world.env import Action, Env

pytestmark = pytest.mark.unit

TINY = preset("tiny")
CHECKPOINT = REPO_ROOT / "checkpoints" / "gsmn"


def mirrored_task(task: Task, config) -> Task:
    world = mirror_world(task.world)
    instruction = mirror_instruction(task.instruction, world.field_size)
    return Task(world, instruction, demonstration_path(world, instruction.goal, config.expert))


def fly_expert(env: Env, task: Task, config, steps: int) -> list:
    expert = ExpertPolicy(config)
    observations = [env.reset(task.world.env_id, task.instruction.text, task.world)]
    expert.reset(task)
    for _ in range(steps - 1):
        a = expert.act(observations[-1])
        observations.append(env.step(Action(a.forward_velocity, a.yaw_rate)))
    return observations


@pytest.fixture(scope="module")
def flight():
    """Twelve real observations of the expert flying environment 85 (the shipped model's settings), its task, and
    the expert's first twelve in the mirrored world (the mirror of its flight: tests/test_augment.py)."""
    config = load_policy(CHECKPOINT).config
    task = task_for_env(85, config)
    with Env(config) as env:
        observations = fly_expert(env, task, config, 12)
        in_mirror = fly_expert(env, mirrored_task(task, config), config, 12)
    return config, task, observations, in_mirror


def test_mirrored_observation_is_what_the_mirrored_world_shows(flight):
    _, task, observations, in_mirror = flight
    F = task.world.field_size
    for obs, there in zip(observations, in_mirror, strict=True):
        m = mirror_observation(obs, F)
        assert np.allclose(m.pose.position, there.pose.position, atol=2e-3)
        assert np.isclose(np.cos(m.pose.yaw - there.pose.yaw), 1.0)
        assert np.allclose(m.pose.R_world_body, there.pose.R_world_body, atol=2e-3)
        assert np.allclose(m.T_world_camera, there.T_world_camera, atol=2e-3)
        assert np.isclose(np.linalg.det(m.T_world_camera[:3, :3]), 1.0, atol=1e-5)
        back = mirror_observation(m, F)  # the reflection is its own inverse
        assert np.array_equal(back.image, obs.image) and np.allclose(back.T_world_camera, obs.T_world_camera)
    # the mirrored task: its path runs from the mirrored start to the mirrored goal, and reflects back
    m = mirror_task(task)
    assert np.allclose(m.path[0], m.world.start_position) and np.allclose(m.path[-1], (m.instruction.goal_x,
                                                                                         m.instruction.goal_y))
    assert np.allclose(mirror_task(m).path, task.path) and mirror_task(m).instruction.side == task.instruction.side
    # the flipped image is what the mirrored world renders, up to the landmark meshes (rotated, not reflected)
    obs, there = observations[0], in_mirror[0].image.astype(np.float32)
    flipped = np.abs(mirror_observation(obs, F).image.astype(np.float32) - there).mean()
    assert flipped < 0.5 * np.abs(obs.image.astype(np.float32) - there).mean()


def test_ensemble_averages_the_model_and_its_mirror_and_is_mirror_symmetric(flight):
    """Flown on a flight and on that flight's mirror image, the ensemble gives mirrored actions (same speed and
    STOP, opposite yaw rate): its two copies swap roles. Each action is the mean of the plain model's on the
    observation and, yaw rate negated, on its mirror image."""
    config, task, observations, _ = flight
    F = task.world.field_size
    ensemble, in_mirror = MirrorEnsemble(load_policy(CHECKPOINT)), MirrorEnsemble(load_policy(CHECKPOINT))
    plain, plain_mirror = load_policy(CHECKPOINT), load_policy(CHECKPOINT)
    mirror = mirrored_task(task, config)
    ensemble.reset(task), in_mirror.reset(mirror), plain.reset(task), plain_mirror.reset(mirror)
    differs = 0.0
    for obs in observations:
        m = mirror_observation(obs, F)
        a, b = ensemble.act(obs), in_mirror.act(m)
        assert a.forward_velocity == pytest.approx(b.forward_velocity, abs=1e-4)
        assert a.yaw_rate == pytest.approx(-b.yaw_rate, abs=1e-4)
        assert a.stop == b.stop
        p, q = plain.act(obs), plain_mirror.act(m)
        assert a.forward_velocity == pytest.approx((p.forward_velocity + q.forward_velocity) / 2, abs=1e-4)
        assert a.yaw_rate == pytest.approx((p.yaw_rate - q.yaw_rate) / 2, abs=1e-4)
        # each copy's own P(stop) is kept, the plain copy's first; STOP is decided on their mean
        assert a.member_stop_probabilities == pytest.approx((p.stop_probability, q.stop_probability), abs=1e-4)
        assert a.stop_probability == pytest.approx(sum(a.member_stop_probabilities) / 2)
        differs = max(differs, abs(a.yaw_rate - p.yaw_rate), abs(a.forward_velocity - p.forward_velocity))
    assert differs > 1e-3  # the mirrored copy changes something: the ensemble is not the plain model
    assert ensemble.last_outputs is ensemble.policy.last_outputs  # the dashboard sees the unmirrored maps


@pytest.mark.slow
def test_mirror_ensemble_only_for_learned_systems_and_never_merged_with_a_plain_run(tmp_path):
    with pytest.raises(ValueError, match="learned system"):
        make_policy("oracle", TINY, mirror_ensemble=True)
    assert isinstance(make_policy("gsmn", TINY, CHECKPOINT, mirror_ensemble=True), MirrorEnsemble)
    out = tmp_path / "ens.json"
    run = subprocess.run([sys.executable, "-m", "gsmn.cli", "eval", "--system", "gsmn", "--env-ids", "85",
                          "--mirror-ensemble", "--json", str(out)], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    d = json.loads(out.read_text())
    assert d["mirror_ensemble"] is True and len(d["episodes"]) == 1
    plain = results_dict("random-point", None, [], TINY, 0.0, 1)
    with pytest.raises(ValueError, match="mirror ensemble"):
        merge_results([{**plain, "mirror_ensemble": True, "env_ids": [1], "episodes": []}, plain])


@pytest.fixture(scope="module")
def second_checkpoint(tmp_path_factory):
    """A second GSMN checkpoint that is not the shipped one: its weights with the controller's output layer scaled
    by 0.8 (a real, different model of the same kind and settings)."""
    policy = load_policy(CHECKPOINT)
    with torch.no_grad():
        policy.model.controller.perceptron.out.weight.mul_(0.8)
    folder = tmp_path_factory.mktemp("ensemble") / "gsmn_b"
    save_checkpoint(folder, policy.model, policy.config, policy.vocabulary)
    return folder


def stop_probability(policy) -> float:
    return float(torch.sigmoid(policy.last_outputs.stop_logit[0, 0]))


def test_ensemble_of_two_checkpoints_averages_their_actions_and_their_mirrors(flight, second_checkpoint):
    """`--ensemble-with`: each action is the mean of the members' (yaw rate of a mirrored member negated), STOP
    when the mean stop probability is above 0.5; with --mirror-ensemble both models also fly the mirror image."""
    config, task, observations, _ = flight
    F = task.world.field_size
    pair = make_policy("gsmn", config, CHECKPOINT, ensemble_with=[second_checkpoint])
    four = make_policy("gsmn", config, CHECKPOINT, mirror_ensemble=True, ensemble_with=[second_checkpoint])
    assert isinstance(pair, Ensemble) and [m for _, m in pair.members] == [False, False]
    assert [m for _, m in four.members] == [False, False, True, True]
    a, b, a_m, b_m = (load_policy(c) for c in (CHECKPOINT, second_checkpoint, CHECKPOINT, second_checkpoint))
    mirror = mirror_task(task)
    for policy, t in ((pair, task), (four, task), (a, task), (b, task), (a_m, mirror), (b_m, mirror)):
        policy.reset(t)
    models_differ = 0.0
    for obs in observations:
        m = mirror_observation(obs, F)
        e, e4 = pair.act(obs), four.act(obs)
        p, q, pm, qm = a.act(obs), b.act(obs), a_m.act(m), b_m.act(m)
        assert e.forward_velocity == pytest.approx((p.forward_velocity + q.forward_velocity) / 2, abs=1e-4)
        assert e.yaw_rate == pytest.approx((p.yaw_rate + q.yaw_rate) / 2, abs=1e-4)
        assert e.stop == ((stop_probability(a) + stop_probability(b)) / 2 > 0.5)
        assert e4.forward_velocity == pytest.approx(
            (p.forward_velocity + q.forward_velocity + pm.forward_velocity + qm.forward_velocity) / 4, abs=1e-4)
        assert e4.yaw_rate == pytest.approx((p.yaw_rate + q.yaw_rate - pm.yaw_rate - qm.yaw_rate) / 4, abs=1e-4)
        assert e4.stop == (sum(map(stop_probability, (a, b, a_m, b_m))) / 4 > 0.5)
        models_differ = max(models_differ, abs(p.yaw_rate - q.yaw_rate), abs(p.forward_velocity - q.forward_velocity))
    assert models_differ > 1e-3  # the second model is another function, so the pair is not the shipped model
    assert pair.last_outputs is pair.policy.last_outputs


@pytest.mark.slow
def test_ensemble_with_refuses_other_kinds_and_is_recorded(tmp_path, second_checkpoint):
    with pytest.raises(ValueError, match="learned system"):
        make_policy("oracle", TINY, ensemble_with=[CHECKPOINT])
    with pytest.raises(ValueError, match="gs-fpv"):
        make_policy("gsmn", TINY, CHECKPOINT, ensemble_with=[REPO_ROOT / "checkpoints" / "gs-fpv"])
    out = tmp_path / "pair.json"
    run = subprocess.run([sys.executable, "-m", "gsmn.cli", "eval", "--system", "gsmn", "--env-ids", "85",
                          "--ensemble-with", str(second_checkpoint), "--json", str(out)],
                         capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    d = json.loads(out.read_text())
    assert d["ensemble_with"] == [str(second_checkpoint)] and d["mirror_ensemble"] is False
    plain = {**results_dict("gsmn", None, [], TINY, 0.0, 1), "env_ids": [2]}
    with pytest.raises(ValueError, match="different ensembles"):
        merge_results([{**plain, "ensemble_with": ["x"], "env_ids": [1]}, plain])
