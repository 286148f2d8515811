"""The visloc command, run as a user runs it: in a fresh process, reading its output."""

import hashlib
import json
import sqlite3

import cv2
import numpy as np
import pytest

import visloc
from visloc.cli.parser import build_parser

from helpers import CSV_PAIR_FRAMES, copy_store, run_cli, write_csv_drive
from helpers import one_line_error


def test_every_command_and_option_has_help_text():
    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    assert set(sub.choices) == {"ingest", "localize", "evaluate", "evaluate-drives", "info", "check", "upgrade", "dashboard", "bench", "track"}
    for name, cmd in sub.choices.items():
        assert cmd.description, name
        for action in cmd._actions:
            if action.dest != "help":
                assert action.help, f"visloc {name}: {action.dest} has no help"
    for name in sub.choices:
        result = run_cli(name, "--help")
        assert result.returncode == 0 and "usage: visloc " + name in result.stdout


@pytest.fixture(scope="module")
def synthetic(csv_pair):
    """The shared synthetic pair (conftest.csv_pair): a database drive in a store, and a query drive of the same
    strip shifted by a quarter frame, 14 frames each at 2 Hz."""
    return csv_pair.folder, csv_pair.db_csv, csv_pair.query_csv, csv_pair.store


def test_reingest_reports_everything_skipped(synthetic, tmp_path):
    _, db_csv, _, store = synthetic
    result = run_cli("ingest", db_csv, "--db", copy_store(store, tmp_path))
    assert result.returncode == 0 and f"0 added, {CSV_PAIR_FRAMES} already stored" in result.stdout


def test_localize_prints_tables_2_and_3_and_finds_the_right_images(synthetic, tmp_path):
    """The query drive is the database's drive, shifted by a quarter frame (same times, same places):
    with the exclusion turned off, each query finds its own database frame, and a warning says what
    that number is worth."""
    _, _, query_csv, store = synthetic
    out = tmp_path / "series.json"
    result = run_cli("localize", query_csv, "--db", store, "--db-camera", "camera", "--steps", "4",
                     "--start-frame", "1", "--exclusion-s", "0", "--json", out)
    assert result.returncode == 0, result.stderr
    assert "warning: --exclusion-s 0 with a database (dbdrive/camera) that holds images of querydrive/camera's own " \
           "drive" in result.stdout
    assert "Table 2: output of the image retrieval step" in result.stdout
    assert "Table 3: Kalman filter estimation of the vehicle location" in result.stdout
    steps = json.loads(out.read_text())["steps"]
    # 2 frames per second, one query per second: frames 1, 3, 5, 7 each find their own database frame
    assert [s["query_frame"] for s in steps] == [1, 3, 5, 7]
    assert [s["best_db_frame"] for s in steps] == [1, 3, 5, 7]
    assert all(s["measurement_error_m"] < 0.05 for s in steps)  # same geotags up to rounding
    assert all(s["best_count"] > 20 for s in steps)


def test_localize_excludes_the_queries_own_drive_by_default_and_says_so(synthetic, tmp_path):
    _, _, query_csv, store = synthetic
    out = tmp_path / "series.json"
    result = run_cli("localize", query_csv, "--db", store, "--db-camera", "camera", "--steps", "3",
                     "--start-frame", "1", "--json", out)
    assert result.returncode == 0, result.stderr
    assert "exclusion 1 s: the database dbdrive/camera holds images of querydrive/camera's own drive" in result.stdout
    assert "warning" not in result.stdout
    for s in json.loads(out.read_text())["steps"]:
        assert abs(s["best_offset_s"]) >= 1.0  # never its own frame or a neighbour within the second


def test_localize_with_exclusion_skips_the_own_frame(synthetic, tmp_path):
    _, _, query_csv, store = synthetic
    out = tmp_path / "series.json"
    result = run_cli("localize", query_csv, "--db", store, "--db-camera", "camera", "--steps", "3",
                     "--start-frame", "2", "--exclusion-s", "0.25", "--json", out)
    assert result.returncode == 0, result.stderr
    for s in json.loads(out.read_text())["steps"]:
        assert s["best_db_frame"] != s["query_frame"] and abs(s["best_offset_s"]) >= 0.25


def test_info_describes_the_store(synthetic):
    _, _, _, store = synthetic
    result = run_cli("info", "--db", store)
    assert result.returncode == 0
    assert f"{CSV_PAIR_FRAMES} images" in result.stdout and f"dbdrive/camera: {CSV_PAIR_FRAMES} images" in result.stdout
    assert "'n_features': 0" in result.stdout
    # a new store keeps every keypoint at half the paper's contrast; the paper's method selects its own
    assert f"'contrast_threshold': {visloc.STORE_SIFT.contrast_threshold}" in result.stdout


@pytest.mark.parametrize("flag,value,name", [
    ("--tau1", "0", "tau1=0.0: must be in (0, 1]"),
    ("--tau1", "1.5", "tau1=1.5"),
    ("--tau2", "2", "tau2=2.0: must be in [-1, 1]"),
    ("--meas-var-m2", "-1", "meas_var_m2 (R)=-1.0: must be >= 0"),
    ("--accel-var-m2-s4", "-1", "accel_var_m2_s4 (Q)=-1.0"),
    ("--init-var", "-1", "init_var (P0)=-1.0"),
    ("--dt-s", "0", "dt_s=0.0"),
    ("--steps", "0", "--steps: steps=0: must be an integer >= 1"),
])
def test_out_of_range_parameters_are_refused(synthetic, flag, value, name):
    _, _, query_csv, store = synthetic
    one_line_error(run_cli("localize", query_csv, "--db", store, "--db-camera", "camera", flag, value), name)


def test_database_built_with_other_sift_settings_is_refused(synthetic):
    _, _, query_csv, store = synthetic
    result = run_cli("localize", query_csv, "--db", store, "--db-camera", "camera", "--sift-features", "500")
    one_line_error(result, str(store), "built with other SIFT settings", "n_features: store 0, asked 500")
    result = run_cli("ingest", query_csv, "--db", store, "--sift-contrast", "0.01")
    one_line_error(result, "contrast_threshold: store 0.02, asked 0.01")


def test_empty_missing_and_foreign_database_files_are_refused_untouched(synthetic, tmp_path):
    _, _, query_csv, _ = synthetic
    empty = tmp_path / "empty.sqlite"
    empty.write_bytes(b"")
    one_line_error(run_cli("localize", query_csv, "--db", empty), "empty.sqlite: empty database file")
    one_line_error(run_cli("localize", query_csv, "--db", tmp_path / "none.sqlite"), "none.sqlite: database file does not exist")
    assert not (tmp_path / "none.sqlite").exists()
    foreign = tmp_path / "foreign.sqlite"
    conn = sqlite3.connect(foreign)
    conn.execute("CREATE TABLE orders (id INTEGER)")
    conn.commit()
    conn.close()
    digest = hashlib.sha256(foreign.read_bytes()).hexdigest()
    for cmd in (("localize", query_csv), ("ingest", query_csv), ("info",)):
        one_line_error(run_cli(*cmd, "--db", foreign), "foreign.sqlite: SQLite database but not a visloc store")
    assert hashlib.sha256(foreign.read_bytes()).hexdigest() == digest
    text = tmp_path / "text.sqlite"
    text.write_text("hello\n" * 100)
    one_line_error(run_cli("info", "--db", text), "text.sqlite: not a SQLite database")


def test_store_without_the_database_camera_is_named(synthetic):
    _, _, query_csv, store = synthetic
    one_line_error(run_cli("localize", query_csv, "--db", store, "--db-camera", "image_01"),
                   "choose the database with --db-source", "dbdrive/camera")
    one_line_error(run_cli("localize", query_csv, "--db", store, "--db-camera", "camera", "--db-source", "elsewhere"),
                   "no images of elsewhere/camera")


def test_bad_query_images_are_named(synthetic, tmp_path):
    tmp, _, _, store = synthetic
    query_csv = write_csv_drive(tmp_path / "q", n_frames=10, offset_px=30)
    (query_csv.parent / "frame_0002.png").unlink()
    one_line_error(run_cli("localize", query_csv, "--db", store, "--db-camera", "camera", "--db-source", "dbdrive", "--steps", "3"),
                   "frame_0002.png: image file not found")
    cv2.imwrite(str(query_csv.parent / "frame_0002.png"), np.full((240, 320), 128, np.uint8))
    one_line_error(run_cli("localize", query_csv, "--db", store, "--db-camera", "camera", "--db-source", "dbdrive", "--steps", "3"),
                   "frame_0002.png: no SIFT keypoints")


def test_series_that_does_not_fit_is_refused(synthetic):
    _, _, query_csv, store = synthetic
    one_line_error(run_cli("localize", query_csv, "--db", store, "--db-camera", "camera", "--start-frame", "8"),
                   "--start-frame 8: 6 queries 1.0 s apart do not fit")
    one_line_error(run_cli("localize", query_csv, "--db", store, "--db-camera", "camera", "--start-frame", "99"),
                   f"--start-frame 99: querydrive/camera has frames 0..{CSV_PAIR_FRAMES - 1}")


def test_ingest_of_a_broken_drive_keeps_what_was_stored(tmp_path):
    csv_path = write_csv_drive(tmp_path / "d", n_frames=10)
    (csv_path.parent / "frame_0006.png").write_bytes(b"\x89PNG broken")
    store = tmp_path / "s.sqlite"
    one_line_error(run_cli("ingest", csv_path, "--db", store, "--workers", "1"), "frame_0006.png: cannot decode image")
    conn = sqlite3.connect(store)
    assert conn.execute("SELECT count(*) FROM images").fetchone()[0] == 6
    conn.close()


def test_missing_data_root_is_named(tmp_path):
    one_line_error(run_cli("evaluate", tmp_path / "no_kitti", "--db", tmp_path / "s.sqlite"),
                   "no_kitti: KITTI data root not found")
    one_line_error(run_cli("ingest", tmp_path / "no_kitti", "--db", tmp_path / "s.sqlite"), "KITTI data root not found")
    assert not (tmp_path / "s.sqlite").exists()  # a source that cannot be read leaves no empty store behind


@pytest.mark.slow
def test_evaluate_on_a_small_kitti_layout_writes_json_and_plot(tmp_path):
    from helpers import make_fake_kitti

    make_fake_kitti(tmp_path / "kitti", n_frames=24, with_calib=False)  # the paper's method needs none
    out = tmp_path / "e.json"
    result = run_cli("evaluate", tmp_path / "kitti", "--db", tmp_path / "s.sqlite", "--steps", "2",
                     "--exclusion-s", "0", "--json", out, "--workers", "1")
    assert result.returncode == 0, result.stderr
    report = json.loads(out.read_text())
    # 24 frames at 10 Hz, one query per second (every 10th frame), 2 steps: starts 0..13
    assert report["n_series"] == 14 and report["steps"] == ["t-1", "t"]
    assert all(s[0]["best_db_frame"] == s[0]["query_frame"] for s in report["series"])  # stereo twin, same view
    assert (tmp_path / "e.png").exists() and "final estimate error" in result.stdout
    again = run_cli("evaluate", tmp_path / "kitti", "--db", tmp_path / "s.sqlite", "--steps", "2",
                    "--exclusion-s", "0", "--json", out)
    assert again.returncode == 0, again.stderr
    # the second run reuses stored features and cached counts: the same results (latency aside,
    # whose filter share is timed afresh)
    def without_latency(series):
        return [[{k: v for k, v in step.items() if k != "latency_ms"} for step in s] for s in series]

    assert without_latency(json.loads(out.read_text())["series"]) == without_latency(report["series"])
    one_line_error(run_cli("evaluate", tmp_path / "kitti", "--db", tmp_path / "s.sqlite", "--steps", "2", "--start-frames", "x"),
                   "--start-frames 'x'")
    one_line_error(run_cli("evaluate", tmp_path / "kitti", "--db", tmp_path / "s.sqlite", "--steps", "2",
                           "--start-frames", "3,20,21"),
                   "no series of 2 queries starts at [20, 21] (this drive's series start at frames 0..13: pick start "
                   "frames there, or leave out --start-frames for every series)")
    one_line_error(run_cli("evaluate", tmp_path / "kitti", "--db", tmp_path / "s.sqlite", "--steps", "9"),
                   "too short for 9 queries")


@pytest.mark.parametrize("breakage,message", [
    ("no_oxts", "oxts/data: OXTS folder not found"),
    ("unequal", "5 images in image_01 but 4 OXTS records"),
])
def test_broken_kitti_drive_through_the_cli(tmp_path, breakage, message):
    from helpers import make_fake_kitti

    drive = make_fake_kitti(tmp_path / "kitti", n_frames=5, with_oxts=breakage != "no_oxts")
    if breakage == "unequal":
        (drive / "oxts" / "data" / "0000000004.txt").unlink()
    one_line_error(run_cli("ingest", tmp_path / "kitti", "--db", tmp_path / "s.sqlite"), message)


def test_damaged_store_file_is_a_one_line_error(synthetic, tmp_path):
    _, _, query_csv, store = synthetic
    damaged = tmp_path / "damaged.sqlite"
    data = bytearray(store.read_bytes())
    data[4096:] = b"\xff" * (len(data) - 4096)  # keep the header page, wreck the rest
    damaged.write_bytes(bytes(data))
    result = run_cli("localize", query_csv, "--db", damaged, "--db-camera", "camera", "--steps", "2")
    one_line_error(result, "damaged.sqlite")


@pytest.mark.parametrize("command", ["localize", "evaluate"])
@pytest.mark.parametrize("flag,value,name", [
    ("--mode", "fancy", "--mode 'fancy': must be one of paper, refined, refined-fast"),
    ("--top-k", "0", "top_k=0: must be an integer >= 1"),
    ("--gate-chi2", "-1", "gate_chi2=-1.0: must be >= 0"),
])
def test_bad_mode_parameters_are_one_line_errors(synthetic, tmp_path, command, flag, value, name):
    _, _, query_csv, store = synthetic
    if command == "localize":
        args = ("localize", query_csv, "--db", store, "--db-camera", "camera")
    else:
        args = ("evaluate", tmp_path / "no_kitti", "--db", tmp_path / "s.sqlite")
    one_line_error(run_cli(*args, flag, value), name)


def test_refined_mode_without_calibration_is_refused_naming_what_is_missing(synthetic, tmp_path):
    _, _, query_csv, store = synthetic
    # a CSV drive has no camera calibration: nothing to pose, so the refined method cannot be built
    one_line_error(run_cli("localize", query_csv, "--db", store, "--db-camera", "camera", "--steps", "3",
                           "--start-frame", "1", "--mode", "refined"),
                   "the refined method needs a calibrated database: database dbdrive/camera: no intrinsics")
    result = run_cli("localize", query_csv, "--db", store, "--db-camera", "camera", "--steps", "3",
                     "--start-frame", "1", "--mode", "paper", "--json", tmp_path / "paper.json")
    assert result.returncode == 0, result.stderr
    assert all(s["measurement_source"] == "geotag" and s["fallback_reason"] is None
               for s in json.loads((tmp_path / "paper.json").read_text())["steps"])


@pytest.mark.slow
def test_both_modes_report_the_same_keys(tmp_path):
    from helpers import make_fake_kitti

    make_fake_kitti(tmp_path / "kitti", n_frames=24)
    reports = {}
    for mode in ("paper", "refined"):
        out = tmp_path / f"{mode}.json"
        result = run_cli("evaluate", tmp_path / "kitti", "--db", tmp_path / "s.sqlite", "--steps", "2",
                         "--start-frames", "0,5", "--json", out, "--workers", "1", "--mode", mode, "--smooth")
        assert result.returncode == 0, result.stderr
        reports[mode] = json.loads(out.read_text())
    paper, refined = reports["paper"], reports["refined"]
    assert set(paper) == set(refined)
    assert set(paper["series"][0][0]) == set(refined["series"][0][0])
    assert paper["mode"] == "paper" and refined["mode"] == "refined"
    assert paper["geometry_fallback_fraction"] is None and refined["geometry_fallback_fraction"] is not None
    assert paper["measurement_source_fraction"]["geometry"] == 0.0
    assert paper["measurement_source_fraction"]["geotag"] == 1.0 - paper["steps_without_measurement"] / 4
    # the smoother's last step is the filter's own
    assert paper["smoothed_error_m"][-1] == pytest.approx(paper["estimate_error_m"][-1])


@pytest.mark.parametrize("args,named", [
    (["--series", "0"], "--series"),
    (["--shortlist", "0"], "--shortlist"),
    (["--fast-scale", "1.5"], "--fast-scale"),
    (["--synthetic-images", "10"], "--synthetic-images"),
    (["--workers", "0"], "--workers"),
    (["--json", "/no/such/folder/bench.json"], "--json"),
])
def test_bench_refuses_bad_parameters_in_one_line(args, named):
    one_line_error(run_cli("bench", *args), named)


@pytest.mark.slow
def test_evaluate_drives_runs_every_drive_with_the_protocols_it_supports(tmp_path):
    import shutil

    from helpers import make_fake_kitti

    stereo = make_fake_kitti(tmp_path / "kitti", n_frames=24, with_calib=False)  # the paper's method needs none
    one_camera = stereo.parent / "2011_09_26_drive_0002_sync"  # a drive dropped into the folder is picked up
    shutil.copytree(stereo, one_camera)
    shutil.rmtree(one_camera / "image_01")
    out = tmp_path / "out"
    result = run_cli("evaluate-drives", tmp_path / "kitti", "--db", tmp_path / "s.sqlite", "--out-dir", out,
                     "--steps", "2", "--modes", "paper", "--workers", "1")
    assert result.returncode == 0, result.stderr
    report = json.loads((out / "drives.json").read_text())
    protocols = {d: [r["protocol"] for r in rows] for d, rows in report["drives"].items()}
    assert protocols == {"2011_09_26_drive_0001": ["stereo", "same_image_00"],
                         "2011_09_26_drive_0002": ["same_image_00"]}
    for rows in report["drives"].values():
        for row in rows:
            evaluation = json.loads((out / row["file"]).read_text())
            assert evaluation["mode"] == "paper" and 0 < row["measurement_error_m"]["n"] <= 2 * evaluation["n_series"]
    assert [r["mode"] for r in report["pooled"]] == ["paper"]
    assert report["pooled"][0]["n_steps"] == sum(r["n_steps"] for rows in report["drives"].values() for r in rows)
    for name in ("2011_09_26_drive_0001", "2011_09_26_drive_0002", "pooled over 2 drive(s)"):
        assert name in result.stdout
    one_line_error(run_cli("evaluate-drives", tmp_path / "kitti", "--db", tmp_path / "s.sqlite", "--out-dir", out,
                           "--modes", "best"), "--mode 'best': must be one of paper, refined, refined-fast")
    (tmp_path / "a_file").write_text("")
    one_line_error(run_cli("evaluate-drives", tmp_path / "kitti", "--db", tmp_path / "s.sqlite", "--out-dir",
                           tmp_path / "a_file"), "a_file: exists and is not a folder")
