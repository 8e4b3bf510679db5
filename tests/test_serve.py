"""`gsmn serve` (the README's main command) starts a real server that prints its URL and serves the page, and stops
on SIGINT even when started as a background job (which a shell starts with SIGINT ignored)."""

from __future__ import annotations

import signal
import urllib.request

import pytest

pytestmark = pytest.mark.server


def test_serve_prints_its_url_and_serves_the_page(tmp_path, gsmn_serve):
    serve = gsmn_serve(tmp_path, port=8391, api_port=None, timeout=60)
    try:
        assert serve.page, serve.output()
        with urllib.request.urlopen(serve.page, timeout=10) as response:
            assert response.status == 200
            assert b"<html" in response.read().lower()
        assert serve.proc.poll() is None, "server exited"
    finally:
        serve.stop(timeout=10)


def test_serve_started_with_sigint_ignored_still_stops_on_it(tmp_path, gsmn_serve):
    # what `gsmn serve &` in a script, or a CI step's background job, hands the server: a shell that ignores SIGINT
    serve = gsmn_serve(tmp_path, ignore_sigint=True, timeout=120)
    try:
        serve.proc.send_signal(signal.SIGINT)
        assert serve.proc.wait(timeout=30) == 0, serve.output()
    finally:
        serve.stop(signal.SIGKILL)
