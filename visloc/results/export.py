"""Trajectories for GIS tools: a run's ground truth, measurements and Kalman estimates (with their
covariance) as GeoJSON (RFC 7946: WGS84, [longitude, latitude]) and as CSV, one row per step.

A run is either series of ``StepRecord`` (localize, evaluate, the dashboard) or the frames of a
``TrackRun`` (track). Both become ``TrajectoryPoint`` rows first; positions stay in the
database's local frame (east, north in metres) there, and latitude and longitude are made here,
at the edge. Covariances are 2x2 east/north, m². Values that do not exist are null in GeoJSON and
empty in CSV; nothing non-finite is written, so strict JSON readers accept the file.
"""

from __future__ import annotations

import csv
import io
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from visloc.errors import ParameterError
from visloc.geo import LocalFrame
from visloc.protocols.records import StepRecord
from visloc.protocols.track import TrackFrame
from visloc.tracking.kalman import covariance_ellipse_m

Position = tuple[float, float]
ELLIPSE_SIGMA = 2.0  # the estimate's ellipse in the GeoJSON: 2σ, as the dashboard draws it
ELLIPSE_POINTS = 36
GEOJSON_SUFFIXES = (".geojson", ".json")


@dataclass(frozen=True)
class TrajectoryPoint:
    """One step of one series, positions in the local frame (east_m, north_m)."""

    series: int
    step: int
    frame: int
    timestamp_s: float
    truth_m: Position
    measurement_m: Position | None
    measurement_source: str | None  # "geotag", "geometry" or None (no measurement)
    measurement_cov_m2: list[list[float]] | None
    estimate_m: Position | None
    estimate_cov_m2: list[list[float]] | None
    measurement_error_m: float | None  # geodesic, against the truth
    estimate_error_m: float | None
    best_db_frame: int | None = None  # the database frame of the best match (of the first view, for a track)


def _cov(value) -> list[list[float]] | None:
    if value is None:
        return None
    m = np.asarray(value, float)
    if m.shape != (2, 2) or not np.all(np.isfinite(m)):
        return None
    return [[float(m[0, 0]), float(m[0, 1])], [float(m[1, 0]), float(m[1, 1])]]


def points_from_records(series: Sequence[Sequence[StepRecord]]) -> list[TrajectoryPoint]:
    return [TrajectoryPoint(k, r.step, r.query_frame, r.query_timestamp_s, r.truth_m, r.measurement_m,
                            r.measurement_source, _cov(r.measurement_cov_m2), r.estimate_m, _cov(r.estimate_cov_m2),
                            r.measurement_error_m, r.estimate_error_m, r.best_db_frame)
            for k, records in enumerate(series) for r in records]


def points_from_track(frames: Sequence[TrackFrame]) -> list[TrajectoryPoint]:
    return [TrajectoryPoint(0, n, f.frame, f.timestamp_s, f.truth_m, f.measurement_m, f.measurement_source,
                            _cov(f.measurement_cov_m2), f.estimate_m, _cov(f.estimate_cov_m2),
                            f.measurement_error_m, f.error_m, f.view_frames[0] if f.view_frames else None)
            for n, f in enumerate(frames)]


def trajectory_points(run) -> list[TrajectoryPoint]:
    """``run``: series of ``StepRecord`` (a list of lists) or a track's ``TrackFrame`` list."""
    run = list(run)
    if all(isinstance(f, TrackFrame) for f in run):
        return points_from_track(run)
    return points_from_records(run)


def finite_or_none(value: float | None) -> float | None:
    """``value`` as a float, None when it is None or not finite (what JSON and CSV files hold for no value)."""
    return None if value is None or not math.isfinite(value) else float(value)


def _lon_lat(frame: LocalFrame, position_m) -> list[float] | None:
    if position_m is None or not np.all(np.isfinite(np.asarray(position_m, float))):
        return None
    lat, lon = frame.to_geo(np.asarray(position_m, float))
    return [round(float(lon), 9), round(float(lat), 9)]  # 1e-9 degree is 0.1 mm


def sigmas_m(cov: list[list[float]] | None) -> tuple[float | None, float | None]:
    """(major, minor) standard deviations of a 2x2 covariance, m; (None, None) for none."""
    if cov is None:
        return None, None
    values = np.sqrt(np.clip(np.linalg.eigvalsh(np.asarray(cov, float)), 0.0, None))
    return float(values[1]), float(values[0])


def _feature(geometry: dict, **properties) -> dict:
    return {"type": "Feature", "geometry": geometry, "properties": properties}


def _line(coords: list[list[float]]) -> dict | None:
    if len(coords) >= 2:
        return {"type": "LineString", "coordinates": coords}
    return {"type": "Point", "coordinates": coords[0]} if coords else None


def trajectory_geojson(run, frame: LocalFrame, *, name: str) -> dict:
    """A FeatureCollection: per series, the truth, measurement and estimate tracks as lines; per step,
    a point for each (measurement and estimate with their covariance) and the estimate's 2σ ellipse
    as a polygon. Every feature's ``kind`` says which."""
    points = trajectory_points(run)
    features: list[dict] = []
    for series in sorted({p.series for p in points}):
        steps = [p for p in points if p.series == series]
        for kind, attr in (("truth track", "truth_m"), ("measurement track", "measurement_m"),
                           ("estimate track", "estimate_m")):
            coords = [c for c in (_lon_lat(frame, getattr(p, attr)) for p in steps) if c is not None]
            geometry = _line(coords)
            if geometry is not None:
                features.append(_feature(geometry, kind=kind, series=series))
        for p in steps:
            common = {"series": series, "step": p.step, "frame": p.frame, "timestamp_s": finite_or_none(p.timestamp_s)}
            truth = _lon_lat(frame, p.truth_m)
            if truth is not None:
                features.append(_feature({"type": "Point", "coordinates": truth}, kind="truth", **common,
                                         east_m=p.truth_m[0], north_m=p.truth_m[1]))
            measured = _lon_lat(frame, p.measurement_m)
            if measured is not None:
                major, minor = sigmas_m(p.measurement_cov_m2)
                features.append(_feature({"type": "Point", "coordinates": measured}, kind="measurement", **common,
                                         source=p.measurement_source, east_m=p.measurement_m[0],
                                         north_m=p.measurement_m[1], cov_m2=p.measurement_cov_m2,
                                         sigma_major_m=major, sigma_minor_m=minor,
                                         error_m=finite_or_none(p.measurement_error_m)))
            estimate = _lon_lat(frame, p.estimate_m)
            if estimate is None:
                continue
            major, minor = sigmas_m(p.estimate_cov_m2)
            features.append(_feature({"type": "Point", "coordinates": estimate}, kind="estimate", **common,
                                     east_m=p.estimate_m[0], north_m=p.estimate_m[1], cov_m2=p.estimate_cov_m2,
                                     sigma_major_m=major, sigma_minor_m=minor, error_m=finite_or_none(p.estimate_error_m)))
            if major:  # a covariance with some spread: its ellipse
                ring_m = covariance_ellipse_m(np.asarray(p.estimate_m), np.asarray(p.estimate_cov_m2),
                                              ELLIPSE_SIGMA, ELLIPSE_POINTS)
                lat, lon = frame.to_geo(ring_m)
                ring = [[round(float(x), 9), round(float(y), 9)] for x, y in zip(lon, lat)]
                ring = ring[::-1] if _signed_area(ring) < 0 else ring  # RFC 7946: exterior rings counterclockwise
                features.append(_feature({"type": "Polygon", "coordinates": [ring + ring[:1]]},
                                         kind=f"estimate {ELLIPSE_SIGMA:g}σ ellipse", **common))
    return {"type": "FeatureCollection", "name": name, "features": features,
            "properties": {"local_frame_origin_lat_deg": frame.origin_lat_deg,
                           "local_frame_origin_lon_deg": frame.origin_lon_deg,
                           "east_north": "metres east and north of the origin (azimuthal equidistant, WGS84)",
                           "cov_m2": "2x2 position covariance, east/north, m²"}}


def _signed_area(ring: list[list[float]]) -> float:
    x, y = np.asarray(ring, float).T
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


CSV_COLUMNS = (
    "series", "step", "frame", "timestamp_s",
    "truth_lat_deg", "truth_lon_deg", "truth_east_m", "truth_north_m",
    "measurement_source", "measurement_lat_deg", "measurement_lon_deg", "measurement_east_m", "measurement_north_m",
    "measurement_cov_ee_m2", "measurement_cov_en_m2", "measurement_cov_nn_m2", "measurement_error_m",
    "estimate_lat_deg", "estimate_lon_deg", "estimate_east_m", "estimate_north_m",
    "estimate_cov_ee_m2", "estimate_cov_en_m2", "estimate_cov_nn_m2", "estimate_error_m",
)


def _geo_columns(frame: LocalFrame, position_m) -> list:
    lon_lat = _lon_lat(frame, position_m)
    if lon_lat is None:
        return ["", "", "", ""]
    return [f"{lon_lat[1]:.9f}", f"{lon_lat[0]:.9f}", f"{position_m[0]:.4f}", f"{position_m[1]:.4f}"]


def _cov_columns(cov: list[list[float]] | None) -> list:
    return ["", "", ""] if cov is None else [f"{cov[0][0]:.6g}", f"{cov[0][1]:.6g}", f"{cov[1][1]:.6g}"]


def _number(value: float | None, fmt: str = ".4f") -> str:
    value = finite_or_none(value)
    return "" if value is None else f"{value:{fmt}}"


def trajectory_csv(run, frame: LocalFrame) -> str:
    """One row per step: truth, measurement and estimate as latitude/longitude and local metres,
    each covariance as its three distinct entries (m²), and the geodesic errors."""
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(CSV_COLUMNS)
    for p in trajectory_points(run):
        writer.writerow([p.series, p.step, p.frame, _number(p.timestamp_s, ".6f"),
                         *_geo_columns(frame, p.truth_m),
                         p.measurement_source or "", *_geo_columns(frame, p.measurement_m),
                         *_cov_columns(p.measurement_cov_m2), _number(p.measurement_error_m),
                         *_geo_columns(frame, p.estimate_m), *_cov_columns(p.estimate_cov_m2),
                         _number(p.estimate_error_m)])
    return out.getvalue()


def trajectory_format(path: Path) -> str:
    """"geojson" or "csv" from a file's suffix; anything else is a one-line error naming the file."""
    suffix = Path(path).suffix.lower()
    if suffix in GEOJSON_SUFFIXES:
        return "geojson"
    if suffix == ".csv":
        return "csv"
    raise ParameterError(f"{path}: a trajectory file ends in .geojson, .json or .csv")


def trajectory_text(run, frame: LocalFrame, *, name: str, fmt: str) -> str:
    """``run`` (series of StepRecord, or TrackFrame list) as the text of a "geojson" or "csv" file."""
    if fmt == "geojson":
        return json.dumps(trajectory_geojson(run, frame, name=name), ensure_ascii=False, allow_nan=False)
    return trajectory_csv(run, frame)


def write_trajectory(path: Path, run, frame: LocalFrame, *, name: str) -> None:
    """Write ``run`` (series of StepRecord, or TrackFrame list) as GeoJSON or CSV, by ``path``'s suffix."""
    Path(path).write_text(trajectory_text(run, frame, name=name, fmt=trajectory_format(path)), encoding="utf-8")
