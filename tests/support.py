"""Waiting for a condition, shared by every test that polls a server, a runner or a page; a shell command in a
private mount namespace, for the fault tests' small or read-only file systems; `gsmn serve` as the tests start it
(through conftest.py's `gsmn_serve`); and the untrained checkpoint built once per run (conftest.py's
`untrained_checkpoint`)."""

from __future__ import annotations

import fcntl
import hashlib
import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import httpx


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


# -- `gsmn serve`, as the tests start it --------------------------------------------------------------------------
def serve_command(*options: str, data_dir: Path | str | None = None, checkpoint: Path | str | None = None,
                  horizon: int | None = None, preset: str = "tiny", port: int | None = 0,
                  api_port: int | None = 0) -> list[str]:
    """The command line of `gsmn serve` (this interpreter's): the tiny preset on free ports by default; a port of
    None leaves that flag out (the server's default), `options` go last."""
    command = [sys.executable, "-m", "gsmn.cli", "serve", "--preset", preset]
    if checkpoint is not None:
        command += ["--checkpoint", str(checkpoint)]
    if port is not None:
        command += ["--port", str(port)]
    if api_port is not None:
        command += ["--api-port", str(api_port)]
    if horizon is not None:
        command += ["--task.horizon", str(horizon)]
    if data_dir is not None:
        command += ["--data-dir", str(data_dir)]
    return [*command, *options]


class Serve:
    """A `gsmn serve` process (`serve_command`'s arguments), restartable: `start` returns once it has printed its
    page and API addresses, with an httpx `client` on the API; `lines` is what it printed since. Tests start one
    through conftest.py's `gsmn_serve` fixture, which stops it at the latest when their module ends.

    `ignore_sigint` starts it as a shell's background job is (`gsmn serve &`: SIGINT ignored); `timeout` is how long
    it may take to serve."""

    def __init__(self, data_dir: Path | str | None = None, checkpoint: Path | str | None = None, *options: str,
                 horizon: int | None = None, preset: str = "tiny", port: int | None = 0, api_port: int | None = 0,
                 ignore_sigint: bool = False, timeout: float = 180.0, client_timeout: float = 60.0):
        self.data_dir = Path(data_dir) if data_dir is not None else None
        self.checkpoint = Path(checkpoint) if checkpoint is not None else None
        self.command = serve_command(*options, data_dir=data_dir, checkpoint=checkpoint, horizon=horizon,
                                     preset=preset, port=port, api_port=api_port)
        if ignore_sigint:
            self.command = ["sh", "-c", 'trap "" INT; exec "$@"', "sh", *self.command]
        self.timeout, self.client_timeout = timeout, client_timeout
        self.proc: subprocess.Popen | None = None
        self.client: httpx.Client | None = None
        self.lines: list[str] = []
        self.page: str | None = None  # http://127.0.0.1:PORT of the page, and of the API (without its /api)
        self.api: str | None = None

    def start(self) -> Serve:
        self.lines = lines = []
        self.page = self.api = None
        self.proc = proc = subprocess.Popen(self.command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                            env={**os.environ, "PYTHONUNBUFFERED": "1"})
        threading.Thread(target=lambda: lines.extend(iter(proc.stdout.readline, "")), daemon=True).start()
        deadline = time.monotonic() + self.timeout
        while time.monotonic() < deadline and proc.poll() is None:
            text = "".join(lines)
            if api := re.search(r"API: (http://127\.0\.0\.1:\d+)/api", text):
                page = re.search(r"gsmn dashboard: (http://127\.0\.0\.1:\d+)", text)
                self.page, self.api = (page.group(1) if page else None), api.group(1)
                self.client = httpx.Client(base_url=self.api, timeout=self.client_timeout)
                return self
            time.sleep(0.1)
        self.stop()
        raise AssertionError(f"gsmn serve did not start in {self.timeout:.0f} s:\n" + self.output())

    def stop(self, sig: int = signal.SIGINT, timeout: float = 30.0) -> None:
        """Send `sig` (SIGINT: Ctrl+C) and wait for it to end, killing it after `timeout` seconds."""
        if self.client is not None:
            self.client.close()
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(sig)
            try:
                self.proc.wait(timeout=timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()

    def kill(self) -> None:
        """SIGKILL: no chance to clean up."""
        self.stop(signal.SIGKILL)

    def output(self) -> str:
        return "".join(self.lines)


# -- one untrained checkpoint for the whole run ------------------------------------------------------------------
def untrained_checkpoint(tmp_path_factory) -> Path:
    """The untrained tiny GSMN of `app.live.fixtures.make_untrained_checkpoint` (seed 0, controller biased to fly),
    built once per test run in a folder every pytest-xdist worker of the run shares (the first to need it builds it
    under a file lock, the others wait for it). Its files are read-only: copy it to change it. conftest.py's
    `untrained_checkpoint` fixture hands it to tests and checks at the end that no test changed it."""
    root = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):  # each worker's basetemp is a folder of the run's
        root = root.parent
    folder = root / "untrained" / "gsmn"
    with open(root / "untrained.lock", "a") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            if not (folder.parent / "built").exists():
                from app.live.fixtures import make_untrained_checkpoint

                building = root / f"untrained.{os.getpid()}"
                shutil.rmtree(building, ignore_errors=True)
                make_untrained_checkpoint(building / "gsmn")
                for path in (building / "gsmn").rglob("*"):
                    if path.is_file():
                        path.chmod(0o444)
                (building / "built").write_text(tree_digest(building / "gsmn"))
                building.rename(folder.parent)
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)
    return folder


def tree_digest(folder: Path) -> str:
    """A digest of every file under `folder`: names and contents."""
    h = hashlib.sha256()
    for path in sorted(folder.rglob("*")):
        if path.is_file():
            h.update(str(path.relative_to(folder)).encode() + b"\0" + path.read_bytes())
    return h.hexdigest()


def compact_evaluation(env_ids, won: Callable[[int], bool], system: str = "gsmn") -> dict:
    """A compact evaluation as the Table 2 programme ships one (checkpoints/table2/*/evaluation.json), flown on
    `env_ids` of the tiny preset with `won(env_id)` deciding each outcome: a winner ends on its goal, a loser on
    its goal too but says it failed at control (the numbers, not the flight, are under test)."""
    from gsmn.config import preset
    from gsmn.task.rollout import task_for_env

    episodes = []
    for env_id in env_ids:
        task = task_for_env(env_id, preset("tiny"))
        i, lm = task.instruction, task.world.landmarks[task.instruction.landmark_index]
        episodes.append({"system": system, "env_id": env_id, "instruction": i.text, "landmark_index": i.landmark_index,
                         "noun_phrase": i.noun_phrase, "side": i.side, "ambiguous": i.ambiguous, "goal_x": i.goal_x,
                         "goal_y": i.goal_y, "landmark_x": lm.x, "landmark_y": lm.y, "start_x": task.world.start_x,
                         "start_y": task.world.start_y, "final_x": i.goal_x, "final_y": i.goal_y, "steps": 30,
                         "stopped": True, "success": won(env_id), "landmark_success": True, "goal_distance": 0.0,
                         "stage": None if won(env_id) else "control"})
    n = len(episodes)
    return {"system": system, "label": system, "recipe": {"preset": "tiny"}, "split": "dev", "env_ids": list(env_ids),
            "summary": {"count": n, "success": 100.0 * sum(e["success"] for e in episodes) / max(1, n)},
            "episodes": episodes}
