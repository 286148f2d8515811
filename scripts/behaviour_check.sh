#!/usr/bin/env bash
# Check that this checkout evaluates and tracks exactly as an earlier commit did: `visloc evaluate --json`
# on every series of the shared drives in every mode (paper, refined, refined-fast), and `visloc track
# --json` over each drive's first 80 frames in full and following points, by the earlier code and by this
# one, then every number compared (scripts/compare_runs.py; wall-clock timings left out).
#
#   bash scripts/behaviour_check.sh [COMMIT]     (default f6c001b, the last commit before the pipeline
#                                                 was rebuilt from parts)
#
# The earlier code runs from a temporary git worktree in out/behaviour/, on this checkout's .venv;
# both read one store (out/behaviour/visloc.sqlite), so they see the same features.
set -euo pipefail
cd "$(dirname "$0")/.."
ref="${1:-f6c001b}"
DATA="$(realpath "${VISLOC_DATA:-../shared/data/kitti}")"
out="$(pwd)/out/behaviour"
mkdir -p "$out"
bash scripts/setup.sh
before_src="$out/source_$ref"
[ -d "$before_src" ] || git worktree add --detach "$before_src" "$ref" >/dev/null
# db/, dashboard/ and bench/ install as visloc.db, ... from this checkout (pyproject.toml's package-dir): linked
# into the earlier checkout's visloc/, its own are imported instead of this checkout's
for folder in db dashboard bench; do
    [ -e "$before_src/visloc/$folder" ] || ln -s "../$folder" "$before_src/visloc/$folder"
done
trap 'git worktree remove --force "$before_src"' EXIT
status=0
compare() {  # name, then the visloc arguments (without --json): run by both, compared
    local name=$1; shift
    # the earlier code, imported from its worktree (run from there, so this checkout's modules are not seen)
    (cd "$before_src" && PYTHONPATH="$before_src" "$OLDPWD/.venv/bin/python" -m visloc "$@" \
        --json "$out/${name}_before.json" >"$out/${name}_before.log" 2>&1)
    .venv/bin/visloc "$@" --json "$out/${name}_after.json" >"$out/${name}_after.log" 2>&1
    .venv/bin/python scripts/compare_runs.py "$out/${name}_before.json" "$out/${name}_after.json" || status=1
}
for run in "2011_09_26_drive_0001 image_00 image_01" "2011_09_26_drive_0005 image_00 image_00" \
           "2011_10_03_drive_0027 image_00 image_00"; do
    set -- $run
    drive=$1 query=$2 database=$3
    [ -n "$(find "$DATA" -maxdepth 2 -name "${drive}_sync" -type d)" ] || { echo "behaviour_check: $drive not in $DATA, skipped"; continue; }
    for mode in paper refined refined-fast; do
        compare "${drive}_${mode}" evaluate "$DATA" --drive "$drive" --query-camera "$query" --db-camera "$database" \
            --db "$out/visloc.sqlite" --mode "$mode" --smooth
    done
    track=(track "$DATA" --drive "$drive" --camera image_00 --db "$out/visloc.sqlite" --frames 80 --no-follow-points)
    compare "${drive}_track" "${track[@]}"
    compare "${drive}_track_following" "${track[@]}" --follow-points --no-background-relocalization --pace-hz 0
done
exit $status
