"""Evaluations and DAggerFM fine-tuning runs through the HTTP API of a real `gsmn serve` process, with real job
processes and a real SQLite record in a data folder: an evaluation with failure attribution and a replay that
reproduces it, a tiny fine-tuning run on its failures that finishes with a checkpoint that loads and flies, a
before/after evaluation, limits, cancelling and resuming, a job process killed from outside, and a server killed and
restarted mid-run that re-attaches to the run and still lists everything."""

from __future__ import annotations

import hashlib
import json
import os
import re
import signal
import time
from pathlib import Path

import httpx
import numpy as np
import pytest
from support import Serve, poll

from gsmn.attribution import BEARINGS, STAGES

HORIZON = 40
ENV_IDS = [70, 71, 72]

pytestmark = [pytest.mark.server, pytest.mark.training]  # DAggerFM runs


@pytest.fixture(scope="module")
def serve(tmp_path_factory, untrained_checkpoint, gsmn_serve):
    """A `gsmn serve` process on a data folder, restartable (support.Serve)."""
    s = gsmn_serve(tmp_path_factory.mktemp("jobs") / "data", untrained_checkpoint, horizon=HORIZON)
    try:
        yield s
    finally:
        try:  # no job outlives the tests
            for r in s.client.get("/api/runs").json():
                if r["status"] in ("queued", "running"):
                    s.client.delete(f"/api/runs/{r['id']}")
        except (httpx.HTTPError, ValueError, AttributeError):
            pass
        s.stop()


def wait_for(get, done, timeout: float = 300.0, what: str = "") -> dict:
    return poll(get, done, what or "a condition", timeout, every=0.5)


def settled(client: httpx.Client, path: str, timeout: float = 300.0) -> dict:
    return wait_for(lambda: client.get(path).json(), lambda b: b["status"] not in ("queued", "running"), timeout,
                    path)


def group_alive(pgid: int) -> bool:
    """Any live (non-zombie) process in this process group."""
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[2]) == pgid and fields[0] not in ("Z", "X"):
            return True
    return False


def gone(pgid: int, timeout: float = 30.0) -> None:
    """Every process of the group is gone within `timeout` s: the server's SIGKILL to the group is sent before the job
    is recorded as settled, but a process killed takes a while to die on a busy machine (its memory freed)."""
    wait_for(lambda: group_alive(pgid), lambda alive: not alive, timeout, "every process of the run to be gone")


def tree_hash(folder: Path) -> str:
    h = hashlib.sha256()
    for p in sorted(folder.rglob("*")):
        if p.is_file():
            h.update(p.name.encode() + p.read_bytes())
    return h.hexdigest()


@pytest.fixture(scope="module")
def evaluation(serve) -> dict:
    client = serve.client
    created = client.post("/api/evaluations", json={"env_ids": ENV_IDS})
    assert created.status_code == 201, created.text
    return settled(client, f"/api/evaluations/{created.json()['id']}")


def test_an_evaluation_records_each_episode_with_its_attribution(serve, evaluation):
    client = serve.client
    assert evaluation["status"] == "finished" and evaluation["done"] == evaluation["total"] == 3, evaluation
    assert evaluation["system"] == "gsmn" and evaluation["checkpoint"] == str(serve.checkpoint)
    assert evaluation["summary"]["count"] == 3 and 0 <= evaluation["summary"]["success"] <= 100
    episodes = client.get(f"/api/evaluations/{evaluation['id']}/episodes").json()
    assert [e["env_id"] for e in episodes] == ENV_IDS
    failures = [e for e in episodes if not e["success"]]
    assert failures, "the untrained model fails"
    for e in failures:
        assert e["stage"] in STAGES and e["attribution"]["stage"] == e["stage"] and e["attribution"]["reason"]
        assert e["attribution"]["peak_bearing"] in BEARINGS  # the final heading reached the dashboard's record
    assert sum(evaluation["stages"].values()) == len(failures)
    # the success region: its steps from the evaluation's progress lines, P(stop) there from the recordings
    assert all(isinstance(e["region_steps"], list) for e in episodes)
    assert evaluation["regions"] == {"entered": sum(bool(e["region_steps"]) for e in failures),
                                     "never": sum(not e["region_steps"] for e in failures)}
    assert all((e["region_stop_p"] is None) == (not e["region_steps"]) for e in episodes)
    never = client.get(f"/api/evaluations/{evaluation['id']}/episodes", params={"entered_region": False}).json()
    assert [e["env_id"] for e in never] == [e["env_id"] for e in episodes if not e["region_steps"]]
    for key in ("instruction", "landmark", "side", "ambiguous", "landmark_success", "goal_distance"):
        assert key in episodes[0]
    # the failure browser's filters
    first = episodes[0]
    by_landmark = client.get(f"/api/evaluations/{evaluation['id']}/episodes",
                             params={"landmark": first["landmark"]}).json()
    assert by_landmark and all(e["landmark"] == first["landmark"] for e in by_landmark)
    by_side = client.get(f"/api/evaluations/{evaluation['id']}/episodes",
                         params={"side": first["side"], "failed_only": True}).json()
    assert all(e["side"] == first["side"] and not e["success"] for e in by_side)
    unambiguous = client.get(f"/api/evaluations/{evaluation['id']}/episodes", params={"ambiguous": False}).json()
    assert all(not e["ambiguous"] for e in unambiguous)
    assert client.get(f"/api/evaluations/{evaluation['id']}/episodes", params={"side": "up"}).status_code == 422
    assert any(e["id"] == evaluation["id"] for e in client.get("/api/evaluations").json())

    # the same results loaded from `gsmn eval --json` (and its --record folder) as an evaluation of their own
    folder = serve.data_dir / "evaluations" / f"{evaluation['id']:04d}"
    loaded = client.post("/api/evaluations/import", json={"path": str(folder / "results.json"),
                                                          "record_dir": str(folder / "episodes")})
    assert loaded.status_code == 201, loaded.text
    loaded = loaded.json()
    assert loaded["status"] == "finished" and loaded["source"] == "import" and loaded["env_ids"] == ENV_IDS
    assert loaded["summary"] == evaluation["summary"] and loaded["stages"] == evaluation["stages"]
    again = client.get(f"/api/evaluations/{loaded['id']}/episodes").json()
    assert [(e["env_id"], e["stage"]) for e in again] == [(e["env_id"], e["stage"]) for e in episodes]
    # measured again from the JSON's trajectories: the same steps as the progress lines gave
    keys = ("env_id", "region_steps", "region_stop_p")
    assert [[e[k] for k in keys] for e in again] == [[e[k] for k in keys] for e in episodes]
    assert loaded["regions"] == evaluation["regions"]
    # without its recordings (as for a baseline, which has none) the region and P(stop) come from the file itself
    # (these three never enter the region; test_jobs_units checks where a P(stop) there is taken from)
    bare = client.post("/api/evaluations/import", json={"path": str(folder / "results.json")}).json()
    bare_episodes = client.get(f"/api/evaluations/{bare['id']}/episodes").json()
    assert [[e[k] for k in keys] for e in bare_episodes] == [[e[k] for k in keys] for e in episodes]
    assert all(e["stage"] is None for e in bare_episodes)  # attribution needs the recorded maps
    bad = client.post("/api/evaluations/import", json={"path": str(folder / "config.json")})
    assert bad.status_code == 422 and "not a `gsmn eval --json` file" in bad.json()["detail"]


def test_a_replay_flies_the_episode_again_in_the_live_view(serve, evaluation):
    client = serve.client
    record = client.get(f"/api/evaluations/{evaluation['id']}/episodes").json()[0]
    replay = client.post(f"/api/evaluations/{evaluation['id']}/replay", json={"env_id": record["env_id"]})
    assert replay.status_code == 201, replay.text
    episode = settled(client, f"/api/episodes/{replay.json()['episode_id']}", timeout=120)
    assert episode["status"] == "finished" and episode["checkpoint"] == str(serve.checkpoint)
    result = episode["result"]
    assert result["steps"] == record["steps"]  # the same model, world and instruction fly the same episode
    assert abs(result["final_x"] - record["final_x"]) < 1e-3 and abs(result["final_y"] - record["final_y"]) < 1e-3
    assert client.get(f"/api/episodes/{episode['id']}/steps/3/maps/goal.png").status_code == 200  # with its maps
    missing = client.post(f"/api/evaluations/{evaluation['id']}/replay", json={"env_id": 5})
    assert missing.status_code == 404 and "no episode in environment 5" in missing.json()["detail"]


def test_a_mirror_ensemble_evaluation_is_recorded_and_replayed_as_one(serve, evaluation):
    """Evaluated as a mirror ensemble, the same episode ends elsewhere than the plain model's, the record and the
    results file say how it was flown, and its replay flies the ensemble again, to the same end."""
    client = serve.client
    created = client.post("/api/evaluations", json={"env_ids": [ENV_IDS[0]], "mirror_ensemble": True})
    assert created.status_code == 201, created.text
    mirrored = settled(client, f"/api/evaluations/{created.json()['id']}")
    assert mirrored["status"] == "finished" and mirrored["mirror_ensemble"] is True, mirrored
    assert "mirror ensemble" in mirrored["label"] and evaluation["mirror_ensemble"] is False
    folder = serve.data_dir / "evaluations" / f"{mirrored['id']:04d}"
    assert json.loads((folder / "results.json").read_text())["mirror_ensemble"] is True
    (record,) = client.get(f"/api/evaluations/{mirrored['id']}/episodes").json()
    plain = client.get(f"/api/evaluations/{evaluation['id']}/episodes").json()[0]
    assert plain["env_id"] == record["env_id"]
    assert (abs(plain["final_x"] - record["final_x"]) + abs(plain["final_y"] - record["final_y"]) > 1e-3
            or plain["steps"] != record["steps"])  # the ensemble is not the plain model
    replay = client.post(f"/api/evaluations/{mirrored['id']}/replay", json={"env_id": record["env_id"]})
    assert replay.status_code == 201, replay.text
    episode = settled(client, f"/api/episodes/{replay.json()['episode_id']}", timeout=120)
    assert episode["status"] == "finished" and episode["policy"] == "mirror"
    assert episode["result"]["steps"] == record["steps"]
    assert abs(episode["result"]["final_x"] - record["final_x"]) < 1e-3
    assert abs(episode["result"]["final_y"] - record["final_y"]) < 1e-3
    loaded = client.post("/api/evaluations/import", json={"path": str(folder / "results.json")}).json()
    assert loaded["mirror_ensemble"] is True and "mirror ensemble" in loaded["label"]
    expert = client.post("/api/evaluations", json={"system": "oracle", "env_ids": [70], "mirror_ensemble": True})
    assert expert.status_code == 422 and "mirror ensemble" in expert.json()["detail"]


def test_a_tiny_run_on_the_failures_finishes_with_a_checkpoint_that_loads(serve, evaluation):
    from gsmn.model.checkpoint import load_checkpoint

    client = serve.client
    before = tree_hash(serve.checkpoint)
    created = client.post("/api/runs", json={"preset": "tiny", "evaluation_id": evaluation["id"], "mirror": 0.5})
    assert created.status_code == 201, created.text
    run = created.json()
    assert run["settings"]["mirror"] == 0.5  # half the training episodes mirrored (train.mirror)
    failures = sorted(e["env_id"] for e in client.get(f"/api/evaluations/{evaluation['id']}/episodes",
                                                        params={"failed_only": True}).json())
    assert run["env_ids"] == failures and run["settings"]["iterations"] == 2
    refused = client.post("/api/runs", json={"preset": "tiny"})
    assert refused.status_code == 409 and "already running" in refused.json()["detail"]
    fractions = []
    done = wait_for(lambda: client.get(f"/api/runs/{run['id']}").json(),
                    lambda b: fractions.append((b["progress"] or {}).get("fraction", 0)) or b["status"] != "running",
                    timeout=400, what="the tiny run")
    assert done["status"] == "finished", done["error"]
    assert fractions == sorted(fractions) and done["progress"]["fraction"] == 1.0
    assert [m["iteration"] for m in done["metrics"]] == [1, 2] and "loss" in done["metrics"][0]["train"]
    # validated on the dev split's expert episodes after every iteration: the Fine-tune tab's Figure 4 curves
    from app.render.jobs_panels import ACCURACY_CURVES, accuracy_data

    assert all(0 <= m["dev"]["acc_perception"] <= 1 and 0 <= m["dev"]["acc_instruction_side"] <= 1
               for m in done["metrics"])
    curves = accuracy_data(done["metrics"])
    assert list(curves[0]) == [1, 2] and len(curves) == 1 + len(ACCURACY_CURVES)
    assert all(np.isfinite(c).all() for c in (curves[1], curves[4], curves[5]))  # perception, landmark, side
    model, config, _, meta = load_checkpoint(done["checkpoint"])
    assert model.kind == "gsmn" and config.dagger.iterations == 2 and meta["metrics"]["iteration"] == 2
    assert config.train.mirror == 0.5  # the setting reached the training process
    assert tree_hash(serve.checkpoint) == before, "the run must not touch the checkpoint it started from"

    # it is a checkpoint to switch to: listed, and an episode flies with it
    names = {c["name"]: c for c in client.get("/api/checkpoints").json()}
    assert f"run-{run['id']}" in names and names[f"run-{run['id']}"]["kind"] == "gsmn"
    flown = client.post("/api/episodes", json={"env_id": 70, "checkpoint": f"run-{run['id']}"})
    assert flown.status_code == 201, flown.text
    flown = settled(client, f"/api/episodes/{flown.json()['id']}", timeout=120)
    assert flown["status"] == "finished" and flown["checkpoint"] == str(Path(done["checkpoint"]).resolve())

    # before/after: the same episodes with the new checkpoint, side by side
    after = client.post("/api/evaluations", json={"run_id": run["id"], "baseline_id": evaluation["id"]})
    assert after.status_code == 201, after.text
    after = settled(client, f"/api/evaluations/{after.json()['id']}")
    assert after["status"] == "finished" and after["env_ids"] == ENV_IDS and after["run_id"] == run["id"]
    compare = client.get(f"/api/evaluations/{evaluation['id']}/compare/{after['id']}").json()
    assert [r["env_id"] for r in compare["episodes"]] == ENV_IDS
    assert all({"success", "goal_distance", "stage"} <= set(r["after"]) for r in compare["episodes"])
    assert compare["before_success"] == evaluation["summary"]["success"]


def test_a_cancelled_run_stops_its_processes_and_is_marked_cancelled(serve):
    client = serve.client
    run = client.post("/api/runs", json={"preset": "tiny", "iterations": 50, "env_ids": [3, 5]}).json()
    row = wait_for(lambda: client.get(f"/api/runs/{run['id']}").json(),
                   lambda b: (b["progress"] or {}).get("phase") not in (None, "expert data"), timeout=200,
                   what="the run's DAgger phase")
    assert row["status"] == "running"
    pid = serve_pid(serve, run["id"])
    assert group_alive(pid)
    cancelled = client.delete(f"/api/runs/{run['id']}")
    assert cancelled.status_code == 200
    final = settled(client, f"/api/runs/{run['id']}", timeout=30)
    assert final["status"] == "cancelled" and final["checkpoint"] is None
    gone(pid)
    again = client.delete(f"/api/runs/{run['id']}")
    assert again.status_code == 409 and "cancelled" in again.json()["detail"]
    assert client.get("/api/health").json()["status"] == "ok"


def test_a_cancelled_run_resumes_from_the_iterations_it_had_saved(serve):
    client = serve.client
    run = client.post("/api/runs", json={"preset": "tiny", "iterations": 3, "env_ids": [3, 5]}).json()
    path = f"/api/runs/{run['id']}"
    wait_for(lambda: client.get(path).json(), lambda b: len(b["metrics"]) >= 1, timeout=300, what="an iteration")
    assert client.delete(path).status_code == 200
    stopped = settled(client, path, timeout=30)
    assert stopped["status"] == "cancelled" and 1 <= len(stopped["metrics"]) < 3, stopped
    resumed = client.post(f"{path}/resume")
    assert resumed.status_code == 200, resumed.text
    assert resumed.json()["status"] == "running" and resumed.json()["error"] is None
    final = settled(client, path, timeout=400)
    assert final["status"] == "finished", final["error"]
    assert [m["iteration"] for m in final["metrics"]] == [1, 2, 3]
    assert final["metrics"][:len(stopped["metrics"])] == stopped["metrics"]  # the saved iterations, not trained again
    from gsmn.model.checkpoint import load_checkpoint

    load_checkpoint(final["checkpoint"])
    again = client.post(f"{path}/resume")
    assert again.status_code == 409 and "finished" in again.json()["detail"]
    assert client.post("/api/runs/99999/resume").status_code == 404


def test_a_run_whose_process_is_killed_is_marked_failed_and_the_server_keeps_serving(serve):
    client = serve.client
    run = client.post("/api/runs", json={"preset": "tiny", "iterations": 50, "env_ids": [3, 5]}).json()
    wait_for(lambda: client.get(f"/api/runs/{run['id']}").json(), lambda b: b["status"] == "running",
             timeout=60, what="a running run")
    pid = serve_pid(serve, run["id"])
    time.sleep(2)
    os.kill(pid, signal.SIGKILL)  # the job's main process dies, as in an out-of-memory kill
    final = settled(client, f"/api/runs/{run['id']}", timeout=30)
    assert final["status"] == "failed" and "SIGKILL" in final["error"]
    assert serve.proc.poll() is None and client.get("/api/health").json()["status"] == "ok"
    gone(pid)
    from gsmn.model.checkpoint import load_checkpoint

    load_checkpoint(serve.checkpoint)  # every saved checkpoint is intact: the one it started from ...
    for other in client.get("/api/runs").json():  # ... and those of earlier runs
        if other["status"] == "finished":
            load_checkpoint(other["checkpoint"])
    other = client.post("/api/evaluations", json={"split": "dev", "episodes": 1})  # the limit is free again
    assert other.status_code == 201, other.text
    assert other.json()["env_ids"] == [85] and other.json()["label"] == "dev, first 1"
    second = client.post("/api/evaluations", json={"env_ids": [75]})
    assert second.status_code == 409 and "1 evaluation already running" in second.json()["detail"]
    assert settled(client, f"/api/evaluations/{other.json()['id']}")["status"] == "finished"


def test_a_cancelled_evaluation_resumes_keeping_the_episodes_it_had_finished(serve):
    client = serve.client
    ids = list(range(70, 85))
    created = client.post("/api/evaluations", json={"env_ids": ids})
    assert created.status_code == 201, created.text
    path = f"/api/evaluations/{created.json()['id']}"
    folder = serve.data_dir / "evaluations" / f"{created.json()['id']:04d}"
    wait_for(lambda: client.get(path).json(), lambda b: b["done"] >= 2, timeout=300, what="two episodes")
    assert client.delete(path).status_code == 200
    stopped = settled(client, path, timeout=30)
    assert stopped["status"] == "cancelled" and 2 <= stopped["done"] < len(ids)
    kept = client.get(f"{path}/episodes").json()
    assert len(kept) == stopped["done"]
    assert (folder / "results.json.partial.jsonl").is_file() and not (folder / "results.json").exists()

    resumed = client.post(f"{path}/resume")
    assert resumed.status_code == 200, resumed.text
    assert resumed.json()["status"] == "running" and resumed.json()["error"] is None
    busy = client.post(f"{path}/resume")
    assert busy.status_code == 409 and "running" in busy.json()["detail"]
    final = settled(client, path)
    assert final["status"] == "finished" and final["done"] == len(ids), final["error"]
    episodes = client.get(f"{path}/episodes").json()
    assert [e["env_id"] for e in episodes] == ids
    by_id = {e["env_id"]: e for e in episodes}
    for e in kept:  # nothing already saved is lost or flown again
        assert by_id[e["env_id"]] == e
    m = re.search(r"resuming: (\d+) of (\d+) episodes kept", (folder / "output.log").read_text())
    assert m and int(m.group(1)) >= len(kept) and int(m.group(2)) == len(ids)
    results = json.loads((folder / "results.json").read_text())
    assert [e["env_id"] for e in results["episodes"]] == ids
    assert final["summary"]["success"] == results["summary"]["success"]
    assert not (folder / "results.json.partial.jsonl").exists()
    again = client.post(f"{path}/resume")
    assert again.status_code == 409 and "finished" in again.json()["detail"]
    assert client.post("/api/evaluations/99999/resume").status_code == 404


def test_a_server_killed_mid_run_reattaches_and_lists_every_past_job(serve, evaluation):
    client = serve.client
    runs_before = client.get("/api/runs").json()
    evaluations_before = client.get("/api/evaluations").json()
    run = client.post("/api/runs", json={"preset": "tiny", "env_ids": [3, 5]}).json()
    wait_for(lambda: client.get(f"/api/runs/{run['id']}").json(),
             lambda b: (b["progress"] or {}).get("phase") not in (None, "expert data"), timeout=200,
             what="the run's DAgger phase")
    pid = serve_pid(serve, run["id"])
    # held still across the restart (SIGSTOP to its process group), so that on a loaded machine it cannot finish
    # while the new server is starting: the new server must find it running
    os.killpg(pid, signal.SIGSTOP)
    try:
        serve.stop(signal.SIGKILL)  # no chance to clean up
        assert group_alive(pid), "the run does not depend on the server"
        serve.start()
    finally:
        os.killpg(pid, signal.SIGCONT)
    client = serve.client
    assert "re-attached to 1 running" in serve.output()
    # the new server is the one that follows it to the end
    assert client.get(f"/api/runs/{run['id']}").json()["status"] in ("running", "finished")
    done = settled(client, f"/api/runs/{run['id']}", timeout=400)
    assert done["status"] == "finished" and len(done["metrics"]) == 2, done["error"]
    listed = {r["id"]: r for r in client.get("/api/runs").json()}
    for r in runs_before:
        assert listed[r["id"]]["status"] == r["status"] and listed[r["id"]]["checkpoint"] == r["checkpoint"]
    evaluations = {e["id"]: e for e in client.get("/api/evaluations").json()}
    for e in evaluations_before:
        assert evaluations[e["id"]]["status"] == e["status"] and evaluations[e["id"]]["summary"] == e["summary"]
    assert len(client.get(f"/api/evaluations/{evaluation['id']}/episodes").json()) == 3

    # a graceful restart, too
    serve.stop()
    serve.start()
    assert {r["id"] for r in serve.client.get("/api/runs").json()} == set(listed)


def serve_pid(serve: Serve, run_id: int) -> int:
    """The run's process id, from the server's database (the API does not expose pids)."""
    import sqlite3

    with sqlite3.connect(serve.data_dir / "gsmn.sqlite") as db:
        return int(db.execute("SELECT pid FROM runs WHERE id = ?", (run_id,)).fetchone()[0])
