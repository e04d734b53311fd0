# Sourced by scripts/demo.sh and scripts/test.sh (run from the repository root, VENV set):
# `ensure_venv EXTRA` creates the virtual environment $VENV if it has no python yet and
# installs pnvlad with EXTRA into it (editable).
ensure_venv() {
    if [ ! -x "$VENV/bin/python" ]; then
        python3 -m venv "$VENV"
    fi
    # Installer chatter goes to a log, shown only if the install fails.
    if ! { "$VENV/bin/python" -m pip install -q --upgrade pip &&
           "$VENV/bin/python" -m pip install -q -e ".[$1]"; } > "$VENV/install.log" 2>&1; then
        cat "$VENV/install.log" >&2
        echo "pip install failed (log: $VENV/install.log)" >&2
        exit 1
    fi
}
