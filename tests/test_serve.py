"""`gsmn serve` (the README's main command) starts a real server that prints its URL and serves the page, and stops
on SIGINT even when started as a background job (which a shell starts with SIGINT ignored)."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import threading
import time
import urllib.request


def test_serve_prints_its_url_and_serves_the_page(tmp_path):
    proc = subprocess.Popen([sys.executable, "-m", "gsmn.cli", "serve", "--port", "8391", "--preset", "tiny",
                             "--data-dir", str(tmp_path)],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})
    try:
        deadline = time.monotonic() + 60
        url = None
        lines = []
        while time.monotonic() < deadline and url is None:
            line = proc.stdout.readline()
            if not line:
                break
            lines.append(line)
            m = re.search(r"(http://127\.0\.0\.1:\d+)", line)
            url = m.group(1) if m else None
        assert url, "".join(lines)
        with urllib.request.urlopen(url, timeout=10) as response:
            assert response.status == 200
            assert b"<html" in response.read().lower()
        assert proc.poll() is None, "server exited"
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def test_serve_started_with_sigint_ignored_still_stops_on_it(tmp_path):
    # what `gsmn serve &` in a script, or a CI step's background job, hands the server: a shell that ignores SIGINT
    serve = [sys.executable, "-m", "gsmn.cli", "serve", "--port", "0", "--api-port", "0", "--preset", "tiny",
             "--data-dir", str(tmp_path)]
    proc = subprocess.Popen(["sh", "-c", 'trap "" INT; exec "$@"', "sh", *serve], stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"})
    try:
        lines: list[str] = []
        threading.Thread(target=lambda: lines.extend(iter(proc.stdout.readline, "")), daemon=True).start()
        deadline = time.monotonic() + 120
        while not any("API: http" in line for line in lines):
            assert proc.poll() is None and time.monotonic() < deadline, "gsmn serve did not serve:\n" + "".join(lines)
            time.sleep(0.1)
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=30) == 0, "".join(lines)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
