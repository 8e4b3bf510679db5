"""The HTTP API against a real `gsmn serve` process (tiny preset, an untrained checkpoint, 60-step horizon):
health, checkpoints, OpenAPI, episodes with their per-step data, counterfactual grounding, and 4xx answers
that say what was wrong while the server keeps serving."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import threading
import time

import httpx
import pytest

from app.live.fixtures import make_untrained_checkpoint

HORIZON = 60


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    folder = make_untrained_checkpoint(tmp_path_factory.mktemp("ckpt") / "gsmn")
    proc = subprocess.Popen([sys.executable, "-m", "gsmn.cli", "serve", "--preset", "tiny", "--checkpoint", str(folder),
                             "--port", "0", "--api-port", "0", "--task.horizon", str(HORIZON),
                             "--data-dir", str(tmp_path_factory.mktemp("data"))],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(iter(proc.stdout.readline, "")), daemon=True)
    reader.start()
    try:
        deadline = time.monotonic() + 180
        urls: dict[str, str] = {}
        while time.monotonic() < deadline and len(urls) < 2 and proc.poll() is None:
            text = "".join(lines)
            if m := re.search(r"gsmn dashboard: (http://127\.0\.0\.1:\d+)", text):
                urls["page"] = m.group(1)
            if m := re.search(r"API: (http://127\.0\.0\.1:\d+)/api", text):
                urls["api"] = m.group(1)
            time.sleep(0.1)
        assert len(urls) == 2, "server did not print both URLs:\n" + "".join(lines)
        with httpx.Client(base_url=urls["api"], timeout=60) as client:
            yield {"client": client, "proc": proc, "lines": lines, "folder": str(folder), **urls}
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


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
    done = subprocess.run([sys.executable, "-m", "gsmn.cli", "serve", "--preset", "tiny", "--checkpoint",
                           str(tmp_path / "missing"), "--port", "0", "--api-port", "0", "--data-dir",
                           str(tmp_path / "data")],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 2
    assert f"no checkpoint at {tmp_path / 'missing'}" in done.stderr
