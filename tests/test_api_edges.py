"""Inputs the API must refuse with a 4xx while the server stays healthy, on a real in-process dashboard (tiny preset,
no checkpoint, so the expert flies): ids beyond what the database and simulator hold, NaN and Infinity, lone
surrogates, loosely typed numbers, wrong methods, a full episode queue; and the record and checkpoint files that
must be refused by name (empty, damaged, NaN weights)."""

from __future__ import annotations

import json
import shutil
import sqlite3
import time

import httpx
import pytest

from app.api.schema import MAX_ID
from app.live.commands import SetSpeed
from app.server import Dashboard
from gsmn.config import preset, with_overrides

pytestmark = pytest.mark.unit

BIG = MAX_ID + 1  # one past the largest id the schema admits (2**53 - 1: exact in every JSON reader)


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    root = tmp_path_factory.mktemp("edges")
    d = Dashboard(with_overrides(preset("tiny"), {"task.horizon": "20"}), port=0, api_port=0,
                  checkpoints_root=root / "none", data_dir=root / "data")
    try:
        with httpx.Client(base_url=d.urls.api, timeout=60) as client:
            yield d, client
    finally:
        d.close()


def raw(client: httpx.Client, path: str, body: str) -> httpx.Response:
    """POST a JSON text as it is (NaN, Infinity and "\\ud800" are what Python's json module reads)."""
    return client.post(path, content=body.encode(), headers={"content-type": "application/json"})


def healthy(d: Dashboard, client: httpx.Client) -> None:
    assert client.get("/api/health").status_code == 200
    assert not d.jobs.supervisor.handles, "a refused request must not hold a job slot"


def test_huge_ids_are_refused_and_the_slot_stays_free(server):
    d, client = server
    r = client.post("/api/evaluations", json={"system": "oracle", "env_ids": [10000000000000000000000]})
    assert r.status_code == 422 and "env_ids" in r.json()["detail"]
    healthy(d, client)
    for path in (f"/api/evaluations/{BIG}", f"/api/runs/{BIG}", f"/api/episodes/{BIG}",
                 f"/api/evaluations/{BIG}/episodes", f"/api/evaluations/1/compare/{BIG}"):
        assert client.get(path).status_code == 422, path
    assert client.get(f"/api/evaluations/{BIG - 1}").status_code == 404
    assert client.get(f"/api/episodes/{2**63 - 1}").status_code == 422  # SQLite's limit, past the schema's
    spec = client.get("/openapi.json").json()
    schemas = [p["schema"] for op in spec["paths"].values() for o in op.values() for p in o.get("parameters", [])
               if p["name"].endswith("_id") and p["name"] != "env_id"]
    schemas += [prop for model in spec["components"]["schemas"].values()
                for name, prop in model.get("properties", {}).items() if name.endswith("_id") and name != "env_id"]
    bounded = [alt for sch in schemas for alt in sch.get("anyOf", [sch]) if "minimum" in alt]  # the inputs
    assert len(bounded) > 20 and {alt.get("maximum") for alt in bounded} == {MAX_ID}  # exact in JSON, not 9.2e+18
    for body in ({"system": "oracle", "baseline_id": BIG}, {"system": "oracle", "env_ids": [70], "run_id": BIG}):
        assert client.post("/api/evaluations", json=body).status_code == 422, body
    assert client.post("/api/runs", json={"evaluation_id": BIG}).status_code == 422
    assert client.post("/api/evaluations", json={"system": "oracle", "env_ids": [2**31]}).status_code == 422
    healthy(d, client)
    # the slot is free: a real evaluation starts, and cancels
    started = client.post("/api/evaluations", json={"system": "oracle", "env_ids": [70]})
    assert started.status_code == 201, started.text
    assert client.delete(f"/api/evaluations/{started.json()['id']}").status_code == 200
    deadline = time.monotonic() + 60
    while d.jobs.supervisor.handles and time.monotonic() < deadline:
        time.sleep(0.2)
    assert client.get(f"/api/evaluations/{started.json()['id']}").json()["status"] == "cancelled"


@pytest.mark.parametrize("path,body", [
    ("/api/episodes", '{"env_id": NaN}'),
    ("/api/episodes", '{"env_id": Infinity}'),
    ("/api/ground", '{"episode_id": 1, "instruction": "go to the barrel", "step": NaN}'),
    ("/api/runs", '{"beta0": NaN}'),
    ("/api/runs", '{"learning_rate": -Infinity}'),
    ("/api/episodes", '{"env_id": 70, "instruction": "go to the \\ud800 barrel"}'),
    ("/api/evaluations/import", '{"path": "\\ud800.json"}'),
    ("/api/evaluations/import", '{"path": "a\\u0000b"}'),
    ("/api/episodes", '{"env_id": 70, "\\udfff": 1}'),
    ("/api/episodes", '{"env_id": false}'),
    ("/api/episodes", '{"env_id": "70"}'),
    ("/api/episodes", '{"env_id": 7e1}'),
    ("/api/episodes", '{"env_id": 70.0}'),
])
def test_nan_surrogates_and_loose_types_are_422_with_a_json_body(server, path, body):
    d, client = server
    r = raw(client, path, body)
    assert r.status_code == 422, (body, r.status_code, r.text)
    answer = r.json()
    assert isinstance(answer["detail"], str) and answer["detail"] and isinstance(answer["errors"], list)
    json.dumps(answer, allow_nan=False)  # plain JSON: no NaN came back
    healthy(d, client)


def test_wrong_methods_answer_405_naming_every_method_the_path_takes(server):
    _, client = server
    r = client.get("/api/evaluations/import")
    assert r.status_code == 405 and r.headers["allow"] == "POST"
    r = client.put("/api/evaluations/1")
    assert r.status_code == 405 and r.headers["allow"] == "DELETE, GET"
    r = client.patch("/api/episodes")
    assert r.status_code == 405 and r.headers["allow"] == "GET, POST"
    assert isinstance(r.json()["detail"], str)


def test_the_episode_queue_is_bounded_and_a_queued_episode_cancels(server):
    d, client = server
    d.runner.call(SetSpeed(0.5))  # the live episode flies for the whole test
    try:
        live = client.post("/api/episodes", json={"env_id": 70, "policy": "expert"})
        assert live.status_code == 201
        queued = [client.post("/api/episodes", json={"env_id": 71 + i, "policy": "expert"})
                  for i in range(d.runner.max_queued)]
        assert all(q.status_code == 201 for q in queued), [q.text for q in queued]
        full = client.post("/api/episodes", json={"env_id": 80, "policy": "expert"})
        assert full.status_code == 409 and "DELETE /api/episodes/" in full.json()["detail"]
        last = queued[-1].json()["id"]
        cancelled = client.delete(f"/api/episodes/{last}")
        assert cancelled.status_code == 200 and cancelled.json()["status"] == "cancelled"
        assert client.delete(f"/api/episodes/{last}").status_code == 409  # nothing left to cancel
        assert client.post("/api/episodes", json={"env_id": 80, "policy": "expert"}).status_code == 201
        assert client.delete(f"/api/episodes/{BIG - 1}").status_code == 404
        # the live one ends too
        assert client.delete(f"/api/episodes/{live.json()['id']}").status_code == 200
    finally:
        for e in client.get("/api/episodes").json():
            if e["status"] in ("queued", "running", "paused"):
                client.delete(f"/api/episodes/{e['id']}")
        d.runner.call(SetSpeed(None))


# -- files refused by name --------------------------------------------------------------------------------------
def test_an_empty_record_is_refused_by_name_and_not_started_afresh(tmp_path):
    from app.jobs.db import Database, RecordError

    path = tmp_path / "gsmn.sqlite"
    path.write_bytes(b"")
    with pytest.raises(RecordError, match=str(path) + r" is empty \(0 bytes\)"):
        Database(path)
    assert path.stat().st_size == 0  # left as it was


def test_a_damaged_record_is_refused_by_name(tmp_path):
    from app.jobs.db import Database, RecordError

    path = tmp_path / "gsmn.sqlite"
    db = Database(path)
    for i in range(200):
        db.add_evaluation(system="oracle", checkpoint=None, env_ids=list(range(i, i + 50)), label=f"e{i}")
    db.close()
    with sqlite3.connect(path) as c:  # fold the WAL in, so the pages are in the file
        c.execute("PRAGMA wal_checkpoint(TRUNCATE)")
    data = bytearray(path.read_bytes())
    page = 4096
    data[3 * page:3 * page + 200] = b"\xa5" * 200  # a page of the table, overwritten
    path.write_bytes(bytes(data))
    with pytest.raises(RecordError, match=str(path)):
        Database(path)
    path.write_bytes(b"not a database at all, but long enough to look like a header" * 100)
    with pytest.raises(RecordError, match=str(path) + " is not a readable dashboard record"):
        Database(path)


def test_a_record_error_later_answers_503_naming_the_file(server, monkeypatch):
    d, client = server

    def broken(*args, **kwargs):
        raise sqlite3.DatabaseError("database disk image is malformed")

    with monkeypatch.context() as m:
        m.setattr(d.jobs.db, "_db", type("Broken", (), {"execute": broken})())
        r = client.get("/api/evaluations")
    assert r.status_code == 503 and str(d.jobs.db.path) in r.json()["detail"]
    assert "malformed" in r.json()["detail"]
    healthy(d, client)


def test_a_checkpoint_with_nan_weights_is_refused(tmp_path, untrained_checkpoint):
    from safetensors.torch import load_file, save_file

    from gsmn.model.checkpoint import CheckpointError, load_checkpoint

    folder = shutil.copytree(untrained_checkpoint, tmp_path / "nan", copy_function=shutil.copyfile)  # writable
    weights = folder / "weights.safetensors"
    tensors = load_file(str(weights))
    name = sorted(k for k, t in tensors.items() if t.is_floating_point())[0]
    tensors[name][...] = float("nan")
    save_file(tensors, str(weights))
    with pytest.raises(CheckpointError, match="NaN or infinite values in " + name.replace(".", r"\.")):
        load_checkpoint(folder)
