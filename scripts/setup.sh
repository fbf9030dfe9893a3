#!/usr/bin/env bash
# One-shot setup: Debian packages (Mesa for offscreen MuJoCo, socat, tmux for the terminal tests; gcc and
# the kernel headers: evdev, the gamepad's library, ships as source only), .venv/, hilstack + deps.
# Idempotent: re-running only installs what is missing.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"

debs=(libegl1 libgl1-mesa-dri libosmesa6 socat tmux gcc linux-libc-dev)
missing=()
for d in "${debs[@]}"; do dpkg -s "$d" >/dev/null 2>&1 || missing+=("$d"); done
if [ "${#missing[@]}" -gt 0 ]; then
  if [ "$(id -u)" = 0 ]; then
    echo "[setup] apt-get install ${missing[*]}"
    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${missing[@]}" >/dev/null
  else
    echo "[setup] warning: missing Debian packages ${missing[*]} (run as root or: sudo apt-get install ${missing[*]})" >&2
  fi
fi

py="${PYTHON:-python3}"
[ -x .venv/bin/python ] || "$py" -m venv .venv
.venv/bin/python -m pip install -q --upgrade pip
# torch is pinned for these machines (a local CPU wheel); the package itself only asks for a range.
.venv/bin/python -m pip install -q "torch==${HIL_TORCH_VERSION:-2.13.0}"
# dev = test tools + the extras the suite exercises (bench: pytorch-mppi, mocap: natnet, fuzz: atheris,
# camera: opencv, calib: mujoco[sysid], cluster: ray, speed: numba, operator: textual and evdev)
.venv/bin/python -m pip install -q -e ".[dev]"
# the Sawyer's MJCF ships in metaworld's wheel; its own pins would drag MuJoCo down to 3.x,
# so it is installed without dependencies and used for its assets only (sim_backends/sawyer)
.venv/bin/python -m pip install -q --no-deps "metaworld==3.1.1"
echo "[setup] done: $(.venv/bin/hil --version 2>/dev/null || echo 'hil installed at .venv/bin/hil')"
