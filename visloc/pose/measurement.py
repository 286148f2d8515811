"""What one retrieved query tells the filter: a ``Measurement``, and the measurers that make it.

* ``GeotagMeasurer`` is the paper's: the geotag of the best match, with the filter's own R.
* ``visloc.pose.refined.PoseMeasurer`` (the refined method) measures a metric position from the
  database's own geometry with its own covariance, and falls back to the geotag with a reason.
* ``MemoisedMeasurer`` wraps either: the same query with the same retrieval measures the same.

Every measurer has ``measure(query, retrieval) -> Measurement``.
"""

from __future__ import annotations

import time
from collections.abc import Hashable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Protocol

import numpy as np

from visloc.features.sift import Query
from visloc.retrieval.retrievers import Retrieval

if TYPE_CHECKING:
    from visloc.pose.viewpose import PosedViews

GEOMETRY = "geometry"
GEOTAG = "geotag"


@dataclass(frozen=True)
class Measurement:
    """What one query tells the filter.

    east_north_m:        (2,) measured position of the vehicle's geotag reference point, metres in
                         the local frame; None when the query gave no measurement at all.
    cov_m2:              (2, 2) its covariance, m^2; None means "use the filter's R" (geotags).
    source:              "geometry" (refined pose), "geotag" (the paper's) or None (no measurement).
    fallback_reason:     why a refined measurement is a geotag; None otherwise.
    db_index:            database image the measurement rests on (the verified best view for
                         geometry, the best match by count for a geotag).
    view_indices:        database images the query was posed against; neighbour_indices: those
                         triangulated with them.
    n_verified_inliers:  the exact refined path (``visloc.pose.refined``): essential-matrix inliers of the best
                         verified candidate; None where nothing was verified (the paper's measurement, the
                         camera-rate path, a query without keypoints). candidate_inliers: the same per
                         verified candidate (database index -> inliers).
    n_structure_matches: the camera-rate path (``visloc.pose.fastpose``): the best candidate's query matches to
                         its stored 3D points (the count that ranks its candidates; no two-view
                         verification); None elsewhere. candidate_structure_matches: the same per candidate.
    n_correspondences_3d, n_pnp_inliers, reprojection_rms_px: the pose's support.
    up_m, heading_deg:   the pose's altitude in the local frame and compass heading (geometry only).
    absolute_sigma_m:    geometry: the stated accuracy of the geotags it rests on (per axis, m), the map's own
                         error, which ``cov_m2`` (relative to the map) leaves out; see ``visloc.pose.uncertainty``.
    side, lever_m:       geometry: "both" when its views lie on both sides of it, else "one"; the distance
                         to the nearest view's geotag, m.
    thin_support:        geometry: no pose reached ``min_pnp_inliers`` at ``pnp_px``, so this one was made at
                         ``thin_support_pnp_px`` with ``thin_support_min_inliers`` (``viewpose.thin_support_params``).
    cov_terms_m2:        geometry: the parts of ``cov_m2`` by name ("pnp", "views", "lever", "geotags"; "views_round":
                         the exact path, on 2-3 views posed apart, what makes their spread round at its longest axis).
    views_posed_apart:   geometry: how many views' own positions the "views" term comes from (the covariance of
                         their mean, from their spread); fewer than 2: the term is zero, nothing stated how far
                         one view's pose strays.
    inliers:             geometry: the pose's 2D-3D inliers (``visloc.pose.viewpose.MapCorrespondences``), what
                         ``visloc.pose.flowtrack`` follows into the next frame.
    compute_ms:          wall time this measurement took when it was made (query side: matching,
                         RANSAC, PnP, and any database structure built on the way).
    structure_ms:        of which building database structure that was not cached yet.
    """

    east_north_m: np.ndarray | None
    cov_m2: np.ndarray | None
    source: str | None
    fallback_reason: str | None = None
    db_index: int | None = None
    view_indices: tuple[int, ...] = ()
    neighbour_indices: tuple[int, ...] = ()
    n_verified_inliers: int | None = None
    n_structure_matches: int | None = None
    n_correspondences_3d: int = 0
    n_pnp_inliers: int = 0
    reprojection_rms_px: float | None = None
    up_m: float | None = None
    heading_deg: float | None = None
    absolute_sigma_m: float | None = None
    side: str | None = None
    lever_m: float | None = None
    thin_support: bool = False
    cov_terms_m2: dict = field(default_factory=dict, repr=False)
    views_posed_apart: int = 0
    compute_ms: float = 0.0
    structure_ms: float = 0.0
    candidate_inliers: dict[int, int] = field(default_factory=dict, repr=False)
    candidate_structure_matches: dict[int, int] = field(default_factory=dict, repr=False)
    inliers: object = field(default=None, repr=False)  # geometry: visloc.pose.viewpose.MapCorrespondences

    @property
    def sigma_m(self) -> float | None:
        """1-sigma along the covariance's longest axis, metres (None: the filter's R applies)."""
        if self.cov_m2 is None:
            return None
        return float(np.sqrt(max(np.linalg.eigvalsh(self.cov_m2).max(), 0.0)))

    @property
    def query_side_ms(self) -> float:
        """What making this measurement costs a live query: its time without database-side structure."""
        return self.compute_ms - self.structure_ms


def geotag_measurement(retrieval: Retrieval, db_east_north_m: np.ndarray, reason: str | None = None) -> Measurement:
    """The paper's measurement: the geotag of the best match by count (None without a match)."""
    best = retrieval.best_index
    if best is None:
        return Measurement(None, None, None, fallback_reason=reason, db_index=None)
    return Measurement(np.asarray(db_east_north_m[best], float), None, GEOTAG, fallback_reason=reason, db_index=best)


def posed_measurement(posed: "PosedViews", **extra) -> Measurement:
    """The geometry measurement of a pose on views (``visloc.pose.viewpose.pose_from_views``, which
    succeeded); ``extra``: the path's own support and timing fields."""
    return Measurement(
        posed.east_north_m, posed.cov_m2, GEOMETRY, fallback_reason=None, db_index=posed.anchor,
        reprojection_rms_px=posed.reprojection_rms_px, up_m=posed.up_m, heading_deg=posed.heading_deg,
        absolute_sigma_m=posed.absolute_sigma_m, side=posed.side, lever_m=posed.lever_m,
        cov_terms_m2=posed.cov_terms_m2, inliers=posed.inliers, thin_support=posed.thin_support,
        views_posed_apart=posed.views_posed_apart, **posed.support,
        **extra)


def query_pixels(keypoints_f32: np.ndarray | None, descriptors_u8: np.ndarray) -> np.ndarray | None:
    """(N, 2) pixel x, y of a query's keypoints ((N, 6) or (N, 2), x and y first), or None when they are
    not given or do not match its descriptors row for row: there is nothing to pose."""
    if keypoints_f32 is None or len(keypoints_f32) != len(descriptors_u8):
        return None
    return np.asarray(keypoints_f32, float)[:, :2]


class MeasurementEnd:
    """How a refined measurement of one query ends, on every path (exact, camera-rate): a geometry
    measurement from a pose on views, or the paper's geotag with the reason geometry failed. Both carry
    the time since this object was made (``compute_ms``) and the database structure built on the way
    (``structure_ms``, which the path adds to)."""

    NO_MATCH = "no database image has a correspondence"
    NO_KEYPOINTS = "query keypoints not given"

    def __init__(self, retrieval: Retrieval, db_east_north_m: np.ndarray):
        self.start = time.perf_counter()
        self.retrieval = retrieval
        self.db_east_north_m = db_east_north_m
        self.structure_ms = 0.0

    def _timing(self) -> dict:
        return dict(compute_ms=(time.perf_counter() - self.start) * 1000.0, structure_ms=self.structure_ms)

    def no_match(self) -> Measurement:
        """A retrieval that matched nothing: no measurement at all (or the best match's geotag)."""
        return geotag_measurement(self.retrieval, self.db_east_north_m, self.NO_MATCH)

    def fallback(self, reason: str, **extra) -> Measurement:
        """The geotag of the best match by count, with ``reason``; ``extra``: the support found so far."""
        m = geotag_measurement(self.retrieval, self.db_east_north_m, reason)
        return Measurement(m.east_north_m, None, GEOTAG, fallback_reason=reason, db_index=m.db_index,
                           **self._timing(), **extra)

    def posed(self, posed: "PosedViews", **extra) -> Measurement:
        """The pose's geometry measurement, or the fallback with the reason it gave."""
        self.structure_ms += posed.structure_ms
        if posed.reason is not None:
            return self.fallback(posed.reason, **posed.support, **extra)
        return posed_measurement(posed, **self._timing(), **extra)


class Measurer(Protocol):
    def measure(self, query: Query, retrieval: Retrieval) -> Measurement: ...


class GeotagMeasurer:
    """The paper's measurer: the best match's geotag; the filter applies its own R."""

    def __init__(self, db_east_north_m: np.ndarray):
        self.db_east_north_m = np.asarray(db_east_north_m, float)

    def measure(self, query: Query, retrieval: Retrieval) -> Measurement:
        return geotag_measurement(retrieval, self.db_east_north_m)


class MemoisedMeasurer:
    """``measurer``, remembering each measurement by (query key, retrieval): an evaluation where the
    same query image recurs with the same candidates measures it once. Queries without a key are
    measured every time."""

    def __init__(self, measurer: Measurer):
        self.measurer = measurer
        self._memo: dict[tuple[Hashable, bytes, bytes, bytes | None], Measurement] = {}

    def measure(self, query: Query, retrieval: Retrieval) -> Measurement:
        if query.key is None:
            return self.measurer.measure(query, retrieval)
        allowed = None if retrieval.allowed is None else retrieval.allowed.tobytes()
        key = (query.key, retrieval.candidates.tobytes(), retrieval.counts.tobytes(), allowed)
        if key not in self._memo:
            self._memo[key] = self.measurer.measure(query, retrieval)
        return self._memo[key]
