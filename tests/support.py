"""Waiting for a condition, shared by every test that polls a server, a runner or a page; and a shell command in a
private mount namespace, for the fault tests' small or read-only file systems."""

from __future__ import annotations

import shutil
import subprocess
import time
from collections.abc import Callable
from typing import Any


def poll(get: Callable[[], Any], done: Callable[[Any], Any], what: str, timeout: float = 60.0,
         every: float = 0.1) -> Any:
    """Call `get` until `done` holds for its value, and return that value; fail saying `what` and the last value."""
    deadline = time.monotonic() + timeout
    value = None
    while time.monotonic() < deadline:
        value = get()
        if done(value):
            return value
        time.sleep(every)
    raise AssertionError(f"timed out after {timeout:.0f} s waiting for {what}; last {value!r}")


def until(predicate: Callable[[], Any], timeout: float = 60.0, what: str = "", every: float = 0.1) -> Any:
    """Wait until `predicate()` is truthy and return it."""
    return poll(predicate, bool, what or "a condition", timeout, every)


def in_private_mounts(shell: str) -> list[str]:
    """The command that runs `shell` (which mounts what it needs, e.g. a 2 MB tmpfs) in a mount namespace of its own,
    so the mounts vanish with it; fails saying why where the machine gives none (it needs root)."""
    probe = subprocess.run(["unshare", "--mount", "true"], capture_output=True, text=True) \
        if shutil.which("unshare") else None
    assert probe is not None and probe.returncode == 0, ("this test needs a private mount namespace for its tmpfs "
                                                         f"(unshare --mount, as root): {probe and probe.stderr}")
    return ["unshare", "--mount", "sh", "-c", shell]
