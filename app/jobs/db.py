"""The dashboard's record of evaluations, their episodes and fine-tuning runs: one SQLite file (standard library
sqlite3, WAL mode) in the data folder, `gsmn.sqlite`, beside one folder per job with its recordings.

Rows are read back as typed records (`Evaluation`, `EpisodeRow`, `Run`); JSON columns are decoded here, so no
caller sees raw SQL rows. One connection is shared by the server's threads behind a lock: every write is a single
statement, so a server killed at any moment leaves either the old row or the new one. Status values:
queued, running, finished, failed, cancelled.

A file that is not a whole record (empty, not SQLite, or failing SQLite's quick check) is refused when opened,
naming it, rather than started afresh over the job folders beside it; any SQLite error later (a full disk, a
damaged page) is a `RecordError` that names the file, and the API answers it with 503.
"""

from __future__ import annotations

import contextlib
import json
import sqlite3
import threading
import time
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

from app.jobs.schema import SCHEMA, SCHEMA_VERSION
from app.live.commands import RunnerError

QUEUED, RUNNING, FINISHED, FAILED, CANCELLED = "queued", "running", "finished", "failed", "cancelled"
ACTIVE = (QUEUED, RUNNING)
STATUSES = (QUEUED, RUNNING, FINISHED, FAILED, CANCELLED)


class RecordError(RunnerError):
    """The record cannot be read or written (a full disk, a damaged file); the message names the file."""

    status = 503


@dataclass(frozen=True)
class Evaluation:
    id: int
    status: str
    created: float
    started: float | None
    finished: float | None
    system: str
    checkpoint: str | None
    env_ids: list[int]
    label: str
    baseline_id: int | None
    run_id: int | None
    source: str
    folder: str | None
    pid: int | None
    command: list[str] | None
    done: int
    total: int
    summary: dict | None
    error: str | None
    cancel_requested: bool
    mirror_ensemble: bool = False  # flown as a test-time mirror ensemble (schema 2)
    intervention: str | None = None  # flown with a map intervention, e.g. "truth-goal" (schema 6)


@dataclass(frozen=True)
class EpisodeRow:
    evaluation_id: int
    position: int
    env_id: int
    instruction: str
    landmark: str
    side: str
    ambiguous: bool
    success: bool
    landmark_success: bool
    goal_distance: float
    steps: int
    stopped: bool
    final_x: float
    final_y: float
    stage: str | None
    attribution: dict | None
    recording: str | None
    region_steps: list[int] | None = None  # the steps at which a STOP would have succeeded (schema 3)
    region_stop_p: float | None = None  # the model's highest P(stop) at those steps (schema 3)


@dataclass(frozen=True)
class Run:
    id: int
    status: str
    created: float
    started: float | None
    finished: float | None
    settings: dict
    env_ids: list[int] | None
    source_evaluation_id: int | None
    init_checkpoint: str
    folder: str
    pid: int | None
    command: list[str] | None
    progress: dict | None
    metrics: list[dict]
    checkpoint: str | None
    error: str | None
    cancel_requested: bool


_JSON = {"env_ids", "command", "summary", "attribution", "settings", "progress", "metrics", "region_steps"}
_BOOL = {"ambiguous", "success", "landmark_success", "stopped", "cancel_requested", "mirror_ensemble"}


def _decode(cls: type, row: sqlite3.Row) -> Any:
    values = {}
    for f in fields(cls):
        v = row[f.name]
        if f.name in _JSON and v is not None:
            v = json.loads(v)
        elif f.name in _BOOL:
            v = bool(v)
        values[f.name] = v
    if cls is Run and values["metrics"] is None:
        values["metrics"] = []
    return cls(**values)


def _encode(name: str, value: Any) -> Any:
    if name in _JSON and value is not None:
        return json.dumps(value)
    if name in _BOOL:
        return int(bool(value))
    return value


class Database:
    """The record in `path` (created with its schema when missing)."""

    def __init__(self, path: Path | str):
        self.path = Path(path)
        self._lock = threading.Lock()
        unwritable = (f"the folder {self.path.parent} must be writable with room to spare: free space, make it "
                      "writable, or give another --data-dir")
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise RecordError(f"cannot make the folder of the record {self.path} ({e.strerror or e}): "
                              f"{unwritable}") from e
        keep = ("Nothing was changed: move it away (a new record then starts; the job folders beside it are kept) "
                "or give another --data-dir.")
        if self.path.is_file() and self.path.stat().st_size == 0:
            raise RecordError(f"{self.path} is empty (0 bytes), not a dashboard record: it was cut short or "
                              f"overwritten. {keep}")
        if not self.path.exists():  # a new record: a failure is the folder's, not a file's to move away
            keep = unwritable
        try:
            self._db = sqlite3.connect(self.path, check_same_thread=False, isolation_level=None, timeout=10)
            self._db.row_factory = sqlite3.Row
            check = self._db.execute("PRAGMA quick_check").fetchone()[0]
            if check != "ok":
                self._db.close()
                raise RecordError(f"{self.path} is damaged (SQLite's quick check: {check}). {keep}")
            version = self._db.execute("PRAGMA user_version").fetchone()[0]
        except sqlite3.Error as e:
            if keep is unwritable:
                raise RecordError(f"cannot create the record {self.path} ({e}): {unwritable}") from e
            raise RecordError(f"{self.path} is not a readable dashboard record ({e}). {keep}") from e
        try:
            self._upgrade(version)
        except sqlite3.Error as e:  # a full disk or a read-only file, found by the first write
            raise RecordError(f"cannot write the record {self.path} ({e}): {unwritable}") from e

    def _upgrade(self, version: int) -> None:
        """Bring the record to SCHEMA_VERSION (the first writes of a start)."""
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.execute("PRAGMA synchronous=NORMAL")
        if version > SCHEMA_VERSION:
            raise RuntimeError(f"{self.path} was written by a newer version (schema {version}); use another "
                               "--data-dir")
        if version == 1:  # the one column version 2 added; every row recorded before it stays as it was
            self._db.execute("ALTER TABLE evaluations ADD COLUMN mirror_ensemble INTEGER NOT NULL DEFAULT 0")
        if 1 <= version <= 2:  # the two columns version 3 added, NULL (not known) in the rows recorded before
            self._db.execute("ALTER TABLE episodes ADD COLUMN region_steps TEXT")
            self._db.execute("ALTER TABLE episodes ADD COLUMN region_stop_p REAL")
        if 1 <= version <= 5 and "intervention" not in {
                row[1] for row in self._db.execute("PRAGMA table_info(evaluations)")}:
            # the column version 6 added: NULL, no intervention, in the rows recorded before
            self._db.execute("ALTER TABLE evaluations ADD COLUMN intervention TEXT")
        self._db.executescript(SCHEMA)
        self._db.execute(f"PRAGMA user_version={SCHEMA_VERSION}")

    def close(self) -> None:
        with self._lock:
            self._db.close()

    def _execute(self, sql: str, params: tuple | dict = ()) -> sqlite3.Cursor:
        with self._lock, self._errors("write"):
            return self._db.execute(sql, params)

    def _all(self, sql: str, params: tuple | dict = ()) -> list[sqlite3.Row]:
        with self._lock, self._errors("read"):
            return self._db.execute(sql, params).fetchall()

    @contextlib.contextmanager
    def _errors(self, what: str):
        try:
            yield
        except sqlite3.Error as e:
            raise RecordError(f"cannot {what} the record {self.path}: {e}") from e

    def _insert(self, table: str, values: dict[str, Any], replace: bool = False) -> int:
        names = list(values)
        sql = (f"INSERT {'OR REPLACE ' if replace else ''}INTO {table} ({', '.join(names)}) "
               f"VALUES ({', '.join('?' for _ in names)})")
        return int(self._execute(sql, tuple(_encode(k, values[k]) for k in names)).lastrowid)

    def _update(self, table: str, row_id: int, values: dict[str, Any]) -> None:
        allowed = {f.name for f in fields(Evaluation if table == "evaluations" else Run)} - {"id"}
        unknown = set(values) - allowed
        if unknown:
            raise ValueError(f"no such {table} column(s): {sorted(unknown)}")
        sets = ", ".join(f"{k} = ?" for k in values)
        self._execute(f"UPDATE {table} SET {sets} WHERE id = ?",
                      (*(_encode(k, v) for k, v in values.items()), row_id))

    # -- evaluations -------------------------------------------------------------------------------------------
    def add_evaluation(self, *, system: str, checkpoint: str | None, env_ids: list[int], label: str,
                       source: str = "dashboard", status: str = QUEUED, baseline_id: int | None = None,
                       run_id: int | None = None, mirror_ensemble: bool = False,
                       intervention: str | None = None) -> int:
        return self._insert("evaluations", {
            "status": status, "created": time.time(), "system": system, "checkpoint": checkpoint,
            "env_ids": [int(e) for e in env_ids], "label": label, "baseline_id": baseline_id, "run_id": run_id,
            "source": source, "total": len(env_ids), "mirror_ensemble": mirror_ensemble,
            "intervention": intervention})

    def update_evaluation(self, evaluation_id: int, **values: Any) -> None:
        self._update("evaluations", evaluation_id, values)

    def evaluation(self, evaluation_id: int) -> Evaluation | None:
        rows = self._all("SELECT * FROM evaluations WHERE id = ?", (evaluation_id,))
        return _decode(Evaluation, rows[0]) if rows else None

    def evaluations(self, statuses: tuple[str, ...] | None = None) -> list[Evaluation]:
        if statuses:
            rows = self._all(f"SELECT * FROM evaluations WHERE status IN ({','.join('?' * len(statuses))}) "
                             "ORDER BY id", statuses)
        else:
            rows = self._all("SELECT * FROM evaluations ORDER BY id")
        return [_decode(Evaluation, r) for r in rows]

    # -- episodes ----------------------------------------------------------------------------------------------
    def add_episode(self, episode: EpisodeRow) -> None:
        """Insert or replace (a monitor re-reading a progress file after a restart writes the same rows)."""
        self._insert("episodes", {f.name: getattr(episode, f.name) for f in fields(EpisodeRow)}, replace=True)

    def episodes(self, evaluation_id: int, failed_only: bool = False, landmark: str | None = None,
                 side: str | None = None, ambiguous: bool | None = None, stage: str | None = None,
                 entered_region: bool | None = None) -> list[EpisodeRow]:
        """The episodes of an evaluation in the order flown, filtered (`entered_region`: whether the drone was
        inside the success region at some step; episodes recorded without that are left out of either choice)."""
        where, params = ["evaluation_id = ?"], [evaluation_id]
        if failed_only:
            where.append("success = 0")
        if landmark is not None:
            where.append("landmark = ?")
            params.append(landmark)
        if side is not None:
            where.append("side = ?")
            params.append(side)
        if ambiguous is not None:
            where.append("ambiguous = ?")
            params.append(int(ambiguous))
        if stage is not None:
            where.append("stage = ?")
            params.append(stage)
        if entered_region is not None:
            where.append("region_steps IS NOT NULL AND region_steps " + ("!=" if entered_region else "=") + " '[]'")
        rows = self._all(f"SELECT * FROM episodes WHERE {' AND '.join(where)} ORDER BY position", tuple(params))
        return [_decode(EpisodeRow, r) for r in rows]

    def episode(self, evaluation_id: int, env_id: int) -> EpisodeRow | None:
        rows = self._all("SELECT * FROM episodes WHERE evaluation_id = ? AND env_id = ?", (evaluation_id, env_id))
        return _decode(EpisodeRow, rows[0]) if rows else None

    def stage_counts(self, evaluation_id: int) -> dict[str, int]:
        """Failures per attribution stage; failures without maps count under "unattributed"."""
        rows = self._all("SELECT coalesce(stage, 'unattributed') AS s, count(*) AS n FROM episodes "
                         "WHERE evaluation_id = ? AND success = 0 GROUP BY s", (evaluation_id,))
        return {r["s"]: r["n"] for r in rows}

    def region_counts(self, evaluation_id: int) -> dict[str, int]:
        """Failures that flew through the success region without a STOP there ("entered"), that never entered it
        ("never"), and that were recorded without the region ("unknown"; omitted when none)."""
        rows = self._all("SELECT CASE WHEN region_steps IS NULL THEN 'unknown' WHEN region_steps = '[]' THEN 'never' "
                         "ELSE 'entered' END AS r, count(*) AS n FROM episodes WHERE evaluation_id = ? AND success = 0 "
                         "GROUP BY r", (evaluation_id,))
        return {"entered": 0, "never": 0, **{r["r"]: r["n"] for r in rows}}

    def add_whole_evaluation(self, values: dict[str, Any], episodes: list[EpisodeRow], facts: dict[int, dict]) -> int:
        """A finished evaluation with its episodes and their facts in one transaction (an imported file): a server
        killed meanwhile leaves the record as before it. The episodes' evaluation_id is this one's."""
        names = list(values)
        columns = [f.name for f in fields(EpisodeRow)]
        with self._lock, self._errors("write"):
            self._db.execute("BEGIN")
            try:
                eid = int(self._db.execute(f"INSERT INTO evaluations ({', '.join(names)}) VALUES "
                                           f"({', '.join('?' for _ in names)})",
                                           tuple(_encode(k, values[k]) for k in names)).lastrowid)
                self._db.executemany(f"INSERT INTO episodes ({', '.join(columns)}) VALUES "
                                     f"({', '.join('?' for _ in columns)})",
                                     [tuple(_encode(c, eid if c == "evaluation_id" else getattr(e, c)) for c in columns)
                                      for e in episodes])
                self._db.executemany("INSERT INTO episode_facts (evaluation_id, env_id, facts) VALUES (?, ?, ?)",
                                     [(eid, int(e), json.dumps(f)) for e, f in facts.items()])
                self._db.execute("COMMIT")
            except BaseException:
                self._rollback()
                raise
        return eid

    def set_facts(self, evaluation_id: int, facts: dict[int, dict]) -> None:
        """Keep episodes' facts (gsmn.analysis.slices.episode_facts), all or none in one transaction."""
        with self._lock, self._errors("write"):
            self._db.execute("BEGIN")
            try:
                self._db.executemany("INSERT OR REPLACE INTO episode_facts (evaluation_id, env_id, facts) VALUES "
                                     "(?, ?, ?)", [(evaluation_id, int(e), json.dumps(f)) for e, f in facts.items()])
                self._db.execute("COMMIT")
            except BaseException:
                self._rollback()
                raise

    def facts(self, evaluation_id: int) -> dict[int, dict]:
        """The facts kept for an evaluation's episodes, by env id; a value that does not decode is left out (it is
        computed again)."""
        out = {}
        for r in self._all("SELECT env_id, facts FROM episode_facts WHERE evaluation_id = ?", (evaluation_id,)):
            with contextlib.suppress(ValueError, TypeError):
                value = json.loads(r["facts"])
                if isinstance(value, dict):
                    out[int(r["env_id"])] = value
        return out

    # -- runs --------------------------------------------------------------------------------------------------
    def add_run(self, *, settings: dict, env_ids: list[int] | None, init_checkpoint: str, folder: str,
                source_evaluation_id: int | None = None, status: str = QUEUED) -> int:
        return self._insert("runs", {
            "status": status, "created": time.time(), "settings": settings,
            "env_ids": [int(e) for e in env_ids] if env_ids is not None else None,
            "source_evaluation_id": source_evaluation_id, "init_checkpoint": init_checkpoint, "folder": folder})

    def update_run(self, run_id: int, **values: Any) -> None:
        self._update("runs", run_id, values)

    def run(self, run_id: int) -> Run | None:
        rows = self._all("SELECT * FROM runs WHERE id = ?", (run_id,))
        return _decode(Run, rows[0]) if rows else None

    def runs(self, statuses: tuple[str, ...] | None = None) -> list[Run]:
        if statuses:
            rows = self._all(f"SELECT * FROM runs WHERE status IN ({','.join('?' * len(statuses))}) ORDER BY id",
                             statuses)
        else:
            rows = self._all("SELECT * FROM runs ORDER BY id")
        return [_decode(Run, r) for r in rows]

    # -- kept episodes (app.jobs.kept) ------------------------------------------------------------------------------
    def next_kept_id(self) -> int:
        """The first episode id never given: ids are not reused after a removal (AUTOINCREMENT's sequence)."""
        rows = self._all("SELECT seq FROM sqlite_sequence WHERE name = 'kept_episodes'")
        return int(rows[0]["seq"]) + 1 if rows else 1

    def add_kept(self, values: dict[str, Any]) -> None:
        """Insert a kept episode's row, or update the columns given of the row with its id (`values` by column; JSON
        columns already encoded): an episode's row is written when it is accepted and again when it starts flying,
        and the second keeps what the row has gathered since (its steps' count and bytes, its pin)."""
        names = list(values)
        sql = (f"INSERT INTO kept_episodes ({', '.join(names)}) VALUES ({', '.join('?' for _ in names)}) "
               f"ON CONFLICT(id) DO UPDATE SET {', '.join(f'{k} = excluded.{k}' for k in names if k != 'id')}")
        self._execute(sql, tuple(_encode(k, values[k]) for k in names))

    def update_kept(self, episode_id: int, **values: Any) -> None:
        sets = ", ".join(f"{k} = ?" for k in values)
        self._execute(f"UPDATE kept_episodes SET {sets} WHERE id = ?", (*values.values(), episode_id))

    def add_kept_steps(self, episode_id: int, steps: list[tuple[int, str, bytes, bytes | None]], size: int) -> None:
        """Steps (step, data JSON, camera JPEG, packed maps) of one episode, and their size added to its bytes, in
        one transaction: a server killed meanwhile leaves the record as before them."""
        with self._lock, self._errors("write"):
            self._db.execute("BEGIN")
            try:
                self._db.executemany("INSERT OR REPLACE INTO kept_steps (episode_id, step, data, camera, maps) "
                                     "VALUES (?, ?, ?, ?, ?)", [(episode_id, *s) for s in steps])
                self._db.execute("UPDATE kept_episodes SET steps = (SELECT count(*) FROM kept_steps WHERE "
                                 "episode_id = ?), bytes = bytes + ? WHERE id = ?", (episode_id, size, episode_id))
                self._db.execute("COMMIT")
            except BaseException:
                self._rollback()
                raise

    def _rollback(self) -> None:
        """Roll back the transaction in progress, where SQLite has not done so itself (it rolls back on a full disk,
        and a second ROLLBACK would hide the real error behind "no transaction is active")."""
        if self._db.in_transaction:
            self._db.execute("ROLLBACK")

    def kept(self, episode_id: int) -> sqlite3.Row | None:
        rows = self._all("SELECT * FROM kept_episodes WHERE id = ?", (episode_id,))
        return rows[0] if rows else None

    def kept_steps(self, episode_id: int) -> list[sqlite3.Row]:
        return self._all("SELECT * FROM kept_steps WHERE episode_id = ? ORDER BY step", (episode_id,))

    def search_kept(self, where: list[str], params: list[Any], newest_first: bool, limit: int,
                    offset: int, columns: str = "*") -> list[sqlite3.Row]:
        sql = f"SELECT {columns} FROM kept_episodes" + (f" WHERE {' AND '.join(where)}" if where else "")
        sql += f" ORDER BY id {'DESC' if newest_first else 'ASC'} LIMIT ? OFFSET ?"
        return self._all(sql, (*params, limit, offset))

    def kept_counts(self) -> dict[str, int]:
        row = self._all("SELECT count(*) AS n, coalesce(sum(pinned), 0) AS p FROM kept_episodes")[0]
        return {"episodes": int(row["n"]), "pinned": int(row["p"])}

    def file_bytes(self) -> int:
        """The record's files on disk: the database and its write-ahead log and shared-memory files."""
        total = 0
        for suffix in ("", "-wal", "-shm"):
            try:
                total += (self.path.parent / (self.path.name + suffix)).stat().st_size
            except OSError:
                pass
        return total

    def kept_bytes(self) -> int:
        return int(self._all("SELECT coalesce(sum(bytes), 0) AS b FROM kept_episodes")[0]["b"])

    def remove_kept(self, episode_id: int) -> None:
        with self._lock, self._errors("write"):
            self._db.execute("BEGIN")
            try:
                self._db.execute("DELETE FROM kept_steps WHERE episode_id = ?", (episode_id,))
                self._db.execute("DELETE FROM kept_episodes WHERE id = ?", (episode_id,))
                self._db.execute("COMMIT")
            except BaseException:
                self._rollback()
                raise
