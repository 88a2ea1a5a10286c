#!/usr/bin/env bash
# Quick start 2/2: set up, then run the whole test suite (CPU only, a few minutes).
set -euo pipefail
cd "$(dirname "$0")"
scripts/setup_env.sh
exec .venv/bin/python -m pytest "$@"
