#!/usr/bin/env bash
# Creates ./.venv with everything the project needs (idempotent; a few seconds when done).
# torch is pinned to 2.13.0: on these machines that is a local CPU wheel; an unpinned torch
# would pull several GB of CUDA packages.  bpy (Blender as a Python module) needs numpy<2
# and a few X11/GL client libraries even headless; they are installed with apt when missing.
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON_GIVEN=${PYTHON:-}
PYTHON=${PYTHON:-python3}
TORCH_SPEC=${NEULF_TORCH:-torch==2.13.0}
BPY_LIBS="libx11-6 libxrender1 libxfixes3 libxi6 libxkbcommon0 libsm6 libice6 libxext6 libgl1"
fail() { echo "setup failed: $*" >&2; exit 1; }
py_version() { "$1" -c 'import sys; print("%d.%d" % sys.version_info[:2])' 2>/dev/null; }

if [ -x .venv/bin/python ]; then
  have=$(py_version .venv/bin/python) || fail ".venv/bin/python does not run; remove .venv and run again"
  if [ -n "$PYTHON_GIVEN" ] && [ "$(py_version "$PYTHON" || true)" != "$have" ]; then
    fail ".venv holds Python $have, not $PYTHON's; remove .venv to make it again with $PYTHON"
  fi
else
  want=$(py_version "$PYTHON") || fail "cannot run '$PYTHON'; set PYTHON to a Python 3.11 (e.g. PYTHON=python3.11)"
  case "$want" in 3.1[0-9]) ;; *) fail "$PYTHON is Python $want; NeuLF needs 3.10+ (3.11 for bpy 5.0.1): set PYTHON=python3.11" ;; esac
  echo "== creating .venv with Python $want" >&2
  "$PYTHON" -m venv .venv || fail "'$PYTHON -m venv' failed (on Debian/Ubuntu: apt-get install python3-venv)"
  have=$want
fi
EXTRAS="blender,dev"
if [ "$have" != 3.11 ]; then
  echo "warning: bpy 5.0.1 exists for Python 3.11 only; Python $have gets no bpy (the demo and the Blender tests skip)" >&2
  EXTRAS="dev"
fi
pip_quiet() {
  .venv/bin/python -m pip install --disable-pip-version-check -q "$@" 2>&1 | { grep -v "^WARNING: Location" || true; } \
    || fail "pip install $* failed (its message is above)"
}
if ! .venv/bin/python -c "import torch" 2>/dev/null; then
  echo "== installing $TORCH_SPEC" >&2
  pip_quiet "$TORCH_SPEC"
fi
stamp=".venv/.neulf-$(sha1sum pyproject.toml | cut -c1-12)-$EXTRAS"
if [ ! -e "$stamp" ]; then
  echo "== installing neulf with the $EXTRAS extras (bpy 5.0.1, pycolmap 4.2.1, pytest)" >&2
  pip_quiet -e ".[$EXTRAS]"
  touch "$stamp"
fi
.venv/bin/python -c "import torch, pycolmap, numpy" || fail "torch/pycolmap/numpy do not import"

if [ "$EXTRAS" = "blender,dev" ] && ! .venv/bin/python -c "import bpy" 2>/dev/null; then
  if command -v apt-get >/dev/null 2>&1 && [ "$(id -u)" = 0 ]; then
    echo "== installing the system libraries bpy needs: $BPY_LIBS" >&2
    apt-get update -qq >/dev/null && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $BPY_LIBS >/dev/null
  fi
  if ! err=$(.venv/bin/python -c "import bpy" 2>&1); then
    echo "warning: bpy cannot load (${err##*$'\n'}); install these system libraries: sudo apt-get install $BPY_LIBS" >&2
  fi
fi
