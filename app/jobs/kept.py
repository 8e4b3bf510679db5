"""Every episode flown in the page or over the API, kept in the SQLite record (`app.jobs.db`, tables kept_episodes and
kept_steps) as it flies, so that it outlives the server, a `kill -9` included, and can be listed, searched,
replayed, pinned and exported later.

- **Written as it flies.** The runner tells `EpisodeKeeper` (a `RunnerListener`) of each step; a writer thread
  stores the steps waiting for it in one transaction at a time, so the simulator never waits for the disk and a
  server killed mid-episode loses only the steps not yet written (the writer's queue: typically none, at most
  the last few). The next server marks an episode left "running" as failed, with the steps it kept.
- **Taken when accepted.** An episode's row is written when the runner accepts it (`KeptStore.add`), so its id is
  the record's at once and a server stopped before it flew keeps it, as not flown. A write that fails later (a full
  disk) waits and is tried again; nothing says more is kept than the record holds (`EpisodeKeeper`).
- **Compact.** Per step: the pose, the actions and P(stop) as a small JSON object, the camera image as the JPEG
  the page already sends, and the model's maps quantised to 8 bits per channel (each channel's own minimum and
  maximum kept as float32 beside it, so a value comes back within 1/510 of its channel's range), zlib-compressed.
- **Read back as episodes.** `KeptStore` is the runner's episode store: an episode no longer in memory is loaded
  from the record on demand (maps back as float16), so the API's routes and the page's replay work on it as on
  one just flown.
- **Retention by disk size.** Once the kept steps' stored bytes pass `limit_bytes`, the oldest unpinned finished
  episodes are removed until they fit again; a pinned episode and the one flying are never removed. SQLite reuses
  the freed pages for the next episodes (the file does not shrink).
"""

from __future__ import annotations

import io
import itertools
import json
import logging
import queue
import threading
import time
import traceback
from collections import OrderedDict, deque
from dataclasses import asdict
from typing import Any

import numpy as np

from app.jobs.db import Database
from app.live.commands import RunnerListener
from app.live.recording import (
    CANCELLED,
    FAILED,
    FINISHED,
    LIVE,
    QUEUED,
    Episode,
    EpisodeResult,
    EpisodeStore,
    StepMaps,
    StepRecord,
)
from gsmn.config import RunConfig, WorldConfig
from gsmn.task.instructions import Instruction
from gsmn.task.rollout import Task
from gsmn.world.spec import world_for_env

log = logging.getLogger("gsmn.dashboard")
DEFAULT_LIMIT_MB = 2000.0  # about 400 paper-preset episodes of about 100 steps (docs/dashboard.md, "Kept episodes")
OUTCOMES = ("success", "failure", "cancelled", "failed", "live")


# -- compact steps ------------------------------------------------------------------------------------------------
def pack_maps(maps: dict[str, np.ndarray]) -> bytes:
    """The maps (each channels first) quantised to uint8 per channel with each channel's float32 range, in one
    compressed .npz."""
    arrays: dict[str, np.ndarray] = {}
    for name, m in maps.items():
        a = np.asarray(m, np.float32)
        flat = a.reshape(a.shape[0], -1) if a.ndim >= 2 else a.reshape(1, -1)
        lo, hi = flat.min(axis=1), flat.max(axis=1)
        scale = np.where(hi > lo, hi - lo, 1.0)
        q = np.round((flat - lo[:, None]) / scale[:, None] * 255.0).astype(np.uint8)
        arrays[f"{name}.q"] = q.reshape(a.shape)
        arrays[f"{name}.range"] = np.stack([lo, hi]).astype(np.float32)
    out = io.BytesIO()
    np.savez_compressed(out, **arrays)
    return out.getvalue()


def unpack_maps(blob: bytes) -> dict[str, np.ndarray]:
    """The maps of `pack_maps`, back as float16."""
    with np.load(io.BytesIO(blob)) as z:
        names = sorted({k.rsplit(".", 1)[0] for k in z.files})
        out = {}
        for name in names:
            q, (lo, hi) = z[f"{name}.q"], z[f"{name}.range"]
            flat = q.reshape(q.shape[0], -1) if q.ndim >= 2 else q.reshape(1, -1)
            values = lo[:, None] + flat.astype(np.float32) / 255.0 * (hi - lo)[:, None]
            out[name] = values.reshape(q.shape).astype(np.float16)
    return out


def step_row(record: StepRecord) -> tuple[int, str, bytes, bytes | None]:
    m = record.maps
    data = {"time": record.time, "position": list(record.position), "yaw": record.yaw,
            "T_world_camera": np.asarray(record.T_world_camera, np.float32).round(6).tolist(), "v": record.v,
            "omega": record.omega, "stop": record.stop, "stop_probability": record.stop_probability,
            "model": None if m is None else {"pose": np.asarray(m.pose, np.float32).tolist(), "v": m.v,
                                             "omega": m.omega, "stop_probability": m.stop_probability}}
    return record.step, json.dumps(data), record.camera_jpeg, pack_maps(m.maps) if m is not None else None


def step_of_row(row, where: str = "the record") -> StepRecord:
    """A kept step. Maps whose bytes were damaged in the record (SQLite's own checks cannot see inside a blob) come
    back as none, with `damaged` saying so, so the rest of the episode still reads."""
    d = json.loads(row["data"])
    model = d["model"]
    maps, damaged = None, None
    if model is not None and row["maps"] is not None:
        try:
            unpacked = unpack_maps(row["maps"])
        except Exception as e:  # noqa: BLE001 - zip, zlib and numpy each fail in their own way on damaged bytes
            damaged = (f"step {row['step']}'s maps are damaged in {where} and cannot be read ({type(e).__name__}: "
                       f"{e}); the episode's other steps read")
        else:
            maps = StepMaps(maps=unpacked, pose=np.array(model["pose"], np.float32), v=model["v"],
                            omega=model["omega"], stop_probability=model["stop_probability"])
    return StepRecord(step=int(row["step"]), time=d["time"], position=tuple(d["position"]), yaw=d["yaw"],
                      T_world_camera=np.array(d["T_world_camera"], np.float32), camera_jpeg=bytes(row["camera"]),
                      v=d["v"], omega=d["omega"], stop=d["stop"], maps=maps, stop_probability=d["stop_probability"],
                      damaged=damaged)


def task_json(task: Task, world_config: WorldConfig, typed: str | None = None) -> str:
    """The parsed instruction (the template flown) and the text typed, the demonstration path, and the world settings
    the world is drawn with (so that the episode reads back the same under a server, or `gsmn export`, started with
    other settings)."""
    return json.dumps({"instruction": asdict(task.instruction), "typed": typed,
                       "path": np.asarray(task.path).round(4).tolist(), "world": asdict(world_config)})


def _result_dict(result: EpisodeResult | None) -> str | None:
    return json.dumps(asdict(result)) if result is not None else None


# -- the record of episodes -----------------------------------------------------------------------------------------
class KeptStore(EpisodeStore):
    """The runner's episodes: those in memory (the last `limit` flown, and the live and queued ones) and every
    episode kept in the record, loaded on demand. Ids continue from the record's: never reused."""

    def __init__(self, db: Database, config: RunConfig, limit: int = 16, cache: int = 4):
        super().__init__(limit)
        self.db, self.config = db, config
        self._next_id = db.next_kept_id()
        self._loaded: OrderedDict[int, Episode] = OrderedDict()  # episodes read back from the record
        self._cache = cache

    def add(self, episode: Episode) -> None:
        """Accept an episode: its row goes into the record at once (queued), so its id is the record's from then on,
        never given again, and a server stopped before it flies keeps it as not flown. A record that cannot be
        written refuses it (RecordError, 503, naming the file)."""
        self.db.add_kept(kept_row(episode, self.config.world))
        super().add(episode)

    def get_in_memory(self, episode_id: int) -> Episode | None:
        return super().get(episode_id)

    def get(self, episode_id: int) -> Episode | None:
        episode = super().get(episode_id)
        if episode is not None:
            return episode
        with self._lock:
            if episode_id in self._loaded:
                self._loaded.move_to_end(episode_id)
                return self._loaded[episode_id]
        episode = self.load(episode_id)
        if episode is not None:
            with self._lock:
                self._loaded[episode_id] = episode
                while len(self._loaded) > self._cache:
                    self._loaded.popitem(last=False)
        return episode

    def load(self, episode_id: int) -> Episode | None:
        """The episode as the record holds it, or None when it was never kept or was removed."""
        row = self.db.kept(episode_id)
        if row is None:
            return None
        task = json.loads(row["task"])
        world_config = WorldConfig(**task["world"]) if "world" in task else self.config.world
        world = world_for_env(int(row["env_id"]), world_config)
        instruction = Instruction(**task["instruction"])
        episode = Episode(id=int(row["id"]), task=Task(world, instruction, np.array(task["path"], np.float64)),
                          policy=row["policy"], system=row["system"], checkpoint=row["checkpoint"],
                          horizon=int(row["horizon"]), status=row["status"], error=row["error"],
                          created=float(row["created"]), typed=task.get("typed"))
        if row["result"] is not None:
            episode.result = EpisodeResult(**json.loads(row["result"]))
        episode.steps.extend(step_of_row(r, str(self.db.path)) for r in self.db.kept_steps(episode_id))
        return episode

    def missing(self, episode_id: int) -> str:
        if episode_id >= self._next_id:
            return f"no episode {episode_id}: none has that id yet"
        return (f"episode {episode_id} is no longer kept: it was removed from the record (the retention limit "
                f"removes the oldest unpinned episodes), or it never flew")

    def forget(self, episode_id: int) -> None:
        """Drop a removed episode from memory too."""
        with self._lock:
            self._loaded.pop(episode_id, None)
            episode = self._episodes.get(episode_id)
            if episode is not None and not episode.live:
                del self._episodes[episode_id]

    def pinned(self, episode_id: int) -> bool:
        row = self.db.kept(episode_id)
        return bool(row["pinned"]) if row is not None else False


def kept_row(episode: Episode, world_config: WorldConfig) -> dict[str, Any]:
    """An episode's row as it is accepted or starts flying (its steps' count, bytes and pin are the record's)."""
    world = episode.task.world
    return {"id": episode.id, "created": episode.created, "status": episode.status, "env_id": world.env_id,
            "split": world.split, "instruction": episode.instruction,
            "task": task_json(episode.task, world_config, episode.typed), "policy": episode.policy,
            "system": episode.system, "checkpoint": episode.checkpoint, "horizon": episode.horizon,
            "error": episode.error}


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
           offset: int = 0) -> list:
    """Kept episodes' rows matching every filter given: `instruction` a case-insensitive substring; `outcome`
    success, failure (finished without success), cancelled, failed (an error, or the server stopped) or live;
    `since` / `until` unix times of the start."""
    where, params = [], []
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
    return db.search_kept(where, params, newest_first, limit, offset)


def row_summary(row) -> dict[str, Any]:
    """A kept row as the API's episode summary fields (app.api.episodes.EpisodeSummary)."""
    task = json.loads(row["task"])
    i = task["instruction"]
    return {"id": int(row["id"]), "status": row["status"], "env_id": int(row["env_id"]), "split": row["split"],
            "instruction": row["instruction"], "typed_instruction": task.get("typed"),
            "landmark": i["noun_phrase"], "side": i["side"],
            "goal_x": i["goal_x"], "goal_y": i["goal_y"], "policy": row["policy"], "system": row["system"],
            "checkpoint": row["checkpoint"], "steps": int(row["steps"]), "horizon": int(row["horizon"]),
            "steps_per_second": None, "result": json.loads(row["result"]) if row["result"] else None,
            "error": row["error"], "pinned": bool(row["pinned"]), "created": float(row["created"]),
            "bytes": int(row["bytes"]), "kept_steps": int(row["steps"])}
