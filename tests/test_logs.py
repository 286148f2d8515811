"""A vehicle's log as a drive (rosbag2 with sqlite3 or MCAP storage, a bare .mcap, a ROS 1 bag), written by
tools nobody here wrote (the ``rosbags`` writer, the published ``kitti2mcap`` converter), and a run exported
as MCAP read back with ``mcap``'s own reader.

Synthetic logs (small textured images along a straight road) test the reading, the pairing and every
refusal; the shared KITTI drives test that a log of a drive is that drive."""

from __future__ import annotations

import importlib.util
import json
import math
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from fault_table import Fault, params
from helpers import DRIVE_0005, KITTI_DRIVE, ORIGIN_LAT_DEG, REPO, one_line_error, read_back_mcap, run_cli
from visloc.sources.drives import Frame, open_kitti
from visloc.sources.opening import open_source
from visloc.geometry.projective import (quaternion_from_rotation, rotation_from_quaternion, rotation_from_rpy,
                                       rpy_from_rotation)
from visloc.sources.log_frames import Fixes, bracket, pair_fix

_spec = importlib.util.spec_from_file_location("kitti_to_log", REPO / "scripts" / "kitti_to_log.py")
kitti_to_log = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(kitti_to_log)

FORMATS = {"sqlite3": "drive_sqlite3", "mcap": "drive_mcap", "bag": "drive.bag"}
M_PER_DEG_LON = 111_320.0 * math.cos(math.radians(ORIGIN_LAT_DEG))


def frames_of_csv(csv_path: Path) -> list[Frame]:
    return list(open_source(csv_path).frames)


def write_synthetic_log(out: Path, fmt: str, frames: list[Frame], *, image_topic: str = "/cam/image_raw",
                        fixes: bool = True, fix_status: int = 0, fix_shift_ns: int = 0,
                        camera_info_size: tuple[int, int] | None = None, extra_images: str | None = None,
                        tf_attitude: bool = False) -> Path:
    """A log of ``frames`` (their images, geotags as NavSatFix at their times + ``fix_shift_ns``, and a
    CameraInfo of ``camera_info_size`` when given; ``tf_attitude``: the frames' attitudes as /tf map to
    base_link and the camera on base_link in /tf_static), written with the rosbags writer."""
    with kitti_to_log.LogWriter(out, fmt) as log:
        m = log.messages
        for f in frames:
            t = int(round(f.timestamp_s * 1e9))
            pixels = cv2.imread(str(f.image_path), cv2.IMREAD_UNCHANGED)
            log.write(image_topic, "sensor_msgs/msg/Image", t, m.image(t, "cam_optical", pixels))
            if extra_images:
                log.write(extra_images, "sensor_msgs/msg/Image", t, m.image(t, "cam2_optical", pixels))
            if camera_info_size is not None:
                P = np.array([[300.0, 0, 160, 0], [0, 300.0, 120, 0], [0, 0, 1, 0]])
                log.write(image_topic.rsplit("/", 1)[0] + "/camera_info", "sensor_msgs/msg/CameraInfo", t,
                          m.camera_info(t, "cam_optical", P, camera_info_size))
            if fixes:
                log.write("/gps/fix", "sensor_msgs/msg/NavSatFix", t + fix_shift_ns,
                          m.fix(t + fix_shift_ns, f, status=fix_status))
            if tf_attitude:  # the vehicle's pose in the map frame on /tf, and no IMU
                pose = np.eye(4)
                pose[:3, :3] = rotation_from_rpy(f.roll_rad, f.pitch_rad, f.yaw_rad)
                moving = m.static_transforms(t, {"base_link": pose})
                moving.transforms[0].header.frame_id = "map"
                log.write("/tf", "tf2_msgs/msg/TFMessage", t, moving)
        if tf_attitude:
            on_vehicle = np.array([[0, 0, 1, 1.5], [-1, 0, 0, 0.1], [0, -1, 0, 1.2], [0, 0, 0, 1]], float)
            log.write("/tf_static", "tf2_msgs/msg/TFMessage", t, m.static_transforms(t, {"cam_optical": on_vehicle}))
    return out


FAULTS = [
    Fault(id="log-truncated", area="a vehicle's log",
          tried="An MCAP file and a ROS 1 bag cut in half, as a copy that stopped part way leaves them.",
          gets="Refused: one line naming the log (cannot read it), exit 2; no store file is created."),
    Fault(id="log-without-fixes", area="a vehicle's log",
          tried="A log with images but no sensor_msgs/NavSatFix topic.",
          gets="Refused: one line naming the log, the missing geotags and the topics it has, exit 2."),
    Fault(id="log-without-images", area="a vehicle's log",
          tried="A log with fixes but no Image or CompressedImage topic.",
          gets="Refused: one line naming the log, the missing images and the topics it has, exit 2."),
    Fault(id="log-no-fix-near-images", area="a vehicle's log",
          tried="Fixes recorded 100 s away from every image.",
          gets="Refused: no image lies within --max-fix-gap-s of fixes, one line, exit 2."),
    Fault(id="log-two-cameras", area="a vehicle's log",
          tried="A log with two image topics and no --camera.",
          gets="Refused: one line listing both topics and saying to choose with --camera, exit 2."),
    Fault(id="log-fixes-without-position", area="a vehicle's log",
          tried="Fixes whose status is NO_FIX, into a store that holds another drive.",
          gets="Refused: one line naming the topic and how many fixes have no position, exit 2; the store is "
               "unchanged, byte for byte."),
    Fault(id="log-camera-info-other-size", area="a vehicle's log",
          tried="A CameraInfo for 640x480 px beside 320x240 px images.",
          gets="Refused: one line naming both sizes, exit 2."),
    Fault(id="log-flags-for-a-csv-drive", area="a vehicle's log",
          tried="--fix-topic given for a CSV drive.",
          gets="Refused: one line saying the flag is only for a log, exit 2."),
]
CASES = {f.id: f for f in FAULTS}


# -- pairing, attitude: pure functions ---------------------------------------------------------------

def test_an_image_takes_the_fix_at_its_time_exactly_else_interpolates_within_the_gap_else_none():
    fixes = Fixes(np.array([0, 1_000_000_000, 3_000_000_000], np.int64), np.array([49.0, 49.001, 49.002]),
                  np.array([8.0, 8.001, 8.002]), np.array([100.0, 110.0, 120.0]), np.array([0.02, np.nan, 0.3]))
    exact = pair_fix(fixes, 1_000_000_000, 1_000_000_000)
    assert (exact.lat_deg, exact.lon_deg, exact.alt_m, exact.sigma_m, exact.gap_s) == (49.001, 8.001, 110.0, None, 0.0)
    half = pair_fix(fixes, 500_000_000, 1_000_000_000)
    assert half.lat_deg == pytest.approx(49.0005, abs=1e-12) and half.alt_m == pytest.approx(105.0)
    assert half.sigma_m is None and half.gap_s == 1.0  # one of the two fixes states no accuracy: none
    assert pair_fix(fixes, 2_000_000_000, 1_000_000_000) is None  # the fixes around it are 2 s apart
    assert pair_fix(fixes, 2_000_000_000, 2_000_000_000).gap_s == 2.0
    assert pair_fix(fixes, -1, 10**10) is None and pair_fix(fixes, 3_000_000_001, 10**10) is None  # outside
    assert bracket(fixes.stamp_ns, 3_000_000_000, 0) == (2, 2, 0.0)


def test_a_camera_is_named_by_the_part_of_its_topic_that_names_it_unless_two_share_it():
    from visloc.sources.logs import camera_names

    assert camera_names(["/kitti/image_00/image_raw", "/kitti/image_01/image_raw", "/cam0/compressed"]) == {
        "/kitti/image_00/image_raw": "image_00", "/kitti/image_01/image_raw": "image_01", "/cam0/compressed": "cam0"}
    assert camera_names(["/left/image_raw", "/left/image_rect"]) == {"/left/image_raw": "left.image_raw",
                                                                     "/left/image_rect": "left.image_rect"}
    assert camera_names(["/image_raw"]) == {"/image_raw": "image_raw"}


def test_an_orientation_reads_back_as_the_oxts_roll_pitch_and_yaw_it_was_made_from():
    for roll, pitch, yaw in ((0.03, -0.01, 2.9), (-0.2, 0.4, -1.2), (0.0, 0.0, math.pi - 1e-9)):
        q = quaternion_from_rotation(rotation_from_rpy(roll, pitch, yaw))
        assert np.allclose(rpy_from_rotation(rotation_from_quaternion(np.array(q))), (roll, pitch, yaw), atol=1e-12)


# -- a log as a drive: the same drive in every format -----------------------------------------------------

@pytest.mark.parametrize("fmt", list(FORMATS))
def test_a_log_in_each_format_is_read_as_the_drive_it_was_written_from(tmp_path, csv_drive, fmt):
    frames = frames_of_csv(csv_drive)
    log = write_synthetic_log(tmp_path / FORMATS[fmt], fmt, frames)
    drive = open_source(log)
    assert drive.camera == "cam" and drive.source == Path(FORMATS[fmt]).stem
    assert [(f.frame, f.timestamp_s, f.lat_deg, f.lon_deg) for f in drive.frames] == \
        [(f.frame, f.timestamp_s, f.lat_deg, f.lon_deg) for f in frames]
    for a, b in zip(frames, drive.frames):
        assert np.array_equal(cv2.imread(str(a.image_path), -1), cv2.imread(str(b.image_path), -1))
    assert drive.P_rect is None and any("refined mode is not available" in n for n in drive.notes)


def test_without_an_imu_the_attitude_comes_from_the_transform_tree(tmp_path, csv_drive):
    from dataclasses import replace

    frames = [replace(f, roll_rad=0.01 * i, pitch_rad=-0.02, yaw_rad=2.5 + 0.05 * i)
              for i, f in enumerate(frames_of_csv(csv_drive))]
    log = write_synthetic_log(tmp_path / "tf.bag", "bag", frames, camera_info_size=(320, 240), tf_attitude=True)
    drive = open_source(log)
    for a, b in zip(frames, drive.frames):
        assert np.allclose((a.roll_rad, a.pitch_rad, a.yaw_rad), (b.roll_rad, b.pitch_rad, b.yaw_rad), atol=1e-12)
    assert drive.T_camera_imu is not None and np.allclose(drive.T_camera_imu[:3, 3], [0.1, 1.2, -1.5])
    assert any("attitude from the transform map -> base_link of /tf" in note for note in drive.notes)


def test_info_lists_a_logs_topics_and_the_largest_gap_a_geotag_was_interpolated_over(tmp_path, csv_drive):
    log = write_synthetic_log(tmp_path / "drive.bag", "bag", frames_of_csv(csv_drive), fix_shift_ns=100_000_000)
    result = run_cli("info", log)
    assert result.returncode == 0, result.stderr
    assert "/cam/image_raw: sensor_msgs/Image, 12 messages" in result.stdout
    assert "/gps/fix: sensor_msgs/NavSatFix, 12 messages" in result.stdout
    # fixes 0.1 s after each image, 0.5 s apart: the first image is before the first fix, left out
    assert "1 of 12 images of /cam/image_raw left out" in result.stdout
    assert "largest gap between the two fixes an image's geotag was interpolated from: 0.500 s" in result.stdout
    assert "drive/cam: 11 frames" in result.stdout


@pytest.mark.slow
def test_a_run_on_a_log_gives_the_figures_of_the_same_drive_read_from_its_csv(tmp_path, csv_pair):
    """The query drive as a log, localized against the pair's store: the same steps, number for number, as
    the query drive read from its CSV; and the run exported as MCAP reads back, every message decoded with
    its schema, its fixes those of the run's JSON."""
    log = write_synthetic_log(tmp_path / "query_mcap", "mcap", frames_of_csv(csv_pair.query_csv))
    runs = {}
    for name, source in (("csv", csv_pair.query_csv), ("log", log)):
        extra = ["--mcap", tmp_path / "run.mcap", "--mcap-images"] if name == "log" else []
        result = run_cli("localize", source, "--db", csv_pair.store, "--steps", "4", "--dt-s", "0.5",
                         "--json", tmp_path / f"{name}.json", *extra)
        assert result.returncode == 0, result.stderr
        runs[name] = json.loads((tmp_path / f"{name}.json").read_text())
    keys = ("query_frame", "measurement_lat_deg", "measurement_lon_deg", "estimate_lat_deg", "estimate_lon_deg",
            "estimate_cov_m2", "best_db_frame", "best_count")
    csv_steps, log_steps = ([{k: s.get(k) for k in keys} for s in runs[n]["steps"]] for n in ("csv", "log"))
    assert csv_steps == log_steps and len(log_steps) == 4
    read_back_mcap(tmp_path / "run.mcap", runs["log"]["steps"], images=True)


# -- bad logs: one line each, exit 2, nothing stored -------------------------------------------------------

def _refused(tmp_path, log, *fragments, db=None):
    db = db or tmp_path / "out" / "store.sqlite"
    result = run_cli("ingest", log, "--db", db)
    one_line_error(result, str(log), *fragments)
    return db


@pytest.mark.parametrize("fault", params([CASES["log-truncated"]]))
def test_a_truncated_log_is_refused_in_one_line_and_nothing_is_stored(tmp_path, csv_drive, fault):
    frames = frames_of_csv(csv_drive)
    whole = write_synthetic_log(tmp_path / "whole_mcap", "mcap", frames) / "whole_mcap.mcap"
    bag = write_synthetic_log(tmp_path / "whole.bag", "bag", frames)
    for source, name in ((whole, "cut.mcap"), (bag, "cut.bag")):
        data = source.read_bytes()
        (tmp_path / name).write_bytes(data[: len(data) // 2])
        db = _refused(tmp_path, tmp_path / name, "cannot read")
        assert not db.exists() and not db.parent.exists()


@pytest.mark.parametrize("fault", params([CASES["log-without-fixes"]]))
def test_a_log_without_fixes_is_refused_naming_the_missing_geotags_and_the_topics_it_has(tmp_path, csv_drive, fault):
    no_fixes = write_synthetic_log(tmp_path / "nofix.bag", "bag", frames_of_csv(csv_drive), fixes=False)
    _refused(tmp_path, no_fixes, "no geotags: the log has no sensor_msgs/NavSatFix topic",
             "its topics: /cam/image_raw (sensor_msgs/Image)")


@pytest.mark.parametrize("fault", params([CASES["log-without-images"]]))
def test_a_log_without_images_is_refused_naming_the_topics_it_has(tmp_path, csv_drive, fault):
    with kitti_to_log.LogWriter(tmp_path / "noimage.bag", "bag") as log:
        log.write("/gps/fix", "sensor_msgs/msg/NavSatFix", 10**9, log.messages.fix(10**9, frames_of_csv(csv_drive)[0]))
    _refused(tmp_path, tmp_path / "noimage.bag", "no image: the log has no sensor_msgs/Image or "
             "sensor_msgs/CompressedImage topic", "/gps/fix (sensor_msgs/NavSatFix)")


@pytest.mark.parametrize("fault", params([CASES["log-no-fix-near-images"]]))
def test_images_with_no_fix_near_them_are_refused(tmp_path, csv_drive, fault):
    far = write_synthetic_log(tmp_path / "far.bag", "bag", frames_of_csv(csv_drive), fix_shift_ns=100 * 10**9)
    _refused(tmp_path, far, "none of the 12 images of /cam/image_raw lies within 1 s of fixes of /gps/fix")


@pytest.mark.parametrize("fault", params([CASES["log-two-cameras"]]))
def test_a_log_of_two_cameras_asks_which(tmp_path, csv_drive, fault):
    two = write_synthetic_log(tmp_path / "two.bag", "bag", frames_of_csv(csv_drive), extra_images="/cam2/image_raw")
    _refused(tmp_path, two, "holds 2 image topics, choose one with --camera (/cam/image_raw, /cam2/image_raw)")


@pytest.mark.parametrize("fault", params([CASES["log-fixes-without-position"]]))
def test_fixes_without_a_position_are_refused_and_a_store_that_existed_keeps_every_image(tmp_path, csv_drive, fault,
                                                                                          csv_pair):
    log = write_synthetic_log(tmp_path / "nofix_status.bag", "bag", frames_of_csv(csv_drive), fix_status=-1)
    store = tmp_path / "kept.sqlite"
    shutil.copy(csv_pair.store, store)
    before = store.read_bytes()
    _refused(tmp_path, log, "/gps/fix: none of its 12 fixes has a position (each has status NO_FIX)", db=store)
    assert store.read_bytes() == before


@pytest.mark.parametrize("fault", params([CASES["log-camera-info-other-size"]]))
def test_a_camera_info_of_another_size_than_the_images_is_refused(tmp_path, csv_drive, fault):
    log = write_synthetic_log(tmp_path / "size.bag", "bag", frames_of_csv(csv_drive), camera_info_size=(640, 480))
    _refused(tmp_path, log, "/cam/camera_info: calibration is for 640x480 px but the images are 320x240 px")


@pytest.mark.parametrize("fault", params([CASES["log-flags-for-a-csv-drive"]]))
def test_log_flags_given_for_a_drive_that_is_no_log_are_refused(csv_drive, fault):
    one_line_error(run_cli("info", csv_drive, "--fix-topic", "/gps/fix"), "--fix-topic: only for a log")


# -- the shared KITTI drives as logs ----------------------------------------------------------------------

@pytest.mark.slow
def test_a_log_of_a_shared_drive_is_that_drive_in_every_format(tmp_path, kitti_root):
    """Both cameras of drive 0001, written by the rosbags writer as rosbag2 (sqlite3, MCAP), a bare .mcap and
    a ROS 1 bag: every frame's time, geotag and stated accuracy bit for bit, attitude to 1e-12 rad, the
    pixels, the projection matrix exactly, the camera's pose on the vehicle to 1e-12 (through a quaternion)."""
    logs = []
    for fmt, name in FORMATS.items():
        logs.append(kitti_to_log.write_log(kitti_root, KITTI_DRIVE, ["image_00", "image_01"], tmp_path / name, fmt,
                                           frames=8))
    logs.append(tmp_path / "drive_mcap" / "drive_mcap.mcap")
    for camera in ("image_00", "image_01"):
        kitti = open_kitti(kitti_root, KITTI_DRIVE, camera)
        for log in logs:
            drive = open_source(log, camera=f"/kitti/{camera}/image_raw")
            assert len(drive) == 8, log
            for a, b in zip(kitti.frames, drive.frames):
                assert (a.frame, a.timestamp_s, a.lat_deg, a.lon_deg, a.alt_m, a.position_accuracy_m) == \
                    (b.frame, b.timestamp_s, b.lat_deg, b.lon_deg, b.alt_m, b.position_accuracy_m), log
                assert np.allclose((a.roll_rad, a.pitch_rad, a.yaw_rad), (b.roll_rad, b.pitch_rad, b.yaw_rad),
                                   rtol=0, atol=1e-12)
                assert np.array_equal(cv2.imread(str(a.image_path), -1), cv2.imread(str(b.image_path), -1))
            assert np.array_equal(kitti.P_rect, drive.P_rect) and kitti.image_size_px == drive.image_size_px
            assert np.abs(kitti.T_camera_imu - drive.T_camera_imu).max() < 1e-12


def test_kitti2mcap_output_gives_the_kitti_calibration_and_is_refused_for_lacking_geotags(tmp_path, kitti_root):
    """The published converter kitti2mcap (images, CameraInfo, TF, IMU of a KITTI drive; no NavSatFix): the
    calibration visloc reads from its file is KITTI's, and the log is refused for its missing geotags."""
    date, kitti_root = KITTI_DRIVE[:10], kitti_root.resolve()
    source = kitti_root / date / f"{KITTI_DRIVE}_sync"
    root = tmp_path / "kitti"  # kitti2mcap counts the frames in velodyne_points/data, which the shared drive lacks
    (root / date / source.name / "velodyne_points" / "data").mkdir(parents=True)
    for name in ("calib_cam_to_cam.txt", "calib_imu_to_velo.txt", "calib_velo_to_cam.txt"):
        (root / date / name).symlink_to(kitti_root / date / name)
    for name in ("image_00", "image_01", "oxts"):
        (root / date / source.name / name).symlink_to(source / name)
    (root / date / source.name / "velodyne_points" / "timestamps.txt").symlink_to(
        source / "velodyne_points" / "timestamps.txt")
    for i in range(len(list((source / "oxts" / "data").glob("*.txt")))):
        (root / date / source.name / "velodyne_points" / "data" / f"{i:010d}.bin").touch()
    out = tmp_path / "kitti2mcap.mcap"
    converted = subprocess.run([str(Path(sys.executable).with_name("kitti2mcap")), "--date", date, "--drive",
                                KITTI_DRIVE[-4:], "--kitti-dir", str(root), "--output", str(out), "--frames", "3",
                                "--cameras", "0,1", "--no-lidar"], capture_output=True, text=True, timeout=300)
    assert converted.returncode == 0, converted.stderr
    from visloc.sources.logs import read_log_camera

    for camera, topic in (("image_00", "camera_gray_left"), ("image_01", "camera_gray_right")):
        kitti = open_kitti(kitti_root, KITTI_DRIVE, camera)
        log_camera = read_log_camera(out, camera=f"/kitti/{topic}/image_raw")
        assert np.array_equal(log_camera.P_rect, kitti.P_rect) and log_camera.distortion is None
        assert log_camera.image_size_px == kitti.image_size_px
        # its IMU's frame ("imu") is not in its transform tree: the pose is base_link's, which it says is the IMU;
        # kitti2mcap makes its quaternions from KITTI's rotations, rotations to 1e-7 only, its own way
        assert np.abs(log_camera.T_camera_imu - kitti.T_camera_imu).max() < 2e-7
        assert log_camera.notes == ("kitti2mcap.mcap: the IMU's frame 'imu' is not in the transform tree: its "
                                    "orientation is taken as base_link's",)
    one_line_error(run_cli("ingest", out, "--camera", "/kitti/camera_gray_left/image_raw", "--db",
                           tmp_path / "s.sqlite"), "no geotags: the log has no sensor_msgs/NavSatFix topic",
                   "/kitti/imu (sensor_msgs/Imu)")
    assert not (tmp_path / "s.sqlite").exists()


def _steps(path: Path) -> list[dict]:
    return json.loads(path.read_text())["steps"]


@pytest.mark.slow
def test_a_log_of_a_shared_drive_is_stored_and_localized_as_the_drive_itself(tmp_path, kitti_root, store_0005):
    """Drive 0005 as a log in each format: its images stored from the log are the store's own, byte for byte
    (keypoints and descriptors); localized against the shared store from an MCAP log, the paper's mode gives
    the same figures exactly, the refined mode to 1e-6 m (the log's camera pose on the vehicle went through a
    quaternion). The other formats hold the same drive (``test_a_log_of_a_shared_drive_is_that_drive_in_
    every_format``), so they give the same figures."""
    from helpers import PAPER_CONTRAST, snapshot

    kitti_features = snapshot(store_0005)
    for fmt, name in FORMATS.items():
        log = kitti_to_log.write_log(kitti_root, DRIVE_0005, ["image_00"], tmp_path / name, fmt, frames=30)
        stored = tmp_path / f"{fmt}.sqlite"
        result = run_cli("ingest", log, "--db", stored, "--features-only", "--limit", "3", "--workers", "1",
                         *PAPER_CONTRAST)  # as the shared store was described
        assert result.returncode == 0, result.stderr
        log_features = snapshot(stored)
        assert len(log_features) == 3 and all(log_features[f] == kitti_features[f] for f in log_features)
    database = ["--db", store_0005, "--db-source", f"{DRIVE_0005}_sync", "--db-camera", "image_00", "--steps", "2"]
    timed = {"latency_ms", "measurement_ms", "measurement_latency_ms"}
    for mode in ("paper", "refined"):
        runs = {}
        for name, source in (("kitti", [kitti_root, "--drive", DRIVE_0005, "--camera", "image_00"]),
                             ("log", [tmp_path / FORMATS["mcap"]])):
            result = run_cli("localize", *source, *database, "--mode", mode, "--json", tmp_path / f"{name}.json")
            assert result.returncode == 0, result.stderr
            runs[name] = [{k: v for k, v in s.items() if k not in timed} for s in _steps(tmp_path / f"{name}.json")]
        if mode == "paper":
            assert runs["kitti"] == runs["log"]
            continue
        for a, b in zip(runs["kitti"], runs["log"]):
            for what in ("measurement", "estimate"):
                if a[f"{what}_lat_deg"] is not None:
                    north_m = (a[f"{what}_lat_deg"] - b[f"{what}_lat_deg"]) * 111_320.0
                    east_m = (a[f"{what}_lon_deg"] - b[f"{what}_lon_deg"]) * M_PER_DEG_LON
                    assert math.hypot(north_m, east_m) < 1e-6, (what, a["step"], math.hypot(north_m, east_m))
            assert a["measurement_source"] == b["measurement_source"] and a["best_db_frame"] == b["best_db_frame"]
