"""Reading KITTI raw drives and CSV drives, and refusing inconsistent ones."""

import shutil

import cv2
import numpy as np
import pytest

from visloc.errors import InputError
from visloc.geo import LocalFrame
from visloc.sources.drives import load_gray, open_csv, open_kitti
from visloc.sources.opening import open_source

from helpers import make_fake_kitti, run_cli, write_csv_drive


def test_fake_kitti_reads_geotags_timestamps_and_calibration(tmp_path):
    make_fake_kitti(tmp_path, n_frames=3)
    seq = open_kitti(tmp_path, "2011_09_26_drive_0001", "image_01")
    assert seq.source == "2011_09_26_drive_0001_sync" and seq.camera == "image_01" and len(seq) == 3
    assert seq.frames[1].lat_deg == pytest.approx(49.015003823272 - 1e-5)
    assert seq.frames[2].timestamp_s - seq.frames[0].timestamp_s == pytest.approx(0.2, abs=1e-6)
    assert seq.P_rect[0, 3] == pytest.approx(-387.5744)
    # yaw -2.6 rad = -148.969 deg (ENU, 0 = east) is compass heading 90 + 148.969 = 238.969 deg
    assert seq.frames[0].heading_deg == pytest.approx(238.969, abs=0.001)


def test_the_only_drive_is_chosen_without_drive_flag(tmp_path):
    make_fake_kitti(tmp_path)
    assert open_source(tmp_path, camera="image_00").source == "2011_09_26_drive_0001_sync"


def test_timestamps_fall_back_to_oxts(tmp_path):
    drive = make_fake_kitti(tmp_path)
    (drive / "image_00" / "timestamps.txt").unlink()
    seq = open_kitti(tmp_path, None, "image_00")
    assert seq.frames[1].timestamp_s - seq.frames[0].timestamp_s == pytest.approx(0.1, abs=1e-6)


def _records_behind_the_images(drive, lag_s: float, east_mps: float, north_mps: float) -> None:
    """Every OXTS record taken ``lag_s`` before its image, the car moving at (east, north) m/s."""
    stamps = drive / "oxts" / "timestamps.txt"
    stamps.write_text("".join(f"2011-09-26 13:02:{25 + i * 0.1 - lag_s:012.9f}\n"
                              for i in range(len(stamps.read_text().split("\n")) - 1)))
    for record in sorted((drive / "oxts" / "data").glob("*.txt")):
        values = record.read_text().split()
        values[6], values[7] = f"{north_mps}", f"{east_mps}"  # fields 7 (vn) and 8 (ve)
        record.write_text(" ".join(values) + "\n")


def test_a_geotag_is_its_records_position_at_the_images_time(tmp_path):
    """KITTI's synced record of a frame is the 100 Hz record nearest the image, up to 5 ms from it: the image's
    geotag is the record's position moved on by its velocity for the time between them."""
    drive = make_fake_kitti(tmp_path, n_frames=3)
    taken_together = open_kitti(tmp_path, None, "image_00")
    _records_behind_the_images(drive, lag_s=0.004, east_mps=10.0, north_mps=-5.0)
    seq = open_kitti(tmp_path, None, "image_00")
    for before, after in zip(taken_together.frames, seq.frames):
        moved = LocalFrame(before.lat_deg, before.lon_deg).to_local(after.lat_deg, after.lon_deg)
        np.testing.assert_allclose(moved, [0.04, -0.02], atol=1e-6)  # 4 ms at 10 m/s east, 5 m/s south
        assert after.timestamp_s == before.timestamp_s  # the image's time, as before
    # a camera without timestamps of its own takes the records' times, and their positions as they are
    (drive / "image_01" / "timestamps.txt").unlink()
    records = open_kitti(tmp_path, None, "image_01")
    assert [(f.lat_deg, f.lon_deg) for f in records.frames] == [(f.lat_deg, f.lon_deg) for f in taken_together.frames]
    # a record farther from its image than a car goes in a few milliseconds is no record of it: refused, named
    _records_behind_the_images(drive, lag_s=0.2, east_mps=10.0, north_mps=0.0)
    with pytest.raises(InputError, match=r"0000000000.txt: 2.0 m from where image 0000000000.png was taken .*"
                                         r"do not pair"):
        open_kitti(tmp_path, None, "image_00")


def test_missing_calibration_is_allowed(tmp_path):
    make_fake_kitti(tmp_path, with_calib=False)
    assert open_kitti(tmp_path, None, "image_00").P_rect is None


def test_colour_and_16_bit_images_become_8_bit_gray(tmp_path):
    rgb = np.zeros((8, 8, 3), np.uint8)
    rgb[..., 2] = 255  # red in BGR
    cv2.imwrite(str(tmp_path / "c.png"), rgb)
    cv2.imwrite(str(tmp_path / "w.png"), np.full((8, 8), 65535, np.uint16))
    assert load_gray(tmp_path / "c.png").shape == (8, 8) and load_gray(tmp_path / "c.png")[0, 0] == 76
    assert load_gray(tmp_path / "w.png")[0, 0] == 255


@pytest.mark.parametrize("breakage,message", [
    ("no_oxts", "oxts/data: OXTS folder not found"),
    ("unequal", "3 images in image_00 but 2 OXTS records"),
    ("no_images", "image_00/data: image folder not found"),
    ("bad_oxts", "0000000001.txt: unreadable OXTS record"),
    ("bad_timestamps", "timestamps.txt:2: not a timestamp"),
])
def test_broken_kitti_drives_are_refused_naming_the_file(tmp_path, breakage, message):
    drive = make_fake_kitti(tmp_path, n_frames=3, with_oxts=breakage != "no_oxts")
    if breakage == "unequal":
        (drive / "oxts" / "data" / "0000000002.txt").unlink()
    elif breakage == "no_images":
        shutil.rmtree(drive / "image_00")
    elif breakage == "bad_oxts":
        (drive / "oxts" / "data" / "0000000001.txt").write_text("49.0 eight")
    elif breakage == "bad_timestamps":
        (drive / "image_00" / "timestamps.txt").write_text("2011-09-26 13:02:25.0\nyesterday\n2011-09-26 13:02:25.2\n")
    with pytest.raises(InputError, match=message) as err:
        open_kitti(tmp_path, None, "image_00")
    assert "\n" not in str(err.value)


def test_unknown_drive_and_camera_are_named(tmp_path):
    make_fake_kitti(tmp_path)
    with pytest.raises(InputError, match="2011_09_26_drive_0009_sync: drive not found"):
        open_kitti(tmp_path, "2011_09_26_drive_0009", "image_00")
    with pytest.raises(InputError, match="--camera 'image_07'"):
        open_kitti(tmp_path, None, "image_07")
    with pytest.raises(InputError, match="KITTI data root not found"):
        open_kitti(tmp_path / "nowhere", None, "image_00")


def test_missing_and_corrupt_images_are_named(tmp_path):
    with pytest.raises(InputError, match="gone.png: image file not found"):
        load_gray(tmp_path / "gone.png")
    (tmp_path / "bad.png").write_bytes(b"\x89PNG\r\n\x1a\nthis is not really a png")
    with pytest.raises(InputError, match="bad.png: cannot decode image"):
        load_gray(tmp_path / "bad.png")


def test_csv_drive_sorted_by_time_with_row_numbers_as_frames(tmp_path):
    csv_path = write_csv_drive(tmp_path / "d", n_frames=4)
    lines = csv_path.read_text().splitlines()
    csv_path.write_text("\n".join([lines[0], lines[3], lines[1], lines[2], lines[4]]) + "\n")
    seq = open_csv(csv_path)
    assert [f.frame for f in seq.frames] == [1, 2, 0, 3]
    assert np.all(np.diff(seq.timestamps_s) > 0)
    assert seq.frames[0].heading_deg == 90.0 and seq.source == "d"


@pytest.mark.parametrize("content,message", [
    ("file,timestamp,lat\nx.png,1,49\n", "missing column"),
    ("file,timestamp,lat,lon\n", "no rows"),
    ("file,timestamp,lat,lon\nx.png,1,95,8\n", r"geotags.csv:2: lat/lon out of range"),
    ("file,timestamp,lat,lon\nx.png,soon,49,8\n", r"geotags.csv:2:"),
])
def test_bad_csv_is_refused_naming_the_line(tmp_path, content, message):
    path = tmp_path / "geotags.csv"
    path.write_text(content)
    with pytest.raises(InputError, match=message):
        open_csv(path)


def test_iso_timestamps_are_accepted(tmp_path):
    path = tmp_path / "g.csv"
    path.write_text("file,timestamp,lat,lon\na.png,2011-09-26T13:02:25.5,49,8\nb.png,2011-09-26T13:02:26.5,49,8\n")
    seq = open_csv(path)
    assert seq.frames[1].timestamp_s - seq.frames[0].timestamp_s == pytest.approx(1.0)


def test_kitti_attitudes_and_camera_extrinsics_are_read(tmp_path):
    make_fake_kitti(tmp_path, n_frames=2)
    left = open_kitti(tmp_path, None, "image_00")
    right = open_kitti(tmp_path, None, "image_01")
    assert (left.frames[0].roll_rad, left.frames[0].pitch_rad, left.frames[0].yaw_rad) == (0.03, 0.01, -2.6)
    # the IMU origin in camera 0: velodyne (-0.8, 0.3, -0.8) -> camera (-0.3, 0.8, -0.8) + (0, -0.08, -0.27)
    np.testing.assert_allclose(left.T_camera_imu[:3, 3], [-0.3, 0.72, -1.07], atol=1e-12)
    # the IMU's forward axis is the camera's optical axis, its left axis the camera's -x
    np.testing.assert_allclose(left.T_camera_imu[:3, :3] @ [1, 0, 0], [0, 0, 1], atol=1e-12)
    np.testing.assert_allclose(left.T_camera_imu[:3, :3] @ [0, 1, 0], [-1, 0, 0], atol=1e-12)
    # image_01 is the same rectified frame shifted by P_rect_01's baseline, -387.5744 / 721.5377 m in x
    np.testing.assert_allclose(right.T_camera_imu[:3, 3] - left.T_camera_imu[:3, 3], [-387.5744 / 721.5377, 0, 0])


@pytest.mark.parametrize("accuracy,expected", [("0.3", 0.3), ("0", None), ("-1", None), ("nan", None), (None, None)])
def test_kitti_position_accuracy_is_field_24(tmp_path, accuracy, expected):
    drive = make_fake_kitti(tmp_path, n_frames=2)
    record = drive / "oxts" / "data" / "0000000001.txt"
    values = record.read_text().split()
    if accuracy is None:
        values = values[:23]  # a short record: no pos_accuracy
    else:
        values[23] = accuracy  # field 24, pos_accuracy (m)
    record.write_text(" ".join(values) + "\n")
    seq = open_kitti(tmp_path, None, "image_00")
    assert seq.frames[1].position_accuracy_m == expected
    assert seq.frames[0].position_accuracy_m is None  # make_fake_kitti states 0: unknown


@pytest.mark.parametrize("posmode,expected", [("6", 0.3), ("0", 0.3), ("-1", None), ("-1.00000000000000", None)])
def test_a_kitti_record_with_no_position_solution_states_no_accuracy(tmp_path, posmode, expected):
    """A record KITTI filled in (position mode -1, as 2011_10_03_drive_0027's first 14) copies the next real record's
    accuracy: it is not its own."""
    drive = make_fake_kitti(tmp_path, n_frames=2)
    record = drive / "oxts" / "data" / "0000000001.txt"
    values = record.read_text().split()
    values[23], values[27] = "0.3", posmode  # fields 24 (pos_accuracy) and 28 (posmode)
    record.write_text(" ".join(values) + "\n")
    assert open_kitti(tmp_path, None, "image_00").frames[1].position_accuracy_m == expected


def test_info_says_how_many_geotags_are_no_fix(tmp_path):
    drive = make_fake_kitti(tmp_path, n_frames=3)
    for i, record in enumerate(sorted((drive / "oxts" / "data").glob("*.txt"))):
        values = record.read_text().split()
        values[23], values[27] = "0.05", "-1" if i == 0 else "6"
        record.write_text(" ".join(values) + "\n")
    result = run_cli("info", tmp_path, "--camera", "image_00")
    assert result.returncode == 0, result.stderr
    assert "stated geotag accuracy 0.05-0.05 m (none for 1 of them: no position fix" in result.stdout, result.stdout


def test_extrinsics_need_every_calibration_file(tmp_path):
    make_fake_kitti(tmp_path)
    (tmp_path / "2011_09_26" / "calib_imu_to_velo.txt").unlink()
    seq = open_kitti(tmp_path, None, "image_00")
    assert seq.P_rect is not None and seq.T_camera_imu is None
