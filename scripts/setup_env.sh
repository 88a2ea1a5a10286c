#!/usr/bin/env bash
# Creates ./.venv with everything the project needs (idempotent; a few seconds when done).
# torch is pinned to 2.13.0: on these machines that is a local CPU wheel; an unpinned torch
# would pull several GB of CUDA packages.  bpy (Blender as a Python module) needs numpy<2
# and a few X11/GL client libraries even headless; they are installed with apt when missing.
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON=${PYTHON:-python3}
TORCH_SPEC=${NEULF_TORCH:-torch==2.13.0}
BPY_LIBS="libx11-6 libxrender1 libxfixes3 libxi6 libxkbcommon0 libsm6 libice6 libxext6 libgl1"

if [ ! -x .venv/bin/python ]; then
  echo "== creating .venv with $($PYTHON --version)" >&2
  "$PYTHON" -m venv .venv
fi
pip_quiet() { .venv/bin/python -m pip install --disable-pip-version-check -q "$@" 2>&1 | grep -v "^WARNING: Location" || true; }
if ! .venv/bin/python -c "import torch" 2>/dev/null; then
  echo "== installing $TORCH_SPEC" >&2
  pip_quiet "$TORCH_SPEC"
fi
echo "== installing neulf with the blender and dev extras (bpy 5.0.1, pycolmap 4.2.1, pytest)" >&2
pip_quiet -e ".[blender,dev]"
.venv/bin/python -c "import torch, pycolmap, numpy" || { echo "setup failed: torch/pycolmap/numpy do not import" >&2; exit 1; }

if ! .venv/bin/python -c "import bpy" 2>/dev/null; then
  if command -v apt-get >/dev/null 2>&1 && [ "$(id -u)" = 0 ]; then
    echo "== installing the system libraries bpy needs: $BPY_LIBS" >&2
    apt-get update -qq >/dev/null && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $BPY_LIBS >/dev/null
  else
    echo "bpy cannot load; install these system libraries: sudo apt-get install $BPY_LIBS" >&2
  fi
fi
