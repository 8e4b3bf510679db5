"""The command line: every subcommand's help renders (config help strings may hold '%'), and `kill PID` stops a
command that runs worker processes without leaving them behind."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from gsmn.cli import build_parser

pytestmark = pytest.mark.unit

COMMANDS = [["world"], ["eval"], ["fit-avg-forward"], ["collect"], ["train", "supervised"], ["train", "dagger"],
            ["average"], ["keep-iterations"], ["attribute"], ["analyze", "table1"], ["analyze", "regions"],
            ["analyze", "stop-threshold"], ["analyze", "compare"], ["analyze", "dagger"], ["serve"]]


@pytest.mark.parametrize("command", COMMANDS, ids=lambda c: " ".join(c))
def test_help_renders(command, capsys):
    with pytest.raises(SystemExit) as exit_:
        build_parser().parse_args([*command, "--help"])
    assert exit_.value.code == 0
    out = capsys.readouterr().out
    assert out.startswith("usage: gsmn " + " ".join(command))
    if command[0] in ("eval", "collect", "train"):
        assert "--train.batch-size" in out
    if command[0] == "serve":  # registered by app.cli through the gsmn.commands entry point
        for flag in ("--checkpoint", "--host", "--port", "--api-port", "--env-id", "--data-dir", "--max-runs",
                     "--max-evaluations", "--preset", "--camera.shadows"):
            assert flag in out


@pytest.mark.slow
def test_the_gsmn_script_lists_serve():
    """`gsmn serve` reaches the dashboard through the entry-point group, not through an import in gsmn/
    (tests/test_structure.py checks that importing gsmn.cli leaves the app out)."""
    script = Path(sys.executable).with_name("gsmn")
    out = subprocess.run([str(script), "--help"], capture_output=True, text=True, check=True).stdout
    assert "serve" in out and "serve the dashboard" in out
    out = subprocess.run([str(script), "serve", "--help"], capture_output=True, text=True, check=True).stdout
    assert "--max-evaluations" in out and "--data-dir" in out


def _children(pid: int) -> list[int]:
    out = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid:
            out.append(int(stat.parent.name))
    return out


def _alive(pid: int) -> bool:
    try:
        state = (Path("/proc") / str(pid) / "stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


@pytest.mark.slow
@pytest.mark.parametrize("signals", [1, 2])
def test_sigterm_stops_collect_and_its_workers(tmp_path, signals):
    """SIGTERM to `gsmn collect` (2 workers, 40 episodes) after its first episode: it exits with 128 + 15 soon,
    without flying the rest, its worker processes are gone, and the episodes written are whole (they load). A second
    SIGTERM while it finishes the episodes in flight (a supervisor and a user both stopping it) ends the workers
    at once instead of leaving the command waiting on them forever."""
    store = tmp_path / "store"
    workers = []
    proc = subprocess.Popen([sys.executable, "-m", "gsmn.cli", "collect", "--preset", "tiny", "--out", str(store),
                             "--env-ids", "0:40", "--workers", "2", "--task.horizon", "20"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 240
        while not list(store.glob("*.npz")):
            assert proc.poll() is None and time.monotonic() < deadline, "collect ended or stalled before an episode"
            time.sleep(0.2)
        workers = [c for c in _children(proc.pid) if "spawn_main" in (Path("/proc") / str(c) / "cmdline").read_text()]
        assert len(workers) == 2
        proc.send_signal(signal.SIGTERM)
        if signals == 2:
            time.sleep(0.3)
            proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=60) == 128 + signal.SIGTERM
    finally:
        if proc.poll() is None:  # hung: leave no process of it behind
            for pid in [*workers, proc.pid]:
                if _alive(pid):
                    os.kill(pid, signal.SIGKILL)
            proc.wait()
    deadline = time.monotonic() + 10
    while any(_alive(w) for w in workers) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not any(_alive(w) for w in workers), "worker processes outlived the command"
    from gsmn.training.store import EpisodeStore

    written = EpisodeStore(store)
    assert 1 <= len(written) < 40
    for key in written.keys():
        assert len(written.read(key).images) > 0
