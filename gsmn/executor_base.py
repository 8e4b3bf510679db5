"""What every backend of `gsmn.executor` shares: the `Executor` interface, how a worker calls a job (`call_job`),
and how a job opens a folder the caller shared (`shared_key`, `open_shared`).

The backends build on this module (`gsmn.executor`: serial and local; `gsmn.executor_ray`: Ray), never on each
other: a handle to a shared folder is a path (the local backends) or an object that fetches its files itself
(`gsmn.executor_ray.SharedFolder`), so opening one needs no backend's module.
"""

from __future__ import annotations

import os
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path


class Executor(ABC):
    """`workers` workers, each set up by `initializer(*initargs)` in its own process (the serial backend: in this
    one), running `fn(job)` or `fn(job, shared)`; `map` yields the results in the order of the jobs."""

    remote = False  # True where workers may run on other hosts (then `share` sends the bytes, not a path)

    @abstractmethod
    def map(self, fn: Callable, jobs: Sequence, shared=None) -> Iterator:
        """`fn(job)` (or `fn(job, shared)`) of every job on the workers, yielded in the order of `jobs`."""

    def share(self, folder: Path | str):
        """A handle to a folder's files for the workers (see `open_shared`): here, its path."""
        return str(folder)

    def close(self) -> None:  # noqa: B027 - nothing to release unless a backend holds workers
        """Release the workers (finishing the jobs in flight)."""

    def __enter__(self) -> Executor:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def call_job(fn: Callable, job, shared):
    """A job as a worker runs it: `fn(job)`, or `fn(job, shared)` where a folder is shared."""
    return fn(job) if shared is None else fn(job, shared)


# -- shared folders (in a worker) -------------------------------------------------------------------
def shared_key(handle) -> str:
    """What tells one `share` handle from another (a path, or the object's id in Ray's store)."""
    return str(handle) if isinstance(handle, str | os.PathLike) else handle.key


def open_shared(handle) -> Path:
    """In a worker: the folder a `share` handle names, on this host. A path is used as it is; files from Ray's
    object store are fetched once per handle into a private folder of this worker process (`handle.open()`)."""
    if isinstance(handle, str | os.PathLike):
        return Path(handle)
    return handle.open()
