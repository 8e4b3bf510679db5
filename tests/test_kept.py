"""Episodes kept in the record (app.jobs.kept): a real `gsmn serve` process flies, is killed with SIGKILL (after an
episode and in the middle of one) and restarted on the same data folder, and every episode is still listed with
its steps, camera images and maps; the retention limit removes the oldest unpinned episode and never a pinned
one. Plus the quantisation's accuracy and an older record's migration."""

from __future__ import annotations

import sqlite3
import time
from pathlib import Path

import httpx
import numpy as np
import pytest

HORIZON = 40

pytestmark = pytest.mark.unit  # its `gsmn serve` tests are marked server


def kept_steps(data: Path, episode_id: int) -> int:
    """How many of the episode's steps the record holds (read beside the server, as a second SQLite reader)."""
    db = sqlite3.connect(f"file:{data / 'gsmn.sqlite'}?mode=ro", uri=True, timeout=5)
    try:
        return db.execute("SELECT count(*) FROM kept_steps WHERE episode_id = ?", (episode_id,)).fetchone()[0]
    except sqlite3.OperationalError:  # the record not created yet
        return 0
    finally:
        db.close()


def finished(client: httpx.Client, episode_id: int, timeout: float = 120.0) -> dict:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        body = client.get(f"/api/episodes/{episode_id}").json()
        if body["status"] not in ("queued", "running", "paused"):
            return body
        time.sleep(0.1)
    raise AssertionError(f"episode {episode_id} did not finish: {body}")


@pytest.mark.server
def test_episodes_outlive_sigkill_with_every_step_and_image(tmp_path, untrained_checkpoint, gsmn_serve):
    data = tmp_path / "data"
    server = gsmn_serve(data, untrained_checkpoint, horizon=HORIZON)
    try:
        done = finished(server.client, server.client.post("/api/episodes", json={"env_id": 70}).json()["id"])
        assert done["status"] == "finished" and done["steps"] > 5
        typed = "please land in front of the fountain"  # in people's words: kept beside the template flown
        expert = finished(server.client, server.client.post(
            "/api/episodes", json={"env_id": 71, "policy": "expert", "instruction": typed}).json()["id"])
        assert (expert["typed_instruction"], expert["instruction"]) == (typed, "go to the front side of the fountain")
        before = {s["step"]: s for s in server.client.get(f"/api/episodes/{done['id']}/steps").json()["steps"]}
        camera = server.client.get(f"/api/episodes/{done['id']}/steps/3/camera.jpg").content
        # one more, killed while it flies: the steps written before the kill are kept
        flying = server.client.post("/api/episodes", json={"env_id": 72}).json()["id"]
        deadline = time.monotonic() + 60
        while kept_steps(data, flying) < 5:  # written, not only flown: the writer thread may lag a step or two
            assert time.monotonic() < deadline, "the third episode's first steps were never written"
            time.sleep(0.02)
        server.kill()
    finally:
        server.stop()

    server = gsmn_serve(data, untrained_checkpoint, horizon=HORIZON)
    try:
        c = server.client
        listed = {e["id"]: e for e in c.get("/api/episodes").json()}
        assert {done["id"], expert["id"], flying} <= set(listed)
        again = listed[done["id"]]
        assert again["status"] == "finished" and again["steps"] == done["steps"]
        assert again["result"] == done["result"] and again["instruction"] == done["instruction"]
        assert listed[expert["id"]]["policy"] == "expert" and listed[expert["id"]]["steps"] == expert["steps"]
        assert (listed[expert["id"]]["typed_instruction"], listed[expert["id"]]["instruction"]) == \
            (typed, expert["instruction"]) and again["typed_instruction"] is None
        steps = c.get(f"/api/episodes/{done['id']}/steps").json()["steps"]
        assert [s["step"] for s in steps] == sorted(before) and len(steps) == done["steps"]
        for s in steps:  # poses and actions as flown
            b = before[s["step"]]
            assert s["x"] == pytest.approx(b["x"], abs=1e-6) and s["v"] == pytest.approx(b["v"], abs=1e-6)
            assert s["model"]["stop_probability"] == pytest.approx(b["model"]["stop_probability"], abs=1e-9)
        for step in range(done["steps"]):
            image = c.get(f"/api/episodes/{done['id']}/steps/{step}/camera.jpg")
            assert image.status_code == 200 and image.content[:2] == b"\xff\xd8"
        assert c.get(f"/api/episodes/{done['id']}/steps/3/camera.jpg").content == camera
        for layer in ("semantic", "relevance", "goal", "goal_robot"):
            png = c.get(f"/api/episodes/{done['id']}/steps/{done['steps'] - 1}/maps/{layer}.png")
            assert png.status_code == 200 and png.content[:4] == b"\x89PNG", (layer, png.text[:200])
        # the episode killed mid-flight: failed, saying why, with the steps written before the kill, readable
        cut = c.get(f"/api/episodes/{flying}").json()
        assert cut["status"] == "failed" and "server stopped" in cut["error"] and cut["steps"] >= 5
        assert len(c.get(f"/api/episodes/{flying}/steps").json()["steps"]) == cut["steps"]
        assert c.get(f"/api/episodes/{flying}/steps/{cut['steps'] - 1}/camera.jpg").status_code == 200
        # searched by environment, instruction, policy and outcome
        assert [e["id"] for e in c.get("/api/episodes", params={"env_id": 71}).json()] == [expert["id"]]
        words = done["instruction"].split()[-1].upper()
        assert done["id"] in [e["id"] for e in c.get("/api/episodes", params={"instruction": words}).json()]
        assert [e["id"] for e in c.get("/api/episodes", params={"policy": "expert"}).json()] == [expert["id"]]
        assert [e["id"] for e in c.get("/api/episodes", params={"outcome": "failed"}).json()] == [flying]
        assert c.get("/api/episodes", params={"since": time.time() + 60}).json() == []
        # a new episode gets a new id, never one of the record's
        new = c.post("/api/episodes", json={"env_id": 73, "policy": "expert"}).json()["id"]
        assert new > flying
    finally:
        server.stop()


@pytest.mark.server
def test_retention_removes_the_oldest_unpinned_and_never_a_pinned_one(tmp_path, untrained_checkpoint, gsmn_serve):
    server = gsmn_serve(tmp_path / "data", untrained_checkpoint, horizon=HORIZON)
    try:
        c = server.client
        ids = [finished(c, c.post("/api/episodes", json={"env_id": 70 + i, "policy": "expert"}).json()["id"])["id"]
               for i in range(4)]
        pinned = c.put(f"/api/episodes/{ids[0]}/pin").json()
        assert pinned["pinned"] is True
        storage = c.get("/api/storage").json()
        sizes = {e["id"]: e["bytes"] for e in c.get("/api/episodes").json()}
        assert storage["episodes"] == 4 and storage["bytes"] == sum(sizes.values()) and min(sizes.values()) > 0
        on_disk = sum(p.stat().st_size for p in (tmp_path / "data").glob("gsmn.sqlite*"))
        assert storage["bytes"] < storage["file_bytes"] and abs(storage["file_bytes"] - on_disk) < 1e6
        # just under all four: one must go, the oldest unpinned (ids[1]), not the pinned oldest (ids[0])
        after = c.put("/api/storage", json={"limit_mb": (storage["bytes"] - 1) / 1e6}).json()
        assert after["removed"] == [ids[1]] and after["episodes"] == 3
        gone = c.get(f"/api/episodes/{ids[1]}")
        assert gone.status_code == 404 and "no longer kept" in gone.json()["detail"]
        assert c.get(f"/api/episodes/{ids[1]}/steps/0/camera.jpg").status_code == 404
        # nothing left to spare: every unpinned one goes, oldest first; the pinned one stays
        after = c.put("/api/storage", json={"limit_mb": 0}).json()
        assert after["removed"] == [ids[1], ids[2], ids[3]] and after["episodes"] == 1 and after["pinned"] == 1
        assert [e["id"] for e in c.get("/api/episodes").json()] == [ids[0]]
        assert c.get(f"/api/episodes/{ids[0]}/steps/0/camera.jpg").status_code == 200
        # an episode flown past the limit is removed as soon as it ends; the pinned one still stays
        last = c.post("/api/episodes", json={"env_id": 75, "policy": "expert"}).json()["id"]
        deadline = time.monotonic() + 120
        while c.get(f"/api/episodes/{last}").status_code != 404:
            assert time.monotonic() < deadline, "the episode past the limit was not removed"
            time.sleep(0.1)
        assert c.get("/api/storage").json()["removed"][-1] == last
        assert [e["id"] for e in c.get("/api/episodes").json()] == [ids[0]]
        assert c.delete(f"/api/episodes/{ids[0]}/pin").json()["pinned"] is False
    finally:
        server.stop()


def test_maps_come_back_within_their_quantisation_step():
    from app.jobs.kept_store import pack_maps, unpack_maps

    rng = np.random.default_rng(0)
    maps = {"semantic_map_w": rng.normal(size=(32, 16, 16)).astype(np.float16),
            "coverage_w": np.zeros((1, 16, 16), np.float16),  # a constant channel comes back exactly
            "goal_map_r": (rng.random((2, 32, 32)) * 40 - 20).astype(np.float16)}
    back = unpack_maps(pack_maps(maps))
    assert set(back) == set(maps)
    for name, m in maps.items():
        a = m.astype(np.float32)
        span = np.ptp(a.reshape(a.shape[0], -1), axis=1)
        error = np.abs(back[name].astype(np.float32) - a).reshape(a.shape[0], -1).max(axis=1)
        assert back[name].shape == m.shape and back[name].dtype == np.float16
        assert np.all(error <= span / 510 + np.abs(a).max() * 1e-3 + 1e-6), name


def test_an_older_record_gains_the_tables_and_keeps_its_rows(tmp_path):
    from app.jobs.db import SCHEMA_VERSION, Database

    path = tmp_path / "gsmn.sqlite"
    db = Database(path)
    evaluation = db.add_evaluation(system="oracle", checkpoint=None, env_ids=[70], label="old")
    db.close()
    raw = sqlite3.connect(path)  # as schema 3 left it: no kept tables
    raw.executescript("DROP TABLE kept_steps; DROP TABLE kept_episodes; PRAGMA user_version=3;")
    raw.close()
    db = Database(path)
    assert db.evaluation(evaluation).label == "old"
    assert db.next_kept_id() == 1 and db.kept_bytes() == 0 and db.kept_counts() == {"episodes": 0, "pinned": 0}
    assert sqlite3.connect(path).execute("PRAGMA user_version").fetchone()[0] == SCHEMA_VERSION == 6
    db.close()


def test_search_filters_on_hand_made_rows(tmp_path):
    import json

    from app.jobs.db import Database
    from app.jobs.kept import search

    db = Database(tmp_path / "gsmn.sqlite")
    task = json.dumps({"instruction": {"noun_phrase": "box", "side": "left", "goal_x": 1.0, "goal_y": 2.0}})
    rows = [  # id, env, instruction, policy, status, success, created, pinned
        (1, 70, "go to the left side of the box", "model", "finished", 1, 100.0, 0),
        (2, 71, "go to the back side of the barrel", "expert", "finished", 0, 200.0, 1),
        (3, 70, "go to the 100% side_of it", "mirror", "failed", None, 300.0, 0),
        (4, 72, "go to the front side of the box", "model", "cancelled", None, 400.0, 0)]
    for i, env, text, policy, status, success, created, pinned in rows:
        db.add_kept({"id": i, "created": created, "status": status, "env_id": env, "split": "test",
                     "instruction": text, "task": task, "policy": policy, "system": "gsmn", "checkpoint": None,
                     "horizon": 10, "success": success, "pinned": pinned})

    def ids(**kw):
        return [int(r["id"]) for r in search(db, **kw)]

    assert ids() == [4, 3, 2, 1] and ids(newest_first=False) == [1, 2, 3, 4]
    assert ids(env_id=70) == [3, 1] and ids(instruction="BOX") == [4, 1] and ids(policy="expert") == [2]
    assert ids(outcome="success") == [1] and ids(outcome="failure") == [2] and ids(outcome="failed") == [3]
    assert ids(outcome="cancelled") == [4] and ids(pinned=True) == [2] and ids(since=200, until=300) == [3, 2]
    assert ids(instruction="100%") == [3] and ids(instruction="e_o") == [3]  # LIKE's wildcards taken literally
    assert ids(instruction="%") == [3] and ids(limit=2, offset=1) == [3, 2]
    with pytest.raises(ValueError, match="outcome must be one of"):
        search(db, outcome="won")
    assert db.next_kept_id() == 5
    db.remove_kept(4)
    assert db.next_kept_id() == 5  # never reused
    db.close()
