#!/usr/bin/env bash
# Set everything up, lint (ruff: undefined names, unused imports), and run the whole test suite (unit tests, CLI tests, and the
# integration test on the real KITTI drive in ../shared/data/kitti or $VISLOC_DATA).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
.venv/bin/ruff check visloc db tests scripts
exec .venv/bin/python -m pytest "$@"
