#!/usr/bin/env bash
# Set up a virtual environment with the test extras and run the linters and the test suite.
# Usage: bash scripts/test.sh [extra pytest args]
set -euo pipefail
cd "$(dirname "$0")/.."
VENV="${PNVLAD_VENV:-.venv}"
. scripts/venv.sh
ensure_venv dev
"$VENV/bin/ruff" check pnvlad_service cli tests benchmarks scripts
"$VENV/bin/python" -m pytest -q -p no:cacheprovider "$@"
