#!/usr/bin/env bash
# Set everything up and run the main job on ../shared/data/kitti (or $VISLOC_DATA), drive
# 2011_09_26_drive_0001:
#   1. store SIFT features of both gray cameras in $VISLOC_OUT/visloc.sqlite (several minutes on
#      2 cores the first time, seconds afterwards);
#   2. serve the dashboard on that store and print its URL: its first run (left camera queries
#      against the right camera's database) fills in as the queries are matched;
#   3. meanwhile, the paper's evaluation (evaluation.json, evaluation.png: Figure 4) and Tables 2
#      and 3 for the series starting at frame 40 (series_40.json, .geojson), printed here.
# The dashboard keeps serving when the evaluation is done; Ctrl-C stops everything.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
DATA="${VISLOC_DATA:-../shared/data/kitti}"
OUT="${VISLOC_OUT:-out}"
DRIVE=2011_09_26_drive_0001
STORE="$OUT/visloc.sqlite"
mkdir -p "$OUT"
visloc=.venv/bin/visloc

"$visloc" ingest "$DATA" --drive "$DRIVE" --camera image_00 --camera image_01 --db "$STORE"

"$visloc" dashboard --db "$STORE" --port "${VISLOC_PORT:-8080}" &
dashboard=$!
stop_dashboard() {
    kill -INT "$dashboard" 2>/dev/null || true
    wait "$dashboard" 2>/dev/null || true
}
trap stop_dashboard EXIT
trap 'exit 130' INT TERM

"$visloc" evaluate "$DATA" --drive "$DRIVE" --db "$STORE" --json "$OUT/evaluation.json"
"$visloc" localize "$DATA" --drive "$DRIVE" --db "$STORE" --camera image_00 --db-camera image_01 \
    --exclusion-s 1 --start-frame 40 --json "$OUT/series_40.json" --geojson "$OUT/series_40.geojson"
echo "main: evaluation written to $OUT/; the dashboard keeps serving (Ctrl-C stops it)"
wait "$dashboard"
