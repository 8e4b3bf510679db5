# Sourced by scripts/device_log.sh (device_eval.sh, device_finetune.sh, device_baselines.sh) on a lent GPU machine:
# MuJoCo, trimesh and their wheels from the carried `.whl`, libEGL from the carried `.gl` (scripts/device_eval.sh
# says how both were made), once per machine; then the environment the project runs in there. Returns non-zero if
# the install fails.
if [ ! -d /tmp/site/mujoco ]; then
    for f in .gl/*.deb; do dpkg -x "$f" /; done
    ldconfig
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
        || return 1
fi
export PYTHONPATH=/tmp/site:$PWD MUJOCO_GL=egl PYTHONUNBUFFERED=1
vendor=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
[ -f "$vendor" ] && export __EGL_VENDOR_LIBRARY_FILENAMES=$vendor
return 0
