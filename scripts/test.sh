#!/usr/bin/env bash
# Set everything up and run the whole test suite (unit tests, CLI tests, and the
# integration test on the real KITTI drive in ../shared/data/kitti or $VISLOC_DATA).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
exec .venv/bin/python -m pytest "$@"
