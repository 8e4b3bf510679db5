"""The process groups of the dashboard's jobs: launch (niced, in a new session, output in the job folder), watch (one
monitor thread), cancel (SIGTERM to the group, SIGKILL `KILL_AFTER` s later), relaunch a resumed job, re-attach after
a server restart, and settle a job whose process ended (finished, failed with the end of its output, or cancelled).

What a job's progress means is not this module's concern: the monitor hands each watched job to `poll(handle)`,
which reads its folder and calls `settle` once its process is gone (`app.jobs.manager.JobManager`). A job whose `poll`
fails (a progress line the record cannot hold, a full disk) is given up at once rather than polled again: its
process group is killed, its slot freed, and it is marked failed with the reason, as soon as the record can be
written (the monitor retries each round, so a full disk loses nothing once space is back).
"""

from __future__ import annotations

import logging
import os
import shutil
import signal
import subprocess
import threading
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from app.jobs.db import ACTIVE, CANCELLED, FAILED, FINISHED, QUEUED, RUNNING, Database, Evaluation, RecordError, Run
from app.live.commands import Conflict, RunnerError

log = logging.getLogger("gsmn.dashboard")

KILL_AFTER = 5.0  # s between SIGTERM and SIGKILL when cancelling
NICE = ["nice", "-n", "10"]  # jobs run below the live view's priority


@dataclass
class Handle:
    kind: str  # "evaluation" or "run"
    id: int
    folder: Path
    pid: int
    proc: subprocess.Popen | None  # None when re-attached after a restart (not our child)
    offset: int = 0  # bytes of the progress file read so far (evaluations)
    kill_at: float | None = None
    last: str = ""  # the last progress written to the database, to write only changes


def resumable(job: Evaluation | Run) -> bool:
    """What `JobManager.resume_evaluation` / `resume_run` accept: a cancelled or failed job with a command
    recorded (not an import)."""
    return job.status in (CANCELLED, FAILED) and bool(job.command)


def alive(h: Handle) -> tuple[bool, int | None]:
    """(running, exit code if known)."""
    if h.proc is not None:
        rc = h.proc.poll()
        return rc is None, rc
    return pid_runs(h.pid, str(h.folder)), None


def pid_runs(pid: int | None, needle: str) -> bool:
    """The process exists, is not a zombie, and its command line mentions `needle` (not a reused pid)."""
    if not pid:
        return False
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
        cmdline = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return False
    state = stat.rsplit(")", 1)[-1].split()[0]
    return state not in ("Z", "X") and needle in cmdline


def signal_group(pid: int, sig: int) -> None:
    try:
        os.killpg(pid, sig)  # the job's process group: started with start_new_session, so pgid == pid
    except (ProcessLookupError, PermissionError):
        pass


def tail(path: Path, lines: int = 12) -> str:
    try:
        data = path.read_bytes()[-20000:].decode(errors="replace")
    except OSError:
        return ""
    parts = [p.rstrip() for p in data.replace("\r", "\n").split("\n") if p.strip()]
    return "\n".join(parts[-lines:])


def exit_reason(rc: int | None) -> str:
    if rc is None:
        return "its process ended while the server was not watching"
    if rc < 0:
        try:
            return f"its process was killed by {signal.Signals(-rc).name}"
        except ValueError:
            return f"its process was killed by signal {-rc}"
    return f"its process exited with status {rc}"


class Supervisor:
    """The running jobs' processes, by (kind, id), and the monitor thread that watches them.

    `root` is the folder a re-attached job without a folder of its own is watched in; `notify(kind, id)` is called
    after each change. Callers hold `lock` around a check and the launch it allows (`check_limit`, then `launch`)."""

    def __init__(self, db: Database, root: Path, poll: Callable[[Handle], None], notify: Callable[[str, int], None],
                 poll_seconds: float = 0.5):
        self.db = db
        self.root = root
        self.poll = poll
        self.notify = notify
        self.poll_seconds = poll_seconds
        self.handles: dict[tuple[str, int], Handle] = {}
        # jobs given up on whose failure the record could not take yet (a full disk): written when it can
        self.unrecorded: dict[tuple[str, int], str] = {}
        self._told: set[tuple[str, int]] = set()
        self.lock = threading.RLock()
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._monitor, name="gsmn-jobs", daemon=True)

    def start(self) -> None:
        self.thread.start()

    def close(self) -> None:
        """Stop watching. Running jobs keep running; the next server re-attaches to them."""
        self._stop.set()
        self.thread.join(timeout=5)

    def _update(self, kind: str) -> Callable:
        return self.db.update_run if kind == "run" else self.db.update_evaluation

    def _row(self, kind: str, job_id: int) -> Evaluation | Run | None:
        return self.db.run(job_id) if kind == "run" else self.db.evaluation(job_id)

    # -- launching and cancelling --------------------------------------------------------------------------------
    def check_limit(self, kind: str, limit: int, flag: str) -> None:
        active = [h for h in self.handles.values() if h.kind == kind]
        if len(active) >= limit:
            ids = ", ".join(str(h.id) for h in active)
            what = "fine-tuning run" if kind == "run" else "evaluation"
            raise Conflict(f"{limit} {what}{'s' if limit > 1 else ''} already running ({kind} {ids}): this machine "
                           f"runs at most {limit} at a time so that the live view keeps its share of the cores. Wait "
                           f"for it, or cancel it (DELETE /api/{kind}s/{active[0].id}); `gsmn serve {flag}` "
                           f"raises the limit.")

    def launch(self, kind: str, job_id: int, folder: Path, command: list[str]) -> None:
        update = self._update(kind)
        if shutil.which("nice"):
            command = [*NICE, *command]
        out = (folder / "output.log").open("ab")
        try:
            proc = subprocess.Popen(command, stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                    start_new_session=True, cwd=str(Path(__file__).resolve().parents[1]),
                                    env={**os.environ, "PYTHONUNBUFFERED": "1"})
        except OSError as e:
            update(job_id, status=FAILED, error=f"could not start: {e}", finished=time.time())
            raise RunnerError(f"could not start the {kind}: {e}") from e
        finally:
            out.close()
        update(job_id, status=RUNNING, pid=proc.pid, command=command, started=time.time())
        self.handles[(kind, job_id)] = Handle(kind, job_id, folder, proc.pid, proc)
        self.notify(kind, job_id)

    def cancel(self, kind: str, row: Evaluation | Run) -> None:
        """Ask an active job to stop: SIGTERM now, SIGKILL later from the monitor; one never started is cancelled."""
        update = self._update(kind)
        with self.lock:
            h = self.handles.get((kind, row.id))
            if row.status not in ACTIVE:
                raise Conflict(f"{kind} {row.id} is {row.status}: nothing to cancel")
            update(row.id, cancel_requested=True)
            if h is None:  # never started
                update(row.id, status=CANCELLED, finished=time.time())
            elif h.kill_at is None:
                signal_group(h.pid, signal.SIGTERM)
                h.kill_at = time.monotonic() + KILL_AFTER
        self.notify(kind, row.id)

    def resumable_command(self, kind: str, row: Evaluation | Run) -> tuple[Path, list[str]]:
        """The folder and command (without `nice`) of a cancelled or failed job to launch again, or Conflict."""
        if row.status not in (CANCELLED, FAILED):
            raise Conflict(f"{kind} {row.id} is {row.status}: only a cancelled or failed one resumes")
        if not resumable(row) or not row.folder:
            raise Conflict(f"{kind} {row.id} has no command recorded (imported, or it never started): "
                           "nothing to resume")
        folder = Path(row.folder)
        if not folder.is_dir():
            raise Conflict(f"{kind} {row.id}'s folder {folder} is gone: start it again instead")
        command = list(row.command)
        if command[:len(NICE)] == NICE:
            command = command[len(NICE):]  # launch adds it again
        return folder, command

    def relaunch(self, kind: str, job_id: int, folder: Path, command: list[str]) -> None:
        self._update(kind)(job_id, status=QUEUED, cancel_requested=False, error=None, finished=None)
        self.launch(kind, job_id, folder, command)

    # -- restart -------------------------------------------------------------------------------------------------
    def recover(self) -> int:
        """Re-attach to the jobs a previous server left running; the monitor settles those whose process is gone."""
        attached = 0
        for kind, rows in (("evaluation", self.db.evaluations(ACTIVE)), ("run", self.db.runs(ACTIVE))):
            for row in rows:
                folder = Path(row.folder) if row.folder else self.root
                if row.status == QUEUED and not row.pid:
                    self._update(kind)(row.id, status=FAILED, error="the server stopped before it started",
                                       finished=time.time())
                    continue
                h = Handle(kind, row.id, folder, row.pid or 0, None)
                running = pid_runs(row.pid, str(folder))
                if row.cancel_requested and running:  # cancelled just before the restart: finish the job
                    signal_group(h.pid, signal.SIGTERM)
                    h.kill_at = time.monotonic() + KILL_AFTER
                self.handles[(kind, row.id)] = h
                attached += running
        return attached

    # -- the monitor ---------------------------------------------------------------------------------------------
    def _monitor(self) -> None:
        while not self._stop.wait(self.poll_seconds):
            for h in list(self.handles.values()):
                try:
                    with self.lock:
                        self.poll(h)
                except Exception as e:  # noqa: BLE001 - one bad job must not stop watching the others
                    log.error("watching %s %d failed; it is given up:\n%s", h.kind, h.id, traceback.format_exc())
                    with self.lock:
                        self.give_up(h, f"its results could not be recorded ({type(e).__name__}: {e})")
            if self.unrecorded:
                with self.lock:
                    self._record_given_up()

    def give_up(self, h: Handle, reason: str) -> None:
        """A job whose progress or results cannot be recorded: end its process group, free its slot, and mark it
        failed with the reason (as soon as the record takes it). Polling it again would only fail again."""
        signal_group(h.pid, signal.SIGKILL)
        self.handles.pop((h.kind, h.id), None)
        self.unrecorded[(h.kind, h.id)] = reason
        self._record_given_up()

    def _record_given_up(self) -> None:
        for (kind, job_id), reason in list(self.unrecorded.items()):
            try:
                row = self._row(kind, job_id)
                if row is not None and row.status in ACTIVE:
                    values = ({"status": CANCELLED, "error": "cancelled"} if row.cancel_requested
                              else {"status": FAILED, "error": reason})
                    self._update(kind)(job_id, finished=time.time(), **values)
            except RecordError as e:  # still cannot write: try again on the next round (said once)
                if (kind, job_id) not in self._told:
                    log.error("cannot mark %s %d failed yet (will retry): %s", kind, job_id, e)
                    self._told.add((kind, job_id))
                continue
            del self.unrecorded[(kind, job_id)]
            self._told.discard((kind, job_id))
            self.notify(kind, job_id)

    def escalate(self, h: Handle, running: bool) -> None:
        """SIGKILL a cancelled job that outlived its SIGTERM by KILL_AFTER (and again every second)."""
        if running and h.kill_at is not None and time.monotonic() >= h.kill_at:
            signal_group(h.pid, signal.SIGKILL)
            h.kill_at = time.monotonic() + 1.0

    def settle(self, h: Handle, rc: int | None, complete: bool, extra: dict) -> None:
        """Record how a job whose process ended came out, and stop watching it."""
        row = self._row(h.kind, h.id)
        if row.cancel_requested:
            values = {"status": CANCELLED, "error": "cancelled"}
        elif complete and (rc == 0 or rc is None):
            values = {"status": FINISHED, **extra}
        else:
            end = tail(h.folder / "output.log")
            error = exit_reason(rc) + (f"; its output ends:\n{end}" if end else "")
            values = {"status": FAILED, "error": error}
        signal_group(h.pid, signal.SIGKILL)  # leftovers of the group (e.g. worker processes), if any
        self._update(h.kind)(h.id, finished=time.time(), **values)
        del self.handles[(h.kind, h.id)]
        self.notify(h.kind, h.id)
