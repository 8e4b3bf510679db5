"""Faults around the dashboard's jobs, with the real job manager, monitor and SQLite record: a job whose result the
record cannot hold is given up (failed with the reason, its slot free) instead of being polled forever; a full disk
(a tiny tmpfs in a private mount namespace) leaves the finished job failed with the reason once space is back and
DELETE answering 503 naming the file meanwhile; an old job folder that holds results is never written over; the
import endpoint reads only regular files inside the data folder, and no larger than its limit.

The job process here is a small script in the place of `gsmn eval` (given to JobManager as its `python`): it writes
the progress lines and results file that `gsmn eval` writes, with the values each fault needs."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest
from support import in_private_mounts, serve_command

from app.jobs.db import RecordError
from app.jobs.manager import JobManager, new_job_folder
from gsmn.config import preset

pytestmark = pytest.mark.unit

REPO = Path(__file__).resolve().parents[1]

FAKE_EVAL = """\
#!{python}
# In the place of `python -m gsmn.cli eval ...`: one progress line per environment, then results.json; it exits
# when the file `release` appears beside the data folder (or at once without one).
import json, sys, time
from pathlib import Path
args = sys.argv[1:]
arg = lambda name: args[args.index(name) + 1]
progress, results = Path(arg("--progress")), Path(arg("--json"))
env_ids = [int(e) for e in arg("--env-ids").split(",")]
steps = {steps}
episodes = []
for done, env_id in enumerate(env_ids, 1):
    ep = dict(env_id=env_id, instruction="go to the left side of the barrel", noun_phrase="barrel", side="left",
              ambiguous=False, success=False, landmark_success=False, goal_distance=1.5, steps=steps, stopped=True,
              final_x=0.0, final_y=0.0, region_steps=[])
    episodes.append(ep)
    with progress.open("a") as f:
        f.write(json.dumps(dict(ep, done=done)) + "\\n")
results.write_text(json.dumps(dict(system="oracle", episodes=episodes, summary=dict(count=len(episodes)))))
release = results.parents[3] / "release"
while {wait} and not release.exists():
    time.sleep(0.05)
"""


def fake_eval(folder: Path, steps: str = "20", wait: bool = False) -> str:
    path = folder / "fake-eval"
    path.write_text(FAKE_EVAL.format(python=sys.executable, steps=steps, wait=wait))
    path.chmod(0o755)
    return str(path)


def wait_until(predicate, timeout: float = 30.0, what: str = ""):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(0.05)
    raise AssertionError(f"timed out waiting for {what}")


def no_checkpoint(ref):
    raise AssertionError("an oracle evaluation needs no checkpoint")


def test_a_result_the_record_cannot_hold_fails_the_job_and_frees_its_slot(tmp_path):
    """The original fault: an episode whose values SQLite cannot hold (an integer past 2^63) was retried twice a
    second forever, the evaluation 'running' and holding the only slot."""
    jobs = JobManager(tmp_path / "data", preset("tiny"), no_checkpoint, python=fake_eval(tmp_path, "10**22", True),
                      poll_seconds=0.1)
    try:
        e = jobs.start_evaluation(system="oracle", env_ids=[70])
        failed = wait_until(lambda: (r := jobs.db.evaluation(e.id)).status == "failed" and r, what="failed")
        assert "could not be recorded" in failed.error and "OverflowError" in failed.error
        assert not jobs.supervisor.handles  # the slot is free, and its process group was ended
        (tmp_path / "release").touch()
        # a second evaluation starts: the limit of one is not held
        assert jobs.start_evaluation(system="oracle", env_ids=[71]).status == "running"
    finally:
        (tmp_path / "release").touch()
        jobs.close()


DISK_FULL = """\
import json, os, sys, time
from pathlib import Path
from app.jobs.db import RecordError
from app.jobs.manager import JobManager
from gsmn.config import preset

root, fake = Path(sys.argv[1]), sys.argv[2]

def no_checkpoint(ref):
    raise AssertionError

def wait_until(predicate, what, timeout=60):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if (value := predicate()):
            return value
        time.sleep(0.05)
    raise AssertionError("timed out waiting for " + what)

jobs = JobManager(root / "data", preset("tiny"), no_checkpoint, python=fake, poll_seconds=0.1)
e = jobs.start_evaluation(system="oracle", env_ids=[70, 71])
wait_until(lambda: jobs.db.evaluation(e.id).done == 2, "both episodes recorded")
with open(root / "filler", "wb") as f:  # fill the tmpfs
    try:
        while True:
            f.write(b"\\0" * 65536)
            f.flush()
    except OSError:
        pass
(root / "release").touch()  # the job ends; its results cannot be recorded
wait_until(lambda: not jobs.supervisor.handles, "the slot freed")
row = jobs.db.evaluation(e.id)
try:
    jobs.cancel_evaluation(e.id)
    cancel = "accepted"
except RecordError as err:
    cancel = f"{err.status} {err}"
os.remove(root / "filler")
final = wait_until(lambda: (r := jobs.db.evaluation(e.id)).status not in ("queued", "running") and r, "settled")
print(json.dumps({"while_full": row.status, "cancel": cancel, "status": final.status, "error": final.error,
                  "results": (Path(final.folder) / "results.json").is_file(), "db": str(jobs.db.path)}))
jobs.close()
"""


def test_a_full_disk_fails_the_finished_job_with_the_reason_and_loses_nothing(tmp_path):
    script = tmp_path / "disk_full.py"
    script.write_text(DISK_FULL)
    root = tmp_path / "small"
    root.mkdir()
    fake = fake_eval(tmp_path, wait=True)
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    command = in_private_mounts(f"mount -t tmpfs -o size=3m tmpfs {root} && {sys.executable} {script} {root} {fake}")
    done = subprocess.run(command, capture_output=True, text=True, timeout=240, env=env, cwd=REPO)
    assert done.returncode == 0, done.stdout + done.stderr
    out = json.loads(done.stdout.strip().splitlines()[-1])
    assert out["while_full"] == "running"  # it could not be written yet, but its slot was free
    assert out["cancel"].startswith("503 ") and out["db"] in out["cancel"] and "full" in out["cancel"]
    assert out["status"] == "failed" and "could not be recorded" in out["error"] and "full" in out["error"]
    assert out["results"]  # what the job saved is still there


def test_a_job_folder_that_holds_results_is_never_reused(tmp_path):
    """A record started afresh (moved away) numbers its jobs from 1 again, beside the old job folders."""
    parent = tmp_path / "evaluations"
    old = parent / "0001"
    old.mkdir(parents=True)
    (old / "results.json").write_text("{}")
    (parent / "0002").mkdir()  # empty: may be used
    assert new_job_folder(parent, 1) == parent / "0001-1"
    assert new_job_folder(parent, 1) == parent / "0001-1"  # still empty
    (parent / "0001-1" / "x").write_text("")
    assert new_job_folder(parent, 1) == parent / "0001-2"
    assert new_job_folder(parent, 2) == parent / "0002"
    assert (old / "results.json").read_text() == "{}"


@pytest.mark.server
def test_an_empty_record_stops_the_server_naming_the_file(tmp_path):
    data = tmp_path / "data"
    data.mkdir()
    (data / "gsmn.sqlite").write_bytes(b"")
    with pytest.raises(RecordError, match=str(data / "gsmn.sqlite")):
        JobManager(data, preset("tiny"), no_checkpoint)
    done = subprocess.run(serve_command(data_dir=data), capture_output=True, text=True, timeout=120, cwd=REPO)
    assert done.returncode == 2 and f"{data / 'gsmn.sqlite'} is empty (0 bytes)" in done.stderr


# -- the import endpoint ----------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def served(tmp_path_factory):
    from app.server import Dashboard
    from gsmn.config import with_overrides

    root = tmp_path_factory.mktemp("import")
    d = Dashboard(with_overrides(preset("tiny"), {"task.horizon": "20"}), port=0, api_port=0,
                  checkpoints_root=root / "none", data_dir=root / "data")
    try:
        with httpx.Client(base_url=d.urls.api, timeout=30) as client:
            yield d, client
    finally:
        d.close()


def test_import_reads_nothing_outside_the_data_folder(served):
    d, client = served
    outside = []
    for path in ("/dev/zero", "/etc/passwd", "/no/such/file", "../../etc/hostname", str(REPO / "pyproject.toml")):
        r = client.post("/api/evaluations/import", json={"path": path})
        assert r.status_code == 403 and "inside the data folder" in r.json()["detail"], (path, r.text)
        outside.append(r.json()["detail"])
    assert len(set(outside)) == 1  # the same answer whether the file exists or not
    (d.jobs.root / "zero").symlink_to("/dev/zero")  # a link out of the folder is outside too
    assert client.post("/api/evaluations/import", json={"path": "zero"}).status_code == 403
    r = client.post("/api/evaluations/import", json={"path": "x.json", "record_dir": "/tmp"})
    assert r.status_code == 403
    assert client.get("/api/health").status_code == 200


def test_import_refuses_fifos_devices_and_huge_files_at_once(served):
    d, client = served
    fifo = d.jobs.root / "pipe.json"
    os.mkfifo(fifo)
    t0 = time.monotonic()
    r = client.post("/api/evaluations/import", json={"path": "pipe.json"})
    assert r.status_code == 422 and "not a regular file" in r.json()["detail"]
    assert time.monotonic() - t0 < 5  # no read blocked on it
    huge = d.jobs.root / "huge.json"
    with huge.open("wb") as f:
        f.truncate(300 * 2**20)  # sparse: no disk used
    r = client.post("/api/evaluations/import", json={"path": str(huge)})
    assert r.status_code == 413 and "300 MiB" in r.json()["detail"]
    r = client.post("/api/evaluations/import", json={"path": "missing.json"})
    assert r.status_code == 404
    (d.jobs.root / "bad.json").write_text("[1, 2]")
    r = client.post("/api/evaluations/import", json={"path": "bad.json"})
    assert r.status_code == 422 and "not a `gsmn eval --json` file" in r.json()["detail"]
    assert client.get("/api/health").status_code == 200


def test_a_good_file_inside_the_data_folder_imports(served, tmp_path):
    d, client = served
    episode = dict(env_id=70, instruction="go to the left side of the barrel", noun_phrase="barrel", side="left",
                   ambiguous=False, success=True, landmark_success=True, goal_distance=0.2, steps=12, stopped=True,
                   final_x=1.0, final_y=2.0, region_steps=[11])
    folder = d.jobs.root / "mine"
    folder.mkdir()
    (folder / "results.json").write_text(json.dumps({"system": "oracle", "episodes": [episode],
                                                      "config": preset("tiny").to_dict(), "summary": {"count": 1}}))
    r = client.post("/api/evaluations/import", json={"path": "mine/results.json"})
    assert r.status_code == 201, r.text
    assert r.json()["source"] == "import" and r.json()["env_ids"] == [70]
