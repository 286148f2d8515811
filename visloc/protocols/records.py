"""What one localized query was, against its ground truth: ``StepRecord``, shared by every report.

Records keep positions in the local metric frame (east, north in metres, ``visloc.geo``).
Geotags appear only where they are data: the query's ground-truth geotag, and the database
geotag a paper-style measurement *is*. Latitude and longitude of computed positions are made
at the edge (``record_geotags``: JSON, tables, the page). Errors are geodesic distances on
WGS84, with the paper's Haversine distance beside them.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from visloc.sources.drives import Drive
from visloc.store.database import GeoDatabase, QuerySet, same_drive
from visloc.geo import LocalFrame, geodesic_distance_m, haversine_distance_m
from visloc.tracking.localizer import StepResult
from visloc.pose.measurement import GEOMETRY, GEOTAG
from visloc.tracking.kalman import SmoothedStep
from visloc.params import REFINED
from visloc.pose.uncertainty import unstated_geotags

Position = tuple[float, float]  # (east_m, north_m) in the database's local frame


@dataclass
class StepRecord:
    """One query of a run, everything a report or a dashboard shows."""

    step: int
    query_frame: int
    query_timestamp_s: float
    truth_geotag_deg: tuple[float, float]  # (lat_deg, lon_deg): the query's recorded geotag
    truth_m: Position
    n_candidates: int
    best_db_index: int | None  # index into the database of the best match
    best_db_frame: int | None
    best_count: int
    best_offset_s: float | None  # best match's timestamp minus the query's
    measurement_m: Position | None
    measurement_geotag_deg: tuple[float, float] | None  # a geotag measurement: the database image's recorded geotag
    estimate_m: Position | None
    estimate_sigma_m: float | None  # sqrt of the largest eigenvalue of the position covariance
    measurement_error_m: float | None  # geodesic (WGS84)
    estimate_error_m: float | None
    measurement_error_haversine_m: float | None
    estimate_error_haversine_m: float | None
    latency_ms: float
    nearest_candidate_error_m: float | None = None  # floor: the candidate geotag closest to the truth
    estimate_cov_m2: list[list[float]] | None = None  # 2x2 east/north position covariance of the estimate
    counts: list[int] = field(default_factory=list, repr=False)
    candidate_frames: list[int] = field(default_factory=list, repr=False)
    # what the measurement was and how the filter took it
    measurement_source: str | None = None  # "geometry", "geotag" or None (no measurement)
    fallback_reason: str | None = None  # refined method: why this step's measurement is a geotag
    measurement_cov_m2: list[list[float]] | None = None  # its covariance, m^2 (east, north): a refined pose's own, the
    #   filter's R for a geotag
    measurement_sigma_m: float | None = None  # sqrt of its largest eigenvalue
    # e' C^-1 e of the measurement error e (about 2 on average if C is honest): C = R where the truth comes from
    # the map's own receiver (truth_shares_map), else R + the map's absolute error + the truth's, a^2 I + s^2 I
    measurement_nees: float | None = None
    truth_sigma_m: float | None = None  # s: the ground-truth geotag's stated accuracy, m per axis (None: unknown)
    truth_shares_map: bool = False  # the truth and the database's geotags come from one drive's receiver
    absolute_sigma_m: float | None = None  # a: refined: the map's own error (its geotags' stated accuracy), m per axis
    measurement_side: str | None = None  # refined: "both" (views before and after the pose) or "one"
    measurement_lever_m: float | None = None  # refined: distance to the nearest view's geotag, m
    measurement_term_sigma_m: dict = field(default_factory=dict)  # refined: sigma of each part of R, m
    estimate_nees: float | None = None  # the estimate's error against its covariance P, as measurement_nees
    mahalanobis: float | None = None  # innovation's Mahalanobis distance to the prediction
    gated: bool = False  # rejected by the filter's gate: this step only predicted
    maneuver: bool = False  # applied with the filter's maneuver prediction (visloc.tracking.kalman)
    retracted_previous: bool = False  # the filter took the previous step's measurement out (visloc.tracking.kalman)
    view_db_frames: list[int] = field(default_factory=list)  # refined: database frames the pose was solved against
    neighbour_db_frames: list[int] = field(default_factory=list)  # refined: frames triangulated with those views
    n_pnp_inliers: int = 0  # refined: the pose's 2D-3D inliers (a query keypoint seen in two views counts twice)
    n_pnp_query_keypoints: int = 0  # refined: the distinct query keypoints among them
    thin_support: bool = False  # refined: posed at the looser thin-support threshold (Measurement.thin_support)
    measurement_ms: float = 0.0  # time the measurement took on the query side (refined: matching, RANSAC, PnP)
    measurement_heading_deg: float | None = None  # refined: compass heading of the pose
    smoothed_m: Position | None = None  # RTS smoother (evaluate --smooth)
    smoothed_error_m: float | None = None


def _position(xy) -> Position:
    return float(xy[0]), float(xy[1])


def truth_extra_m2(absolute_sigma_m: float | None, truth_sigma_m: float | None, truth_shares_map: bool) -> float:
    """What the truth a position is compared with adds to its covariance, per axis (m^2): nothing where the truth
    shares the map's receiver (its absolute error then cancels), else the map's absolute error a^2 and the
    truth's own s^2 (``visloc.pose.uncertainty``; None or NaN: none)."""
    if truth_shares_map:
        return 0.0
    a = float(absolute_sigma_m) if absolute_sigma_m is not None else 0.0
    s = float(truth_sigma_m) if truth_sigma_m is not None and np.isfinite(truth_sigma_m) else 0.0
    return a**2 + s**2


def nees_against_truth(position_m, cov_m2, truth_m, extra_m2: float) -> float | None:
    """NEES of a position against the truth: e' (cov + extra I)^-1 e (2 on average when honest); None without
    a finite position or a covariance. The one rule every run's records use."""
    if position_m is None or cov_m2 is None or not np.all(np.isfinite(position_m)):
        return None
    e = np.asarray(position_m, float)[:2] - np.asarray(truth_m, float)[:2]
    return float(e @ np.linalg.solve(np.asarray(cov_m2, float) + extra_m2 * np.eye(2), e))


def step_record(step: int, result: StepResult, db: GeoDatabase, *, query_frame: int, truth_lat_deg: float,
                truth_lon_deg: float, latency_ms: float, keep_counts: bool = False,
                smoothed: SmoothedStep | None = None, truth_sigma_m: float | None = None,
                truth_shares_map: bool = False) -> StepRecord:
    """Everything about one localized query, in metres, against its ground-truth geotag.

    ``truth_sigma_m``: the ground truth's stated accuracy (standard deviation per axis, m; None or NaN:
    taken as exact). ``truth_shares_map``: the truth comes from the receiver that geotagged the
    database, on the same drive (``visloc.store.database.same_drive``), so it shares the map's absolute
    error: the NEES compares the error with the relative covariance R alone. Otherwise with
    R + a^2 I + s^2 I, the map's absolute error a and the truth's s added (``visloc.pose.uncertainty``)."""
    truth = (float(truth_lat_deg), float(truth_lon_deg))
    truth_m = db.frame.to_local(*truth)
    best = result.best_index
    m = result.measurement
    m_geotag = m_lat_lon = None
    m_err = e_err = m_hav = e_hav = cov = sigma = estimate = None
    if m.source == GEOTAG:
        m_geotag = (float(db.lat_deg[m.db_index]), float(db.lon_deg[m.db_index]))
        m_lat_lon = m_geotag
    elif m.source == GEOMETRY:
        lat, lon = db.frame.to_geo(m.east_north_m)
        m_lat_lon = (float(lat), float(lon))
    if m_lat_lon is not None:
        m_err = float(geodesic_distance_m(*m_lat_lon, *truth))
        m_hav = float(haversine_distance_m(*m_lat_lon, *truth))
    # the measurement's own covariance (a refined pose's; the filter's R for a geotag): what its error is held to
    R = m.cov_m2 if m.cov_m2 is not None else result.filter.R
    extra_m2 = truth_extra_m2(m.absolute_sigma_m, truth_sigma_m, truth_shares_map)
    nees = m_sigma = e_nees = None
    if R is not None and m.east_north_m is not None:
        m_sigma = float(np.sqrt(np.linalg.eigvalsh(R).max()))
        nees = nees_against_truth(m.east_north_m, R, truth_m, extra_m2)
    s_truth = float(truth_sigma_m) if truth_sigma_m is not None and np.isfinite(truth_sigma_m) else 0.0
    s_m = s_err = None
    if smoothed is not None and np.all(np.isfinite(smoothed.x)):
        s_m = _position(smoothed.x[:2])
        lat, lon = db.frame.to_geo(smoothed.x[:2])
        s_err = float(geodesic_distance_m(float(lat), float(lon), *truth))
    candidates = result.retrieval.candidates
    floor = None
    if candidates.size:
        floor = float(geodesic_distance_m(db.lat_deg[candidates], db.lon_deg[candidates], *truth).min())
    if np.all(np.isfinite(result.filter.x)):
        estimate = _position(result.filter.x[:2])
        lat, lon = db.frame.to_geo(result.filter.x[:2])
        e_err = float(geodesic_distance_m(float(lat), float(lon), *truth))
        e_hav = float(haversine_distance_m(float(lat), float(lon), *truth))
        sigma = float(np.sqrt(np.linalg.eigvalsh(result.filter.position_cov_m2).max()))
        cov = result.filter.position_cov_m2.tolist()
        e_nees = nees_against_truth(result.filter.x[:2], result.filter.position_cov_m2, truth_m, extra_m2)
    return StepRecord(
        step=step, query_frame=int(query_frame), query_timestamp_s=float(result.query.timestamp_s),
        truth_geotag_deg=truth, truth_m=_position(truth_m), n_candidates=int(candidates.size),
        best_db_index=best, best_db_frame=None if best is None else int(db.images[best].frame),
        best_count=result.retrieval.best_count,
        best_offset_s=None if best is None else float(db.timestamps_s[best] - result.query.timestamp_s),
        measurement_m=None if m.east_north_m is None else _position(m.east_north_m), measurement_geotag_deg=m_geotag,
        estimate_m=estimate, estimate_sigma_m=sigma, measurement_error_m=m_err, estimate_error_m=e_err,
        measurement_error_haversine_m=m_hav, estimate_error_haversine_m=e_hav, latency_ms=latency_ms,
        nearest_candidate_error_m=floor, estimate_cov_m2=cov,
        counts=[int(c) for c in result.retrieval.counts] if keep_counts else [],
        candidate_frames=[int(db.images[i].frame) for i in candidates] if keep_counts else [],
        measurement_source=m.source, fallback_reason=m.fallback_reason,
        measurement_cov_m2=None if R is None else np.asarray(R, float).tolist(), measurement_sigma_m=m_sigma,
        measurement_nees=nees, truth_sigma_m=s_truth if s_truth > 0 else None, truth_shares_map=bool(truth_shares_map),
        absolute_sigma_m=m.absolute_sigma_m, measurement_side=m.side, measurement_lever_m=m.lever_m,
        measurement_term_sigma_m={k: float(np.sqrt(max(np.linalg.eigvalsh(v).max(), 0.0)))
                                  for k, v in (m.cov_terms_m2 or {}).items()},
        estimate_nees=e_nees,
        mahalanobis=None if result.filter.innovation is None else float(result.filter.innovation.mahalanobis),
        gated=bool(result.filter.gated), maneuver=bool(result.filter.maneuver),
        retracted_previous=bool(result.filter.retracted_previous),
        view_db_frames=[int(db.images[i].frame) for i in m.view_indices],
        neighbour_db_frames=[int(db.images[i].frame) for i in m.neighbour_indices],
        n_pnp_inliers=int(m.n_pnp_inliers),
        n_pnp_query_keypoints=0 if m.inliers is None else len(np.unique(m.inliers.query_rows)),
        thin_support=bool(m.thin_support),
        measurement_ms=float(m.query_side_ms),
        measurement_heading_deg=m.heading_deg, smoothed_m=s_m, smoothed_error_m=s_err,
    )


@dataclass(frozen=True)
class RecordGeotags:
    """A record's positions as (lat_deg, lon_deg), None where it has none."""

    truth: tuple[float, float]
    measurement: tuple[float, float] | None
    estimate: tuple[float, float] | None
    smoothed: tuple[float, float] | None


@dataclass(frozen=True)
class QueryTruth:
    """The ground truth of a run's queries, by query index: frame numbers, recorded geotags and their
    stated accuracy (sigma per axis, m; NaN: unknown), and whether it comes from the receiver that
    geotagged the database, on the same drive (``visloc.store.database.same_drive``)."""

    frames: np.ndarray
    lat_deg: np.ndarray
    lon_deg: np.ndarray
    sigma_m: np.ndarray
    shares_map: bool
    unstated_sigma_m: float = REFINED.geotag_sigma_m  # a no-fix truth's accuracy: the run's geotag_sigma_m

    @classmethod
    def of_queries(cls, queries: QuerySet, db: GeoDatabase,
                   unstated_sigma_m: float = REFINED.geotag_sigma_m) -> "QueryTruth":
        """Stored queries' truth (their own geotags)."""
        sigma = (np.full(len(queries.frames), np.nan) if queries.truth_sigma_m is None
                 else np.asarray(queries.truth_sigma_m, float))
        return cls(np.asarray(queries.frames), queries.lat_deg, queries.lon_deg, sigma,
                   same_drive(db, queries.timestamps_s, queries.lat_deg, queries.lon_deg), unstated_sigma_m)

    @classmethod
    def of_drive(cls, seq: Drive, db: GeoDatabase, unstated_sigma_m: float = REFINED.geotag_sigma_m) -> "QueryTruth":
        """A drive's frames' truth (their geotags), for queries described now."""
        sigma = np.array([np.nan if f.position_accuracy_m is None else f.position_accuracy_m for f in seq.frames])
        return cls(np.array([f.frame for f in seq.frames]), np.array([f.lat_deg for f in seq.frames]),
                   np.array([f.lon_deg for f in seq.frames]), sigma,
                   same_drive(db, seq.timestamps_s, seq.lat_deg, seq.lon_deg), unstated_sigma_m)

    def sigma(self, index: int) -> float | None:
        """Query ``index``'s truth's accuracy, None where taken as exact (its drive states no accuracy at all). A
        truth that states none where its drive's other records do (a record with no position solution) is taken as
        good to ``unstated_sigma_m``, what the run assumes for a geotag of unknown accuracy (``geotag_sigma_m``)."""
        value = float(self.sigma_m[index])
        if np.isfinite(value):
            return value
        return self.unstated_sigma_m if self._unstated[index] else None

    def shares_map_at(self, index: int) -> bool:
        """Whether query ``index``'s truth shares the map's error: not where it is no fix of the receiver."""
        return self.shares_map and not self._unstated[index]

    @cached_property
    def _unstated(self) -> np.ndarray:
        return unstated_geotags(self.sigma_m)


def records_of(results: Sequence[StepResult], latencies_ms: Sequence[float], indices: Sequence[int],
               truth: QueryTruth, db: GeoDatabase, *, keep_counts: bool = False,
               smoothed: Sequence[SmoothedStep | None] | None = None) -> list[StepRecord]:
    """The records of a run: step k is ``results[k]``, query ``indices[k]`` of ``truth``, taking
    ``latencies_ms[k]`` (``keep_counts``: every candidate's count too; ``smoothed``: the RTS smoother's
    steps). The one place a run's steps become records."""
    smoothed = [None] * len(results) if smoothed is None else smoothed
    return [step_record(k, result, db, query_frame=int(truth.frames[q]), truth_lat_deg=truth.lat_deg[q],
                        truth_lon_deg=truth.lon_deg[q], latency_ms=float(latency), keep_counts=keep_counts,
                        smoothed=sm, truth_sigma_m=truth.sigma(q), truth_shares_map=truth.shares_map_at(q))
            for k, (q, result, latency, sm) in enumerate(zip(indices, results, latencies_ms, smoothed))]


def record_geotags(record: StepRecord, frame: LocalFrame) -> RecordGeotags:
    """Latitude and longitude of a record's positions: recorded geotags as they are, computed
    positions converted from the local frame ``frame`` (the database's)."""

    def geo(position: Position | None) -> tuple[float, float] | None:
        if position is None:
            return None
        lat, lon = frame.to_geo(np.asarray(position, float))
        return float(lat), float(lon)

    measurement = record.measurement_geotag_deg or geo(record.measurement_m)
    return RecordGeotags(record.truth_geotag_deg, measurement, geo(record.estimate_m), geo(record.smoothed_m))
