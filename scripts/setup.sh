#!/usr/bin/env bash
# One-shot, idempotent set-up for a fresh Debian machine: system packages for headless GL,
# the virtual environment at .venv, the Python dependencies and the C++ extension.
set -euo pipefail
cd "$(dirname "$0")/.."

APT_PACKAGES="libegl1 libegl-mesa0 libgl1-mesa-dri libgl1 libgbm1 libopengl0 libosmesa6 xvfb xauth ffmpeg"
missing=""
for p in $APT_PACKAGES; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing="$missing $p"
done
if [ -n "$missing" ]; then
  echo "[setup] apt-get install$missing"
  SUDO=""; [ "$(id -u)" = 0 ] || SUDO="sudo"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends $missing >/dev/null
fi

# pip, without the index's "Location ... is ignored" noise; its real output (and errors) still shows.
pip_quiet() {
  local log; log=$(mktemp)
  if ! .venv/bin/python -m pip "$@" >"$log" 2>&1; then grep -v "is ignored: it is neither" "$log"; rm -f "$log"; return 1; fi
  grep -v -e "is ignored: it is neither" -e "^ *$" "$log" || true
  rm -f "$log"
}

PY=${PYTHON:-python3}
[ -x .venv/bin/python ] || "$PY" -m venv .venv
stamp=.venv/.requirements.sha
want=$(cat requirements.txt | sha256sum | cut -d' ' -f1)
if [ "$(cat "$stamp" 2>/dev/null)" != "$want" ]; then
  echo "[setup] installing Python dependencies into .venv"
  pip_quiet install -q --upgrade pip setuptools wheel ninja
  # torch first and pinned, so nothing later pulls a multi-GB CUDA build.
  pip_quiet install -q torch==2.13.0
  pip_quiet install -q -r requirements.txt
  echo "$want" > "$stamp"
fi

# The C++ extension; ninja keeps rebuilds incremental. No build isolation: build against the venv's torch.
echo "[setup] building torchmanifold._C"
pip_quiet install -q --no-build-isolation --no-deps -e .
