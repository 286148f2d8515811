"""A CSV drive with attitude, stated accuracy and calibration.json: the same drive brought as KITTI
and as CSV (scripts/kitti_to_csv.py) is stored alike and localized alike in the refined mode; the
CSV's new columns and calibration.json are parsed and checked; a store of schema 2 is migrated."""

from __future__ import annotations

import csv
import json
import math
import sqlite3
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from visloc import (GEOMETRY, GEOTAG, REFINED_METHOD, FilterParams, MatchParams, RetrievalParams, SiftParams, Workspace,
                    match_drive, track_drive)
from visloc.sources.calibration import read_calibration
from visloc.db import SCHEMA_VERSION, FeatureStore
from visloc.errors import InputError
from visloc.features.sift import extract_sift, undistort_keypoints
from visloc.store.ingest import ingest
from visloc.sources.drives import load_gray, open_csv

from helpers import DRIVE_0005, DRIVE_0005_FRAMES, PAPER_CONTRAST, REPO, copy_store, run_cli, write_csv_drive

DRIVE = DRIVE_0005
KITTI_SOURCE = DRIVE + "_sync"
N_FRAMES = DRIVE_0005_FRAMES  # the shared store's (conftest.store_0005)
CSV_SOURCE = "drive_0005_csv"  # the export folder's name: the CSV drive's source
COLUMNS = ["file", "timestamp", "lat", "lon", "alt", "heading", "roll_deg", "pitch_deg", "accuracy_m"]
# the refined poses of the two stores agree to this (see test_refined_measurements_agree_between_both_stores)
SAME_POSITION_M = 1e-5


def export(root: Path, out_dir: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(REPO / "scripts" / "kitti_to_csv.py"), str(root), "--drive", DRIVE,
                           "--camera", "image_00", str(out_dir), *args], capture_output=True, text=True, timeout=300)


@pytest.fixture(scope="module")
def both(kitti_root, store_0005, tmp_path_factory) -> SimpleNamespace:
    """The first 40 frames of drive 0005's image_00 exported as a CSV drive and ingested with the CLI, beside
    the shared store of the same frames ingested from the KITTI drive (--limit 40), copied here. The CSV drive
    is ingested ``--features-only``: what a CSV drive changes is how images, geotags, attitudes and calibration
    are read, which these tests compare; the structure and self-check made from them are the same functions of
    the same arrays either way (tests/test_camera_rate.py checks stored structure against structure made
    afresh), and the refined comparison below makes the structure it needs as a query does."""
    tmp = tmp_path_factory.mktemp("csv_drive")
    csv_dir = tmp / CSV_SOURCE
    result = export(kitti_root, csv_dir, "--frames", str(N_FRAMES))
    assert result.returncode == 0, result.stderr
    kitti_db, csv_db = copy_store(store_0005, tmp / "kitti"), tmp / "csv.sqlite"
    result = run_cli("ingest", csv_dir / "geotags.csv", "--db", csv_db, "--features-only", "--workers", "2",
                     *PAPER_CONTRAST)  # as the shared store was described
    assert result.returncode == 0, result.stderr
    assert f"{CSV_SOURCE}/camera: {N_FRAMES} added" in result.stdout
    return SimpleNamespace(root=kitti_root, csv_dir=csv_dir, kitti_db=kitti_db, csv_db=csv_db, tmp=tmp)


def load(path: Path, source: str, camera: str):
    ws = Workspace(path)
    return ws.load_database(source, camera), ws.load_queries(source, camera)


# -- the same drive as KITTI and as CSV -------------------------------------------------------------

def test_the_export_writes_geotags_calibration_and_symlinks(both):
    with (both.csv_dir / "geotags.csv").open(newline="") as fh:
        rows = list(csv.reader(fh))
    assert rows[0] == COLUMNS and len(rows) == N_FRAMES + 1
    drive_images = both.root / "2011_09_26" / KITTI_SOURCE / "image_00" / "data"
    for row in rows[1:]:
        link = both.csv_dir / row[0]
        assert row[0].startswith("images/") and link.is_symlink()
        assert link.resolve() == (drive_images / link.name).resolve()
    calibration = json.loads((both.csv_dir / "calibration.json").read_text())
    assert set(calibration) == {"fx", "fy", "cx", "cy", "width_px", "height_px", "T_vehicle_camera"}
    assert (calibration["width_px"], calibration["height_px"]) == (1242, 375)
    # the stated accuracy of drive 0005's geotags: differential / RTK-float, 0.3-0.52 m
    assert all(0.3 <= float(row[-1]) <= 0.53 for row in rows[1:])


def test_the_export_refuses_bad_input_in_one_line(both, tmp_path):
    for result, fragment in ((export(both.root, both.csv_dir), "geotags.csv: already exists"),
                             (export(tmp_path / "nowhere", tmp_path / "out"), "KITTI data root not found"),
                             (export(both.root, tmp_path / "out", "--frames", "0"), "--frames 0")):
        assert result.returncode == 2
        assert len(result.stderr.strip().splitlines()) == 1 and fragment in result.stderr, result.stderr


def test_both_stores_hold_the_same_geotags_attitudes_accuracies_and_calibration(both):
    kitti_db, kitti_q = load(both.kitti_db, KITTI_SOURCE, "image_00")
    csv_db, csv_q = load(both.csv_db, CSV_SOURCE, "camera")
    assert len(kitti_db) == len(csv_db) == N_FRAMES
    np.testing.assert_array_equal(csv_db.frames, kitti_db.frames)
    np.testing.assert_array_equal(csv_db.timestamps_s, kitti_db.timestamps_s)
    np.testing.assert_array_equal(csv_db.lat_deg, kitti_db.lat_deg)
    np.testing.assert_array_equal(csv_db.lon_deg, kitti_db.lon_deg)
    np.testing.assert_array_equal(csv_db.up_m, kitti_db.up_m)
    # radians -> degrees -> radians and yaw -> compass heading -> yaw: equal to the last bit or two
    assert np.isfinite(kitti_db.rpy_rad).all()
    np.testing.assert_allclose(csv_db.rpy_rad, kitti_db.rpy_rad, rtol=0, atol=1e-15)
    np.testing.assert_allclose([im.heading_deg for im in csv_db.images], [im.heading_deg for im in kitti_db.images],
                               rtol=0, atol=1e-12)
    # the stated accuracy, as OXTS records it (field 24), in both roles
    assert np.isfinite(kitti_db.geotag_sigma_m).all() and (kitti_db.geotag_sigma_m >= 0.3).all()
    np.testing.assert_array_equal(csv_db.geotag_sigma_m, kitti_db.geotag_sigma_m)
    np.testing.assert_array_equal(csv_q.truth_sigma_m, kitti_q.truth_sigma_m)
    np.testing.assert_array_equal(kitti_q.truth_sigma_m, kitti_db.geotag_sigma_m)
    np.testing.assert_array_equal(kitti_db.geometry().geotag_sigma_m, kitti_db.geotag_sigma_m)
    # the calibration: P_rect_00 is [K | 0]; T_camera_imu inverted twice
    kc, cc = kitti_db.calibration, csv_db.calibration
    np.testing.assert_array_equal(cc.P_rect, kc.P_rect)
    np.testing.assert_allclose(cc.T_camera_imu, kc.T_camera_imu, rtol=0, atol=1e-15)
    assert (cc.width_px, cc.height_px) == (kc.width_px, kc.height_px) == (1242, 375)
    # the same images and SIFT settings: the same features
    for a, b in zip(kitti_db.keypoints_f32, csv_db.keypoints_f32):
        np.testing.assert_array_equal(a, b)
    for a, b in zip(kitti_db.descriptors_u8, csv_db.descriptors_u8):
        np.testing.assert_array_equal(a, b)


@pytest.mark.slow
def test_refined_measurements_agree_between_both_stores(both):
    """Same camera, 1 s exclusion, the refined method on both stores: the same measurements.

    Not bit for bit: a compass heading in degrees cannot hold every yaw in radians, so some attitudes
    differ by one unit in the last place (2e-16 rad), and the pose's final PnP refinement (OpenCV's
    default termination) carries such differences into positions at the 1e-6 m level."""
    runs = []
    for path, source, camera in ((both.kitti_db, KITTI_SOURCE, "image_00"), (both.csv_db, CSV_SOURCE, "camera")):
        db, queries = load(path, source, camera)
        matches = match_drive(queries, db, MatchParams(), RetrievalParams(exclusion_s=1.0), [0, 10, 15, 24, 27],
                              method=REFINED_METHOD)
        runs.append((track_drive(matches, queries, db, FilterParams()), queries))
    (kitti, kitti_q), (csv_records, _) = runs
    assert [r.measurement_source for r in kitti] == [r.measurement_source for r in csv_records]
    assert sum(r.measurement_source == GEOMETRY for r in kitti) >= 3, [r.fallback_reason for r in kitti]
    for a, b in zip(kitti, csv_records):
        assert (a.best_db_frame, a.view_db_frames, a.n_pnp_inliers) == (b.best_db_frame, b.view_db_frames,
                                                                        b.n_pnp_inliers)
        np.testing.assert_allclose(b.measurement_m, a.measurement_m, rtol=0, atol=SAME_POSITION_M)
        if a.measurement_source == GEOTAG:
            assert b.measurement_m == a.measurement_m
    # the truth comes from the receiver that geotagged the database, on the same drive: it shares the map's
    # absolute error (the stated 0.3-0.5 m of this drive's float GPS), so the NEES is e' R^-1 e; the truth's
    # stated accuracy and the map's are recorded beside it
    for r in kitti:
        s = kitti_q.truth_sigma(kitti_q.frames.tolist().index(r.query_frame))
        assert r.truth_sigma_m == s and 0.3 <= s <= 0.53 and r.truth_shares_map
        e = np.subtract(r.measurement_m, r.truth_m)
        R = np.array(r.measurement_cov_m2)
        assert r.measurement_nees == pytest.approx(e @ np.linalg.solve(R, e), rel=1e-12)
        if r.measurement_source == GEOMETRY:
            assert 0.3 <= r.absolute_sigma_m <= 0.53 and r.measurement_side in ("both", "one")


@pytest.mark.slow
def test_a_csv_with_attitude_but_no_calibration_runs_the_paper_mode_only(both, tmp_path):
    drive = tmp_path / "uncalibrated"
    drive.mkdir()
    lines = (both.csv_dir / "geotags.csv").read_text().splitlines()
    (drive / "geotags.csv").write_text("\n".join(lines[:13]) + "\n")  # header and 12 frames, no calibration.json
    (drive / "images").symlink_to(both.csv_dir / "images")
    store = tmp_path / "s.sqlite"
    result = run_cli("ingest", drive / "geotags.csv", "--db", store, "--workers", "1")
    assert result.returncode == 0, result.stderr
    (dataset,) = Workspace(store).drives()
    assert (dataset.n_images, dataset.has_calibration, dataset.has_extrinsics, dataset.n_without_attitude) == (
        12, False, False, 0)
    db, _ = load(store, "uncalibrated", "camera")
    assert np.isfinite(db.rpy_rad).all() and np.isfinite(db.geotag_sigma_m).all()
    args = ("localize", drive / "geotags.csv", "--db", store, "--db-camera", "camera", "--steps", "2")
    result = run_cli(*args)
    assert result.returncode == 0, result.stderr
    result = run_cli(*args, "--mode", "refined")
    assert result.returncode == 2
    (line,) = result.stderr.strip().splitlines()
    assert line.startswith("visloc: error: the refined method needs a calibrated database") and "P_rect" in line


# -- calibration.json ---------------------------------------------------------------------------------

GOOD_CALIBRATION = {"fx": 700.0, "fy": 700.0, "cx": 160.0, "cy": 120.0, "width_px": 320, "height_px": 240,
                    "T_vehicle_camera": [[0, 0, 1, 1.5], [-1, 0, 0, 0.1], [0, -1, 0, 1.2], [0, 0, 0, 1]]}


def calibrated_drive(folder: Path, n_frames: int = 4, **changes) -> Path:
    csv_path = write_csv_drive(folder, n_frames=n_frames)
    calibration = {**GOOD_CALIBRATION, **changes}
    (folder / "calibration.json").write_text(json.dumps({k: v for k, v in calibration.items() if v is not None}))
    return csv_path


def test_a_good_calibration_gives_p_rect_and_the_inverse_extrinsics(tmp_path):
    seq = open_csv(calibrated_drive(tmp_path / "d", distortion=[0.1, -0.05, 0.001, 0.002, 0.0]))
    np.testing.assert_array_equal(seq.P_rect, [[700, 0, 160, 0], [0, 700, 120, 0], [0, 0, 1, 0]])
    # the camera 1.5 m ahead, 0.1 m left and 1.2 m above the geotag's point, looking forward
    np.testing.assert_allclose(seq.T_camera_imu @ [1.5, 0.1, 1.2, 1], [0, 0, 0, 1], atol=1e-15)
    np.testing.assert_allclose(seq.T_camera_imu[:3, :3] @ [1, 0, 0], [0, 0, 1])  # forward = optical axis
    assert seq.image_size_px == (320, 240) and seq.camera_model is not None
    np.testing.assert_array_equal(seq.distortion, [0.1, -0.05, 0.001, 0.002, 0.0])
    assert open_csv(calibrated_drive(tmp_path / "e", distortion=[0, 0, 0, 0, 0])).distortion is None


@pytest.mark.parametrize("changes,message", [
    ({"fx": -700.0}, "fx: focal length must be > 0"),
    ({"fy": None}, "fy: missing"),
    ({"cx": "160"}, "cx: expected a finite number"),
    ({"width_px": 320.5}, "width_px: expected a positive whole number"),
    ({"distortion": [0.1, 0.2, 0.3]}, "distortion: expected a list of 4, 5, 8, 12 or 14"),
    ({"T_vehicle_camera": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]]}, "T_vehicle_camera: expected a 4x4 matrix"),
    ({"T_vehicle_camera": [[1, 0.01, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]},
     "T_vehicle_camera: not a rigid transform"),
    ({"T_vehicle_camera": None}, "T_vehicle_camera: missing"),
    ({"focal": 700}, "focal: unknown key"),
])
def test_a_malformed_calibration_is_refused_naming_the_file_and_key(tmp_path, changes, message):
    with pytest.raises(InputError, match="calibration.json: " + message) as err:
        open_csv(calibrated_drive(tmp_path / "d", **changes))
    assert "\n" not in str(err.value)


def test_a_calibration_that_is_not_json_is_one_line_from_the_cli(tmp_path):
    csv_path = calibrated_drive(tmp_path / "d")
    (tmp_path / "d" / "calibration.json").write_text('{"fx": 700,\n "fy": }\n')
    with pytest.raises(InputError, match=r"d/calibration.json: not valid JSON \(line 2"):
        read_calibration(tmp_path / "d" / "calibration.json")
    result = run_cli("ingest", csv_path, "--db", tmp_path / "s.sqlite")
    assert result.returncode == 2 and not (tmp_path / "s.sqlite").exists()
    (line,) = result.stderr.strip().splitlines()
    assert "calibration.json: not valid JSON" in line


def test_distorted_keypoints_are_stored_undistorted_by_parallel_workers_too(tmp_path):
    distortion = [-0.3, 0.1, 0.001, -0.002, 0.0]
    seq = open_csv(calibrated_drive(tmp_path / "d", distortion=distortion))
    with FeatureStore(tmp_path / "s.sqlite", create=True) as store:
        assert ingest(store, seq, SiftParams(), workers=2).n_added == 4
        stored = {im.frame: im.image_id for im in store.images()}
        features = store.features(stored.values())
    K = seq.P_rect[:, :3]
    for frame in seq.frames:
        raw = extract_sift(load_gray(frame.image_path), SiftParams())
        expected = undistort_keypoints(raw.keypoints_f32, K, np.array(distortion))
        kp, desc = features[stored[frame.frame]]
        np.testing.assert_array_equal(kp, expected)
        np.testing.assert_array_equal(desc, raw.descriptors_u8)
        assert np.abs(kp[:, :2] - raw.keypoints_f32[:, :2]).max() > 1.0  # the corners moved
        np.testing.assert_array_equal(kp[:, 2:], raw.keypoints_f32[:, 2:])
    # undistorting and distorting again with OpenCV's model gives the detected pixels back
    obj = np.c_[(expected[:, :2] - K[:2, 2]) / np.diag(K)[:2], np.ones(len(expected))]
    again, _ = cv2.projectPoints(obj, np.zeros(3), np.zeros(3), K, np.array(distortion))
    np.testing.assert_allclose(again.reshape(-1, 2), raw.keypoints_f32[:, :2], atol=1e-3)


def test_images_of_another_size_than_the_calibration_are_refused(tmp_path):
    seq = open_csv(calibrated_drive(tmp_path / "d", width_px=640))
    with FeatureStore(tmp_path / "s.sqlite", create=True) as store:
        with pytest.raises(InputError, match=r"frame_0000.png: image is 320x240 px but the calibration .* 640x240"):
            ingest(store, seq, SiftParams(), workers=1)
        assert store.image_count() == 0


def test_distortion_is_refused_for_a_drive_stored_without_calibration(tmp_path):
    csv_path = write_csv_drive(tmp_path / "d", n_frames=4)
    with FeatureStore(tmp_path / "s.sqlite", create=True) as store:
        ingest(store, open_csv(csv_path), SiftParams(), workers=1, limit=2)
        calibrated_drive(tmp_path / "d", distortion=[-0.3, 0.1, 0.0, 0.0])
        with pytest.raises(InputError, match="stored without calibration, so its keypoints are not undistorted"):
            ingest(store, open_csv(csv_path), SiftParams(), workers=1)
        assert store.image_count() == 2
    # without distortion, a calibration added later is filled in, features untouched
    calibrated_drive(tmp_path / "d")
    with FeatureStore(tmp_path / "s.sqlite") as store:
        report = ingest(store, open_csv(csv_path), SiftParams(), workers=1)
        assert (report.n_added, report.n_skipped) == (2, 2)
        camera = store.get_camera("d", "camera")
        assert camera.P_rect is not None and camera.T_camera_imu is not None


# -- the CSV's columns --------------------------------------------------------------------------------

def write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def test_accuracy_and_attitude_columns_are_read(tmp_path):
    path = write(tmp_path / "g.csv", "file,timestamp,lat,lon,heading,roll_deg,pitch_deg,accuracy_m\n"
                                     "a.png,1,49,8,0,1.5,-2,0.25\n"
                                     "b.png,2,49,8,90,0,0,\n"
                                     "c.png,3,49,8,270,0,0,3\n"
                                     "d.png,4,49,8,180.0,,0,1e-2\n"
                                     "e.png,5,49,8,,1,2,0.5\n")
    a, b, c, d, e = open_csv(path).frames
    assert [f.position_accuracy_m for f in (a, b, c, d, e)] == [0.25, None, 3.0, 0.01, 0.5]
    # heading 0 (north) is yaw +pi/2; 90 (east) yaw 0; 270 (west) yaw pi, in (-pi, pi]
    assert (a.roll_rad, a.pitch_rad, a.yaw_rad) == (math.radians(1.5), math.radians(-2), math.pi / 2)
    assert b.yaw_rad == 0.0 and c.yaw_rad == math.pi and c.heading_deg == 270.0
    # an attitude needs roll, pitch and heading: the heading alone is kept
    assert (d.roll_rad, d.pitch_rad, d.yaw_rad, d.heading_deg) == (None, None, None, 180.0)
    assert (e.roll_rad, e.heading_deg) == (None, None)


def test_the_attitude_columns_come_together(tmp_path):
    path = write(tmp_path / "g.csv", "file,timestamp,lat,lon,roll_deg,pitch_deg\na.png,1,49,8,1,2\n")
    with pytest.raises(InputError, match="g.csv: roll_deg, pitch_deg and heading give the attitude together; "
                                         "missing heading"):
        open_csv(path)


@pytest.mark.parametrize("column,value,message", [
    ("accuracy_m", "-0.5", "column accuracy_m: must be > 0"),
    ("accuracy_m", "0", "column accuracy_m: must be > 0"),
    ("accuracy_m", "nan", "column accuracy_m: not a finite number: 'nan'"),
    ("roll_deg", "abc", "column roll_deg: not a finite number: 'abc'"),
    ("pitch_deg", "91", r"column pitch_deg: must be within \[-90, 90\]"),
    ("heading", "inf", "column heading: not a finite number"),
    ("alt", "high", "column alt: not a finite number"),
    ("timestamp", "soon", "column timestamp: neither seconds nor ISO 8601"),
])
def test_bad_numbers_are_refused_naming_the_line_and_column(tmp_path, column, value, message):
    good = {"file": "a.png", "timestamp": "1", "lat": "49", "lon": "8", "alt": "100", "heading": "10",
            "roll_deg": "1", "pitch_deg": "2", "accuracy_m": "0.3"}
    rows = [",".join(good), ",".join(good.values()), ",".join({**good, column: value}.values())]
    path = write(tmp_path / "geotags.csv", "\n".join(rows) + "\n")
    with pytest.raises(InputError, match="geotags.csv:3: " + message) as err:
        open_csv(path)
    assert "\n" not in str(err.value)


# -- a store of schema version 2 -------------------------------------------------------------------------

def test_a_schema_2_store_is_migrated_keeping_its_rows_and_reingest_fills_accuracies(both, tmp_path):
    path = tmp_path / "v2.sqlite"
    source = sqlite3.connect(both.csv_db)
    target = sqlite3.connect(path)
    source.backup(target)
    source.close()
    # what schema version 2 wrote: no accuracy column
    target.execute("ALTER TABLE images DROP COLUMN position_accuracy_m")
    target.execute("UPDATE visloc_schema SET version = 2")
    target.commit()
    before = target.execute("SELECT id, frame, lat_deg, keypoints_f32, descriptors_u8 FROM images ORDER BY id").fetchall()
    target.close()
    db, _ = load(path, CSV_SOURCE, "camera")  # migrated in place on opening
    assert np.isnan(db.geotag_sigma_m).all() and len(db) == N_FRAMES
    with FeatureStore(path) as store:
        assert store.frames_without_accuracy(CSV_SOURCE, "camera") == set(range(N_FRAMES))
    result = run_cli("ingest", both.csv_dir / "geotags.csv", "--db", path, "--features-only", "--workers", "1")
    assert result.returncode == 0, result.stderr
    assert f"0 added, {N_FRAMES} already stored" in result.stdout
    conn = sqlite3.connect(path)
    assert conn.execute("SELECT version FROM visloc_schema").fetchone() == (SCHEMA_VERSION,) == (7,)
    after = conn.execute("SELECT id, frame, lat_deg, keypoints_f32, descriptors_u8 FROM images ORDER BY id").fetchall()
    conn.close()
    assert after == before  # every row and feature kept
    migrated, _ = load(path, CSV_SOURCE, "camera")
    kitti, _ = load(both.kitti_db, KITTI_SOURCE, "image_00")
    np.testing.assert_array_equal(migrated.geotag_sigma_m, kitti.geotag_sigma_m)
