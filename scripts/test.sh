#!/usr/bin/env bash
# Set everything up (.venv, and Debian's chromium for the dashboard's browser tests), lint (ruff: undefined names,
# unused imports), and run the whole test suite (unit tests, CLI tests, browser tests of the dashboard, and the
# integration tests on the real KITTI drive in ../shared/data/kitti or $VISLOC_DATA).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
bash scripts/install_chromium.sh
.venv/bin/ruff check visloc db dashboard bench tests scripts benchmarks
# every core (pytest-xdist; tests sharing a module-scoped fixture stay on one worker), and the 25 slowest tests
exec .venv/bin/python -m pytest -n auto --dist loadgroup --durations=25 "$@"
