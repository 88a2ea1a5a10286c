#!/usr/bin/env bash
# Quick start 1/2: set up, then render a small Blender scene, reconstruct it with pycolmap,
# train a NeuLF, and render held-out views and a spiral video into ./neulf_demo.
set -euo pipefail
cd "$(dirname "$0")"
scripts/setup_env.sh
exec .venv/bin/python -m neulf_core demo --out neulf_demo "$@"
