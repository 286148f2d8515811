#!/usr/bin/env bash
# Create .venv (if needed) and install visloc with its test dependencies into it.
set -euo pipefail
cd "$(dirname "$0")/.."
python3 -m venv .venv
.venv/bin/python -m pip install --quiet --upgrade pip 2>&1 | grep -v "^WARNING: Location" || true
.venv/bin/python -m pip install --quiet -e '.[test]' 2>&1 | grep -v "^WARNING: Location" || true
.venv/bin/python -c "import visloc, filterpy, pytest" # fail here, not later, if the install did not work
