"""The HTTP API against a real `gsmn serve` process (tiny preset, an untrained checkpoint, 60-step horizon):
health, checkpoints, OpenAPI, episodes with their per-step data, counterfactual grounding, and 4xx answers
that say what was wrong while the server keeps serving."""

from __future__ import annotations

import math
import subprocess
import time

import httpx
import pytest
from support import serve_command

HORIZON = 60

pytestmark = pytest.mark.server


@pytest.fixture(scope="module")
def server(tmp_path_factory, untrained_checkpoint, gsmn_serve):
    serve = gsmn_serve(tmp_path_factory.mktemp("data"), untrained_checkpoint, horizon=HORIZON)
    try:
        assert serve.page, "server did not print both URLs:\n" + serve.output()
        yield {"client": serve.client, "proc": serve.proc, "lines": serve.lines, "folder": str(untrained_checkpoint),
               "page": serve.page, "api": serve.api}
    finally:
        serve.stop(timeout=20)


def finished(client: httpx.Client, episode_id: int, timeout: float = 120.0) -> dict:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        body = client.get(f"/api/episodes/{episode_id}").json()
        if body["status"] not in ("queued", "running", "paused"):
            return body
        time.sleep(0.2)
    raise AssertionError(f"episode {episode_id} did not finish: {body}")


def test_health_checkpoints_and_docs(server):
    client = server["client"]
    health = client.get("/api/health").json()
    assert health["status"] == "ok" and health["model_loaded"] and health["viewer_url"] == server["page"]
    assert any(c["path"] == server["folder"] and c["default"] and c["loaded"] and c["kind"] == "gsmn"
               for c in client.get("/api/checkpoints").json())
    spec = client.get("/openapi.json").json()
    for path in ("/api/health", "/api/checkpoints", "/api/episodes", "/api/episodes/{episode_id}",
                 "/api/episodes/{episode_id}/steps", "/api/ground"):
        assert path in spec["paths"]
    assert "EpisodeRequest" in spec["components"]["schemas"]
    assert client.get("/docs").status_code == 200
    page = httpx.get(server["page"], timeout=30)
    assert page.status_code == 200 and "<html" in page.text.lower()


def test_an_episode_from_request_to_per_step_data(server):
    client = server["client"]
    response = client.post("/api/episodes", json={"env_id": 70, "instruction": "go to the left side of the pumpkin"})
    assert response.status_code == 201, response.text
    created = response.json()
    assert created["instruction"] == "go to the left side of the pumpkin" and created["policy"] == "model"
    body = finished(client, created["id"])
    assert body["status"] == "finished" and body["landmark"] == "pumpkin" and body["side"] == "left"
    result = body["result"]
    for key in ("success", "landmark_success", "goal_distance", "landmark_distance", "steps", "stopped",
                "stop_probability", "final_side"):
        assert key in result
    assert result["steps"] <= HORIZON and body["steps"] == result["steps"] + 1
    steps = client.get(f"/api/episodes/{created['id']}/steps").json()["steps"]
    assert len(steps) == body["steps"] and steps[0]["step"] == 0 and steps[-1]["step"] == result["steps"]
    assert steps[0]["model"] is not None and 0 <= steps[0]["model"]["stop_probability"] <= 1
    camera = client.get(f"/api/episodes/{created['id']}/steps/3/camera.jpg")
    assert camera.headers["content-type"] == "image/jpeg" and camera.content[:2] == b"\xff\xd8"
    semantic = client.get(f"/api/episodes/{created['id']}/steps/3/maps/semantic.png")
    assert semantic.headers["content-type"] == "image/png" and semantic.content[:4] == b"\x89PNG"
    assert client.get(f"/api/episodes/{created['id']}/steps/3/maps/elevation.png").status_code == 422
    assert client.get(f"/api/episodes/{created['id']}/steps/999/camera.jpg").status_code == 422
    assert any(e["id"] == created["id"] for e in client.get("/api/episodes").json())

    # counterfactual grounding on that episode's map, at a chosen step and at the last one
    g = client.post("/api/ground", json={"episode_id": created["id"], "instruction": "go to the back side of the box",
                                         "step": 10})
    assert g.status_code == 200, g.text
    g = g.json()
    assert g["step"] == 10 and g["landmark"] == "box" and g["side"] == "back"
    assert len(g["goal_probability"]) == 32 and len(g["goal_probability"][0]) == 32
    assert len(g["relevance_probability"]) == 32 and 0 <= g["stop_probability"] <= 1
    assert g["seconds"] < 1.0
    last = client.post("/api/ground", json={"episode_id": created["id"],
                                            "instruction": "go to the back side of the box"})
    assert last.json()["step"] == result["steps"]


def test_the_expert_on_its_own_instruction(server):
    client = server["client"]
    created = client.post("/api/episodes", json={"env_id": 71, "policy": "expert"}).json()
    body = finished(client, created["id"])
    assert body["status"] == "finished" and body["system"] == "oracle"
    assert body["result"]["goal_distance"] >= 0


def test_the_expert_flies_a_world_with_a_landmark_moved(server):
    """Environment 70 with the box removed and the pumpkin moved where it stood: the instruction keeps its words,
    its goal moved with the pumpkin, the expert flies toward it, and the episode (and its kept row) say what was
    changed."""
    from gsmn.config import preset
    from gsmn.task.edits import edited_task, parse_edits
    from gsmn.task.rollout import task_for_env

    client = server["client"]
    task = task_for_env(70, preset("tiny"))
    box = next(k for k, lm in enumerate(task.world.landmarks) if lm.noun_phrase == "box")
    edits = [{"op": "remove", "landmark": box}, {"op": "move", "landmark": task.instruction.landmark_index,
                                                  "x": task.world.landmarks[box].x, "y": task.world.landmarks[box].y}]
    expected = edited_task(task, parse_edits(edits), preset("tiny")).instruction
    created = client.post("/api/episodes", json={"env_id": 70, "policy": "expert", "world_edits": edits})
    assert created.status_code == 201, created.text
    body = finished(client, created.json()["id"])
    assert body["instruction"] == task.instruction.text and body["world_edits"] == edits
    assert (body["goal_x"], body["goal_y"]) == pytest.approx((expected.goal_x, expected.goal_y))
    assert abs(body["goal_x"] - task.instruction.goal_x) + abs(body["goal_y"] - task.instruction.goal_y) > 5
    steps = client.get(f"/api/episodes/{body['id']}/steps").json()["steps"]
    first, last = (steps[0]["x"], steps[0]["y"]), (steps[-1]["x"], steps[-1]["y"])
    goal = (expected.goal_x, expected.goal_y)
    assert math.dist(last, goal) < math.dist(first, goal) - 3, "the expert flew toward the moved goal"


def test_a_fork_edits_the_world_at_its_step_and_the_drone_keeps_its_state(server):
    """The expert's flight in environment 70, forked at step 12 with the pumpkin moved where the box stood: the
    fork's first 12 steps are the original's, it goes on from the drone's exact state at step 12 toward the moved
    goal, and says what was changed; a landmark put where the drone then is is refused."""
    from gsmn.config import preset
    from gsmn.task.rollout import task_for_env

    client = server["client"]
    task = task_for_env(70, preset("tiny"))
    original = finished(client, client.post("/api/episodes", json={"env_id": 70, "policy": "expert"}).json()["id"])
    box = next(k for k, lm in enumerate(task.world.landmarks) if lm.noun_phrase == "box")
    edits = [{"op": "remove", "landmark": box}, {"op": "move", "landmark": task.instruction.landmark_index,
                                                  "x": task.world.landmarks[box].x, "y": task.world.landmarks[box].y}]
    forked = client.post(f"/api/episodes/{original['id']}/fork", json={"step": 12, "world_edits": edits})
    assert forked.status_code == 201, forked.text
    fork = finished(client, forked.json()["id"])
    assert fork["world_edits"] == edits and fork["fork_of"] == original["id"] and fork["fork_step"] == 12
    assert abs(fork["goal_x"] - original["goal_x"]) + abs(fork["goal_y"] - original["goal_y"]) > 5
    assert fork["status"] == "finished", fork["error"]
    a = client.get(f"/api/episodes/{original['id']}/steps").json()["steps"]
    b = client.get(f"/api/episodes/{fork['id']}/steps").json()["steps"]
    assert [(s["x"], s["y"]) for s in b[:12]] == [(s["x"], s["y"]) for s in a[:12]]
    assert (b[12]["x"], b[12]["y"], b[12]["z"]) == pytest.approx((a[12]["x"], a[12]["y"], a[12]["z"]), abs=1e-9)
    goal = (fork["goal_x"], fork["goal_y"])
    assert math.dist((b[-1]["x"], b[-1]["y"]), goal) < math.dist((a[-1]["x"], a[-1]["y"]), goal), \
        "the fork flew toward the moved goal"
    at = (a[12]["x"], a[12]["y"])
    k = 3.0 / math.dist(at, (15.0, 15.0))  # 3 m from the drone toward the middle of the field
    near = (at[0] + k * (15.0 - at[0]), at[1] + k * (15.0 - at[1]))
    refused = client.post(f"/api/episodes/{original['id']}/fork", json={"step": 12, "world_edits": [
        {"op": "move", "landmark": task.instruction.landmark_index, "x": near[0], "y": near[1]}]})
    assert refused.status_code == 422 and "would stand on the drone" in refused.json()["detail"]


def test_the_model_as_a_mirror_ensemble(server):
    client = server["client"]
    created = client.post("/api/episodes", json={"env_id": 72, "policy": "mirror"}).json()
    assert created["policy"] == "mirror"
    body = finished(client, created["id"])
    assert body["status"] == "finished" and body["policy"] == "mirror" and body["system"] == "gsmn"


@pytest.mark.parametrize("method, path, payload, status, words", [
    ("post", "/api/episodes", {"env_id": -1}, 422, "env_id"),
    ("post", "/api/episodes", {"env_id": "seventy"}, 422, "env_id"),
    ("post", "/api/episodes", {}, 422, "env_id"),
    ("post", "/api/episodes", {"env_id": 70, "colour": "red"}, 422, "colour"),
    ("post", "/api/episodes", {"env_id": 70, "instruction": "fly to the moon"}, 422, "not a landmark: moon"),
    ("post", "/api/episodes", {"env_id": 70, "instruction": "go to the left side of the anvil"}, 422,
     "no anvil in this world"),
    ("post", "/api/episodes", {"env_id": 70, "instruction": "go to the pumpkin"}, 422, "no side"),
    ("post", "/api/episodes", {"env_id": 70, "checkpoint": "/no/such/folder"}, 422, "not one this dashboard offers"),
    ("post", "/api/episodes", {"env_id": 70, "checkpoint": "/etc"}, 422, "not one this dashboard offers"),
    ("post", "/api/episodes", {"env_id": 70, "checkpoint": " "}, 422, "checkpoint is empty"),
    ("post", "/api/episodes", {"env_id": 70, "policy": "pilot"}, 422, "policy"),
    ("post", "/api/episodes", {"env_id": 70, "world_edits": [{"op": "remove", "landmark": 2}]}, 422,
     "names the pumpkin (landmark 2), which the edits remove"),
    ("post", "/api/episodes", {"env_id": 70, "world_edits": [{"op": "move", "landmark": 2, "x": 1.0, "y": 9.0}]}, 422,
     "would be off the field"),
    ("post", "/api/episodes", {"env_id": 70, "world_edits": [{"op": "paint", "landmark": 2}]}, 422, "op"),
    ("post", "/api/episodes", {"env_id": 70, "world_edits": [{"op": "move", "landmark": 2}]}, 422, "needs x, y"),
    ("post", "/api/episodes", {"env_id": 70, "world_edits": [{"op": "add", "noun_phrase": "unicorn", "x": 9.0,
                                                              "y": 9.0}]}, 422, "no landmark called 'unicorn'"),
    ("get", "/api/episodes/424242", None, 404, "no episode 424242"),
    ("get", "/api/episodes/abc", None, 422, "episode_id"),
    ("get", "/api/episodes/424242/steps", None, 404, "no episode"),
    ("post", "/api/ground", {"episode_id": 424242, "instruction": "go to the left side of the box"}, 404,
     "no episode"),
    ("post", "/api/ground", {"episode_id": 1, "instruction": ""}, 422, "instruction"),
    ("post", "/api/ground", {"episode_id": 1, "instruction": "go left", "step": -2}, 422, "step"),
    ("post", "/api/ground", {"episode_id": 1, "instruction": "go to the left side of the box", "step": 5000}, 422,
     "not recorded"),
    ("post", "/api/ground", {"episode_id": 1, "instruction": "go to the left side of the spaceship"}, 422,
     "not a landmark: spaceship"),
])
def test_bad_input_gets_a_4xx_that_says_what_was_wrong(server, method, path, payload, status, words):
    client = server["client"]
    response = client.request(method, path, json=payload)
    assert response.status_code == status, response.text
    detail = response.json()["detail"]
    assert isinstance(detail, str) and words in detail
    assert client.get("/api/health").status_code == 200  # still serving


def test_malformed_json_is_a_422_not_a_crash(server):
    client = server["client"]
    response = client.post("/api/episodes", content=b"{not json", headers={"content-type": "application/json"})
    assert response.status_code == 422 and "JSON" in response.json()["detail"]
    assert server["proc"].poll() is None


def test_without_a_model_the_api_says_so_and_the_expert_flies(tmp_path):
    """In-process, on real sockets: no checkpoint under the (empty) checkpoints folder."""
    from app.server import Dashboard
    from gsmn.config import preset, with_overrides

    dashboard = Dashboard(with_overrides(preset("tiny"), {"task.horizon": "30"}), port=0, api_port=0,
                          checkpoints_root=tmp_path, data_dir=tmp_path / "data")
    try:
        with httpx.Client(base_url=dashboard.urls.api, timeout=60) as client:
            health = client.get("/api/health").json()
            assert not health["model_loaded"] and "No model loaded" in health["checkpoint_message"]
            assert client.get("/api/checkpoints").json() == []
            refused = client.post("/api/episodes", json={"env_id": 70})
            assert refused.status_code == 409 and "no checkpoint to fly" in refused.json()["detail"]
            created = client.post("/api/episodes", json={"env_id": 70, "policy": "expert"}).json()
            body = finished(client, created["id"])
            assert body["status"] == "finished" and body["checkpoint"] is None
            g = client.post("/api/ground", json={"episode_id": created["id"],
                                                 "instruction": "go to the left side of the box"})
            assert g.status_code == 409 and "no semantic map" in g.json()["detail"]
            assert client.get(f"/api/episodes/{created['id']}/steps/0/maps/goal.png").status_code == 422
        assert httpx.get(dashboard.urls.page, timeout=30).status_code == 200
    finally:
        dashboard.close()


def test_an_explicit_checkpoint_that_does_not_load_stops_serve(tmp_path):
    done = subprocess.run(serve_command(data_dir=tmp_path / "data", checkpoint=tmp_path / "missing"),
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 2
    assert f"no checkpoint at {tmp_path / 'missing'}" in done.stderr
