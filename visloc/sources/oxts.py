"""KITTI's OXTS records: an image's geotag, attitude, stated accuracy and velocity, read from one record.

A record is one line of 30 numbers (KITTI's ``dataformat.txt``): lat, lon, alt, roll, pitch, yaw, then the
velocities (vn, ve, ...), accelerations and rates, then pos_accuracy (field 24), ..., posmode (field 28).
An image's geotag is its record's position at the image's time (``geotag_at_image_time``).
"""

from __future__ import annotations

import math
from pathlib import Path

from visloc.errors import InputError
from visloc.geo import moved_deg, yaw_enu_to_heading_deg
from visloc.sources.calibration import read_text

OXTS_FIELDS = ("lat", "lon", "alt", "roll", "pitch", "yaw")  # the first 6 of an OXTS record's 30
OXTS_POS_ACCURACY, OXTS_POSMODE = 24, 28  # 1-based field numbers of pos_accuracy and posmode
OXTS_VN, OXTS_VE = 7, 8  # 1-based field numbers of the north and east velocities, m/s
# farthest an image's geotag is moved from its OXTS record (a car at 40 m/s moves 0.2 m in KITTI's 5 ms): farther,
# the image and its record were not taken together
MAX_GEOTAG_MOVE_M = 1.0


def read_oxts(path: Path) -> tuple[float, float, float, float, float, float, float, float | None,
                                    tuple[float, float] | None]:
    """(lat_deg, lon_deg, alt_m, heading_deg, roll_rad, pitch_rad, yaw_rad, position_accuracy_m, velocity_en_mps)
    of one OXTS record; the accuracy is None when the record states none of its own (``_stated_accuracy_m``),
    the (east, north) velocity (fields ``ve`` and ``vn``) None when the record has none or it is not finite."""
    tokens = read_text(path).split()
    values = []
    for i, token in enumerate(tokens, 1):
        name = f" ({OXTS_FIELDS[i - 1]})" if i <= len(OXTS_FIELDS) else ""
        try:
            values.append(float(token))
        except ValueError:
            raise InputError(f"{path}: unreadable OXTS record: field {i}{name} is not a number: {token[:40]!r}") \
                from None
        if i <= len(OXTS_FIELDS) and not math.isfinite(values[-1]):
            raise InputError(f"{path}: OXTS record field {i}{name} is not a finite number: {token[:40]!r}")
    if len(values) < 6:
        raise InputError(f"{path}: OXTS record needs at least 6 numbers (lat lon alt roll pitch yaw), "
                         f"found {len(values)}")
    lat, lon, alt, roll, pitch, yaw = values[:6]
    if not (-90 <= lat <= 90 and -180 <= lon <= 180):
        raise InputError(f"{path}: lat/lon out of range ({lat}, {lon})")
    velocity_en = None
    if len(values) >= OXTS_VE and math.isfinite(values[OXTS_VE - 1]) and math.isfinite(values[OXTS_VN - 1]):
        velocity_en = (values[OXTS_VE - 1], values[OXTS_VN - 1])
    return lat, lon, alt, yaw_enu_to_heading_deg(yaw), roll, pitch, yaw, _stated_accuracy_m(values), velocity_en


def _stated_accuracy_m(values: list[float]) -> float | None:
    """An OXTS record's stated position accuracy (field 24), None when absent, not finite, not > 0, or not the
    record's own: a record with a negative position mode (field 28) had no position solution."""
    if len(values) < OXTS_POS_ACCURACY:
        return None
    accuracy = values[OXTS_POS_ACCURACY - 1]
    if not (math.isfinite(accuracy) and accuracy > 0):
        return None
    if len(values) >= OXTS_POSMODE and values[OXTS_POSMODE - 1] < 0:
        return None
    return accuracy


def geotag_at_image_time(lat_deg: float, lon_deg: float, velocity_en_mps: tuple[float, float] | None,
                         image_minus_record_s: float) -> tuple[float, float]:
    """The geotag of an image taken ``image_minus_record_s`` after its OXTS record: the record's position moved
    on by the record's east/north velocity for that time (the record's own where it states no velocity)."""
    if velocity_en_mps is None or image_minus_record_s == 0.0:
        return lat_deg, lon_deg
    east_mps, north_mps = velocity_en_mps
    return moved_deg(lat_deg, lon_deg, east_mps * image_minus_record_s, north_mps * image_minus_record_s)
