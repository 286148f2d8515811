"""What a vehicle's log holds, turned into a drive's frames: pure functions over numbers and arrays.

* geotags: each image paired with the fix at its time, interpolated between the two fixes around it when
  they are at most ``max_gap_ns`` apart (a fix at the image's very time is taken as it is);
* attitude: the orientation at the image's time, interpolated (slerp) the same way, as OXTS roll, pitch
  and yaw (the vehicle frame x forward, y left, z up, relative to east-north-up);
* the camera's pose on the vehicle from the static transform tree;
* image messages (``sensor_msgs/Image``) as OpenCV arrays (gray, BGR or BGRA, 8 or 16 bit).

Times are integer nanoseconds, so that a fix stamped at an image's own time is matched exactly.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from visloc.errors import InputError
from visloc.geometry.projective import rigid, rotation_from_quaternion, rpy_from_rotation

NO_FIX = -1  # sensor_msgs/NavSatStatus.STATUS_NO_FIX


@dataclass(frozen=True)
class Fixes:
    """Valid fixes of a ``NavSatFix`` topic, in time order."""

    stamp_ns: np.ndarray  # (N,) int64
    lat_deg: np.ndarray
    lon_deg: np.ndarray
    alt_m: np.ndarray
    sigma_m: np.ndarray  # stated accuracy, standard deviation per horizontal axis; nan when unknown


@dataclass(frozen=True)
class Paired:
    """One image's geotag: position, stated accuracy, and the gap between the fixes it came from."""

    lat_deg: float
    lon_deg: float
    alt_m: float | None  # None: the fixes state none (NaN)
    sigma_m: float | None
    gap_s: float  # 0 when a fix lies at the image's time


def horizontal_sigma_m(covariance: np.ndarray, covariance_type: int) -> float:
    """A ``NavSatFix``'s stated accuracy: the standard deviation per horizontal axis, sqrt of the mean of the
    east and north variances (nan when its covariance type is unknown, 0, or the variances are not > 0)."""
    if covariance_type == 0 or len(covariance) != 9:
        return math.nan
    east, north = float(covariance[0]), float(covariance[4])
    if not (math.isfinite(east) and math.isfinite(north) and east > 0 and north > 0):
        return math.nan
    return math.sqrt((east + north) / 2.0)


def bracket(stamps_ns: np.ndarray, t_ns: int, max_gap_ns: int) -> tuple[int, int, float] | None:
    """(index before, index after, weight of the after one) of the samples around ``t_ns``: the same index
    twice with weight 0 when a sample lies at ``t_ns``; None when ``t_ns`` lies outside the samples or
    between two more than ``max_gap_ns`` apart."""
    j = int(np.searchsorted(stamps_ns, t_ns))
    if j < len(stamps_ns) and stamps_ns[j] == t_ns:
        return j, j, 0.0
    if j == 0 or j == len(stamps_ns):
        return None
    gap = int(stamps_ns[j]) - int(stamps_ns[j - 1])
    if gap > max_gap_ns:
        return None
    return j - 1, j, (t_ns - int(stamps_ns[j - 1])) / gap


def pair_fix(fixes: Fixes, t_ns: int, max_gap_ns: int) -> Paired | None:
    """The geotag at ``t_ns`` (see the module docstring); None when no fixes lie close enough around it."""
    found = bracket(fixes.stamp_ns, t_ns, max_gap_ns)
    if found is None:
        return None
    a, b, w = found

    def at(values: np.ndarray) -> float | None:
        value = float(values[a]) if a == b else float(values[a] + w * (values[b] - values[a]))
        return None if math.isnan(value) else value

    sigma = float(np.max(fixes.sigma_m[[a, b]]))  # the larger; nan if either is unknown (np.max keeps a nan)
    return Paired(at(fixes.lat_deg), at(fixes.lon_deg), at(fixes.alt_m), None if math.isnan(sigma) else sigma,
                  (int(fixes.stamp_ns[b]) - int(fixes.stamp_ns[a])) / 1e9)


def slerp(q0: np.ndarray, q1: np.ndarray, w: float) -> np.ndarray:
    """Spherical interpolation of unit quaternions (x, y, z, w) by weight ``w`` in [0, 1]."""
    q0, q1 = np.asarray(q0, float), np.asarray(q1, float)
    if w == 0.0:
        return q0
    dot = float(q0 @ q1)
    if dot < 0.0:
        q1, dot = -q1, -dot
    if dot > 0.9995:
        q = q0 + w * (q1 - q0)
        return q / np.linalg.norm(q)
    theta = math.acos(dot)
    return (math.sin((1 - w) * theta) * q0 + math.sin(w * theta) * q1) / math.sin(theta)


def attitude_at(stamps_ns: np.ndarray, quaternions: np.ndarray, t_ns: int,
                max_gap_ns: int) -> tuple[float, float, float] | None:
    """(roll, pitch, yaw) in radians at ``t_ns`` from orientation samples (N, 4) as (x, y, z, w); None when
    none lie close enough around it."""
    found = bracket(stamps_ns, t_ns, max_gap_ns)
    if found is None:
        return None
    a, b, w = found
    return rpy_from_rotation(rotation_from_quaternion(slerp(quaternions[a], quaternions[b], w)))


def transform_matrix(translation: tuple[float, float, float], rotation_xyzw: tuple[float, float, float, float]
                     ) -> np.ndarray:
    """4x4 pose of a ``geometry_msgs/Transform``."""
    return rigid(rotation_from_quaternion(np.asarray(rotation_xyzw, float)), translation)


def chain(transforms: dict[tuple[str, str], np.ndarray], start: str, end: str) -> np.ndarray | None:
    """T_start_end (X_start = T X_end) through a tree of transforms {(parent, child): T_parent_child},
    walked either way; None when the two frames are not connected."""
    if start == end:
        return np.eye(4)
    edges: dict[str, list[tuple[str, np.ndarray]]] = {}
    for (parent, child), T in transforms.items():
        edges.setdefault(parent, []).append((child, T))
        edges.setdefault(child, []).append((parent, np.linalg.inv(T)))
    seen, frontier = {start}, [(start, np.eye(4))]
    while frontier:
        frame, T = frontier.pop()
        for other, step in edges.get(frame, ()):
            if other in seen:
                continue
            if other == end:
                return T @ step
            seen.add(other)
            frontier.append((other, T @ step))
    return None


PIXEL_LAYOUT = {  # encoding: (dtype, channels, OpenCV conversion to what cv2.imwrite takes, or None)
    "mono8": (np.uint8, 1, None), "8UC1": (np.uint8, 1, None),
    "mono16": (np.uint16, 1, None), "16UC1": (np.uint16, 1, None),
    "bgr8": (np.uint8, 3, None), "8UC3": (np.uint8, 3, None), "rgb8": (np.uint8, 3, cv2.COLOR_RGB2BGR),
    "bgra8": (np.uint8, 4, None), "8UC4": (np.uint8, 4, None), "rgba8": (np.uint8, 4, cv2.COLOR_RGBA2BGRA),
    "bgr16": (np.uint16, 3, None), "rgb16": (np.uint16, 3, cv2.COLOR_RGB2BGR),
    "bayer_rggb8": (np.uint8, 1, cv2.COLOR_BayerRG2BGR), "bayer_bggr8": (np.uint8, 1, cv2.COLOR_BayerBG2BGR),
    "bayer_gbrg8": (np.uint8, 1, cv2.COLOR_BayerGB2BGR), "bayer_grbg8": (np.uint8, 1, cv2.COLOR_BayerGR2BGR),
}


def image_array(encoding: str, width: int, height: int, step: int, big_endian: bool, data: np.ndarray,
                where: str) -> np.ndarray:
    """A ``sensor_msgs/Image``'s pixels as an array ``cv2.imwrite`` stores (gray, BGR or BGRA, 8 or 16 bit);
    ``InputError`` naming ``where`` for an encoding visloc does not read or a size its data does not fill."""
    if encoding not in PIXEL_LAYOUT:
        raise InputError(f"{where}: image encoding {encoding!r} is not read (known: {', '.join(PIXEL_LAYOUT)})")
    dtype, channels, conversion = PIXEL_LAYOUT[encoding]
    row_bytes = width * channels * np.dtype(dtype).itemsize
    data = np.asarray(data, np.uint8).reshape(-1)
    if width <= 0 or height <= 0 or step < row_bytes or data.size < step * height:
        raise InputError(f"{where}: image of {width}x{height} px ({encoding}, step {step}) does not fit its "
                         f"{data.size} bytes of data")
    rows = data[: step * height].reshape(height, step)[:, :row_bytes]
    pixels = np.ascontiguousarray(rows).view(np.dtype(dtype).newbyteorder(">" if big_endian else "<"))
    pixels = pixels.astype(dtype).reshape((height, width) if channels == 1 else (height, width, channels))
    return pixels if conversion is None else cv2.cvtColor(pixels, conversion)
