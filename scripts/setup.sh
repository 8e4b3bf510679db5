#!/usr/bin/env bash
# Idempotent set-up on a fresh machine: Debian packages for headless rendering, a virtual environment
# in .venv, torch==2.13.0 first (the local CPU wheel; any other torch spec pulls GBs of CUDA packages),
# then the project with its dev extras (GSMN_EXTRAS=dev,ray adds Ray, as ./test.sh asks). Re-running it only
# re-installs when pyproject.toml or the extras changed.
set -euo pipefail
cd "$(dirname "$0")/.."

need_apt=()
ldconfig -p 2>/dev/null | grep -q 'libEGL.so.1' || need_apt+=(libegl1)
ldconfig -p 2>/dev/null | grep -q 'libGL.so.1' || need_apt+=(libgl1)
[ -e /usr/lib/x86_64-linux-gnu/dri/swrast_dri.so ] || [ -e /usr/lib/x86_64-linux-gnu/dri/llvmpipe_dri.so ] \
  || ls /usr/lib/*/libgallium* >/dev/null 2>&1 || need_apt+=(libgl1-mesa-dri)
if [ "${GSMN_BROWSER:-0}" = "1" ] && ! command -v chromium >/dev/null; then need_apt+=(chromium); fi
if [ ${#need_apt[@]} -gt 0 ]; then
  echo "setup: installing Debian packages: ${need_apt[*]}"
  apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${need_apt[@]}" >/dev/null
fi

PY=${PYTHON:-python3}
[ -x .venv/bin/python ] || "$PY" -m venv .venv
stamp=.venv/.gsmn-installed
extras=${GSMN_EXTRAS:-dev}
want=$( (cat pyproject.toml; echo "extras=$extras") | sha256sum | cut -d' ' -f1)
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ]; then
  .venv/bin/pip install -q --upgrade pip
  .venv/bin/python -c 'import torch' 2>/dev/null || .venv/bin/pip install -q torch==2.13.0
  .venv/bin/pip install -q -e ".[$extras]"
  echo "$want" > "$stamp"
fi
