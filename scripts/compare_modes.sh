#!/usr/bin/env bash
# Both modes x both camera setups on KITTI drive 0001 with the paper's protocol (1 s exclusion,
# every start frame), then the README's comparison table. Reuses out/visloc.sqlite (features,
# cached correspondence counts); the first run builds it (5-7 minutes).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
mkdir -p out/modes
DATA="${VISLOC_DATA:-../shared/data/kitti}"
for setup in "image_00 image_01" "image_01 image_01"; do
    set -- $setup
    for mode in paper refined; do
        .venv/bin/visloc evaluate "$DATA" --drive 2011_09_26_drive_0001 --db out/visloc.sqlite \
            --query-camera "$1" --db-camera "$2" --mode "$mode" --smooth --json "out/modes/${mode}_${1}_${2}.json"
    done
done
.venv/bin/python scripts/modes_table.py out/modes
