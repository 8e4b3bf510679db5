"""The episode store and data collection (expert labels, DAgger mixture), with the real simulator."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest

from gsmn.config import preset
from gsmn.task.baselines import AverageAction, AvgForwardPolicy
from gsmn.task.rollout import task_for_env
from gsmn.training.collect import MixturePolicy, collect_expert, episode_key, record_episode
from gsmn.training.store import EpisodeStore, StoreError
from gsmn.world.env import Env

pytestmark = pytest.mark.unit

TINY = preset("tiny")


def test_expert_episode_has_expert_labels_at_every_frame():
    task = task_for_env(70, TINY)
    with Env(TINY) as env:
        sample = record_episode(env, MixturePolicy(TINY), task, TINY.task.horizon)
    T = len(sample.images)
    assert sample.images.shape == (T, 144, 256, 3) and sample.images.dtype == np.uint8
    assert sample.T_world_camera.shape == (T, 4, 4) and sample.poses.shape == (T, 3) and sample.actions.shape == (T, 3)
    assert np.allclose(sample.poses[0, :2], task.world.start_position, atol=1e-6)
    v, omega, stop = sample.actions.T
    assert ((0 <= v) & (v <= 1)).all() and ((-1 <= omega) & (omega <= 1)).all()
    assert stop[-1] == 1 and not stop[:-1].any(), "the expert says STOP once, at the end"
    assert np.allclose(sample.T_world_camera[:, :2, 3], sample.poses[:, :2], atol=0.2)  # camera rides the drone


def test_store_round_trip_is_exact_and_atomic(tmp_path):
    task = task_for_env(71, TINY)
    with Env(TINY) as env:
        sample = record_episode(env, MixturePolicy(TINY), task, TINY.task.horizon)
    store = EpisodeStore(tmp_path / "store")
    store.write("a", sample, meta={"env_id": 71})
    back, meta = store.read_with_meta("a")
    assert meta == {"env_id": 71} and store.read_meta("a") == meta
    assert np.array_equal(store.read_labels("a"), sample.actions)
    assert back.world == sample.world and back.instruction == sample.instruction
    for name in ("images", "T_world_camera", "K", "poses", "actions"):
        assert np.array_equal(getattr(back, name), getattr(sample, name)), name
    assert store.keys() == ["a"] and len(store) == 1 and store.frames() == len(sample.images)
    assert not list((tmp_path / "store").glob(".*tmp*")), "no temporary files left behind"
    with pytest.raises(StoreError, match="no episode"):
        store.read("missing")
    store.path("bad").write_bytes(b"not an npz file")
    with pytest.raises(StoreError, match="malformed"):
        store.read("bad")
    store.path("empty").write_bytes(b"")
    whole = store.path("a").read_bytes()
    store.path("cut").write_bytes(whole[: len(whole) // 2])  # a zip cut short
    for key in ("empty", "cut"):
        with pytest.raises(StoreError, match="malformed"):
            store.read(key)


def test_a_write_killed_part_way_leaves_no_episode_and_its_file_is_swept(tmp_path):
    """A run cancelled while writing leaves `.KEY.PID.tmp.npz` behind: it is never listed as an episode, and a
    store opened later removes it once its writer is gone (a writer still alive keeps its file)."""
    store = EpisodeStore(tmp_path / "store")
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True,
                          text=True, check=True).stdout.strip()
    left = tmp_path / "store" / f".env_000070.{dead}.tmp.npz"
    left.write_bytes(b"PK\x03\x04 part of a zip")
    live = tmp_path / "store" / f".env_000071.{os.getpid()}.tmp.npz"
    live.write_bytes(b"")
    assert store.keys() == [] and len(store) == 0 and "env_000070" not in store
    EpisodeStore(tmp_path / "store")
    assert not left.exists() and live.exists()


@pytest.mark.slow
def test_collection_resumes_and_parallel_workers_write_the_same_episodes(tmp_path):
    one, two = EpisodeStore(tmp_path / "one"), EpisodeStore(tmp_path / "two")
    assert collect_expert(one, [70, 71], TINY) == [70, 71]
    assert collect_expert(one, [70, 71, 72], TINY) == [72], "already-collected episodes are skipped"
    collect_expert(two, [70, 71, 72], TINY, workers=2)
    assert one.keys() == two.keys() == [episode_key(e) for e in (70, 71, 72)]
    for key in one.keys():
        a, b = one.read(key), two.read(key)
        assert np.array_equal(a.images, b.images) and np.array_equal(a.actions, b.actions)


def test_mixture_lets_the_learner_act_but_labels_with_the_expert():
    task = task_for_env(73, TINY)
    learner = AvgForwardPolicy(AverageAction(forward_velocity=1.6, yaw_rate=0.3, steps=200, episodes=1))
    rng = np.random.default_rng(0)
    with Env(TINY) as env:
        mixed = MixturePolicy(TINY, learner=learner, beta=0.5, rng=rng)
        sample = record_episode(env, mixed, task, horizon=40)
        assert mixed.expert_steps > 0 and mixed.learner_steps > 0
        only_learner = MixturePolicy(TINY, learner=learner, beta=0.0, rng=rng, max_deviation=4.5)
        cut = record_episode(env, only_learner, task, horizon=TINY.task.horizon)
    assert only_learner.expert_steps == 0
    # The learner flies a 5.3 m-radius circle away from the path: the rollout is cut once it strays 4.5 m.
    assert len(cut.images) < TINY.task.horizon
    assert not cut.actions[:, 2].any(), "labels are the expert's (no STOP far from the goal)"
    assert (np.abs(sample.actions[:, 1]) <= 1).all()
    with pytest.raises(ValueError, match="learner"):
        MixturePolicy(TINY, beta=0.5)
