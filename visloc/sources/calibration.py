"""A camera's calibration: ``calibration.json`` beside a CSV drive, and KITTI's calibration files.

``calibration.json`` is UTF-8 (a byte-order mark is skipped), one JSON object, numbers only::

    {"fx": 721.5377, "fy": 721.5377, "cx": 609.5593, "cy": 172.854,
     "width_px": 1242, "height_px": 375,
     "distortion": [-0.37, 0.2, 0.0022, 0.0014, -0.072],
     "T_vehicle_camera": [[0, 0, 1, 1.08],
                          [-1, 0, 0, -0.31],
                          [0, -1, 0, 0.73],
                          [0, 0, 0, 1]]}

``fx, fy, cx, cy``  pinhole intrinsics in pixels (focal lengths > 0); ``width_px``, ``height_px``
the size of every image of the drive. ``distortion`` (optional) is OpenCV's coefficients
``[k1, k2, p1, p2, k3]`` (4, 5, 8, 12 or 14 numbers, OpenCV's order); when given, ingest
undistorts every keypoint to the pinhole camera ``fx, fy, cx, cy`` before storing it.
``T_vehicle_camera`` is the camera's pose in the geotag's reference frame, a 4x4 rigid
transform in metres, row by row (a list of 4 rows, or 16 numbers): X_vehicle =
T_vehicle_camera @ X_camera, with the vehicle frame x forward, y left, z up (the frame whose
attitude ``roll_deg, pitch_deg, heading`` give) and the camera frame x right, y down,
z forward. visloc stores ``P_rect = [K | 0]`` and ``T_camera_imu = inverse(T_vehicle_camera)``.

KITTI's ``calib_cam_to_cam.txt`` (``P_rect_0X``, ``R_rect_00``), ``calib_velo_to_cam.txt`` and
``calib_imu_to_velo.txt`` (``R``, ``T``) hold ``key: numbers`` lines; each value read must be finite
and the 3x3 part of ``P_rect_0X`` regular.
Camera extrinsics (KITTI's chain, all rigid, metres): a point X_imu in the OXTS/IMU
frame is X_velo = T_velo_imu X_imu, X_cam0 = T_cam0_velo X_velo (unrectified left
gray camera), then rotated by R_rect_00 into the common rectified frame, and camera N
sits at t_N = K^-1 P_rect_0N[:, 3] from the rectified camera 0 (for image_01 about
-0.54 m in x: 0.54 m to the right). So T_camera_imu = [I | t_N] R_rect_00 T_cam0_velo
T_velo_imu, and the rectified intrinsics are K = P_rect_0N[:, :3]. The product's rotation is taken to the nearest
rotation (KITTI writes its rotations to 6-8 digits: their product is a rotation to about 1e-7).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from visloc.errors import InputError

CALIBRATION_FILE = "calibration.json"
DISTORTION_LENGTHS = (4, 5, 8, 12, 14)  # what OpenCV takes
RIGID_TOLERANCE = 1e-3  # max |R'R - I| and |det R - 1| of T_vehicle_camera's rotation


@dataclass(frozen=True)
class Calibration:
    """A pinhole camera and where it sits on the vehicle."""

    K: np.ndarray  # (3, 3) pixels
    width_px: int
    height_px: int
    T_vehicle_camera: np.ndarray  # (4, 4) metres: X_vehicle = T_vehicle_camera @ X_camera
    distortion: np.ndarray | None = None  # OpenCV coefficients of the images, None: none

    @property
    def P_rect(self) -> np.ndarray:
        """(3, 4) [K | 0]."""
        return np.c_[self.K, np.zeros(3)]

    @property
    def T_camera_imu(self) -> np.ndarray:
        """(4, 4) X_camera = T_camera_imu @ X_vehicle: the matrix inverse of ``T_vehicle_camera``."""
        return inverse_pose(self.T_vehicle_camera)


def calibration_dict(K: np.ndarray, width_px: int, height_px: int, T_vehicle_camera: np.ndarray,
                     distortion: np.ndarray | None = None) -> dict:
    """What ``calibration.json`` holds, as a JSON-ready dict (floats at full precision)."""
    K = np.asarray(K, float)
    out = {"fx": float(K[0, 0]), "fy": float(K[1, 1]), "cx": float(K[0, 2]), "cy": float(K[1, 2]),
           "width_px": int(width_px), "height_px": int(height_px)}
    if distortion is not None:
        out["distortion"] = [float(v) for v in np.asarray(distortion, float).ravel()]
    out["T_vehicle_camera"] = np.asarray(T_vehicle_camera, float).tolist()
    return out


def inverse_pose(T: np.ndarray) -> np.ndarray:
    """inverse(T) of a 4x4 pose, last row exactly 0 0 0 1: ``T_camera_imu`` from ``T_vehicle_camera``
    and, for writing the file, ``T_vehicle_camera`` from ``T_camera_imu``."""
    out = np.linalg.inv(np.asarray(T, float))
    out[3] = (0.0, 0.0, 0.0, 1.0)
    return out


def write_calibration(path: Path, calibration: dict) -> None:
    """``calibration.json``, one key per line and one matrix row per line."""
    def value(key: str, v: object) -> str:
        if key == "T_vehicle_camera":
            return "[\n  " + ",\n  ".join(json.dumps(row) for row in v) + "]"
        return json.dumps(v)
    body = ",\n".join(f" {json.dumps(k)}: {value(k, v)}" for k, v in calibration.items())
    Path(path).write_text("{\n" + body + "\n}\n")


def read_text(path: Path, *, encoding: str = "utf-8") -> str:
    """A text file's content; ``InputError`` naming the file, and the line of the first byte that is not
    UTF-8, if it is unreadable (``encoding="utf-8-sig"`` also takes a leading byte-order mark)."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise InputError(f"{path}: unreadable ({exc.strerror or exc})") from None
    try:
        return data.decode(encoding)
    except UnicodeDecodeError as exc:
        line = data[: exc.start].count(b"\n") + 1
        raise InputError(f"{path}:{line}: not UTF-8 text (byte 0x{data[exc.start]:02x}); save the file as UTF-8") \
            from None


def _finite(value: object) -> bool:
    """A JSON number (not a bool) that is finite as a float (an int too large for a float is not)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return False
    try:
        return math.isfinite(value)
    except OverflowError:
        return False


def _number(data: dict, key: str, where: str) -> float:
    if key not in data:
        raise InputError(f"{where}: {key}: missing")
    value = data[key]
    if not _finite(value):
        raise InputError(f"{where}: {key}: expected a finite number, got {_short(value)}")
    return float(value)


def _short(value: object) -> str:
    """``repr(value)`` cut to one short line, for messages."""
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


def _size(data: dict, key: str, where: str) -> int:
    if key not in data:
        raise InputError(f"{where}: {key}: missing")
    value = data[key]
    if isinstance(value, bool) or not isinstance(value, int) or not 0 < value < 2**31:
        raise InputError(f"{where}: {key}: expected a positive whole number of pixels, got {_short(value)}")
    return value


def _matrix(value: object, where: str) -> np.ndarray:
    if isinstance(value, list) and len(value) == 4 and all(isinstance(row, list) and len(row) == 4 for row in value):
        numbers = [v for row in value for v in row]
    elif isinstance(value, list) and len(value) == 16 and not any(isinstance(v, list) for v in value):
        numbers = value
    else:
        raise InputError(f"{where}: T_vehicle_camera: expected a 4x4 matrix (4 rows of 4 numbers, or 16 numbers)")
    if not all(_finite(v) for v in numbers):
        raise InputError(f"{where}: T_vehicle_camera: holds a value that is not a finite number")
    T = np.array(numbers, dtype=float).reshape(4, 4)
    R = T[:3, :3]
    with np.errstate(over="ignore", invalid="ignore"):  # huge entries: off is inf or nan, refused below
        off = float(np.max([np.abs(R.T @ R - np.eye(3)).max(), abs(np.linalg.det(R) - 1.0),
                            np.abs(T[3] - (0.0, 0.0, 0.0, 1.0)).max()]))  # nan if any is nan
    if not off <= RIGID_TOLERANCE:
        raise InputError(f"{where}: T_vehicle_camera: not a rigid transform (rotation off by {off:.2g}, "
                         f"tolerance {RIGID_TOLERANCE:g}; last row must be 0 0 0 1)")
    return T


def read_calibration(path: Path) -> Calibration:
    """``calibration.json`` (see the module docstring), checked; ``InputError`` naming the file and key."""
    path = Path(path)
    where = str(path)
    text = read_text(path, encoding="utf-8-sig")
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise InputError(f"{where}: not valid JSON (line {exc.lineno}: {exc.msg})") from None
    except (ValueError, RecursionError) as exc:  # e.g. an integer of more than 4300 digits, or nesting too deep
        raise InputError(f"{where}: not a calibration file ({str(exc).splitlines()[0][:80]})") from None
    if not isinstance(data, dict):
        raise InputError(f"{where}: expected a JSON object with fx, fy, cx, cy, width_px, height_px, "
                         "T_vehicle_camera")
    known = {"fx", "fy", "cx", "cy", "width_px", "height_px", "distortion", "T_vehicle_camera"}
    unknown = sorted(set(data) - known)
    if unknown:
        raise InputError(f"{where}: {unknown[0]}: unknown key (expected {', '.join(sorted(known))})")
    fx, fy, cx, cy = (_number(data, key, where) for key in ("fx", "fy", "cx", "cy"))
    for key, value in (("fx", fx), ("fy", fy)):
        if value <= 0:
            raise InputError(f"{where}: {key}: focal length must be > 0, got {value!r}")
    width_px, height_px = _size(data, "width_px", where), _size(data, "height_px", where)
    if "T_vehicle_camera" not in data:
        raise InputError(f"{where}: T_vehicle_camera: missing (the camera's pose on the vehicle, 4x4)")
    T = _matrix(data["T_vehicle_camera"], where)
    distortion = None
    if data.get("distortion") is not None:
        d = data["distortion"]
        ok = isinstance(d, list) and len(d) in DISTORTION_LENGTHS and all(_finite(v) for v in d)
        if not ok:
            raise InputError(f"{where}: distortion: expected a list of 4, 5, 8, 12 or 14 finite numbers "
                             "(OpenCV's k1, k2, p1, p2[, k3, ...])")
        distortion = np.array(d, float) if any(d) else None  # all zero: no distortion
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    return Calibration(K=K, width_px=width_px, height_px=height_px, T_vehicle_camera=T, distortion=distortion)


# -- KITTI's calibration files ---------------------------------------------------

def _calib_entries(path: Path) -> dict[str, str]:
    """The ``key: values`` lines of a KITTI calibration file (the first line of a repeated key)."""
    out: dict[str, str] = {}
    for line in read_text(path).split("\n"):
        key, sep, rest = line.partition(":")
        if sep:
            out.setdefault(key.strip(), rest)
    return out


def _calib_numbers(path: Path, entries: dict[str, str], key: str, count: int) -> np.ndarray | None:
    """The ``count`` finite numbers of ``key``, None if the file has no such key."""
    if key not in entries:
        return None
    try:
        values = np.array([float(v) for v in entries[key].split()])
    except ValueError:
        values = np.array([])
    if values.size != count:
        raise InputError(f"{path}: {key} must hold {count} numbers")
    if not np.all(np.isfinite(values)):
        raise InputError(f"{path}: {key} holds a number that is not finite")
    return values


def read_kitti_calibration(calib_path: Path, camera: str) -> np.ndarray | None:
    """``P_rect_0X`` (3x4) from ``calib_cam_to_cam.txt``, or None if the file is absent."""
    if not calib_path.is_file():
        return None
    key = "P_rect_" + camera[-2:]
    values = _calib_numbers(calib_path, _calib_entries(calib_path), key, 12)
    if values is None:
        raise InputError(f"{calib_path}: no {key} entry")
    P = values.reshape(3, 4)
    try:
        with np.errstate(all="ignore"):
            sv = np.linalg.svd(P[:, :3], compute_uv=False)
    except np.linalg.LinAlgError:
        sv = np.zeros(3)
    if not sv[-1] > 1e-9 * sv[0]:  # also inf or nan singular values, from numbers near the float limit
        raise InputError(f"{calib_path}: {key}: its 3x3 part is singular (no camera projects so)")
    return P


def read_kitti_image_size(calib_path: Path, camera: str) -> tuple[int, int] | None:
    """(width, height) in pixels of the rectified images, ``S_rect_0X`` of ``calib_cam_to_cam.txt``;
    None if the file or the entry is absent."""
    if not calib_path.is_file():
        return None
    key = "S_rect_" + camera[-2:]
    values = _calib_numbers(calib_path, _calib_entries(calib_path), key, 2)
    if values is None:
        return None
    if not (np.all(values >= 1) and np.all(values == np.round(values))):
        raise InputError(f"{calib_path}: {key} must be two whole numbers of pixels >= 1")
    return int(values[0]), int(values[1])


def _rigid(entries: dict[str, str], path: Path, r_key: str = "R", t_key: str = "T") -> np.ndarray:
    R, t = _calib_numbers(path, entries, r_key, 9), _calib_numbers(path, entries, t_key, 3)
    if R is None or t is None:
        raise InputError(f"{path}: needs {r_key} (9 numbers) and {t_key} (3 numbers)")
    T = np.eye(4)
    T[:3, :3] = R.reshape(3, 3)
    T[:3, 3] = t
    return T


def read_kitti_extrinsics(date_folder: Path, camera: str) -> np.ndarray | None:
    """T_camera_imu (4x4, metres) of a rectified KITTI camera, or None if a calibration file is absent.

    See the module docstring for the chain of transforms.
    """
    paths = [date_folder / n for n in ("calib_cam_to_cam.txt", "calib_velo_to_cam.txt", "calib_imu_to_velo.txt")]
    if not all(p.is_file() for p in paths):
        return None
    cam, velo, imu = (_calib_entries(p) for p in paths)
    T_velo_imu = _rigid(imu, paths[2])
    T_cam0_velo = _rigid(velo, paths[1])
    r_rect = _calib_numbers(paths[0], cam, "R_rect_00", 9)
    if r_rect is None:
        raise InputError(f"{paths[0]}: no R_rect_00 entry with 9 numbers")
    T_rect_cam0 = np.eye(4)
    T_rect_cam0[:3, :3] = r_rect.reshape(3, 3)
    P = read_kitti_calibration(paths[0], camera)  # its 3x3 part is regular
    T_camera_rect = np.eye(4)
    with np.errstate(all="ignore"):
        T_camera_rect[:3, 3] = np.linalg.solve(P[:, :3], P[:, 3])  # baseline of camera N in the rectified frame
        T = T_camera_rect @ T_rect_cam0 @ T_cam0_velo @ T_velo_imu
    return _rigid_part(T, paths)


def _rigid_part(T: np.ndarray, paths: list[Path]) -> np.ndarray:
    """``T`` with its rotation replaced by the nearest rotation (SVD): KITTI's calibration rotations are written
    to 6-8 digits, so their product is a rotation to about 1e-7 only, and a camera's pose is rigid (a log's
    transform tree, quaternions, can only say a rigid one). A product further than ``RIGID_TOLERANCE`` from
    any rotation is refused."""
    R = T[:3, :3]
    if not np.all(np.isfinite(T)):
        raise InputError(f"{paths[0].parent}: the camera's calibration chain holds a value that is not finite")
    U, _, Vt = np.linalg.svd(R)
    nearest = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    if not np.abs(nearest - R).max() <= RIGID_TOLERANCE:
        raise InputError(f"{paths[0].parent}: calib_*.txt: the camera's calibration chain is not a rigid transform "
                         f"(its rotation is off by {np.abs(nearest - R).max():.2g}, tolerance {RIGID_TOLERANCE:g})")
    out = T.copy()
    out[:3, :3] = nearest
    return out
