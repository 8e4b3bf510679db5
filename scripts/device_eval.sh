#!/usr/bin/env bash
# Run `gsmn eval` on a lent GPU machine (the workplace's `device` tool; 16 cores, no registries reachable).
#
#   bash scripts/device_eval.sh NAME EVAL-ARGS...      # e.g. NAME=shipped --system gsmn --checkpoint checkpoints/gsmn
#                                                      #      --split test --episodes 500 --workers 16
#
# The machine has Python 3.12 with torch and numpy but not MuJoCo or trimesh, and no libEGL: carry `.whl`
# (mujoco, mujoco-core, mujoco-studio, glfw, PyOpenGL and trimesh wheels for cp312, as pinned here) and `.gl`
# (the libglvnd/libEGL .deb files), both ignored through .git/info/exclude. Made here once with:
#   printf '/.whl/\n/.gl/\n' >> .git/info/exclude
#   python3 -m pip download --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
#       --platform manylinux_2_28_x86_64 --platform manylinux2014_x86_64 -d .whl \
#       mujoco==4.0.0 mujoco-core==4.0.0 mujoco-studio==4.0.0 glfw==2.11.0 PyOpenGL==3.1.10 trimesh==5.2.0
#   mkdir -p .gl /tmp/amd64/partial; o='-oAPT::Architecture=amd64 -oAPT::Architectures=amd64 -oDir::State::Lists=/tmp/amd64'
#   apt-get $o update; (cd .gl && apt-get $o download libvulkan1 libegl1 libglvnd0 libopengl0 libgl1 libglx0 libgles2)
# and run there with the tool's `run` (carry [".whl", ".gl"]). Each evaluation writes NAME.json (the `--json`
# file), NAME.progress.jsonl (one line per finished episode, so a run stopped at its time limit still returns what
# it did) and NAME.log into /tmp/device_eval, and after each one packs them into $OUT/NAME.tgz (a 500-episode test
# run with its failures' traces is about 8 MB packed); $OUT/machine.txt says what the machine was. The tool returns
# at most 8 files of 16 MiB each, so one call takes at most 7 evaluations. `--record-failures` among the EVAL-ARGS
# records every episode's trace (`--record`) into NAME_rec and then keeps only the failures' traces, which is all that
# scripts/attribution_counts.py and scripts/compare_evals.py read (500 traces are 36 MB). Several
# NAME EVAL-ARGS groups may follow one another, separated by `--next`; they run one after the other. Setup is
# skipped when the same machine runs the script again.
set -uo pipefail
OUT=${OUT:-/tmp/out}
W=/tmp/device_eval
mkdir -p "$OUT" "$W"
DEVICE=${DEVICE:-cuda} PY=python3 L=$W/machine.txt
source scripts/device_log.sh || exit 1  # the set-up and the machine's header, as the other device scripts
cp "$W/machine.txt" "$OUT/"

run_one() {
    local name=$1; shift
    local args=() record=""
    for a in "$@"; do
        if [ "$a" = "--record-failures" ]; then record="$W/${name}_rec"; args+=(--record "$record"); else args+=("$a"); fi
    done
    echo "== $name: gsmn eval ${args[*]}"
    local t0=$SECONDS
    python3 -m gsmn.cli eval "${args[@]}" --json "$W/$name.json" --progress "$W/$name.progress.jsonl" 2>&1 \
        | tr '\r' '\n' | grep -v 'episode/s\]$\|s/episode\]$' | tee "$W/$name.log"
    echo "== $name: $((SECONDS - t0)) s" | tee -a "$W/$name.log"
    if [ -n "$record" ] && [ -f "$W/$name.json" ]; then  # keep the failures' traces only
        python3 - "$W/$name.json" "$record" <<'PY'
import json, sys
from pathlib import Path
from gsmn.attribution import trace_path
for e in json.load(open(sys.argv[1]))["episodes"]:
    if e["success"]:
        trace_path(sys.argv[2], int(e["env_id"])).unlink(missing_ok=True)
PY
    fi
    local files=("$name".json "$name".progress.jsonl "$name".log)
    [ -n "$record" ] && files+=("${name}_rec")
    (cd "$W" && tar czf "$OUT/$name.tgz" --ignore-failed-read "${files[@]}")
}

args=()
for a in "$@"; do
    if [ "$a" = "--next" ]; then run_one "${args[@]}"; args=(); else args+=("$a"); fi
done
[ ${#args[@]} -gt 0 ] && run_one "${args[@]}"
exit 0
