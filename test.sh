#!/usr/bin/env bash
# Test command: set everything up, then run the whole test suite (see README.md).
set -euo pipefail
cd "$(dirname "$0")"
GSMN_BROWSER=1 GSMN_EXTRAS=dev,ray bash scripts/setup.sh  # chromium for the browser test, Ray for tests/test_ray.py
# a test file per worker at a time (module fixtures stay whole), one worker per core up to four; -n 0: one process;
# `./test.sh -m fast`: the fast tier only (README.md, "The tests in tiers")
exec .venv/bin/python -m pytest -q -n auto --maxprocesses 4 --dist loadfile "$@"
