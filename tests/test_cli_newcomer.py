"""The command line as a newcomer meets it: help with examples, one default store, the database
found in the store, clear refusals, no empty store left behind, progress off a terminal, trajectory
files. Each case runs the visloc command in a fresh process, as a user would."""

from __future__ import annotations

import csv
import io
import json
import sqlite3
from importlib.metadata import version

import pytest

from visloc.cli.parser import build_parser
from visloc.cli.help_text import DEFAULT_DB
from visloc.progress import duration_text, progress_reporter

from helpers import make_fake_kitti, run_cli, write_csv_drive
from helpers import PROGRESS_LINE, error_lines, one_line_error

COMMANDS = ("ingest", "localize", "evaluate", "evaluate-drives", "track", "dashboard", "bench", "upgrade", "info")


def subcommands():
    parser = build_parser()
    return next(a for a in parser._actions if a.dest == "command").choices


# -- help -----------------------------------------------------------------------------------------------

@pytest.mark.parametrize("command", COMMANDS)
def test_every_command_help_shows_examples_of_itself(command):
    result = run_cli(command, "--help")
    assert result.returncode == 0, result.stderr
    examples = result.stdout.split("examples:", 1)[1]
    assert f"visloc {command}" in examples


def test_every_flag_says_what_it_does_not_only_its_default():
    for name, cmd in subcommands().items():
        for action in cmd._actions:
            text = (action.help or "").strip().lower()
            assert text and not text.startswith(("default", "(default")), f"visloc {name} {action.option_strings}"


def test_version_is_the_installed_package_version():
    result = run_cli("--version")
    assert result.returncode == 0 and result.stdout.strip() == f"visloc {version('visloc')}"


# what a command line that starts at once must not load before a command runs
HEAVY_MODULES = ("cv2", "numpy", "faiss", "viser", "pyproj", "sqlite_utils", "matplotlib", "distributed", "dask",
                 "PIL", "scipy", "filterpy")
STARTUP_PROBE = """
import sys
from visloc.cli.parser import main
try:
    status = main(sys.argv[1:])
except SystemExit as exc:
    status = exc.code
print("loaded:", ",".join(m for m in HEAVY if m in sys.modules), file=sys.stderr)
sys.exit(status)
"""


@pytest.mark.parametrize("args, status", [
    ((), 2), (("--help",), 0), (("--version",), 0), (("localize", "--help"), 0), (("dashboard", "--help"), 0),
    (("localize", "x.csv", "--tau1", "1.5"), 2), (("track", "x.csv", "--init-var", "-1"), 2),
    (("evaluate", "--steps", "0"), 2), (("ingest", "x.csv", "--max-image-mp", "0"), 2),
    (("evaluate", "--sampling", "often"), 2), (("nonsense",), 2),
])
def test_help_version_and_refusals_load_nothing_heavy(args, status):
    """``visloc --help``, a command's help, ``--version`` and a refused argument answer without importing OpenCV,
    numpy, faiss, viser or the store: they answer at once."""
    import subprocess
    import sys

    result = subprocess.run([sys.executable, "-c", f"HEAVY = {HEAVY_MODULES!r}" + STARTUP_PROBE, *args],
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == status, result.stderr
    assert result.stderr.splitlines()[-1] == "loaded: ", result.stderr
    if status == 2 and args and args[0] != "nonsense" and len(args) > 1:
        assert result.stderr.splitlines()[0].startswith(("visloc: error: ", "usage: ")), result.stderr


def test_importing_the_command_line_parser_leaves_opencv_out():
    import subprocess
    import sys

    code = "import sys, visloc, visloc.cli.parser; print(sorted(m for m in %r if m in sys.modules))" % (HEAVY_MODULES,)
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0 and result.stdout.strip() == "[]", result.stdout + result.stderr


def test_the_public_api_is_still_reached_through_visloc():
    """``import visloc`` loads its names when first used: every name ``__all__`` lists is there."""
    import visloc

    missing = [name for name in visloc.__all__ if getattr(visloc, name, None) is None]
    assert missing == []
    assert set(visloc.__all__) <= set(dir(visloc))
    with pytest.raises(AttributeError):
        visloc.no_such_name  # noqa: B018


def test_mode_lists_its_choices_and_refuses_others_in_one_line(tmp_path):
    assert "{paper,refined,refined-fast}" in run_cli("localize", "--help").stdout
    one_line_error(run_cli("localize", write_csv_drive(tmp_path / "d", 4), "--db", tmp_path / "s.sqlite",
                           "--mode", "fast"), "--mode 'fast': must be one of paper, refined, refined-fast")


def test_one_default_store_for_every_command():
    for name, cmd in subcommands().items():
        defaults = {a.dest: a.default for a in cmd._actions}
        if "db" in defaults:
            assert str(defaults["db"]) == DEFAULT_DB == "out/visloc.sqlite", name
    assert str({a.dest: a.default for a in subcommands()["bench"]._actions}["fast_db"]) == "out/visloc_s05.sqlite"


# -- a CSV drive, start to end, in the default store ----------------------------------------------------------

@pytest.fixture(scope="module")
def newcomer(tmp_path_factory):
    """A folder holding my_drive (a CSV drive) and, after 'visloc ingest my_drive/geotags.csv', out/visloc.sqlite."""
    home = tmp_path_factory.mktemp("newcomer")
    write_csv_drive(home / "my_drive", n_frames=10)
    result = run_cli("ingest", "my_drive/geotags.csv", "--workers", "1", cwd=home)
    assert result.returncode == 0, result.stderr
    assert "out/visloc.sqlite: my_drive/camera: 10 added" in result.stdout
    return home


def test_ingest_prints_progress_lines_off_a_terminal(newcomer):
    home = newcomer
    result = run_cli("ingest", "my_drive/geotags.csv", "--db", "out/other.sqlite", "--workers", "1", cwd=home)
    assert result.returncode == 0, result.stderr
    lines = result.stderr.strip().splitlines()
    assert lines[0] == "ingest my_drive/camera: 0/10 images (0%), started"
    assert any(line.startswith("ingest my_drive/camera: 10/10 images (100%), done in ") for line in lines)
    assert all(PROGRESS_LINE.match(line) for line in lines), lines


def test_info_and_localize_find_the_default_store_and_its_only_drive(newcomer):
    home = newcomer
    info = run_cli("info", cwd=home)
    assert info.returncode == 0 and "out/visloc.sqlite: 10 images" in info.stdout
    result = run_cli("localize", "my_drive/geotags.csv", "--exclusion-s", "1", "--steps", "3", "--start-frame", "2",
                     cwd=home)
    assert result.returncode == 0, result.stderr
    assert "database: my_drive/camera (10 images)" in result.stdout


def test_reading_commands_create_nothing(tmp_path):
    one_line_error(run_cli("info", cwd=tmp_path), "out/visloc.sqlite: database file does not exist")
    one_line_error(run_cli("localize", write_csv_drive(tmp_path / "d", 4), cwd=tmp_path), "out/visloc.sqlite")
    assert not (tmp_path / "out").exists()


def test_tables_label_haversine_as_the_papers_and_everything_else_geodesic(newcomer):
    result = run_cli("localize", "my_drive/geotags.csv", "--exclusion-s", "1", "--steps", "3", cwd=newcomer)
    assert result.returncode == 0, result.stderr
    out = result.stdout
    assert "(inaccuracies by Haversine, as the paper's Table 3)" in out
    assert "Measurement inaccuracy (Haversine, m)" in out and "Estimation inaccuracy (Haversine, m)" in out
    assert "Measurement inaccuracy (m)" not in out and "(geodesic, m)" not in out
    assert "errors: WGS84 geodesic" in out and "Measurement error (m)" in out and "Estimate error (m)" in out


def test_localize_and_evaluate_write_trajectory_files(newcomer):
    home = newcomer
    result = run_cli("localize", "my_drive/geotags.csv", "--exclusion-s", "1", "--steps", "3",
                     "--geojson", "out/series.geojson", "--csv", "out/series.csv", cwd=home)
    assert result.returncode == 0, result.stderr
    geojson = json.loads((home / "out" / "series.geojson").read_text())
    kinds = {f["properties"]["kind"] for f in geojson["features"]}
    assert {"truth", "measurement", "estimate"} <= kinds
    rows = list(csv.DictReader(io.StringIO((home / "out" / "series.csv").read_text())))
    assert len(rows) == 3 and rows[0]["estimate_cov_ee_m2"]
    result = run_cli("evaluate", "my_drive/geotags.csv", "--steps", "2", "--start-frames", "0,4", "--workers", "1",
                     "--csv", "out/eval.csv", cwd=home)
    assert result.returncode == 0, result.stderr
    rows = list(csv.DictReader(io.StringIO((home / "out" / "eval.csv").read_text())))
    assert sorted({r["series"] for r in rows}) == ["0", "1"] and len(rows) == 4
    # a CSV drive is not the paper's drive: no comparison with its numbers
    assert "paper" not in result.stdout.split("final estimate error")[-1]


@pytest.mark.parametrize("flag,value,message", [
    ("--geojson", "out/x.csv", "--geojson out/x.csv: the file name must end in .geojson or .json"),
    ("--csv", "out/x.geojson", "--csv out/x.geojson: the file name must end in .csv"),
    ("--csv", "nowhere/x.csv", "--csv nowhere/x.csv: folder does not exist"),
])
def test_bad_trajectory_paths_are_refused_before_any_work(newcomer, flag, value, message):
    one_line_error(run_cli("localize", "my_drive/geotags.csv", flag, value, cwd=newcomer), message)


@pytest.mark.parametrize("args,flag", [
    (("ingest", "my_drive/geotags.csv", "--camera", "image_00"), "--camera image_00"),
    (("localize", "my_drive/geotags.csv", "--camera", "image_01"), "--camera image_01"),
    (("track", "my_drive/geotags.csv", "--camera", "image_00"), "--camera image_00"),
    (("evaluate", "my_drive/geotags.csv", "--query-camera", "image_00"), "--query-camera image_00"),
])
def test_a_camera_for_a_csv_drive_is_refused(newcomer, args, flag):
    one_line_error(run_cli(*args, cwd=newcomer), flag, "my_drive/geotags.csv is a CSV drive", "leave")


@pytest.mark.slow
def test_an_ambiguous_database_lists_what_the_store_holds(newcomer, tmp_path):
    store = tmp_path / "two.sqlite"
    for name in ("drive_a", "drive_b"):
        csv_path = write_csv_drive(tmp_path / name, n_frames=4)
        assert run_cli("ingest", csv_path, "--db", store, "--workers", "1").returncode == 0
    query = write_csv_drive(tmp_path / "query", n_frames=4)
    one_line_error(run_cli("localize", query, "--db", store), "choose the database with --db-source",
                   "drive_a/camera, drive_b/camera")
    result = run_cli("localize", query, "--db", store, "--db-source", "drive_b", "--steps", "2")
    assert result.returncode == 0 and "database: drive_b/camera" in result.stdout, result.stderr


# -- the paper's comparison, the KITTI layout ---------------------------------------------------------------

@pytest.fixture(scope="module")
def fake_kitti(tmp_path_factory):
    root = tmp_path_factory.mktemp("fake_kitti") / "kitti"
    make_fake_kitti(root, n_frames=24)  # drive 0001, both gray cameras
    return root


@pytest.mark.slow
def test_the_papers_numbers_appear_only_for_its_drive_and_protocol(tmp_path):
    # the paper's method needs no calibration; without one, ingest stores no structure or self-check, which only
    # the refined modes read
    fake_kitti = tmp_path / "kitti"  # a data root of its own, not the module's calibrated one
    make_fake_kitti(fake_kitti, n_frames=24, with_calib=False)
    store = tmp_path / "s.sqlite"
    common = ("--db", store, "--steps", "2", "--start-frames", "0", "--workers", "1")
    paper = run_cli("evaluate", fake_kitti, *common)
    assert paper.returncode == 0, paper.stderr
    assert "the paper on this drive and protocol" in paper.stdout and "1.85 m" in paper.stdout
    same = run_cli("evaluate", fake_kitti, *common, "--db-camera", "image_00")
    assert same.returncode == 0, same.stderr
    assert "1.85" not in same.stdout and "paper on this drive" not in same.stdout
    # a store of two cameras of one drive: left queries take the right camera, as the paper; others must choose
    left = run_cli("localize", fake_kitti, "--db", store, "--steps", "2", "--exclusion-s", "0")
    assert left.returncode == 0 and "database: 2011_09_26_drive_0001_sync/image_01" in left.stdout, left.stderr
    one_line_error(run_cli("localize", fake_kitti, "--db", store, "--camera", "image_01", "--steps", "2"),
                   "2011_09_26_drive_0001_sync has cameras image_00, image_01; choose one with --db-camera")


# -- no empty store left behind -------------------------------------------------------------------------------

def test_a_failed_ingest_removes_the_store_it_created_and_its_folder(tmp_path):
    csv_path = write_csv_drive(tmp_path / "broken", n_frames=4)
    (csv_path.parent / "frame_0000.png").write_bytes(b"not an image")
    one_line_error(run_cli("ingest", csv_path, "--workers", "1", cwd=tmp_path), "frame_0000.png: cannot decode image")
    assert not (tmp_path / "out").exists()
    one_line_error(run_cli("ingest", csv_path, "--db", "fresh.sqlite", "--workers", "1", cwd=tmp_path),
                   "cannot decode image")
    assert list(tmp_path.glob("fresh.sqlite*")) == []


def test_a_failed_ingest_keeps_a_store_that_existed(tmp_path):
    store = tmp_path / "kept.sqlite"
    good = write_csv_drive(tmp_path / "good", n_frames=4)
    assert run_cli("ingest", good, "--db", store, "--workers", "1").returncode == 0
    broken = write_csv_drive(tmp_path / "broken", n_frames=4)
    (broken.parent / "frame_0000.png").write_bytes(b"not an image")
    one_line_error(run_cli("ingest", broken, "--db", store, "--workers", "1"), "cannot decode image")
    conn = sqlite3.connect(store)
    assert conn.execute("SELECT count(*) FROM images").fetchone()[0] == 4
    conn.close()
    # an empty store that existed before is kept too
    empty = tmp_path / "empty.sqlite"
    assert run_cli("ingest", good, "--db", empty, "--limit", "1", "--workers", "1").returncode == 0
    conn = sqlite3.connect(empty)
    conn.execute("DELETE FROM images")
    conn.commit()
    conn.close()
    one_line_error(run_cli("ingest", broken, "--db", empty, "--workers", "1"), "cannot decode image")
    assert empty.exists()


# -- progress, on a fake clock ---------------------------------------------------------------------------------

class FakeClock:
    def __init__(self):
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def test_progress_lines_start_throttle_estimate_and_end():
    clock, out = FakeClock(), io.StringIO()
    progress = progress_reporter("ingest d/image_00", "images", stream=out, clock=clock, terminal=False)
    progress(0, 108)
    for done in range(1, 109):
        clock.now += 0.775  # 40 images in 31 s
        progress(done, 108)
    lines = out.getvalue().splitlines()
    assert lines[0] == "ingest d/image_00: 0/108 images (0%), started"
    assert lines[-1] == "ingest d/image_00: 108/108 images (100%), done in 84 s"
    assert "ingest d/image_00: 13/108 images (12%), 10 s elapsed, about 74 s left" in lines
    assert len(lines) == 2 + 8  # one line per 10 s of an 84 s run, besides start and end
    assert all(PROGRESS_LINE.match(line) for line in lines)
    progress(108, 108)
    assert out.getvalue().splitlines() == lines  # the end is told once


def test_progress_without_a_start_call_counts_from_its_creation_and_nothing_for_no_work():
    clock, out = FakeClock(), io.StringIO()
    progress = progress_reporter("evaluate paper", "series", stream=out, clock=clock, terminal=False)
    clock.now += 30
    progress(1, 4)
    assert out.getvalue() == "evaluate paper: 1/4 series (25%), 30 s elapsed, about 90 s left\n"
    silent = io.StringIO()
    progress_reporter("ingest x", "images", stream=silent, clock=clock, terminal=False)(0, 0)
    assert silent.getvalue() == ""
    assert [duration_text(s) for s in (0.4, 119, 245, 3725)] == ["0 s", "119 s", "4 min 05 s", "1 h 02 min"]


def test_error_lines_ignore_progress():
    stderr = "ingest d/camera: 0/4 images (0%), started\nvisloc: error: d/frame_0000.png: cannot decode image\n"
    assert error_lines(stderr) == ["visloc: error: d/frame_0000.png: cannot decode image"]


@pytest.mark.slow
def test_track_writes_its_frames_as_trajectory_files(fake_kitti, tmp_path):
    result = run_cli("track", fake_kitti, "--camera", "image_00", "--exclusion-s", "1", "--frames", "3", "--workers",
                     "1", "--geojson", "out/track.geojson", "--csv", "out/track.csv", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert (tmp_path / "out" / "visloc.sqlite").exists()  # the default store, its folder made
    rows = list(csv.DictReader(io.StringIO((tmp_path / "out" / "track.csv").read_text())))
    assert [r["frame"] for r in rows] == ["0", "1", "2"] and all(r["estimate_cov_ee_m2"] for r in rows)
    geojson = json.loads((tmp_path / "out" / "track.geojson").read_text())
    assert sum(f["properties"]["kind"] == "estimate" for f in geojson["features"]) == 3
    assert "track 2011_09_26_drive_0001_sync/image_00: 0/3 frames (0%), started" in result.stderr
