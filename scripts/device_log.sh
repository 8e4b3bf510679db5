# Sourced by scripts/device_eval.sh, device_finetune.sh and device_baselines.sh after they set DEVICE, PY and L (the call's
# log): the lent machine's set-up (scripts/device_setup.sh; skipped with DEVICE=cpu, for trying a script here), the
# environment, `stamp MESSAGE` (a timed line into the log) and what the machine is, at the top of the log.
# Returns non-zero if the set-up fails.
if [ "$DEVICE" != cpu ]; then
    source scripts/device_setup.sh || return 1
fi
export MUJOCO_GL=egl PYTHONUNBUFFERED=1
t0=$SECONDS
stamp() { echo "== $(date -u +%H:%M:%S) +$((SECONDS - t0)) s: $*" | tee -a "$L"; }
{ date -u; nvidia-smi -L 2>/dev/null; lscpu | grep 'Model name'; nproc
  $PY -c "import torch, mujoco, trimesh; print('torch', torch.__version__, 'mujoco', mujoco.__version__, 'trimesh', trimesh.__version__)"
} 2>&1 | tee -a "$L"
return 0
