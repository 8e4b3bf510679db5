"""The record of kept episodes under faults (app/jobs/kept.py, app/jobs/db.py): a full disk loses no episode (what
could not be written waits and goes in once there is room, and the API says what the record holds meanwhile), ids
are taken from the record when an episode is accepted and never given twice across a kill -9, a queued episode
outlives the kill as not flown, and a step whose stored maps were damaged leaves the rest of its episode readable."""

from __future__ import annotations

import json
import os
import sqlite3
import subprocess
import sys
from pathlib import Path

import pytest
from support import in_private_mounts
from test_kept import HORIZON, finished

REPO = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.unit  # its `gsmn serve` tests are marked server


@pytest.mark.server
def test_ids_are_taken_when_accepted_never_reused_and_queued_episodes_outlive_a_kill(tmp_path, untrained_checkpoint,
                                                                                   gsmn_serve):
    data = tmp_path / "data"
    server = gsmn_serve(data, untrained_checkpoint, horizon=150)
    try:
        ids = [server.client.post("/api/episodes", json={"env_id": 70 + k}).json()["id"] for k in range(4)]
        assert ids == [1, 2, 3, 4]
        cancelled = server.client.delete(f"/api/episodes/{ids[3]}").json()  # dropped from the queue, never flown
        assert cancelled["status"] == "cancelled"
        queued = server.client.get(f"/api/episodes/{ids[2]}").json()
        assert queued["status"] == "queued", queued  # the first still flies: the others wait
        server.kill()
    finally:
        server.stop()

    server = gsmn_serve(data, untrained_checkpoint, horizon=HORIZON)
    try:
        c = server.client
        again = c.post("/api/episodes", json={"env_id": 75}).json()
        assert again["id"] == 5, "an id a link may point at (the cancelled 4) was given again"
        listed = {e["id"]: e for e in c.get("/api/episodes").json()}
        assert set(ids) <= set(listed)
        for i in ids[1:3]:  # accepted, queued at the kill: kept, as not flown
            assert listed[i]["status"] == "cancelled" and "not flown" in listed[i]["error"], listed[i]
            assert listed[i]["steps"] == 0
        assert listed[ids[3]]["status"] == "cancelled" and "not flown" in listed[ids[3]]["error"]
        assert listed[ids[0]]["status"] == "failed"  # it flew when killed: failed, with the steps written
        finished(c, again["id"])
    finally:
        server.stop()


@pytest.mark.server
def test_a_damaged_stored_map_leaves_the_rest_of_the_episode_readable(tmp_path, untrained_checkpoint, gsmn_serve):
    data = tmp_path / "data"
    server = gsmn_serve(data, untrained_checkpoint, horizon=HORIZON)
    try:
        done = finished(server.client, server.client.post("/api/episodes", json={"env_id": 70}).json()["id"])
        assert done["steps"] > 5
    finally:
        server.stop()
    db = sqlite3.connect(data / "gsmn.sqlite")
    blob = db.execute("SELECT maps FROM kept_steps WHERE episode_id = ? AND step = 3", (done["id"],)).fetchone()[0]
    damaged = blob[:200] + os.urandom(64) + blob[264:]  # 64 random bytes inside the compressed maps
    db.execute("UPDATE kept_steps SET maps = ? WHERE episode_id = ? AND step = 3", (damaged, done["id"]))
    db.commit()
    assert db.execute("PRAGMA quick_check").fetchone()[0] == "ok"  # SQLite cannot see inside a blob
    db.close()

    server = gsmn_serve(data, untrained_checkpoint, horizon=HORIZON)
    try:
        c = server.client
        episode = c.get(f"/api/episodes/{done['id']}")
        assert episode.status_code == 200 and episode.json()["steps"] == done["steps"]
        steps = c.get(f"/api/episodes/{done['id']}/steps")
        assert steps.status_code == 200
        by_step = {s["step"]: s for s in steps.json()["steps"]}
        assert "step 3's maps are damaged" in by_step[3]["damaged"] and by_step[3]["model"] is None
        assert all(s["damaged"] is None and s["model"] for k, s in by_step.items() if k != 3)
        broken = c.get(f"/api/episodes/{done['id']}/steps/3/maps/goal.png")
        assert broken.status_code == 503 and "step 3's maps are damaged" in broken.json()["detail"]
        assert str(data / "gsmn.sqlite") in broken.json()["detail"]
        for step in (2, 4):
            assert c.get(f"/api/episodes/{done['id']}/steps/{step}/maps/goal.png").content[:4] == b"\x89PNG"
        assert c.get(f"/api/episodes/{done['id']}/steps/3/camera.jpg").content[:2] == b"\xff\xd8"
        for kind in ("html", "gif"):
            export = c.get(f"/api/episodes/{done['id']}/export", params={"format": kind})
            assert export.status_code == 200, (kind, export.text[:300])
    finally:
        server.stop()


FULL_DISK = """\
import json, os, sys, time
from pathlib import Path
import numpy as np
from app.jobs.db import Database, RecordError
from app.jobs.kept import EpisodeKeeper
from app.jobs.kept_store import KeptStore
from app.live.recording import FINISHED, Episode, EpisodeResult, StepRecord
from gsmn.config import preset
from gsmn.task.rollout import task_for_env

root = Path(sys.argv[1])
config = preset("tiny")
db = Database(root / "gsmn.sqlite")
store = KeptStore(db, config)
keeper = EpisodeKeeper(store, 10**12, retry_seconds=0.2, max_pending_steps=int(sys.argv[2]))

def step(k):  # incompressible camera bytes: about 40 kB a step
    return StepRecord(step=k, time=0.2 * k, position=(1.0, 2.0, 3.0), yaw=0.0, T_world_camera=np.eye(4),
                      camera_jpeg=os.urandom(40_000), v=1.0, omega=0.0, stop=False, maps=None)

def accept():
    e = Episode(id=store.new_id(), task=task_for_env(70, config), policy="expert", system="oracle", checkpoint=None,
                horizon=200)
    store.add(e)
    return e

def fly(e, n):
    keeper.on_episode_start(e)
    for k in range(n):
        e.steps.append(step(k))
        keeper.on_step(e, e.steps[-1])
    e.status = FINISHED
    e.result = EpisodeResult(success=True, landmark_success=True, goal_distance=1.0, landmark_distance=2.0,
                             final_side="left", steps=n, stopped=True, final_x=1.0, final_y=2.0, stop_probability=0.9)
    keeper.on_episode_end(e)
    return e

first = fly(accept(), 5)
assert keeper.flush(), "the first episode was not written"
second = accept()
with open(root / "filler", "wb") as f:  # fill the tmpfs
    try:
        while True:
            f.write(os.urandom(65536))
            f.flush()
    except OSError:
        pass
try:  # a new episode is refused while the record cannot be written (the API's 503), naming the file
    accept()
    refused = None
except RecordError as e:
    refused = f"{e.status} {e}"
fly(second, 30)  # 1.2 MB of steps: they cannot go in
deadline = time.monotonic() + 30
while keeper.error is None and time.monotonic() < deadline:
    time.sleep(0.05)
time.sleep(1.0)  # a few more tries (every 0.2 s), now with every step of the episode waiting
row = db.kept(second.id)
while_full = {"error": keeper.error, "behind": keeper.behind(second.id), "flush": keeper.flush(1.0),
              "kept_steps": row["steps"] if row else None, "status": row["status"] if row else None}
os.remove(root / "filler")
deadline = time.monotonic() + 30
while keeper.error is not None and time.monotonic() < deadline:  # the next try, once there is room
    time.sleep(0.05)
assert keeper.flush(30), "keeping did not resume once there was room"
row = db.kept(second.id)
after = {"steps": row["steps"], "status": row["status"], "error": row["error"], "behind": keeper.behind(second.id),
         "keeper_error": keeper.error}
print(json.dumps({"refused": refused, "while_full": while_full, "after": after,
                  "first": db.kept(first.id)["steps"], "db": str(db.path)}))
keeper.close()
"""


def _in_small_tmpfs(tmp_path: Path, script: str, *args: str, size: str = "2m") -> dict:
    path = tmp_path / "script.py"
    path.write_text(script)
    root = tmp_path / "small"
    root.mkdir()
    command = in_private_mounts(f"mount -t tmpfs -o size={size} tmpfs {root} && {sys.executable} {path} {root} "
                                f"{' '.join(args)}")
    done = subprocess.run(command, capture_output=True, text=True, timeout=240,
                          env={**os.environ, "PYTHONPATH": str(REPO)}, cwd=REPO)
    assert done.returncode == 0, done.stdout + done.stderr
    return json.loads(done.stdout.strip().splitlines()[-1]), done.stderr


def test_a_full_disk_loses_no_step_and_says_what_the_record_holds_meanwhile(tmp_path):
    out, log = _in_small_tmpfs(tmp_path, FULL_DISK, "4000")
    assert out["refused"].startswith("503 ") and out["db"] in out["refused"] and "full" in out["refused"]
    full = out["while_full"]
    assert out["db"] in full["error"] and "full" in full["error"], full
    assert full["flush"] is False  # readers do not wait on a record that cannot be written
    assert (full["kept_steps"] or 0) < 30 and "wait to be written" in full["behind"], full
    after = out["after"]
    assert (after["steps"], after["status"], after["error"]) == (30, "finished", None), after
    assert after["behind"] is None and after["keeper_error"] is None and out["first"] == 5
    assert log.count("keeping episodes failed") == 1, log  # said once, not once per try
    assert "works again" in log


def test_past_its_bound_a_full_disk_gives_up_the_oldest_steps_and_says_how_many(tmp_path):
    out, _ = _in_small_tmpfs(tmp_path, FULL_DISK, "10")
    after = out["after"]
    assert after["status"] == "finished" and after["steps"] < 30
    assert f"{30 - after['steps']} of its steps could not be kept" in after["error"], after
    assert after["steps"] + int(after["error"].split()[0]) == 30


START = """\
import json, os, sys
from pathlib import Path
from app.jobs.db import Database, RecordError

root = Path(sys.argv[1])
out = {}
for name, folder in (("read_only", root / "ro"), ("full", root / "full")):
    try:
        Database(folder / "gsmn.sqlite")
        out[name] = None
    except RecordError as e:
        out[name] = str(e)
print(json.dumps(out))
"""


def test_a_record_that_cannot_be_started_is_refused_naming_its_file_and_what_to_do(tmp_path):
    """An empty read-only folder and a full disk, at start: the message names the file and the folder to mend, and
    asks to move away no file that does not exist."""
    script = tmp_path / "start.py"
    script.write_text(START)
    root = tmp_path / "small"
    root.mkdir()
    setup = (f"mount -t tmpfs -o size=2m tmpfs {root} && mkdir {root}/ro {root}/full && mount -t tmpfs -o ro,size=1m "
             f"tmpfs {root}/ro && mount -t tmpfs -o size=64k tmpfs {root}/full && "
             f"(head -c 1000000 /dev/urandom > {root}/full/filler; true)")
    done = subprocess.run(in_private_mounts(f"{setup} && {sys.executable} {script} {root}"),
                          capture_output=True, text=True, timeout=120, env={**os.environ, "PYTHONPATH": str(REPO)},
                          cwd=REPO)
    assert done.returncode == 0, done.stdout + done.stderr
    out = json.loads(done.stdout.strip().splitlines()[-1])
    for name in ("read_only", "full"):
        message = out[name]
        assert message and str(root / ("ro" if name == "read_only" else "full") / "gsmn.sqlite") in message, out
        assert "move it away" not in message and "must be writable with room to spare" in message, message
