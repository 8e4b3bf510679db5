"""Forks and comparisons (tiny preset, an untrained checkpoint biased to fly): a fork at step t with the same policy
and instruction ends exactly as the original, for the model, the mirror ensemble and the expert; a fork with
another instruction flies to another landmark; two episodes stepping together in one simulator fly exactly as
each alone; where two flights part; and the HTTP routes."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
import torch
from fastapi.testclient import TestClient

from app.live.commands import Conflict, NotFound, RunnerError, StartEpisode
from app.live.compare import ForkEpisode, PolicySpec, StartComparison, diverged_at
from app.live.fixtures import make_untrained_checkpoint
from app.live.recording import FINISHED
from app.live.runner import Runner
from gsmn.config import preset, with_overrides
from gsmn.task.fork import KEYFRAME_EVERY
from gsmn.task.understand import parse_instruction

pytestmark = pytest.mark.slow

HORIZON = 36


def wait_done(episodes, timeout: float = 180.0) -> None:
    deadline = time.monotonic() + timeout
    while any(e.live for e in episodes):
        if time.monotonic() > deadline:
            raise AssertionError("timed out waiting for the episodes to end")
        time.sleep(0.02)


@pytest.fixture(scope="module")
def runner(tmp_path_factory, untrained_checkpoint):
    torch.set_num_threads(1)
    folder = untrained_checkpoint
    config = with_overrides(preset("tiny"), {"task.horizon": str(HORIZON)})
    r = Runner(config, checkpoint=str(folder), require_checkpoint=True,
               checkpoints_root=tmp_path_factory.mktemp("empty"), max_episodes=64).start()
    yield r
    r.close()


def fly(runner, *args, **kwargs):
    episode = runner.call(StartEpisode(*args, **kwargs))
    wait_done([episode])
    assert episode.status == FINISHED, episode.error
    return episode


def positions(episode) -> np.ndarray:
    return np.array([s.position for s in episode.steps])


def _key(s) -> tuple:
    return s.step, s.position, s.yaw, s.v, s.omega, s.stop, s.camera_jpeg


def assert_same_end(fork, original, t: int) -> None:
    assert fork.status == FINISHED, fork.error
    assert fork.result.steps == original.result.steps
    assert len(fork.steps) == len(original.steps)
    assert [_key(s) for s in fork.steps[:t]] == [_key(s) for s in original.steps[:t]]  # the original's records
    end = math.dist((fork.result.final_x, fork.result.final_y), (original.result.final_x, original.result.final_y))
    assert end < 0.01, f"fork at step {t} ends {end:.4f} m from the original"
    assert fork.result.success == original.result.success and fork.result.stopped == original.result.stopped
    # every step after t too: the state restored is exact, not close
    np.testing.assert_allclose(positions(fork), positions(original), atol=1e-9)


@pytest.mark.parametrize("policy", ["model", "expert", "mirror"])
def test_a_fork_with_the_same_policy_ends_exactly_as_the_original(runner, policy):
    original = fly(runner, 70, None, policy)
    last = len(original.steps) - 1
    assert last >= 20  # enough steps for keyframes (every KEYFRAME_EVERY) and replays between them
    k = KEYFRAME_EVERY
    steps = [0, k - 1, k, 2 * k + 3, last // 2, last] if policy != "mirror" else [0, 2 * k + 3, last]
    forks = [runner.call(ForkEpisode(original.id, t)) for t in steps]
    wait_done(forks)
    for t, fork in zip(steps, forks, strict=True):
        assert fork.fork.step == t and fork.policy == policy and fork.instruction == original.instruction
        assert_same_end(fork, original, t)
        if policy != "expert":  # the maps the model held are the original's too
            np.testing.assert_array_equal(fork.steps[-1].maps.semantic_w, original.steps[-1].maps.semantic_w)


def test_a_fork_of_a_fork_and_a_fork_with_the_expert_watching_model(runner):
    """An expert episode's watching model carries into a fork the model flies: its keyframes apply."""
    original = fly(runner, 71, None, "model")
    fork = runner.call(ForkEpisode(original.id, 12))
    wait_done([fork])
    again = runner.call(ForkEpisode(fork.id, 25))
    wait_done([again])
    assert_same_end(again, original, 25)


def test_a_fork_with_another_instruction_flies_to_another_landmark(runner):
    original = fly(runner, 70, None, "expert")
    world = original.task.world
    t = len(original.steps) // 4
    here = np.array(original.steps[t].position[:2])
    others = [lm for lm in world.landmarks if lm.noun_phrase != original.task.instruction.noun_phrase
              and len(world.landmarks_named(lm.noun_phrase)) == 1]
    end = np.array([original.result.final_x, original.result.final_y])
    near = [lm for lm in others if np.linalg.norm(lm.position - here) < 16.0] or others  # within the horizon's reach
    other = max(near, key=lambda lm: np.linalg.norm(lm.position - end))  # away from where the original went
    texts = [f"go to the {side} side of the {other.noun_phrase}" for side in ("left", "right", "front", "back")]
    text = next(x for x in texts if world.on_field(parse_instruction(x, world).goal))
    goal = parse_instruction(text, world).goal
    fork = runner.call(ForkEpisode(original.id, t, instruction=text))
    wait_done([fork])
    assert fork.status == FINISHED, fork.error
    assert fork.instruction == text and all(a is b for a, b in zip(fork.steps[:t], original.steps[:t], strict=True))
    assert fork.steps[t].position == original.steps[t].position  # it starts where the original was at step t
    final = (fork.result.final_x, fork.result.final_y)
    start = math.dist(original.steps[t].position[:2], goal)
    assert fork.result.landmark_success and math.dist(final, goal) < start - 5.0, "it flies to the new landmark"
    assert math.dist(end, other.position) > 6.0  # the original did not end in that landmark's region


def test_another_checkpoint_rebuilds_its_own_map_along_the_original_path(runner, tmp_path):
    make_untrained_checkpoint(runner.checkpoints.root / "other", seed=1)  # offered: a name under checkpoints/
    original = fly(runner, 72, None, "model")
    t = 15
    fork = runner.call(ForkEpisode(original.id, t, checkpoint="other"))
    wait_done([fork])
    assert fork.status == FINISHED, fork.error
    assert fork.steps[t].position == original.steps[t].position
    assert fork.checkpoint != original.checkpoint
    # its map at step t is the one it builds flying the original's path from the start
    solo = fly(runner, 72, None, "model", "other")
    assert not np.array_equal(fork.steps[t].maps.semantic_w, original.steps[t].maps.semantic_w)
    assert solo.steps[0].maps.semantic_w.shape == fork.steps[t].maps.semantic_w.shape


def test_fork_errors_say_what_was_wrong(runner):
    original = fly(runner, 70, None, "expert")
    with pytest.raises(NotFound):
        runner.call(ForkEpisode(10_000, 0))
    with pytest.raises(RunnerError, match="step 999 is not recorded"):
        runner.call(ForkEpisode(original.id, 999))
    with pytest.raises(RunnerError, match="not a landmark: blorp"):
        runner.call(ForkEpisode(original.id, 3, instruction="go to the blorp"))
    live = runner.call(StartEpisode(70, None, "model", paused=True))
    try:
        deadline = time.monotonic() + 60
        while not live.steps and time.monotonic() < deadline:
            time.sleep(0.02)
        with pytest.raises(Conflict, match="fork it once it has ended"):
            runner.call(ForkEpisode(live.id, 0))
    finally:
        from app.live.commands import CancelEpisode

        runner.call(CancelEpisode(live.id))
        wait_done([live])


def test_two_episodes_stepping_together_fly_as_each_alone(runner):
    comparison = runner.call(StartComparison(73, None, [PolicySpec("model"), PolicySpec("expert")]))
    a, b = comparison.episodes
    wait_done([a, b])
    assert a.status == b.status == FINISHED and a.comparison == b.comparison == comparison.id
    solo_a, solo_b = fly(runner, 73, None, "model"), fly(runner, 73, None, "expert")
    np.testing.assert_allclose(positions(a), positions(solo_a), atol=1e-9)
    np.testing.assert_allclose(positions(b), positions(solo_b), atol=1e-9)
    np.testing.assert_array_equal(a.steps[-1].maps.semantic_w, solo_a.steps[-1].maps.semantic_w)
    t = comparison.diverged_at()
    assert t is not None and t > 0
    pa, pb = positions(a), positions(b)
    assert np.hypot(*(pa[t, :2] - pb[t, :2])) > 1.0 or a.steps[t].stop != b.steps[t].stop
    assert all(np.hypot(*(pa[s, :2] - pb[s, :2])) <= 1.0 for s in range(t))
    # a comparison's episode forks like any other
    fork = runner.call(ForkEpisode(a.id, t))
    wait_done([fork])
    assert_same_end(fork, a, t)


def test_diverged_at():
    line = [(x, 0.0) for x in range(6)]
    never = [False] * 6
    assert diverged_at(line, never, False, line, never, False) is None
    apart = [(x, 0.0 if x < 3 else 1.5) for x in range(6)]
    assert diverged_at(line, never, False, apart, never, False) == 3
    stops = [False, False, True]
    assert diverged_at(line[:3], stops, False, line, never, False) == 2  # one says STOP, the other flies on
    assert diverged_at(line[:3], stops, False, line[:3], stops, False) is None  # both stop there together
    assert diverged_at(line[:3], [False] * 3, True, line, never, False) is None  # still flying


def test_the_http_routes(runner):
    from app.api.app import make_api

    client = TestClient(make_api(runner))
    body = {"env_id": 74, "policies": [{"policy": "expert"}, {"policy": "model"}]}
    r = client.post("/api/comparisons", json=body)
    assert r.status_code == 201, r.text
    cid, episodes = r.json()["id"], r.json()["episodes"]
    assert len(episodes) == 2
    deadline = time.monotonic() + 180
    while client.get(f"/api/comparisons/{cid}").json()["status"] != "finished":
        assert time.monotonic() < deadline
        time.sleep(0.1)
    c = client.get(f"/api/comparisons/{cid}").json()
    assert [e["id"] for e in c["episodes"]] == episodes and all(e["result"] for e in c["episodes"])
    assert isinstance(c["diverged_at"], int)
    assert c["succeeded"] == [e["id"] for e in c["episodes"] if e["result"]["success"]]
    assert client.get("/api/comparisons/999").status_code == 404
    assert client.post("/api/comparisons", json={**body, "policies": body["policies"][:1]}).status_code == 422
    r = client.post(f"/api/episodes/{episodes[0]}/fork", json={"step": 5, "policy": "model"})
    assert r.status_code == 201, r.text
    assert r.json()["policy"] == "model"
    assert client.post(f"/api/episodes/{episodes[0]}/fork", json={"step": 10_000}).status_code == 422
    assert client.post("/api/episodes/99999/fork", json={"step": 0}).status_code == 404
    fork_id = r.json()["id"]
    deadline = time.monotonic() + 120
    while client.get(f"/api/episodes/{fork_id}").json()["status"] != "finished":
        assert time.monotonic() < deadline
        time.sleep(0.1)


def test_truth_layers_and_figures_are_served(runner):
    from app.api.app import make_api
    from app.render.colors import decode_image

    client = TestClient(make_api(runner))
    episode = fly(runner, 75, None, "expert")  # the model watches
    r = client.get(f"/api/episodes/{episode.id}/steps")
    assert r.status_code == 200
    body = r.json()
    figures = [s["truth"] for s in body["steps"]]
    assert all(f is not None for f in figures) and len(figures) == len(episode.steps)
    last = figures[-1]
    assert 0 <= last["perception"] <= 1 and 0 <= last["relevance"] <= 1 and 0 <= last["goal"] <= 1
    assert set(body["went_wrong"]) == {"perception", "relevance", "goal"}
    n = episode.steps[0].maps.semantic_w.shape[-1]
    for layer in ("truth_semantic", "truth_relevance", "truth_goal"):
        r = client.get(f"/api/episodes/{episode.id}/steps/3/maps/{layer}.png")
        assert r.status_code == 200 and r.headers["content-type"] == "image/png"
        image = decode_image(r.content)
        assert image.shape[:2] == (4 * n, 4 * n) and len(np.unique(image.reshape(-1, 3), axis=0)) >= 2
    assert client.get(f"/api/episodes/{episode.id}/steps/3/maps/truth_nothing.png").status_code == 422
    truth = client.get(f"/api/episodes/{episode.id}/steps/0/maps/truth_relevance.png").content
    assert truth == client.get(f"/api/episodes/{episode.id}/steps/3/maps/truth_relevance.png").content


def test_forks_and_comparisons_are_kept_in_the_record_with_every_step(tmp_path, untrained_checkpoint):
    """A fork starts with the original's steps 0..t-1, never flown again: the record keeps them too, so the kept
    fork has all its steps; both episodes of a comparison are kept."""
    from app.jobs.db import Database
    from app.jobs.kept import EpisodeKeeper
    from app.jobs.kept_store import KeptStore

    torch.set_num_threads(1)
    folder = untrained_checkpoint
    config = with_overrides(preset("tiny"), {"task.horizon": str(HORIZON)})
    db = Database(tmp_path / "record.sqlite")
    store = KeptStore(db, config, 64)
    r = Runner(config, checkpoint=str(folder), require_checkpoint=True, checkpoints_root=tmp_path / "empty",
               episodes=store).start()
    keeper = EpisodeKeeper(store, 10**9)
    r.listeners.append(keeper)
    try:
        original = fly(r, 73, None, "model")
        fork = r.call(ForkEpisode(original.id, 12))
        comparison = r.call(StartComparison(70, None, [PolicySpec("model"), PolicySpec("expert")]))
        wait_done([fork, *comparison.episodes])
        keeper.flush()
        for episode in (original, fork, *comparison.episodes):
            kept = KeptStore(db, config).load(episode.id)
            assert kept is not None and kept.status == FINISHED
            assert [s.step for s in kept.steps] == [s.step for s in episode.steps]
            np.testing.assert_allclose(positions(kept), positions(episode), atol=1e-6)
        assert [s.camera_jpeg for s in KeptStore(db, config).load(fork.id).steps[:12]] == \
            [s.camera_jpeg for s in original.steps[:12]]
    finally:
        keeper.close()
        r.close()
        db.close()
