"""The Ray backend of `gsmn.executor` (the optional extra: pip install -e '.[ray]'; docs/scale.md).

One actor (`EpisodeWorker`, one CPU each) per worker: it sets itself up once with the caller's initializer (its
simulator, renderer and policy live in that actor's process) and then runs one job at a time, the driver keeping
one job in flight per actor and handing the next to whichever finishes first; results are yielded in the order
of the jobs. An actor whose process dies (killed, its node lost) is restarted by Ray, set up again, and its job
retried (`max_restarts`, `max_task_retries`), so every job gives exactly one result.

Shared folders (DAggerFM's policy checkpoint) are put in the object store once per `share` and fetched by each
actor once, into a private folder of its process, removed when the executor closes (an actor killed otherwise
leaves its last folder in its node's temporary directory).

The initializer and job functions are sent by name (module and function) and imported in the actor only after
the driver's rendering settings (MUJOCO_GL, PYOPENGL_PLATFORM) are in its environment: MuJoCo reads them when it
is first imported.
"""

from __future__ import annotations

import importlib
import os
import shutil
import tempfile
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path

import ray

from gsmn.executor_base import Executor, call_job, open_shared

RETRIES = 3  # restarts of a dead actor, and retries of the job it was running
FORWARDED_ENV = ("MUJOCO_GL", "PYOPENGL_PLATFORM", "EGL_DEVICE_ID")
RELEASE_SECONDS = 30  # at close: how long the actors get to remove their shared folders


def _name(fn: Callable) -> tuple[str, str]:
    return fn.__module__, fn.__qualname__


def _resolve(name: tuple[str, str]) -> Callable:
    module, qualname = name
    return getattr(importlib.import_module(module), qualname)


class EpisodeWorker:
    """A worker of a `RayExecutor`, as a Ray actor: set up once, then jobs one at a time."""

    def __init__(self, env: dict[str, str], initializer: tuple[str, str], initargs: tuple):
        os.environ.update(env)
        _resolve(initializer)(*initargs)

    def run(self, fn: tuple[str, str], job, shared):
        return call_job(_resolve(fn), job, shared)

    def pid(self) -> int:
        return os.getpid()

    def release(self) -> None:
        """Remove the shared folder this actor fetched last (`RayExecutor.close`, before the actor is killed)."""
        release_shared(_opened)


class SharedFolder:
    """A folder's files in Ray's object store. The reference sits inside this object so that Ray does not fetch
    the files for every job: an actor fetches them once (`fetch_shared`)."""

    def __init__(self, ref: ray.ObjectRef):
        self.ref = ref
        self.key = ref.hex()

    def open(self) -> Path:
        """The folder in this actor's process (`gsmn.executor_base.open_shared`)."""
        return fetch_shared(self, _opened)


_opened: dict = {}  # in an actor: the folder of the handle it fetched last, by its key


def release_shared(opened: dict) -> None:
    """Remove the folders in `opened` (fetched by `fetch_shared`) from this process's disk."""
    for old in opened.values():
        shutil.rmtree(old, ignore_errors=True)
    opened.clear()


def fetch_shared(handle: SharedFolder, opened: dict) -> Path:
    """The folder of `handle` in this actor's process: fetched and written once, the previous one removed."""
    if handle.key not in opened:
        files: dict[str, bytes] = ray.get(handle.ref)
        release_shared(opened)
        folder = Path(tempfile.mkdtemp(prefix="gsmn-shared-"))
        for name, data in files.items():
            (folder / name).write_bytes(data)
        opened[handle.key] = folder
    return opened[handle.key]


class RayExecutor(Executor):
    """`workers` EpisodeWorker actors on the Ray cluster at `address` (default: $RAY_ADDRESS, else a Ray instance
    started for this process alone)."""

    remote = True

    def __init__(self, workers: int, initializer: Callable, initargs: tuple, address: str | None = None):
        self.workers = max(1, workers)
        self._setup = (_name(initializer), initargs)
        self._address = address or os.environ.get("RAY_ADDRESS") or None
        self._actors: list | None = None
        self._started_ray = False

    def _start(self) -> list:
        if self._actors is None:
            if not ray.is_initialized():
                if self._address is None:  # a Ray of this process alone, on loopback
                    ray.init(include_dashboard=False, log_to_driver=False, _node_ip_address="127.0.0.1")
                else:
                    ray.init(address=self._address, log_to_driver=False)
                self._started_ray = True
            env = {k: os.environ[k] for k in FORWARDED_ENV if k in os.environ}
            actor = ray.remote(EpisodeWorker).options(num_cpus=1, max_restarts=RETRIES, max_task_retries=RETRIES)
            self._actors = [actor.remote(env, *self._setup) for _ in range(self.workers)]
        return self._actors

    def share(self, folder: Path | str) -> SharedFolder:
        self._start()
        folder = Path(folder)
        return SharedFolder(ray.put({p.name: p.read_bytes() for p in sorted(folder.iterdir()) if p.is_file()}))

    def map(self, fn: Callable, jobs: Sequence, shared=None) -> Iterator:
        actors = self._start()
        name, jobs = _name(fn), list(jobs)
        pending: dict = {}  # object ref -> (job index, actor)
        idle, done = list(actors), {}
        following = yielded = 0
        try:
            while yielded < len(jobs):
                while idle and following < len(jobs):
                    actor = idle.pop(0)
                    pending[actor.run.remote(name, jobs[following], shared)] = (following, actor)
                    following += 1
                ready, _ = ray.wait(list(pending), num_returns=1)
                for ref in ready:
                    index, actor = pending.pop(ref)
                    done[index] = ray.get(ref)  # raises when the job failed (beyond the retries)
                    idle.append(actor)
                while yielded in done:
                    yield done.pop(yielded)
                    yielded += 1
        finally:  # stopped early: the jobs in flight are abandoned (their results are written atomically, or not)
            for ref in pending:
                ray.cancel(ref)

    def pids(self) -> list[int]:
        """The process ids of the actors now (for tests and benchmarks)."""
        return ray.get([a.pid.remote() for a in self._start()])

    def close(self) -> None:
        if self._actors is not None:
            try:  # each actor's shared folder off its node's disk first; an actor already dead has none to remove
                ray.get([actor.release.remote() for actor in self._actors], timeout=RELEASE_SECONDS)
            except ray.exceptions.RayError:  # a timeout included
                pass
            for actor in self._actors:
                ray.kill(actor, no_restart=True)
            self._actors = None
        if self._started_ray:
            ray.shutdown()
            self._started_ray = False


# -- probes for scripts/bench_executors.py ------------------------------------------------------------
def fetch_seconds(job, shared) -> float:
    """Seconds this worker takes to fetch a shared folder (0 once it has it)."""
    import time

    t0 = time.perf_counter()
    open_shared(shared)
    return time.perf_counter() - t0
