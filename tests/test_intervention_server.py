"""Map interventions over the HTTP API against a real `gsmn serve` (tiny preset, an untrained GSMN given map codes
from two real calibration flights): a fork at step t flies on from the drone's exact state with the true goal map
held in place of the model's own, says so in its summary, and a request that cannot be met is refused saying why."""

from __future__ import annotations

import shutil

import pytest
from test_api_server import finished

pytestmark = pytest.mark.server
HORIZON = 40


@pytest.fixture(scope="module")
def client(tmp_path_factory, untrained_checkpoint, gsmn_serve):
    from gsmn.analysis.rescue import calibrate, save_codes
    from gsmn.config import preset, with_overrides

    folder = tmp_path_factory.mktemp("ckpt") / "gsmn"
    shutil.copytree(untrained_checkpoint, folder, copy_function=shutil.copyfile)
    save_codes(folder, calibrate(folder, [85, 86], with_overrides(preset("tiny"), {"task.horizon": "12"})))
    serve = gsmn_serve(tmp_path_factory.mktemp("data"), folder, horizon=HORIZON)
    yield serve.client
    serve.stop(timeout=20)


def test_a_fork_flies_on_with_the_true_goal_map_held(client):
    original = finished(client, client.post("/api/episodes", json={"env_id": 70}).json()["id"])
    assert original["status"] == "finished", original["error"]
    forked = client.post(f"/api/episodes/{original['id']}/fork",
                         json={"step": 8, "intervention": {"map": "goal", "with": "truth"}})
    assert forked.status_code == 201, forked.text
    fork = finished(client, forked.json()["id"])
    assert fork["status"] == "finished", fork["error"]
    assert fork["intervention"] == {"map": "goal", "with": "truth", "hold": True} and original["intervention"] is None
    a = client.get(f"/api/episodes/{original['id']}/steps").json()["steps"]
    b = client.get(f"/api/episodes/{fork['id']}/steps").json()["steps"]
    assert [(s["x"], s["y"]) for s in b[:8]] == [(s["x"], s["y"]) for s in a[:8]]
    assert (b[8]["x"], b[8]["y"], b[8]["z"]) == pytest.approx((a[8]["x"], a[8]["y"], a[8]["z"]), abs=1e-9)
    assert any(abs(p["x"] - q["x"]) + abs(p["y"] - q["y"]) > 1e-6 for p, q in zip(a[9:], b[9:], strict=False)), \
        "the held goal map changed what the model did"

    def goal_png(episode: dict, step: int) -> bytes:
        return client.get(f"/api/episodes/{episode['id']}/steps/{step}/maps/goal.png").content

    last = min(len(a), len(b)) - 1
    assert goal_png(fork, 9) == goal_png(fork, last), "the true goal map is the same at every step"
    assert goal_png(original, 9) != goal_png(original, last)


@pytest.mark.parametrize("payload, words", [
    ({"step": 3, "intervention": {"map": "goal", "hold": False}}, "can only be held"),
    ({"step": 3, "intervention": {"map": "goal", "with": "painted", "paint": [{"op": "dab", "x": 1, "y": 1}]}},
     "each paint is"),
    ({"step": 3, "policy": "expert", "intervention": {"map": "goal"}}, "with policy 'model'"),
])
def test_an_intervention_that_cannot_be_made_is_refused_saying_why(client, payload, words):
    original = finished(client, client.post("/api/episodes", json={"env_id": 71}).json()["id"])
    refused = client.post(f"/api/episodes/{original['id']}/fork", json=payload)
    assert refused.status_code == 422 and words in refused.json()["detail"], refused.text


def evaluation_done(client, evaluation_id: int, timeout: float = 240.0) -> dict:
    from support import poll

    return poll(lambda: client.get(f"/api/evaluations/{evaluation_id}").json(),
                lambda e: e["status"] not in ("queued", "running"), f"evaluation {evaluation_id}", timeout, 0.5)


def test_an_evaluations_failures_flown_again_with_the_true_goal_map(client):
    """An evaluation job, then its failures flown again with the true goal map as another job: the rescue table
    counts, per attributed stage, the failures the second one turned into successes."""
    first = evaluation_done(client, client.post("/api/evaluations", json={"env_ids": [70, 71, 72]}).json()["id"])
    assert first["status"] == "finished", first["error"]
    episodes = client.get(f"/api/evaluations/{first['id']}/episodes").json()
    failures = [e["env_id"] for e in episodes if not e["success"]]
    assert failures, "the untrained model fails"
    started = client.post(f"/api/evaluations/{first['id']}/rescue", json={"intervention": "truth-goal"})
    assert started.status_code == 201, started.text
    rescue = started.json()
    assert rescue["intervention"] == "truth-goal" and rescue["baseline_id"] == first["id"]
    assert rescue["env_ids"] == failures and "perfect goal" in rescue["label"]
    rescue = evaluation_done(client, rescue["id"])
    assert rescue["status"] == "finished", rescue["error"]
    saved = {e["env_id"] for e in client.get(f"/api/evaluations/{rescue['id']}/episodes").json() if e["success"]}
    table = client.get(f"/api/evaluations/{first['id']}/rescue").json()
    assert table["failures"] == len(failures) and table["evaluations"] == {"truth-goal": rescue["id"]}
    row = table["interventions"]["truth-goal"]
    assert row["all"]["of"] == len(failures) and row["all"]["rescued"] == len(saved)
    assert sum(r["of"] for r in row["per_stage"].values()) == len(failures)
    # a replay of a rescued episode flies with the same true map, and ends where the evaluation's flight did
    flown = client.get(f"/api/evaluations/{rescue['id']}/episodes").json()[0]
    replayed = client.post(f"/api/evaluations/{rescue['id']}/replay", json={"env_id": flown["env_id"]})
    assert replayed.status_code == 201, replayed.text
    live = finished(client, replayed.json()["episode_id"])
    assert live["intervention"] == {"map": "goal", "with": "truth", "hold": True}, live
    assert (live["result"]["final_x"], live["result"]["final_y"]) == pytest.approx(
        (flown["final_x"], flown["final_y"]), abs=0.01)
    again = client.post(f"/api/evaluations/{rescue['id']}/rescue", json={"intervention": "truth-goal"})
    assert again.status_code == 422 and "flew with an intervention already" in again.json()["detail"]
    assert client.post(f"/api/evaluations/{first['id']}/rescue", json={"intervention": "truth-camera"}).status_code \
        == 422
