"""The API does what its OpenAPI schema says: Schemathesis, with every check, over every operation of a real
`gsmn serve` (tiny preset, an untrained checkpoint, a 20-step horizon), with a fixed seed and 10 examples per
operation (its examples, coverage, fuzzing and stateful phases; about a minute here).

Every check but one: `use_after_free` expects a DELETE to remove what it names, and the API's DELETE cancels a
job (or an episode) whose record stays, by design (docs/dashboard.md). tests/schemathesis.toml says why the
positive-data check also takes a 422.
"""

from __future__ import annotations

import re
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest

CONFIG = Path(__file__).with_name("schemathesis.toml")

pytestmark = pytest.mark.server


@pytest.fixture(scope="module")
def api(tmp_path_factory, untrained_checkpoint, gsmn_serve):
    serve = gsmn_serve(tmp_path_factory.mktemp("contract") / "data", untrained_checkpoint, horizon=20)
    url = serve.api
    try:
        yield url, serve.proc, serve.lines
    finally:
        try:  # no job the generated requests started outlives the test
            for kind in ("runs", "evaluations"):
                for job in httpx.get(f"{url}/api/{kind}", timeout=30).json():
                    if job["status"] in ("queued", "running"):
                        httpx.delete(f"{url}/api/{kind}/{job['id']}", timeout=30)
            deadline = time.monotonic() + 30
            while time.monotonic() < deadline and any(
                    j["status"] in ("queued", "running") for kind in ("runs", "evaluations")
                    for j in httpx.get(f"{url}/api/{kind}", timeout=30).json()):
                time.sleep(0.5)
        except (httpx.HTTPError, ValueError, TypeError):
            pass
        serve.stop(timeout=20)


def test_the_api_keeps_to_its_openapi_schema(api, tmp_path):
    url, proc, lines = api
    st = Path(sys.executable).with_name("schemathesis")
    result = subprocess.run([str(st), "--config-file", str(CONFIG), "run", f"{url}/openapi.json", "--checks", "all",
                             "--exclude-checks", "use_after_free", "--seed", "1", "--max-examples", "10",
                             "--generation-database", "none", "--no-shrink", "--no-color"],
                            capture_output=True, text=True, timeout=600, cwd=tmp_path)  # its cache goes there
    report = result.stdout + result.stderr
    assert result.returncode == 0, report[-12000:]
    summary = re.search(r"API Operations:\s+Selected: (\d+)/(\d+)\s+Tested: (\d+)", report)
    assert summary and summary.group(1) == summary.group(2) == summary.group(3), report[-3000:]
    assert int(summary.group(3)) >= 24  # every operation of the API
    assert proc.poll() is None and httpx.get(f"{url}/api/health", timeout=30).status_code == 200
    assert "Traceback" not in "".join(lines), "".join(lines)[-6000:]
