#!/usr/bin/env bash
# Create .venv (if needed) and install visloc with its test dependencies into it.
# pip's output goes to .venv/install.log and is shown only if the install fails.
set -euo pipefail
cd "$(dirname "$0")/.."
python3 -m venv .venv
log=.venv/install.log
if ! { .venv/bin/python -m pip install --upgrade pip && .venv/bin/python -m pip install -e '.[test]'; } >"$log" 2>&1; then
    cat "$log" >&2
    echo "setup: pip install failed (log above, also in $log)" >&2
    exit 1
fi
# Byte-compile visloc's own code once: an environment that turns Python's bytecode cache off
# (PYTHONDONTWRITEBYTECODE) would otherwise compile it anew in every process, about 0.6 s of each command's start.
.venv/bin/python -m compileall -q visloc db dashboard bench >/dev/null
.venv/bin/python -c "import visloc, visloc.db, visloc.dashboard, visloc.bench, filterpy, pytest"  # fail here, not later, if the install is broken
echo "setup: .venv ready ($(.venv/bin/python -c 'import visloc; print("visloc", visloc.__version__)'))"
