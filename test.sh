#!/usr/bin/env bash
# Quick start 2/2: set up, then run the whole test suite (CPU only; 10 minutes on 2 cores, 2026-12-07, plus the setup).
set -euo pipefail
cd "$(dirname "$0")"
scripts/setup_env.sh
exec .venv/bin/python -m pytest "$@"
