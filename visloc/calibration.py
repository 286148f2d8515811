"""A camera's calibration brought beside a CSV drive: ``calibration.json``.

One JSON object, numbers only::

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


def _number(data: dict, key: str, where: str) -> float:
    if key not in data:
        raise InputError(f"{where}: {key}: missing")
    value = data[key]
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise InputError(f"{where}: {key}: expected a finite number, got {value!r}")
    return float(value)


def _size(data: dict, key: str, where: str) -> int:
    if key not in data:
        raise InputError(f"{where}: {key}: missing")
    value = data[key]
    if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
        raise InputError(f"{where}: {key}: expected a positive whole number of pixels, got {value!r}")
    return value


def _matrix(value: object, where: str) -> np.ndarray:
    try:
        T = np.array(value, dtype=float)
    except (TypeError, ValueError):
        T = np.zeros(0)
    if T.size != 16 or T.ndim not in (1, 2) or (T.ndim == 2 and T.shape != (4, 4)):
        raise InputError(f"{where}: T_vehicle_camera: expected a 4x4 matrix (4 rows of 4 numbers, or 16 numbers)")
    T = T.reshape(4, 4)
    if not np.all(np.isfinite(T)):
        raise InputError(f"{where}: T_vehicle_camera: holds a number that is not finite")
    R = T[:3, :3]
    off = max(float(np.abs(R.T @ R - np.eye(3)).max()), abs(float(np.linalg.det(R)) - 1.0),
              float(np.abs(T[3] - (0.0, 0.0, 0.0, 1.0)).max()))
    if off > RIGID_TOLERANCE:
        raise InputError(f"{where}: T_vehicle_camera: not a rigid transform (rotation off by {off:.2g}, "
                         f"tolerance {RIGID_TOLERANCE:g}; last row must be 0 0 0 1)")
    return T


def read_calibration(path: Path) -> Calibration:
    """``calibration.json`` (see the module docstring), checked; ``InputError`` naming the file and key."""
    path = Path(path)
    where = str(path)
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{where}: unreadable ({exc})") from None
    except json.JSONDecodeError as exc:
        raise InputError(f"{where}: not valid JSON (line {exc.lineno}: {exc.msg})") from None
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
        ok = isinstance(d, list) and len(d) in DISTORTION_LENGTHS and all(
            isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in d)
        if not ok:
            raise InputError(f"{where}: distortion: expected a list of 4, 5, 8, 12 or 14 finite numbers "
                             "(OpenCV's k1, k2, p1, p2[, k3, ...])")
        distortion = np.array(d, float) if any(d) else None  # all zero: no distortion
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    return Calibration(K=K, width_px=width_px, height_px=height_px, T_vehicle_camera=T, distortion=distortion)
