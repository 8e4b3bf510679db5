"""`--executor ray`: evaluation, collection and DAggerFM's rollouts on a Ray cluster that these tests start (on
loopback, two CPUs, no dashboard) and stop themselves: the same episodes as the local pool, a worker killed mid-run
retried with nothing lost or counted twice."""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest
import ray  # noqa: F401 - the optional extra, which ./test.sh installs (pip install -e '.[dev,ray]')

from gsmn.config import preset, with_overrides
from gsmn.evaluation import evaluate
from gsmn.task.rollout import EpisodeRecord
from gsmn.training.collect import collect_expert
from gsmn.training.store import EpisodeStore

pytestmark = pytest.mark.cluster

TINY = preset("tiny")
RAY = Path(sys.executable).with_name("ray")
# A single-node cluster on 127.0.0.1: without this Ray swaps a loopback --node-ip-address for the host's address.
LOOPBACK = {"RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER": "0"}
HEAD_PID = "GSMN_TEST_RAY_HEAD_PID"  # in the cluster fixture's environment: the pid of its `ray start --head`


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def cluster():
    """A Ray head on 127.0.0.1 (`ray start --head --block`), stopped by SIGTERM to that command, which takes its
    processes down with it; yields the environment a client command runs with."""
    temp = tempfile.mkdtemp(prefix="gsr")  # short: Ray's socket paths live under it
    port = _free_port()
    scratch = Path(temp) / "tmp"  # the temporary directory of the cluster's processes (and of the client commands)
    scratch.mkdir()
    env = {**os.environ, **LOOPBACK, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl"), "TMPDIR": str(scratch)}
    head = subprocess.Popen([str(RAY), "start", "--head", "--block", "--port", str(port), "--node-ip-address",
                             "127.0.0.1", "--num-cpus", "2", "--object-store-memory", str(200 * 2**20),
                             "--include-dashboard=false", "--disable-usage-stats", "--temp-dir", temp],
                            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    address = f"127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:  # the head is up once a client connects
            assert head.poll() is None, "ray start --head exited"
            probe = subprocess.run([sys.executable, "-c", f"import ray; ray.init(address={address!r}); "
                                    "print(ray.cluster_resources().get('CPU'))"], env=env, capture_output=True,
                                   text=True)
            if probe.returncode == 0:
                assert probe.stdout.split()[-1] == "2.0"
                break
            time.sleep(1)
        else:
            pytest.fail("the Ray head did not come up in 120 s")
        yield {**env, "RAY_ADDRESS": address, HEAD_PID: str(head.pid)}
    finally:
        head.send_signal(signal.SIGTERM)
        try:
            head.wait(timeout=60)
        except subprocess.TimeoutExpired:
            head.kill()
            head.wait()
        shutil.rmtree(temp, ignore_errors=True)


def _gsmn(*args: str) -> list[str]:
    return [sys.executable, "-m", "gsmn.cli", *args]


def _parent(pid: int) -> int:
    stat = Path(f"/proc/{pid}/stat").read_text()
    return int(stat[stat.rindex(")") + 2:].split()[1])  # the fields after the command's name: state, ppid, ...


def _actor_pids(head: int) -> list[int]:
    """The processes of the EpisodeWorker actors under this module's `ray start --head` (pid `head`): Ray names an
    actor's process after its class, and its raylet, a child of that command, starts them. Another cluster on the
    machine (a second test run, a user's) is left out."""
    pids = []
    for proc in Path("/proc").iterdir():
        try:
            if not (proc.name.isdigit() and (proc / "cmdline").read_bytes().startswith(b"ray::EpisodeWorker")):
                continue
            pid = int(proc.name)
            while pid > 1 and pid != head:
                pid = _parent(pid)
            if pid == head:
                pids.append(int(proc.name))
        except (OSError, ValueError, IndexError):
            continue  # gone while read
    return pids


def test_eval_on_ray_flies_the_same_episodes_as_the_local_pool(cluster, tmp_path):
    ids = [70, 71, 72, 73]
    out = tmp_path / "ray.json"
    run = subprocess.run(_gsmn("eval", "--system", "random-point", "--env-ids", "70:74", "--preset", "tiny",
                               "--workers", "2", "--executor", "ray", "--json", str(out)),
                         env=cluster, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr
    local = evaluate("random-point", ids, TINY, workers=2)
    episodes = json.loads(out.read_text())["episodes"]
    assert [e["env_id"] for e in episodes] == ids
    assert [EpisodeRecord.from_dict(e) for e in episodes] == local  # episode by episode: paths, stops, distances
    refused = subprocess.run(_gsmn("eval", "--system", "oracle", "--env-ids", "70", "--ray-address", "127.0.0.1:1"),
                             capture_output=True, text=True)
    assert refused.returncode == 2 and "--ray-address needs --executor ray" in refused.stderr


def test_a_ray_worker_killed_mid_run_is_retried_and_no_episode_is_lost_or_counted_twice(cluster, tmp_path):
    ids = list(range(70, 78))
    out, progress = tmp_path / "eval.json", tmp_path / "progress.jsonl"
    proc = subprocess.Popen(_gsmn("eval", "--system", "oracle", "--env-ids", "70:78", "--preset", "tiny",
                                  "--workers", "2", "--executor", "ray", "--json", str(out), "--progress",
                                  str(progress)), env=cluster, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            text=True)
    try:
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline and not (progress.is_file() and progress.read_text().strip()):
            assert proc.poll() is None, proc.stderr.read()
            time.sleep(0.1)
        actors = _actor_pids(int(cluster[HEAD_PID]))
        done_at_kill = len(progress.read_text().splitlines())
        assert len(actors) == 2 and done_at_kill < len(ids), "the run got ahead of the test"
        os.kill(actors[0], signal.SIGKILL)  # a worker lost mid-run, its episode in flight
        _, stderr = proc.communicate(timeout=600)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, stderr
    assert actors[0] not in _actor_pids(int(cluster[HEAD_PID]))
    episodes = json.loads(out.read_text())["episodes"]
    assert [e["env_id"] for e in episodes] == ids  # complete
    lines = [json.loads(x) for x in progress.read_text().splitlines()]
    assert sorted(x["env_id"] for x in lines) == ids and [x["done"] for x in lines] == list(range(1, 9))  # once each
    assert [EpisodeRecord.from_dict(e) for e in episodes] == evaluate("oracle", ids, TINY)


def test_collect_on_ray_writes_the_local_pools_episodes_and_skips_what_exists(cluster, tmp_path):
    config = with_overrides(TINY, {"task.horizon": "20"})
    args = ("collect", "--out", str(tmp_path / "ray"), "--env-ids", "0:3", "--workers", "2", "--preset", "tiny",
            "--task.horizon", "20", "--executor", "ray")
    first = subprocess.run(_gsmn(*args), env=cluster, capture_output=True, text=True, timeout=600)
    assert first.returncode == 0, first.stderr
    assert "3 episodes (3 new" in first.stdout
    again = subprocess.run(_gsmn(*args), env=cluster, capture_output=True, text=True, timeout=600)
    assert again.returncode == 0 and "3 episodes (0 new" in again.stdout, again.stderr
    ray_store, local = EpisodeStore(tmp_path / "ray"), EpisodeStore(tmp_path / "local")
    collect_expert(local, [0, 1, 2], config, workers=2)
    assert ray_store.keys() == local.keys()
    for key in local.keys():
        a, b = ray_store.read(key), local.read(key)
        assert np.array_equal(a.images, b.images) and np.array_equal(a.actions, b.actions)
        assert np.array_equal(a.poses, b.poses)


def test_a_dagger_iteration_with_ray_rollouts_finishes(cluster, stores, tmp_path):
    """One DAggerFM iteration (2 rollouts of the mixture policy, its weights through Ray's object store) on the
    cluster: the dataset holds M episodes, the 2 rollouts among them, and the iteration is logged; the copies of
    the weights the actors fetched are off their disk once the run ends."""
    from gsmn.training.supervised import train_supervised

    train, _ = stores
    flags = {"task.horizon": "20", "train.epochs": "1", "train.batch_size": "2", "dagger.iterations": "1",
             "dagger.rollouts_per_iteration": "2", "dagger.dataset_size": "3", "dagger.beta0": "0.5",
             "dagger.workers": "2"}
    init = train_supervised(tmp_path / "sup", "gsmn", with_overrides(TINY, flags), train, log=lambda s: None)
    args = ["train", "dagger", "--init", str(init), "--data", str(train.root), "--run", str(tmp_path / "dagger"),
            "--preset", "tiny", "--executor", "ray"]
    for key, value in flags.items():
        args += ["--" + key.replace("_", "-"), value]
    run = subprocess.run(_gsmn(*args), env=cluster, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr
    log = [json.loads(x) for x in (tmp_path / "dagger" / "log.jsonl").read_text().splitlines()]
    assert [r["iteration"] for r in log] == [1] and log[0]["dataset"] == 3
    dataset = EpisodeStore(tmp_path / "dagger" / "dataset")
    rollouts = [k for k in dataset.keys() if k.startswith("dagger_0001_")]
    assert len(dataset) == 3 and len(rollouts) == 2
    assert all(dataset.read_meta(k)["iteration"] == 1 for k in rollouts)
    assert not list(Path(cluster["TMPDIR"]).glob("gsmn-shared-*")), "an actor's copy of the shared weights is left"
