"""Every episode flown in the page or over the API, kept in the SQLite record (`app.jobs.db`, tables kept_episodes and
kept_steps) as it flies, so that it outlives the server, a `kill -9` included, and can be listed, searched,
replayed, pinned and exported later. How an episode's row and steps are stored and read back: `app.jobs.kept_store`.

- **Written as it flies.** The runner tells `EpisodeKeeper` (a `RunnerListener`) of each step; a writer thread
  stores the steps waiting for it in one transaction at a time, so the simulator never waits for the disk and a
  server killed mid-episode loses only the steps not yet written (the writer's queue: typically none, at most
  the last few). The next server marks an episode left "running" as failed, with the steps it kept.
- **Taken when accepted.** An episode's row is written when the runner accepts it (`KeptStore.add`), so its id is
  the record's at once and a server stopped before it flew keeps it, as not flown. A write that fails later (a full
  disk) waits and is tried again; nothing says more is kept than the record holds (`EpisodeKeeper`).
- **Retention by disk size.** Once the kept steps' stored bytes pass `limit_bytes`, the oldest unpinned finished
  episodes are removed until they fit again; a pinned episode and the one flying are never removed. SQLite reuses
  the freed pages for the next episodes (the file does not shrink).
"""

from __future__ import annotations

import itertools
import json
import logging
import queue
import threading
import time
import traceback
from collections import deque
from dataclasses import asdict
from typing import Any

from app.jobs.db import Database
from app.jobs.kept_store import KeptStore, kept_row, step_row
from app.live.commands import RunnerListener
from app.live.recording import (
    CANCELLED,
    FAILED,
    FINISHED,
    LIVE,
    QUEUED,
    Episode,
    EpisodeResult,
    StepRecord,
)

log = logging.getLogger("gsmn.dashboard")
DEFAULT_LIMIT_MB = 2000.0  # about 400 paper-preset episodes of about 100 steps (docs/dashboard.md, "Kept episodes")
OUTCOMES = ("success", "failure", "cancelled", "failed", "live")


def _result_dict(result: EpisodeResult | None) -> str | None:
    return json.dumps(asdict(result)) if result is not None else None


# -- the keeper -------------------------------------------------------------------------------------------------------
class EpisodeKeeper(RunnerListener):
    """Records each episode the runner flies into `store`'s record, step by step, on a writer thread; applies the
    retention limit after each episode and on start.

    A write that fails (a full disk, a read-only folder) loses nothing: what was taken from the queue stays pending
    and is written again every `retry_seconds` until it goes in, in its order, and meanwhile `error` says why (the
    record names its file; logged once, and once more when keeping resumes). Pending steps are bounded: past
    `max_pending_steps` the oldest are given up, and their episode's row says how many of its steps were not kept
    (`cut`), so nothing reports more than the record holds."""

    def __init__(self, store: KeptStore, limit_bytes: int, live: callable = lambda: None,
                 retry_seconds: float = 2.0, max_pending_steps: int = 4000):
        self.store, self.db = store, store.db
        self.limit_bytes = int(limit_bytes)
        self._live = live  # the id of the episode flying now (never removed)
        self.retry_seconds, self.max_pending_steps = retry_seconds, max_pending_steps
        self._queue: queue.Queue = queue.Queue()
        self._pending: deque = deque()  # taken from the queue, not yet written (the writer's own)
        self._started: set[int] = set()
        self.cut: dict[int, int] = {}  # episode id -> steps given up while the record could not be written
        self.unwritten: dict[int, int] = {}  # episode id -> its steps waiting to be written (read by the API)
        self._counting = threading.Lock()  # the runner's thread adds to `unwritten`, the writer takes away
        self.error: str | None = None  # why the last write failed, until one succeeds
        self.removed: list[int] = []  # ids removed by the retention limit, oldest first
        self._retention = threading.Lock()  # the writer (after an episode) and the API (a new limit) both apply it
        self._settle_interrupted()
        self.apply_retention()
        self.thread = threading.Thread(target=self._loop, name="gsmn-keeper", daemon=True)
        self.thread.start()

    def _settle_interrupted(self) -> None:
        """Episodes a stopped server left flying: failed, with the steps that were written; left queued: kept, as
        not flown."""
        for row in self.db.search_kept([f"status IN ({','.join('?' * len(LIVE))})"], list(LIVE), False, 10**9, 0):
            if row["status"] == QUEUED:
                self.db.update_kept(int(row["id"]), status=CANCELLED, error=(
                    "not flown: the server stopped before its turn came"))
            else:
                self.db.update_kept(int(row["id"]), status=FAILED, error=(
                    f"the server stopped while it flew; the {row['steps']} steps written before are kept"))

    def behind(self, episode_id: int) -> str | None:
        """Why some of this episode's steps are not in the record: they wait while it cannot be written, or were
        given up; None otherwise (the writer's usual lag of a step or two behind a flight is not a fault)."""
        waiting, cut = self.unwritten.get(episode_id, 0), self.cut.get(episode_id, 0)
        if not cut and not (waiting and self.error):
            return None
        parts = ([f"{waiting} steps wait to be written"] if waiting else []) + (
            [f"{cut} steps could not be kept"] if cut else [])
        return "; ".join(parts) + (f" ({self.error}); retried every {self.retry_seconds:g} s" if self.error else "")

    # -- the runner's thread: only enqueue --------------------------------------------------------------------------
    def on_episode_start(self, episode: Episode) -> None:
        # the steps it starts with: a fork's steps 0..t-1 are the original's (app.live.compare), never told one by one
        self._count(episode.id, len(episode.steps))
        self._queue.put(("start", episode, tuple(episode.steps)))

    def on_step(self, episode: Episode, record: StepRecord) -> None:
        self._count(episode.id, 1)
        self._queue.put(("step", episode, record))

    def on_episode_end(self, episode: Episode) -> None:
        self._queue.put(("end", episode, None))

    def _count(self, episode_id: int, n: int) -> None:
        with self._counting:
            self.unwritten[episode_id] = self.unwritten.get(episode_id, 0) + n

    def flush(self, timeout: float = 10.0) -> bool:
        """Wait until everything enqueued so far is written; False if it was not within `timeout`, and at once
        while the record cannot be written (`error`): readers then see what it holds."""
        if self.error is not None:
            return False
        done = threading.Event()
        self._queue.put(("flush", done, None))
        return done.wait(timeout)

    def close(self, timeout: float = 10.0) -> None:
        self._queue.put(None)
        self.thread.join(timeout)

    # -- the writer ---------------------------------------------------------------------------------------------------
    def _take(self, timeout: float | None) -> bool:
        """Move what the queue holds into the pending items (waiting up to `timeout` for the first); False if none."""
        try:
            self._pending.append(self._queue.get(timeout=timeout))
        except queue.Empty:
            return False
        try:
            while len(self._pending) < self.max_pending_steps + 200:
                self._pending.append(self._queue.get_nowait())
        except queue.Empty:
            pass
        return True

    def _loop(self) -> None:
        while True:
            if not self._pending:
                self._take(None)
            else:  # after a failed write: wait, taking what comes meanwhile, then try again
                deadline = time.monotonic() + self.retry_seconds
                while (left := deadline - time.monotonic()) > 0 and None not in self._pending:
                    self._take(left)
            try:
                if self._write():
                    return
            except Exception as e:  # noqa: BLE001 - a full disk must not stop the simulator; the log says so, once
                if self.error is None:
                    log.error("keeping episodes failed (retried every %g s until it works):\n%s",
                              self.retry_seconds, traceback.format_exc())
                self.error = str(e)
                self._shed()
                if None in self._pending and self._closing_given_up():
                    return
                continue
            if self.error is not None:
                log.warning("keeping episodes works again: everything pending is written")
                self.error = None

    def _closing_given_up(self) -> bool:
        """Closing while the record cannot be written: one last try has failed; say what is lost."""
        steps = sum(1 for item in self._pending if item is not None and item[0] == "step")
        log.error("closing with %d steps not written to the record (%s)", steps, self.error)
        for item in self._pending:
            if item is not None and item[0] == "flush":
                item[1].set()
        return True

    def _shed(self) -> None:
        """Give up the oldest pending steps beyond `max_pending_steps`, counting them against their episode."""
        steps = [item for item in self._pending if item is not None and item[0] == "step"]
        drop = {id(item) for item in steps[:max(0, len(steps) - self.max_pending_steps)]}
        if not drop:
            return
        kept = deque()
        for item in self._pending:
            if id(item) in drop:
                episode_id = item[1].id
                self.cut[episode_id] = self.cut.get(episode_id, 0) + 1
                self._count(episode_id, -1)
            else:
                kept.append(item)
        self._pending = kept

    def _write(self) -> bool:
        """Write the pending items in order, each leaving the pending ones once it is in the record (a failure leaves
        it and the rest for the next try); True once the close item is reached."""
        pending = self._pending
        while pending:
            item = pending[0]
            if item is None:
                return True
            kind, episode, record = item
            if kind == "flush":
                pending.popleft()
                episode.set()
            elif kind == "start":
                self._start(episode)
                pending.popleft()
                for r in reversed(record):  # a fork's first steps: written as any other steps, next
                    pending.appendleft(("step", episode, r))
            elif kind == "step":
                batch = list(itertools.takewhile(
                    lambda it, e=episode: it is not None and it[0] == "step" and it[1] is e, pending))
                if episode.id not in self._started:
                    self._start(episode)
                rows = [step_row(it[2]) for it in batch]
                size = sum(len(r[1]) + len(r[2]) + (len(r[3]) if r[3] is not None else 0) for r in rows)
                self.db.add_kept_steps(episode.id, rows, size)
                for _ in batch:
                    pending.popleft()
                self._count(episode.id, -len(batch))
            elif kind == "end":
                self._end(episode)
                pending.popleft()
        return False

    def _start(self, episode: Episode) -> None:
        self.db.add_kept(kept_row(episode, self.store.config.world))
        self._started.add(episode.id)

    def _end(self, episode: Episode) -> None:
        result = episode.result
        error = episode.error
        if episode.id not in self._started:  # dropped from the queue before it flew: kept, as not flown
            error = error or "not flown: cancelled before its turn came"
        cut = self.cut.pop(episode.id, 0)
        if cut:
            error = (f"{error}; " if error else "") + (f"{cut} of its steps could not be kept: the record could not "
                                                       "be written meanwhile (a full disk?)")
        self.db.update_kept(episode.id, status=episode.status, finished=time.time(), error=error,
                            result=_result_dict(result), success=None if result is None else int(result.success))
        self._started.discard(episode.id)
        with self._counting:
            if not self.unwritten.get(episode.id):
                self.unwritten.pop(episode.id, None)
        self.apply_retention()

    # -- retention ----------------------------------------------------------------------------------------------------
    def set_limit(self, limit_bytes: int) -> list[int]:
        self.limit_bytes = int(limit_bytes)
        return self.apply_retention()

    def apply_retention(self) -> list[int]:
        """Remove the oldest unpinned, not flying episodes while the kept bytes exceed the limit; the ids removed."""
        with self._retention:
            return self._apply_retention()

    def _apply_retention(self) -> list[int]:
        removed = []
        total = self.db.kept_bytes()
        live = self._live()
        while total > self.limit_bytes:
            rows = self.db.search_kept(["pinned = 0", f"status NOT IN ({','.join('?' * len(LIVE))})"], list(LIVE),
                                       False, 16, 0)
            rows = [r for r in rows if int(r["id"]) != live]
            if not rows:
                break
            for row in rows:
                if total <= self.limit_bytes:
                    break
                self.db.remove_kept(int(row["id"]))
                self.store.forget(int(row["id"]))
                total -= int(row["bytes"])
                removed.append(int(row["id"]))
        if removed:
            log.info("retention (%.1f MB): removed episodes %s", self.limit_bytes / 1e6, removed)
            self.removed.extend(removed)
        return removed


# -- search -----------------------------------------------------------------------------------------------------------
def search(db: Database, env_id: int | None = None, instruction: str | None = None, policy: str | None = None,
           system: str | None = None, outcome: str | None = None, pinned: bool | None = None,
           since: float | None = None, until: float | None = None, newest_first: bool = True, limit: int = 100,
           offset: int = 0, checkpoint: str | None = None, columns: str = "*") -> list:
    """Kept episodes' rows matching every filter given: `instruction` a case-insensitive substring; `outcome`
    success, failure (finished without success), cancelled, failed (an error, or the server stopped) or live;
    `since` / `until` unix times of the start; `checkpoint` the folder that flew or watched, as the row has it.
    `columns`: the columns read (e.g. "id" to count them)."""
    where, params = [], []
    if checkpoint is not None:
        where.append("checkpoint = ?")
        params.append(checkpoint)
    if env_id is not None:
        where.append("env_id = ?")
        params.append(int(env_id))
    if instruction:
        escaped = instruction.lower().replace("\\", "\\\\").replace("%", "\\%").replace("_", "\\_")
        where.append("lower(instruction) LIKE ? ESCAPE '\\'")
        params.append(f"%{escaped}%")
    if policy is not None:
        where.append("policy = ?")
        params.append(policy)
    if system is not None:
        where.append("system = ?")
        params.append(system)
    if outcome is not None:
        if outcome not in OUTCOMES:
            raise ValueError(f"outcome must be one of {', '.join(OUTCOMES)}, got {outcome!r}")
        where.append({"success": f"status = '{FINISHED}' AND success = 1",
                      "failure": f"status = '{FINISHED}' AND success = 0",
                      "cancelled": "status = 'cancelled'", "failed": "status = 'failed'",
                      "live": "status IN ('queued', 'running', 'paused')"}[outcome])
    if pinned is not None:
        where.append("pinned = ?")
        params.append(int(pinned))
    if since is not None:
        where.append("created >= ?")
        params.append(float(since))
    if until is not None:
        where.append("created <= ?")
        params.append(float(until))
    return db.search_kept(where, params, newest_first, limit, offset, columns)


def policies_flown(db: Database) -> list[tuple[str, str | None]]:
    """Each policy and checkpoint that flew a kept episode (the expert once, whoever watched), newest first."""
    seen: dict[tuple[str, str | None], None] = {}
    for row in db.search_kept([], [], True, 10**9, 0, "policy, checkpoint"):
        seen.setdefault((row["policy"], None if row["policy"] == "expert" else row["checkpoint"]), None)
    return list(seen)


def row_summary(row) -> dict[str, Any]:
    """A kept row as the API's episode summary fields (app.api.models.EpisodeSummary)."""
    task = json.loads(row["task"])
    i = task["instruction"]
    fork, comparison = task.get("fork") or {}, task.get("comparison") or {}  # app.jobs.kept_store.episode_relation
    return {"id": int(row["id"]), "status": row["status"], "env_id": int(row["env_id"]), "split": row["split"],
            "instruction": row["instruction"], "typed_instruction": task.get("typed"),
            "landmark": i["noun_phrase"], "side": i["side"],
            "goal_x": i["goal_x"], "goal_y": i["goal_y"], "policy": row["policy"], "system": row["system"],
            "checkpoint": row["checkpoint"], "steps": int(row["steps"]), "horizon": int(row["horizon"]),
            "steps_per_second": None, "result": json.loads(row["result"]) if row["result"] else None,
            "error": row["error"], "pinned": bool(row["pinned"]), "created": float(row["created"]),
            "bytes": int(row["bytes"]), "kept_steps": int(row["steps"]), "fork_of": fork.get("episode_id"),
            "fork_step": fork.get("step"), "comparison": comparison.get("id"),
            "comparison_side": comparison.get("side"), "compared_with": comparison.get("with"),
            "world_edits": task.get("world_edits", []), "intervention": task.get("intervention")}
