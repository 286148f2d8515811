"""Image sequences with geotags: KITTI raw drives and a generic folder + CSV.

A ``Drive`` is a list of ``Frame`` (image file, timestamp, geotag) from one
camera, plus the camera's rectified projection matrix when known. Nothing here
computes anything; it reads files and checks that they agree.

KITTI raw layout: ``ROOT/<date>/<date>_drive_<NNNN>_sync/`` with ``image_0X/data/*.png``,
``image_0X/timestamps.txt`` (falls back to ``oxts/timestamps.txt``), ``oxts/data/*.txt``
(lat, lon, alt, roll, pitch, yaw, ...) and ``ROOT/<date>/calib_cam_to_cam.txt``
(``P_rect_0X``, ``R_rect_00``), ``calib_velo_to_cam.txt`` and ``calib_imu_to_velo.txt``
(rigid transforms, read by ``visloc.sources.calibration``). Timestamps are read as UTC and kept as Unix
seconds; each line must be later than the one before. Every text file is read as UTF-8.

An image's geotag is its OXTS record's position at the image's time. KITTI's synced record of a frame is the
100 Hz record nearest the image, up to 5 ms from it (0.05 m at 10 m/s, along the road): where the camera has
timestamps of its own, the record's position is moved on by its velocity (``ve``, ``vn``) for the time between
them. A camera without its own takes the records' times, and their positions as they are.

KITTI's OXTS record also states its position accuracy (field 24, ``pos_accuracy``, metres,
north/east): read as ``Frame.position_accuracy_m``, the standard deviation per horizontal axis. A record
whose position mode (field 28, ``posmode``) is negative had no position solution: KITTI filled it in (its
position extrapolated, its other fields copied from the next real record), so its stated accuracy is not
its own and is read as unknown (None).

CSV: a header with ``file,timestamp,lat,lon`` and optionally ``alt`` (metres), ``heading``
(compass degrees, 0 = north, clockwise), ``roll_deg``, ``pitch_deg`` and ``accuracy_m``;
``file`` is a path inside the CSV's folder, relative to it (not absolute, no ``..`` leading out of
it, symbolic links resolved; a symbolic link inside may point anywhere, as those
``scripts/kitti_to_csv.py`` makes do); ``timestamp`` is seconds (any epoch) or ISO 8601, and no two
rows may share one (rows may come in any order: frames are ordered by time).
``roll_deg``, ``pitch_deg`` and ``heading`` give the attitude of the geotag's reference frame
(x forward, y left, z up) in KITTI's OXTS convention: roll about x, pitch about y (same signs
as OXTS), yaw_rad = radians(90 - heading) wrapped to (-pi, pi]; a row has an attitude only
when all three are present. ``accuracy_m`` is the geotag's stated accuracy, the standard
deviation per horizontal axis in metres (> 0). Empty cells mean unknown. A
``calibration.json`` beside the CSV gives the camera's intrinsics, distortion and pose on the
vehicle (format: ``visloc.sources.calibration``); the refined mode needs it and the attitudes. The CSV is
UTF-8, with or without a byte-order mark.
"""

from __future__ import annotations

import csv
import hashlib
import datetime as _dt
import io
import math
import os
import re
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from visloc.sources.calibration import (
    CALIBRATION_FILE,
    read_calibration,
    read_kitti_calibration,
    read_kitti_image_size,
    read_kitti_extrinsics,
    read_text,
)
from visloc.errors import InputError
from visloc.sources.oxts import MAX_GEOTAG_MOVE_M, geotag_at_image_time, read_oxts
from visloc.features.sift import to_gray_u8
from visloc.geometry.projective import CameraModel

KITTI_CAMERAS = ("image_00", "image_01", "image_02", "image_03")
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")


@dataclass(frozen=True)
class Frame:
    frame: int
    image_path: Path
    timestamp_s: float
    lat_deg: float
    lon_deg: float
    alt_m: float | None = None
    heading_deg: float | None = None
    # attitude of the geotag's reference frame, OXTS convention (see db.ImageRecord); None if unknown
    roll_rad: float | None = None
    pitch_rad: float | None = None
    yaw_rad: float | None = None
    position_accuracy_m: float | None = None  # stated geotag accuracy, sigma per horizontal axis, m; None if unknown


@dataclass(frozen=True)
class Drive:
    source: str  # the drive's name, as the store's images.source column and the --db-source flags name it
    camera: str
    frames: tuple[Frame, ...]
    P_rect: np.ndarray | None = None  # (3, 4) rectified projection matrix, pixels
    image_size_px: tuple[int, int] | None = None  # (width, height)
    T_camera_imu: np.ndarray | None = None  # (4, 4) X_camera = T_camera_imu @ X_imu, metres (KITTI calibration)
    # OpenCV distortion coefficients of the images (CSV calibration.json); ingest undistorts keypoints
    # to the pinhole K = P_rect[:, :3]. None: the images are already pinhole (KITTI's rectified ones).
    distortion: np.ndarray | None = None
    notes: tuple[str, ...] = ()  # what reading it changed, for the user (e.g. intrinsics scaled to the images)

    def __len__(self) -> int:
        return len(self.frames)

    @property
    def timestamps_s(self) -> np.ndarray:
        return np.array([f.timestamp_s for f in self.frames])

    @property
    def lat_deg(self) -> np.ndarray:
        return np.array([f.lat_deg for f in self.frames])

    @property
    def lon_deg(self) -> np.ndarray:
        return np.array([f.lon_deg for f in self.frames])

    @property
    def name(self) -> str:
        return f"{self.source}/{self.camera}"

    @property
    def camera_model(self) -> CameraModel | None:
        """The camera's calibration (intrinsics and extrinsics), None when either is unknown."""
        if self.P_rect is None or self.T_camera_imu is None:
            return None
        return CameraModel.from_projection(self.P_rect, self.T_camera_imu)


def default_data_root() -> Path:
    """$VISLOC_DATA, else ../shared/data/kitti beside the checkout, else relative to the working folder."""
    env = os.environ.get("VISLOC_DATA")
    if env:
        return Path(env)
    beside_checkout = Path(__file__).resolve().parent.parent.parent / "shared" / "data" / "kitti"
    return beside_checkout if beside_checkout.is_dir() else Path("../shared/data/kitti")


def load_gray(path: Path) -> np.ndarray:
    """Read an image file as 2-D uint8 gray; ``InputError`` naming the file if it is missing or corrupt."""
    return read_image(path)[0]


def read_image(path: Path) -> tuple[np.ndarray, str, int]:
    """(the image as 2-D uint8 gray, the SHA-256 of the file's bytes (hex), their count), from one read
    of the file; ``InputError`` naming the file if it is missing or corrupt."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: image file not found")
    data = np.fromfile(path, dtype=np.uint8)
    image = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    if image is None:
        raise InputError(f"{path}: cannot decode image (corrupt or not an image)")
    return to_gray_u8(image, name=str(path)), hashlib.sha256(data).hexdigest(), int(data.size)


def file_digest(path: Path) -> tuple[str, int] | None:
    """(SHA-256 of the file's bytes (hex), their count), None when the file cannot be read."""
    try:
        data = Path(path).read_bytes()
    except OSError:
        return None
    return hashlib.sha256(data).hexdigest(), len(data)


# -- KITTI raw -------------------------------------------------------------------

def kitti_drives(root: Path) -> list[str]:
    """Names of the ``*_sync`` drive folders under a KITTI raw root."""
    root = Path(root)
    if not root.is_dir():
        raise InputError(f"{root}: KITTI data root not found (set it with the ROOT argument or VISLOC_DATA)")
    return sorted(p.name for p in root.glob("*/*_drive_*_sync") if p.is_dir())


def resolve_drive(root: Path, drive: str | None) -> Path:
    """Folder of ``drive`` (with or without the ``_sync`` suffix); the only drive if None."""
    drives = kitti_drives(root)
    if not drives:
        raise InputError(f"{root}: no KITTI drive folders (<date>/<date>_drive_NNNN_sync) found")
    if drive is None:
        if len(drives) > 1:
            raise InputError(f"{root}: holds {len(drives)} drives, choose one with --drive ({', '.join(drives)})")
        drive = drives[0]
    name = drive if drive.endswith("_sync") else drive + "_sync"
    match = re.match(r"(\d{4}_\d{2}_\d{2})_drive_\d{4}_sync$", name)
    if not match:
        raise InputError(f"--drive {drive!r}: expected a name like 2011_09_26_drive_0001")
    folder = Path(root) / match.group(1) / name
    if not folder.is_dir():
        raise InputError(f"{folder}: drive not found (available: {', '.join(drives)})")
    return folder


def _read_timestamps(path: Path) -> list[float]:
    """Unix seconds of each line of a KITTI ``timestamps.txt``; each must be later than the one before."""
    out: list[float] = []
    previous = (0, "")  # line number and text of the last timestamp
    for line_no, line in enumerate(read_text(path).split("\n"), 1):
        line = line.strip()
        if not line:
            continue
        # KITTI writes nanoseconds; datetime takes microseconds.
        day, dot, frac = line.partition(".")
        try:
            if dot and not (frac.isascii() and frac.isdigit()):
                raise ValueError(frac)
            stamp = _dt.datetime.strptime(day, "%Y-%m-%d %H:%M:%S").replace(tzinfo=_dt.timezone.utc)
        except ValueError:
            raise InputError(f"{path}:{line_no}: not a timestamp: {line[:40]!r}") from None
        t = stamp.timestamp() + float("0." + (frac or "0"))
        if out and t <= out[-1]:
            what = "repeats" if t == out[-1] else f"is earlier than {previous[1]!r}"
            raise InputError(f"{path}:{previous[0]} and :{line_no}: timestamp {line[:40]!r} {what}; "
                             "timestamps must increase")
        out.append(t)
        previous = (line_no, line)
    return out


def oxts_records(folder: Path) -> tuple[np.ndarray, np.ndarray]:
    """A KITTI drive folder's OXTS records as numbers, (N, fields) in ``OXTS_FIELDS`` order, and their Unix
    timestamps (UTC, as every timestamp visloc reads), s."""
    files = sorted((Path(folder) / "oxts" / "data").glob("*.txt"))
    records = np.array([[float(v) for v in read_text(path).split()] for path in files])
    return records, np.array(_read_timestamps(Path(folder) / "oxts" / "timestamps.txt"))


def _record_stamps(folder: Path, image_stamps_path: Path, n_images: int) -> list[float] | None:
    """The OXTS records' timestamps where the camera has timestamps of its own (KITTI's synced record of a frame
    is the one nearest the image, up to half the OXTS period, 5 ms, away from it); None where the images take
    the records' times (no ``timestamps.txt`` of their own) or the records have none."""
    path = folder / "oxts" / "timestamps.txt"
    if image_stamps_path == path or not path.is_file():
        return None
    stamps = _read_timestamps(path)
    if len(stamps) != n_images:
        raise InputError(f"{path}: {len(stamps)} timestamps for {n_images} OXTS records; counts must match")
    return stamps


def open_kitti(root: Path, drive: str | None, camera: str) -> Drive:
    """One camera of a KITTI raw drive, every frame checked for an image and an OXTS record."""
    if camera not in KITTI_CAMERAS:
        raise InputError(f"--camera {camera!r}: must be one of {', '.join(KITTI_CAMERAS)}")
    folder = resolve_drive(Path(root), drive)
    image_dir = folder / camera / "data"
    oxts_dir = folder / "oxts" / "data"
    if not image_dir.is_dir():
        raise InputError(f"{image_dir}: image folder not found")
    if not oxts_dir.is_dir():
        raise InputError(f"{oxts_dir}: OXTS folder not found (geotags are required)")
    images = sorted(p for p in image_dir.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    oxts = sorted(oxts_dir.glob("*.txt"))
    if not images:
        raise InputError(f"{image_dir}: no images")
    if len(images) != len(oxts):
        raise InputError(f"{folder}: {len(images)} images in {camera} but {len(oxts)} OXTS records; counts must match")
    stamps_path = folder / camera / "timestamps.txt"
    if not stamps_path.is_file():
        stamps_path = folder / "oxts" / "timestamps.txt"
    if not stamps_path.is_file():
        raise InputError(f"{folder / camera / 'timestamps.txt'}: no timestamps (nor oxts/timestamps.txt)")
    stamps = _read_timestamps(stamps_path)
    if len(stamps) != len(images):
        raise InputError(f"{stamps_path}: {len(stamps)} timestamps for {len(images)} images; counts must match")
    record_stamps = _record_stamps(folder, stamps_path, len(images))
    frames = []
    for i, (img, rec, t) in enumerate(zip(images, oxts, stamps, strict=True)):
        if img.stem != rec.stem:
            raise InputError(f"{rec}: OXTS record does not pair with image {img.name}")
        lat, lon, alt, heading, roll, pitch, yaw, accuracy, velocity_en = read_oxts(rec)
        if record_stamps is not None and velocity_en is not None:
            move_m = math.hypot(*velocity_en) * abs(t - record_stamps[i])
            if move_m > MAX_GEOTAG_MOVE_M:
                raise InputError(f"{rec}: {move_m:.1f} m from where image {img.name} was taken ({t - record_stamps[i]:+.3f}"
                                 f" s at {math.hypot(*velocity_en):.1f} m/s; at most {MAX_GEOTAG_MOVE_M:g} m): "
                                 f"{stamps_path} and {folder / 'oxts' / 'timestamps.txt'} do not pair")
            lat, lon = geotag_at_image_time(lat, lon, velocity_en, t - record_stamps[i])
        frames.append(Frame(frame=i, image_path=img, timestamp_s=t, lat_deg=lat, lon_deg=lon, alt_m=alt,
                            heading_deg=heading, roll_rad=roll, pitch_rad=pitch, yaw_rad=yaw,
                            position_accuracy_m=accuracy))
    calib = read_kitti_calibration(folder.parent / "calib_cam_to_cam.txt", camera)
    extrinsics = read_kitti_extrinsics(folder.parent, camera) if calib is not None else None
    size = read_kitti_image_size(folder.parent / "calib_cam_to_cam.txt", camera) if calib is not None else None
    return Drive(source=folder.name, camera=camera, frames=tuple(frames), P_rect=calib, image_size_px=size,
                    T_camera_imu=extrinsics)


# -- folder of images + CSV ------------------------------------------------------

def _parse_time(text: str, where: str) -> float:
    try:
        t = float(text)
    except ValueError:
        try:
            stamp = _dt.datetime.fromisoformat(text.strip())
        except ValueError:
            raise InputError(f"{where}: column timestamp: neither seconds nor ISO 8601: {text[:40]!r}") from None
        if stamp.tzinfo is None:
            stamp = stamp.replace(tzinfo=_dt.timezone.utc)
        t = stamp.timestamp()
    if not math.isfinite(t):
        raise InputError(f"{where}: column timestamp: not a finite number: {text[:40]!r}")
    return t


def _number(row: dict[str, str], column: str, where: str) -> float | None:
    """The finite number in ``column`` (None if the cell is empty or the column absent)."""
    text = row.get(column, "")
    if not text:
        return None
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not math.isfinite(value):
        raise InputError(f"{where}: column {column}: not a finite number: {text[:40]!r}")
    return value


def heading_deg_to_yaw_rad(heading_deg: float) -> float:
    """Compass heading (0 = north, clockwise, degrees) to OXTS yaw (0 = east, counter-clockwise),
    radians in (-pi, pi]."""
    yaw = math.radians(90.0 - heading_deg % 360.0)  # in (-3 pi / 2, pi / 2]
    return yaw + 2.0 * math.pi if yaw <= -math.pi else yaw


def _image_path(name: str, folder: Path, inside: Path, where: str) -> Path:
    """``folder / name``, refused if ``name`` is absolute or its ``..`` lead out of ``inside`` (the folder
    resolved; ``..`` after a symbolic link is resolved as the system does, from the link's target)."""
    path = folder / name
    try:
        ok = "\x00" not in name and not Path(name).is_absolute() and (
            ".." not in Path(name).parts or path.resolve().is_relative_to(inside))
    except (OSError, RuntimeError, ValueError):  # a symbolic-link loop, a name too long
        ok = False
    if not ok:
        raise InputError(f"{where}: column file: {name[:60]!r} must be a path inside {inside}")
    return path


def _csv_frame(row: dict[str, str], frame: int, folder: Path, inside: Path, where: str) -> Frame:
    if not row["file"]:
        raise InputError(f"{where}: column file: empty file name")
    image_path = _image_path(row["file"], folder, inside, where)
    t = _parse_time(row["timestamp"], where)
    lat, lon = _number(row, "lat", where), _number(row, "lon", where)
    if lat is None or lon is None or not (-90 <= lat <= 90 and -180 <= lon <= 180):
        raise InputError(f"{where}: lat/lon out of range ({row['lat'][:40]!r}, {row['lon'][:40]!r})")
    heading = _number(row, "heading", where)
    heading = None if heading is None else heading % 360.0
    roll, pitch = _number(row, "roll_deg", where), _number(row, "pitch_deg", where)
    if pitch is not None and not -90.0 <= pitch <= 90.0:
        raise InputError(f"{where}: column pitch_deg: must be within [-90, 90], got {pitch!r}")
    accuracy = _number(row, "accuracy_m", where)
    if accuracy is not None and accuracy <= 0:
        raise InputError(f"{where}: column accuracy_m: must be > 0 (standard deviation, metres), got {accuracy!r}")
    attitude = (None, None, None)
    if None not in (roll, pitch, heading):
        attitude = (math.radians(roll), math.radians(pitch), heading_deg_to_yaw_rad(heading))
    return Frame(frame=frame, image_path=image_path, timestamp_s=t, lat_deg=lat, lon_deg=lon,
                 alt_m=_number(row, "alt", where), heading_deg=heading, roll_rad=attitude[0],
                 pitch_rad=attitude[1], yaw_rad=attitude[2], position_accuracy_m=accuracy)


def _rows(csv_path: Path) -> list[tuple[int, dict[str, str]]]:
    """(line number, row with stripped keys and values) of every data row, the header checked."""
    reader = csv.DictReader(io.StringIO(read_text(csv_path, encoding="utf-8-sig"), newline=""))
    try:
        header = [h.strip() for h in (reader.fieldnames or [])]
        missing = {"file", "timestamp", "lat", "lon"} - set(header)
        if missing:
            raise InputError(f"{csv_path}: missing column(s) {', '.join(sorted(missing))} (need file,timestamp,lat,lon)")
        attitude_columns = {"roll_deg", "pitch_deg", "heading"}
        if {"roll_deg", "pitch_deg"} & set(header) and not attitude_columns <= set(header):
            lacking = ", ".join(sorted(attitude_columns - set(header)))
            raise InputError(f"{csv_path}: roll_deg, pitch_deg and heading give the attitude together; missing {lacking}")
        # keys: None gathers the cells beyond the header; values: None for cells a short row lacks
        return [(reader.line_num, {k.strip(): (v or "").strip() for k, v in row.items() if k})
                for row in reader]
    except csv.Error as exc:
        raise InputError(f"{csv_path}:{reader.reader.line_num}: not readable as CSV ({exc})") from None


def open_csv(csv_path: Path, *, source: str | None = None, camera: str = "camera") -> Drive:
    """A drive brought as images plus a CSV of geotags, and ``calibration.json`` beside it when present
    (see the module docstring), its frames ordered by time."""
    csv_path = Path(csv_path)
    if not csv_path.is_file():
        raise InputError(f"{csv_path}: CSV file not found")
    rows = _rows(csv_path)
    if not rows:
        raise InputError(f"{csv_path}: no rows")
    folder = csv_path.parent
    inside = folder.resolve()
    # frame = data row number, so appending rows to the CSV keeps earlier frames' identity
    parsed = [_csv_frame(row, frame, folder, inside, f"{csv_path}:{line_no}")
              for frame, (line_no, row) in enumerate(rows)]
    frames = tuple(sorted(parsed, key=lambda f: (f.timestamp_s, f.frame)))
    for a, b in zip(frames, frames[1:]):
        if a.timestamp_s == b.timestamp_s:
            (line_a, row_a), (line_b, row_b) = rows[a.frame], rows[b.frame]
            same = (f"timestamp {row_a['timestamp'][:40]} repeats" if row_a["timestamp"] == row_b["timestamp"] else
                    f"timestamps {row_a['timestamp'][:40]} and {row_b['timestamp'][:40]} are the same time")
            raise InputError(f"{csv_path}:{line_a} and :{line_b}: {same}; timestamps must increase")
    source = source or csv_path.parent.name
    calibration_path = csv_path.parent / CALIBRATION_FILE
    if not calibration_path.is_file():
        return Drive(source=source, camera=camera, frames=frames)
    calib = read_calibration(calibration_path)
    return Drive(source=source, camera=camera, frames=frames, P_rect=calib.P_rect,
                    image_size_px=(calib.width_px, calib.height_px), T_camera_imu=calib.T_camera_imu,
                    distortion=calib.distortion)
