#!/usr/bin/env bash
# Main command: set everything up, then run the main job (see README.md).
set -euo pipefail
cd "$(dirname "$0")"
bash scripts/setup.sh
exec .venv/bin/gsmn serve "$@"
