#!/usr/bin/env bash
# Test command: set everything up, then run the whole test suite (see README.md).
set -euo pipefail
cd "$(dirname "$0")"
GSMN_BROWSER=1 bash scripts/setup.sh  # chromium for the browser end-to-end test
exec .venv/bin/python -m pytest -q "$@"
