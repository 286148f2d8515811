#!/usr/bin/env bash
# Check that pyproject.toml's dependency floors are versions the code really works with.
#
# In a throwaway venv (under ${TMPDIR:-/tmp}, removed afterwards) it installs visloc with every dependency of
# [project] dependencies and the "test" extra pinned to its floor ("name>=X" becomes "name==X", see
# scripts/min_versions.py), builds it with the floor's setuptools, imports every dependency, lints with the
# floor's ruff, and runs the tests that exercise each dependency without a browser or the KITTI drive.
#
#   bash scripts/check_min_versions.sh                      # the default test selection below
#   bash scripts/check_min_versions.sh tests/test_store.py  # other pytest arguments instead of it
#
# PYTHON picks the interpreter (default python3); KEEP_VENV=1 keeps the venv (its path is printed).
# Non-interactive (CI=true, no stdin). Prints one line per failure ("check_min_versions: FAIL ..." and
# pytest's "FAILED test-id - reason" lines) and exits 1 if anything failed, 0 if all passed.
set -uo pipefail
export CI=true
exec </dev/null
cd "$(dirname "$0")/.."

# The tests that exercise each dependency (about 3-6 minutes on 2 cores; ruff and playwright are checked above
# them, by the lint and by importing playwright, since the browser tests need Chromium and the KITTI drive):
#   numpy, opencv: ingest, sources, matching, geometry     pyproj: geo          sqlite-utils: store, schema, faults_store
#   faiss: fast, retrieval    matplotlib: evaluation (the error plot)    pillow: faults_process (image header)
#   viser: faults_process (starts the dashboard's server)  filterpy: tracking   hypothesis: fuzz_parsers
#   geojson: export   setuptools: layout (builds the wheel)   pytest: all   tqdm: a smoke run of the bar, above them
#   and dependency_floors (the floors against the APIs the code calls, at the floors themselves)
DEFAULT_TESTS=(
    tests/test_store.py tests/test_schema.py tests/test_faults_store.py tests/test_params.py tests/test_geo.py
    tests/test_matching.py tests/test_geometry.py tests/test_tracking.py tests/test_ingest.py
    tests/test_sources.py tests/test_fast.py tests/test_retrieval.py tests/test_evaluation.py
    tests/test_faults_input.py tests/test_faults_process.py tests/test_drive.py tests/test_fuzz_parsers.py
    tests/test_export.py tests/test_layout.py tests/test_dependency_floors.py
)
# Module each distribution is imported as (a missing entry fails the check: add it with the dependency).
declare -A IMPORT_NAME=(
    [numpy]=numpy [opencv-python-headless]=cv2 [pyproj]=pyproj [sqlite-utils]=sqlite_utils [tqdm]=tqdm
    [faiss-cpu]=faiss [matplotlib]=matplotlib [pillow]=PIL [viser]=viser [pytest]=pytest
    [filterpy]=filterpy.kalman [ruff]=ruff [hypothesis]=hypothesis [geojson]=geojson
    [playwright]=playwright.sync_api [setuptools]=setuptools
)

PYTHON=${PYTHON:-python3}
failures=0
fail() { echo "check_min_versions: FAIL $*"; failures=$((failures + 1)); }
started=$SECONDS

work=$(mktemp -d "${TMPDIR:-/tmp}/visloc-min-versions.XXXXXX") || { echo "check_min_versions: FAIL mktemp"; exit 1; }
if [[ ${KEEP_VENV:-} == 1 ]]; then
    echo "check_min_versions: keeping the venv in $work/venv"
else
    trap 'rm -rf "$work"' EXIT
fi
venv=$work/venv
log=$work/pip.log

if ! "$PYTHON" scripts/min_versions.py >"$work/pins.txt" 2>"$work/pins.err"; then
    while read -r line; do fail "$line"; done <"$work/pins.err"
    exit 1
fi
echo "check_min_versions: floors: $(tr '\n' ' ' <"$work/pins.txt")"

"$PYTHON" -m venv "$venv" || { fail "could not create a venv with $PYTHON"; exit 1; }
py=$venv/bin/python
# setuptools first, so that the project is built (--no-build-isolation) with the floor's setuptools too
if ! { "$py" -m pip install --upgrade pip \
        && "$py" -m pip install -c "$work/pins.txt" setuptools \
        && "$py" -m pip install --no-build-isolation -c "$work/pins.txt" -e '.[test]'; } >"$log" 2>&1; then
    grep -E "^ERROR|requested|depends on|No matching distribution" "$log" | head -20 | sed 's/^/    /'
    fail "pip could not install visloc with its dependencies at their floors (full log: $log)"
    trap - EXIT
    exit 1
fi

# each distribution really at its floor, and importable
"$py" - "$work/pins.txt" <<'EOF' || failures=$((failures + 1))
import importlib.metadata, sys
from pip._vendor.packaging.version import Version
bad = 0
for line in open(sys.argv[1]):
    name, floor = line.strip().split("==")
    got = importlib.metadata.version(name)
    if Version(got) != Version(floor):
        print(f"check_min_versions: FAIL {name} installed as {got}, not its floor {floor}")
        bad += 1
sys.exit(1 if bad else 0)
EOF
while IFS= read -r pin; do
    name=${pin%%==*}
    module=${IMPORT_NAME[$name]:-}
    if [[ -z $module ]]; then
        fail "$name: no import name known for it; add it to IMPORT_NAME in $0"
    elif ! err=$("$py" -c "import $module" 2>&1); then
        fail "import $module ($pin): $(tail -n 1 <<<"$err")"
    fi
done <"$work/pins.txt"
for module in visloc visloc.db visloc.dashboard visloc.bench; do
    err=$("$py" -c "import $module" 2>&1) || fail "import $module: $(tail -n 1 <<<"$err")"
done

# a dependency's code path that no test below reaches: the tqdm bar (the tests see progress as plain lines)
err=$("$py" - 2>&1 <<'EOF'
import io
from visloc.progress import progress_reporter
stream = io.StringIO()
progress = progress_reporter("smoke", "items", stream=stream, terminal=True)
for done in range(4):
    progress(done, 3)
assert "smoke:" in stream.getvalue() and "items/s" in stream.getvalue(), repr(stream.getvalue())
EOF
) || fail "tqdm progress bar (visloc.progress): $(tail -n 1 <<<"$err")"

# the lint scripts/test.sh runs, with the floor's ruff
if ! out=$("$venv/bin/ruff" check --output-format concise visloc db dashboard bench tests scripts benchmarks 2>&1); then
    grep -E "^[^ ].*:[0-9]+:[0-9]+: " <<<"$out" | sed 's/^/check_min_versions: FAIL ruff /'
    fail "ruff check (floor's ruff): $(tail -n 1 <<<"$out")"
fi

if (($# == 0)); then set -- -m "not browser and not kitti" "${DEFAULT_TESTS[@]}"; fi
# -rfE: one "FAILED id - reason" / "ERROR id - reason" line per failure in the summary
"$py" -m pytest -q -p no:cacheprovider -rfE "$@" 2>&1 | tee "$work/pytest.log" | grep -E "^(FAILED|ERROR) |(passed|failed|error|no tests ran).* in [0-9.]+s"
status=${PIPESTATUS[0]}
if ((status != 0)) && ! grep -qE "^(FAILED|ERROR) " "$work/pytest.log"; then  # e.g. a conftest that does not import
    fail "pytest exited $status: $(grep -E "^E  " "$work/pytest.log" | tail -n 1 | sed 's/^E *//')"
elif ((status != 0)); then
    fail "pytest exited $status"
fi

elapsed=$((SECONDS - started))
if ((failures)); then
    trap - EXIT
    echo "check_min_versions: FAILED, $failures step(s) failed with the floors, in ${elapsed}s (logs and venv kept in $work)"
    exit 1
fi
echo "check_min_versions: OK, every dependency at its floor, in ${elapsed}s"
