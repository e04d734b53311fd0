#!/usr/bin/env bash
# Set up a virtual environment with the test extras and run the linters and the test suite.
# Usage: bash scripts/test.sh [extra pytest args]
set -euo pipefail
cd "$(dirname "$0")/.."
VENV="${PNVLAD_VENV:-.venv}"
if [ ! -x "$VENV/bin/python" ]; then
    python3 -m venv "$VENV"
fi
# Installer chatter goes to a log, shown only if the install fails.
if ! { "$VENV/bin/python" -m pip install -q --upgrade pip &&
       "$VENV/bin/python" -m pip install -q -e '.[dev]'; } > "$VENV/install.log" 2>&1; then
    cat "$VENV/install.log" >&2
    echo "pip install failed (log: $VENV/install.log)" >&2
    exit 1
fi
"$VENV/bin/ruff" check pnvlad_service cli tests benchmarks scripts
"$VENV/bin/python" -m pytest -q -p no:cacheprovider "$@"
