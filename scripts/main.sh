#!/usr/bin/env bash
# Set everything up and run the main job on ../shared/data/kitti (or $VISLOC_DATA):
# the paper's evaluation of drive 2011_09_26_drive_0001 (left camera queries against
# the right camera database, 1 s exclusion), then Tables 2 and 3 for one series, then
# the dashboard on that store (it prints its URL; Ctrl-C stops it).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
mkdir -p out
DATA="${VISLOC_DATA:-../shared/data/kitti}"
.venv/bin/visloc evaluate "$DATA" --drive 2011_09_26_drive_0001 --db out/visloc.sqlite --json out/evaluation.json
.venv/bin/visloc localize "$DATA" --drive 2011_09_26_drive_0001 --db out/visloc.sqlite --camera image_00 \
    --db-camera image_01 --exclusion-s 1 --start-frame 40 --json out/series_40.json
exec .venv/bin/visloc dashboard --db out/visloc.sqlite --port "${VISLOC_PORT:-8080}"
