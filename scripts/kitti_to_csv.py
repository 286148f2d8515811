"""Export one camera of a KITTI raw drive as a CSV drive (the format of "Bring your own drive").

    .venv/bin/python scripts/kitti_to_csv.py ROOT --drive 2011_09_26_drive_0005 --camera image_00 OUT_DIR [--frames N]

Writes OUT_DIR/geotags.csv (file,timestamp,lat,lon,alt,heading,roll_deg,pitch_deg,accuracy_m),
OUT_DIR/calibration.json (the camera's K and its pose on the vehicle, T_vehicle_camera = inverse of
KITTI's T_camera_imu) and symlinks every image into OUT_DIR/images/ (the CSV names them relative to
its folder). The values are what visloc's own KITTI reader (``visloc.sources.drives.open_kitti``) makes of
the drive, so ``visloc ingest OUT_DIR/geotags.csv`` stores what ``visloc ingest ROOT --drive ...
--camera ...`` does. Numbers are written at full precision (repr): geotags, timestamps, accuracies
and intrinsics read back bit for bit; what changes unit on the way (radians to degrees, yaw to
compass heading, the inverted extrinsics) reads back to within a unit or two in the last place
(compass degrees cannot hold every yaw in radians exactly). Nothing is copied: OUT_DIR needs the
drive to stay where it is. Bad input: a one-line error and exit status 2.
"""

from __future__ import annotations

import argparse
import csv
import math
import sys
from pathlib import Path

import numpy as np

from visloc.sources.calibration import CALIBRATION_FILE, calibration_dict, inverse_pose, write_calibration
from visloc.errors import InputError
from visloc.sources.drives import KITTI_CAMERAS, Frame, load_gray, open_kitti

COLUMNS = ("file", "timestamp", "lat", "lon", "alt", "heading", "roll_deg", "pitch_deg", "accuracy_m")
CSV_NAME = "geotags.csv"
IMAGE_FOLDER = "images"


def _text(value: float | None) -> str:
    """A number at full precision (repr round-trips a float exactly); empty when unknown."""
    return "" if value is None else repr(float(value))


def csv_row(frame: Frame, image_name: str) -> list[str]:
    roll_deg = None if frame.roll_rad is None else math.degrees(frame.roll_rad)
    pitch_deg = None if frame.pitch_rad is None else math.degrees(frame.pitch_rad)
    return [f"{IMAGE_FOLDER}/{image_name}", _text(frame.timestamp_s), _text(frame.lat_deg), _text(frame.lon_deg),
            _text(frame.alt_m), _text(frame.heading_deg), _text(roll_deg), _text(pitch_deg),
            _text(frame.position_accuracy_m)]


def export(root: Path, drive: str | None, camera: str, out_dir: Path, n_frames: int | None = None) -> str:
    """Write the CSV drive; returns a one-line summary."""
    sequence = open_kitti(root, drive, camera)
    frames = sequence.frames if n_frames is None else sequence.frames[:n_frames]
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError(f"{out_dir}: exists and is not a folder")
    if (out_dir / CSV_NAME).exists():
        raise InputError(f"{out_dir / CSV_NAME}: already exists (choose a new OUT_DIR or delete it)")
    width_px = height_px = None
    if sequence.P_rect is not None and sequence.T_camera_imu is not None:
        height_px, width_px = load_gray(frames[0].image_path).shape
    images = out_dir / IMAGE_FOLDER
    try:
        images.mkdir(parents=True, exist_ok=True)  # missing folders on the way are made, as out/ on a fresh clone
    except OSError as exc:
        raise InputError(f"{out_dir}: cannot make the folder ({exc.strerror})") from None
    rows = []
    for frame in frames:
        link = images / frame.image_path.name
        if link.is_symlink() or link.exists():
            link.unlink()
        link.symlink_to(frame.image_path.resolve())
        rows.append(csv_row(frame, frame.image_path.name))
    with (out_dir / CSV_NAME).open("w", newline="") as fh:
        writer = csv.writer(fh, lineterminator="\n")
        writer.writerow(COLUMNS)
        writer.writerows(rows)
    what = f"{out_dir / CSV_NAME}: {len(rows)} frames of {sequence.name}"
    if width_px is None:
        return what + "; no calibration.json (the drive has no calibration files)"
    T_vehicle_camera = inverse_pose(sequence.T_camera_imu)  # the inverse: X_vehicle = T_vehicle_camera @ X_camera
    write_calibration(out_dir / CALIBRATION_FILE,
                      calibration_dict(np.asarray(sequence.P_rect)[:, :3], width_px, height_px, T_vehicle_camera))
    return what + f", {CALIBRATION_FILE} ({width_px}x{height_px} px)"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="kitti_to_csv.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("root", type=Path, help="KITTI raw root (holds <date>/<date>_drive_NNNN_sync)")
    parser.add_argument("out_dir", type=Path, help="folder to write geotags.csv, calibration.json and images/ into")
    parser.add_argument("--drive", default=None, help="drive, e.g. 2011_09_26_drive_0005 (needed if ROOT holds several)")
    parser.add_argument("--camera", default="image_00", choices=KITTI_CAMERAS, help="camera (default %(default)s)")
    parser.add_argument("--frames", type=int, default=None, help="only the first N frames (default: all)")
    a = parser.parse_args(argv)
    try:
        if a.frames is not None and a.frames < 1:
            raise InputError(f"--frames {a.frames}: must be at least 1")
        print(export(a.root, a.drive, a.camera, a.out_dir, a.frames))
    except (InputError, OSError) as exc:
        print(f"kitti_to_csv.py: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
