"""Where episodes are flown: one seam for evaluation, expert collection and DAggerFM's rollouts.

Each of the three has the same shape of work: start a number of workers, each set up once by an initializer
(its simulator, renderer and policy), then hand them jobs (an environment id, a rollout) and take back one
result per job, in the order of the jobs. An `Executor` does exactly that, on one of three backends:

- `serial` (one worker): the jobs run in this process, one after the other.
- `local` (the default for more workers): a pool of worker processes on this host started with "spawn" (a
  forked MuJoCo/EGL context is not safe); the standard library's ProcessPoolExecutor, no new dependency.
- `ray`: one Ray actor per worker on a Ray cluster (`gsmn.executor_ray`, the optional extra `.[ray]`), each
  holding its simulator, renderer and policy and reused across jobs; an actor whose process dies is restarted
  and its job retried by Ray.

A job's result does not depend on the worker it runs on (episodes are seeded per job, never per worker), so
every backend gives the same results for the same jobs. Work that changes rarely and is big (DAggerFM's policy
weights, once per iteration) is `share`d: the local backends hand the worker a path on this host, Ray puts the
files in its object store once and each actor fetches them once (`open_shared`). The interface and the shared
folders are `gsmn.executor_base`'s, which both this module and `gsmn.executor_ray` build on.

Stopping early (SIGTERM, Ctrl-C, an error in the caller) finishes the jobs in flight on the local pool and
starts no more; on Ray the actors are ended. Callers write each result atomically, so a stopped run resumes
from what was finished (`gsmn eval --resume`, `collect` skipping what exists, DAggerFM from its saved state).
"""

from __future__ import annotations

import multiprocessing
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass

from gsmn.executor_base import Executor, call_job
from gsmn.executor_base import open_shared as open_shared
from gsmn.executor_base import shared_key as shared_key

BACKENDS = ("local", "ray")


@dataclass(frozen=True)
class ExecutorOptions:
    """How a command's work is spread: `backend` 'local' (worker processes on this host) or 'ray' (actors on the
    Ray cluster at `ray_address`, else $RAY_ADDRESS, else a cluster started for this process alone)."""

    backend: str = "local"
    ray_address: str | None = None

    def __post_init__(self):
        if self.backend not in BACKENDS:
            raise ValueError(f"--executor must be one of {', '.join(BACKENDS)}, not {self.backend!r}")


LOCAL = ExecutorOptions()


def make_executor(options: ExecutorOptions | None, workers: int, initializer: Callable, initargs: tuple = (),
                  in_process: Callable | None = None) -> Executor:
    """The executor `options` names, with `workers` workers. With one worker, the local backend and `in_process`
    given, the jobs run in this process, set up by `in_process()` (which may return a function that tears the
    set-up down); without `in_process` one worker is one worker process."""
    options = options or LOCAL
    if options.backend == "ray":
        from gsmn.executor_ray import RayExecutor

        return RayExecutor(workers, initializer, initargs, address=options.ray_address)
    if workers <= 1 and in_process is not None:
        return SerialExecutor(in_process)
    return LocalExecutor(workers, initializer, initargs)


class SerialExecutor(Executor):
    def __init__(self, setup: Callable[[], Callable[[], None] | None]):
        self._setup = setup
        self._teardown = None
        self._ready = False

    def map(self, fn: Callable, jobs: Sequence, shared=None) -> Iterator:
        if not self._ready:
            self._teardown = self._setup()
            self._ready = True
        for job in jobs:
            yield call_job(fn, job, shared)

    def close(self) -> None:
        if self._ready and callable(self._teardown):
            self._teardown()
        self._ready = False


def _pool_call(fn: Callable, shared, job):
    return call_job(fn, job, shared)


class LocalExecutor(Executor):
    def __init__(self, workers: int, initializer: Callable, initargs: tuple):
        self._args = (workers, initializer, initargs)
        self._pool: ProcessPoolExecutor | None = None

    def map(self, fn: Callable, jobs: Sequence, shared=None) -> Iterator:
        if self._pool is None:  # started at the first jobs: an executor that gets none starts no process
            workers, initializer, initargs = self._args
            self._pool = ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn"),
                                             initializer=initializer, initargs=initargs)
        if shared is None:
            return self._pool.map(fn, jobs)
        from functools import partial

        return self._pool.map(partial(_pool_call, fn, shared), jobs)

    def close(self) -> None:
        pool, self._pool = self._pool, None
        if pool is None:
            return
        try:
            pool.shutdown(cancel_futures=True)  # finish the jobs in flight, start no more
        except BaseException:
            # Interrupted again while waiting (a second SIGTERM or Ctrl-C): end the workers now. Left alone, the
            # pool's manager thread and its idle workers keep the process from exiting. The jobs in flight are
            # lost; their results are written atomically, so nothing part-written is left.
            for process in list((pool._processes or {}).values()):  # no public way before Python 3.14
                process.terminate()
            raise


# -- probes (scripts/bench_executors.py) -----------------------------------------------------------
def no_setup() -> None:
    """An initializer that sets nothing up."""


def echo(job, shared=None):
    """A job that does nothing: its round trip is an executor's own cost per job."""
    return job


# -- command line -----------------------------------------------------------------------------------
def add_arguments(parser) -> None:
    """`--executor` and `--ray-address` on a command whose episodes fly on workers."""
    parser.add_argument("--executor", choices=BACKENDS, default="local",
                        help="where the workers run: 'local' worker processes on this host (default), or 'ray' "
                             "actors on a Ray cluster (pip install -e '.[ray]'; docs/scale.md)")
    parser.add_argument("--ray-address", default=None,
                        help="the Ray cluster's head, HOST:PORT (default: $RAY_ADDRESS; without either, a Ray "
                             "instance of this process alone); only with --executor ray")


def options_from_args(args) -> ExecutorOptions:
    if args.ray_address and args.executor != "ray":
        raise ValueError("--ray-address needs --executor ray")
    return ExecutorOptions(args.executor, args.ray_address)
