"""Waiting for a condition, shared by every test that polls a server, a runner or a page."""

from __future__ import annotations

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
