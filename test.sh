#!/usr/bin/env bash
# Test command: set everything up, then run the whole test suite (see README.md).
set -euo pipefail
cd "$(dirname "$0")"
bash scripts/setup.sh
exec .venv/bin/python -m pytest -q "$@"
