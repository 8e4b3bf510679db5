#!/usr/bin/env bash
# Test command: set everything up, then run the whole test suite (see README.md).
set -euo pipefail
cd "$(dirname "$0")"
GSMN_BROWSER=1 GSMN_EXTRAS=dev,ray bash scripts/setup.sh  # chromium for the browser test, Ray for tests/test_ray.py
exec .venv/bin/python -m pytest -q "$@"
