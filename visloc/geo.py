"""Geodesy: the local metric frame and distances between geotags.

Local frame: east, north, up in metres, the azimuthal equidistant projection
(geodesics on WGS84, pyproj) centred on an origin geotag. visloc puts the origin at the
geotag of the first database image (earliest timestamp) of the drive in use.
Over a few kilometres the projection's scale error is below 1e-6.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from pyproj import Geod

from visloc.errors import ParameterError

EARTH_MEAN_RADIUS_M = 6_371_008.8  # IUGG mean radius, for the Haversine formula
_GEOD = Geod(ellps="WGS84")


@dataclass(frozen=True)
class LocalFrame:
    """East/north metres around (origin_lat_deg, origin_lon_deg)."""

    origin_lat_deg: float
    origin_lon_deg: float

    def __post_init__(self) -> None:
        if not (-90 <= self.origin_lat_deg <= 90 and -180 <= self.origin_lon_deg <= 180):
            raise ParameterError(f"origin ({self.origin_lat_deg}, {self.origin_lon_deg}): not a valid lat/lon in degrees")

    def to_local(self, lat_deg, lon_deg) -> np.ndarray:
        """(..., 2) east_m, north_m of the given geotags: the geodesic from the origin, its length along its
        azimuth (the azimuthal equidistant projection, as PROJ's ``aeqd`` computes it, without its snapping of
        points within 0.6 mm of the origin onto it)."""
        lat, lon = np.broadcast_arrays(np.asarray(lat_deg, float), np.asarray(lon_deg, float))
        azimuth_deg, _, distance_m = _GEOD.inv(np.full(lon.shape, self.origin_lon_deg),
                                               np.full(lat.shape, self.origin_lat_deg), lon, lat)
        azimuth = np.radians(azimuth_deg)
        return np.stack([distance_m * np.sin(azimuth), distance_m * np.cos(azimuth)], axis=-1)

    def to_geo(self, east_north_m) -> tuple[np.ndarray, np.ndarray]:
        """(lat_deg, lon_deg) of local east/north positions (..., 2): ``to_local``'s inverse."""
        en = np.asarray(east_north_m, float)
        east, north = en[..., 0], en[..., 1]
        lon, lat, _ = _GEOD.fwd(np.full(east.shape, self.origin_lon_deg), np.full(east.shape, self.origin_lat_deg),
                                np.degrees(np.arctan2(east, north)), np.hypot(east, north))
        return np.asarray(lat), np.asarray(lon)


def geodesic_distance_m(lat1_deg, lon1_deg, lat2_deg, lon2_deg) -> np.ndarray:
    """Distance on the WGS84 ellipsoid (pyproj Geod.inv), metres."""
    shape = np.broadcast(np.asarray(lat1_deg), np.asarray(lon1_deg), np.asarray(lat2_deg), np.asarray(lon2_deg)).shape
    args = [np.broadcast_to(np.asarray(a, float), shape).ravel() for a in (lon1_deg, lat1_deg, lon2_deg, lat2_deg)]
    _, _, dist = _GEOD.inv(*args)
    return np.asarray(dist, float).reshape(shape)


def moved_deg(lat_deg: float, lon_deg: float, east_m: float, north_m: float) -> tuple[float, float]:
    """(lat, lon) of the point ``east_m``, ``north_m`` from (``lat_deg``, ``lon_deg``), along the WGS84 geodesic."""
    distance_m = math.hypot(east_m, north_m)
    if distance_m == 0.0:
        return float(lat_deg), float(lon_deg)
    lon, lat, _ = _GEOD.fwd(lon_deg, lat_deg, math.degrees(math.atan2(east_m, north_m)), distance_m)
    return float(lat), float(lon)


def haversine_distance_m(lat1_deg, lon1_deg, lat2_deg, lon2_deg) -> np.ndarray:
    """Great-circle distance on a sphere of the mean Earth radius (the paper's formula), metres."""
    lat1, lon1, lat2, lon2 = (np.radians(np.asarray(a, float)) for a in (lat1_deg, lon1_deg, lat2_deg, lon2_deg))
    a = np.sin((lat2 - lat1) / 2) ** 2 + np.cos(lat1) * np.cos(lat2) * np.sin((lon2 - lon1) / 2) ** 2
    return 2 * EARTH_MEAN_RADIUS_M * np.arcsin(np.sqrt(np.clip(a, 0.0, 1.0)))


def yaw_enu_to_heading_deg(yaw_rad: float) -> float:
    """KITTI OXTS yaw (0 = east, counter-clockwise) to compass heading (0 = north, clockwise), degrees."""
    return (90.0 - math.degrees(yaw_rad)) % 360.0
