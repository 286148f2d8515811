"""One query's measurement: the paper's geotag, or (refined mode) a metric position from the database alone.

Refined mode, for a query whose retrieval has ranked the database candidates by
correspondence count:

1. **Verification.** The ``top_k`` candidates are matched to the query again (Lowe's
   ratio alone) and re-ranked by their inliers under an essential matrix (RANSAC,
   both cameras' intrinsics).
2. **Structure.** Each of the ``n_views`` best verified candidates (a *view*) is
   triangulated with its database neighbours ``neighbour_gaps`` frames before and
   after it, among the images the retrieval allows (so the exclusion window holds
   for them too) and at least ``min_baseline_m`` away. Their poses come from the
   geotags and attitudes, their scale from the geotags: no query information.
3. **Pose.** The query's keypoints matched to the views' triangulated keypoints give
   2D-3D correspondences; PnP RANSAC and Levenberg-Marquardt give the query camera's
   pose, and the query camera's extrinsics give the pose of the query vehicle's
   geotag reference point (its IMU): the measurement is its east/north.
4. **Uncertainty.** The PnP pose covariance (residual variance times the inverse
   normal matrix) is propagated to east/north, and ``sigma_floor_m`` is added in
   quadrature on each axis for what residuals cannot show (database poses,
   calibration, triangulated points).

Whenever a stage fails (no calibration or attitude, too few inliers, no neighbour
with a baseline because the car stood still, PnP failure, an implausible pose) the
measurement falls back to the paper's: the geotag of the best match by count, with
the filter's own R, and ``fallback_reason`` says why.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from visloc.geometry import (CameraModel, essential_inliers, heading_deg_of, imu_east_north_covariance,
                             imu_pose_from_camera, solve_pnp, triangulate)
from visloc.matching import correspondences
from visloc.params import MatchParams, RefinedParams, check_mode
from visloc.retrieval import Retrieval

GEOMETRY = "geometry"
GEOTAG = "geotag"


@dataclass(frozen=True)
class Measurement:
    """What one query tells the filter.

    east_north_m:        (2,) measured position of the vehicle's geotag reference point, metres in
                         the local frame; None when the query gave no measurement at all.
    cov_m2:              (2, 2) its covariance, m^2; None means "use the filter's R" (geotags).
    source:              "geometry" (refined pose), "geotag" (the paper's) or None (no measurement).
    fallback_reason:     why a refined-mode measurement is a geotag; None otherwise.
    db_index:            database image the measurement rests on (the verified best view for
                         geometry, the best match by count for a geotag).
    view_indices:        database images the query was posed against; neighbour_indices: those
                         triangulated with them.
    n_verified_inliers:  essential-matrix inliers of the best verified candidate.
    n_correspondences_3d, n_pnp_inliers, reprojection_rms_px: the pose's support.
    up_m, heading_deg:   the pose's altitude in the local frame and compass heading (geometry only).
    compute_ms:          wall time this measurement took (query side: matching, RANSAC, PnP).
    structure_ms:        of which building database structure that was not cached yet.
    """

    east_north_m: np.ndarray | None
    cov_m2: np.ndarray | None
    source: str | None
    fallback_reason: str | None = None
    db_index: int | None = None
    view_indices: tuple[int, ...] = ()
    neighbour_indices: tuple[int, ...] = ()
    n_verified_inliers: int = 0
    n_correspondences_3d: int = 0
    n_pnp_inliers: int = 0
    reprojection_rms_px: float | None = None
    up_m: float | None = None
    heading_deg: float | None = None
    compute_ms: float = 0.0
    structure_ms: float = 0.0
    candidate_inliers: dict[int, int] = field(default_factory=dict, repr=False)

    @property
    def sigma_m(self) -> float | None:
        """1-sigma along the covariance's longest axis, metres (None: the filter's R applies)."""
        if self.cov_m2 is None:
            return None
        return float(np.sqrt(max(np.linalg.eigvalsh(self.cov_m2).max(), 0.0)))


@dataclass(frozen=True)
class DatabaseGeometry:
    """The database as the refined mode needs it, in arrays.

    T_world_camera: (N, 4, 4) pose of each database camera in the local ENU frame,
    NaN where the image's attitude is unknown; camera: intrinsics and extrinsics of
    the database camera, or None with ``unavailable_reason`` saying why.
    """

    T_world_camera: np.ndarray
    keypoints_xy_px: Sequence[np.ndarray]
    descriptors_u8: Sequence[np.ndarray]
    camera: CameraModel | None
    unavailable_reason: str | None = None


@dataclass(frozen=True)
class Structure:
    """Triangulated keypoints of one database view: keypoint rows of the view and their world points."""

    keypoint_index: np.ndarray  # (M,) int64 rows of the view's keypoints
    points_world: np.ndarray  # (M, 3) metres
    parallax_deg: np.ndarray  # (M,)


class StructureCache:
    """Memoised two-view structure per (view, neighbour) pair; database-side work, reusable across queries."""

    def __init__(self) -> None:
        self._pairs: dict[tuple[int, int], Structure] = {}
        self.build_ms = 0.0

    def get(self, key: tuple[int, int]) -> Structure | None:
        return self._pairs.get(key)

    def put(self, key: tuple[int, int], value: Structure, ms: float) -> None:
        self._pairs[key] = value
        self.build_ms += ms

    def __len__(self) -> int:
        return len(self._pairs)


def paper_measurement(retrieval: Retrieval, db_east_north_m: np.ndarray, reason: str | None = None) -> Measurement:
    """The paper's measurement: the geotag of the best match by count (None without a match)."""
    best = retrieval.best_index
    if best is None:
        return Measurement(None, None, None, fallback_reason=reason, db_index=None)
    return Measurement(np.asarray(db_east_north_m[best], float), None, GEOTAG, fallback_reason=reason, db_index=best)


def pair_structure(geometry: DatabaseGeometry, view: int, neighbour: int, params: RefinedParams) -> Structure:
    """Triangulate the keypoints of ``view`` that match ``neighbour`` (both posed database images)."""
    match = MatchParams(tau1=params.ratio, tau2=-1.0)
    pairs = correspondences(geometry.descriptors_u8[view], geometry.descriptors_u8[neighbour], match)
    K = geometry.camera.K
    tri = triangulate(K, geometry.T_world_camera[view], geometry.keypoints_xy_px[view][pairs[:, 0]],
                      K, geometry.T_world_camera[neighbour], geometry.keypoints_xy_px[neighbour][pairs[:, 1]],
                      max_reprojection_px=params.triangulation_px, min_parallax_deg=params.min_parallax_deg,
                      max_depth_m=params.max_depth_m)
    keep = tri.keep
    return Structure(pairs[keep, 0].astype(np.int64), tri.points_world[keep], tri.parallax_deg[keep])


def view_structure(geometry: DatabaseGeometry, view: int, neighbours: Sequence[int], params: RefinedParams,
                   cache: StructureCache | None) -> tuple[dict[int, np.ndarray], float]:
    """keypoint row of ``view`` -> world point, merged over its neighbours (largest parallax wins).

    Returns the map and the milliseconds spent building pairs that were not cached.
    """
    best: dict[int, tuple[float, np.ndarray]] = {}
    spent_ms = 0.0
    for j in neighbours:
        s = cache.get((view, j)) if cache is not None else None
        if s is None:
            t0 = time.perf_counter()
            s = pair_structure(geometry, view, j, params)
            ms = (time.perf_counter() - t0) * 1000.0
            spent_ms += ms
            if cache is not None:
                cache.put((view, j), s, ms)
        for k, X, par in zip(s.keypoint_index.tolist(), s.points_world, s.parallax_deg):
            if k not in best or par > best[k][0]:
                best[k] = (float(par), X)
    return {k: v[1] for k, v in best.items()}, spent_ms


def neighbours_of(view: int, allowed: np.ndarray, T_world_camera: np.ndarray, params: RefinedParams) -> list[int]:
    """Database images ``neighbour_gaps`` frames before/after ``view`` that are allowed, posed and far enough."""
    allowed_set = set(int(i) for i in allowed)
    centre = T_world_camera[view][:3, 3]
    out = []
    for gap in params.neighbour_gaps:
        for j in (view - gap, view + gap):
            if j in allowed_set and np.all(np.isfinite(T_world_camera[j])):
                if np.linalg.norm(T_world_camera[j][:3, 3] - centre) >= params.min_baseline_m:
                    out.append(j)
    return out


def measurement_from_retrieval(
    query_keypoints_f32: np.ndarray | None,
    query_descriptors_u8: np.ndarray,
    retrieval: Retrieval,
    db_east_north_m: np.ndarray,
    *,
    mode: str = "paper",
    geometry: DatabaseGeometry | None = None,
    query_camera: CameraModel | None = None,
    params: RefinedParams = RefinedParams(),
    cache: StructureCache | None = None,
) -> Measurement:
    """Turn one query and its retrieval into the filter's measurement (see the module docstring).

    ``mode="paper"`` gives the paper's geotag measurement (``cov_m2`` None). ``mode="refined"``
    tries the metric pose and falls back to the geotag with a reason. ``query_keypoints_f32``
    is (N, 6) or (N, 2) with pixel x, y first. Pass a ``StructureCache`` to reuse database
    structure across queries.
    """
    start = time.perf_counter()
    check_mode(mode)
    if mode == "paper" or retrieval.best_index is None:
        reason = None if mode == "paper" else "no database image has a correspondence"
        return paper_measurement(retrieval, db_east_north_m, reason)

    structure_ms = 0.0

    def fallback(reason: str, **extra) -> Measurement:
        m = paper_measurement(retrieval, db_east_north_m, reason)
        return Measurement(m.east_north_m, None, GEOTAG, fallback_reason=reason, db_index=m.db_index,
                           compute_ms=(time.perf_counter() - start) * 1000.0, structure_ms=structure_ms, **extra)

    if geometry is None:
        return fallback("no database geometry given")
    if geometry.camera is None:
        return fallback(geometry.unavailable_reason or "database camera has no calibration")
    if query_camera is None:
        return fallback("query camera has no calibration (intrinsics and extrinsics)")
    if query_keypoints_f32 is None or len(query_keypoints_f32) != len(query_descriptors_u8):
        return fallback("query keypoints not given")
    query_xy = np.asarray(query_keypoints_f32, float)[:, :2]

    # 1. verification: re-rank the top-k candidates by essential-matrix inliers
    order = np.argsort(-retrieval.counts, kind="stable")[: params.top_k]
    order = [k for k in order if retrieval.counts[k] > 0]
    match = MatchParams(tau1=params.ratio, tau2=-1.0)
    verified: list[tuple[int, int, np.ndarray]] = []  # (inliers, db index, pairs)
    for k in order:
        i = int(retrieval.candidates[k])
        pairs = correspondences(query_descriptors_u8, geometry.descriptors_u8[i], match)
        mask = essential_inliers(query_xy[pairs[:, 0]], geometry.keypoints_xy_px[i][pairs[:, 1]],
                                 query_camera.K, geometry.camera.K, threshold_px=params.essential_px,
                                 seed=params.seed)
        verified.append((int(mask.sum()), i, pairs))
    verified.sort(key=lambda v: -v[0])  # stable: ties keep the count order
    inliers_of = {i: n for n, i, _ in verified}
    best_inliers = verified[0][0] if verified else 0
    if best_inliers < params.min_verified_inliers:
        return fallback(f"verification: best candidate has {best_inliers} essential-matrix inliers "
                        f"(need {params.min_verified_inliers})", n_verified_inliers=best_inliers,
                        candidate_inliers=inliers_of)
    views = [v for v in verified if v[0] >= params.min_verified_inliers
             and np.all(np.isfinite(geometry.T_world_camera[v[1]]))]
    if not views:
        return fallback(f"database image {verified[0][1]} has no attitude (re-run 'visloc ingest' to fill it)",
                        n_verified_inliers=best_inliers, candidate_inliers=inliers_of)

    # 2. structure of the n_views best verified candidates that have allowed neighbours (in inlier
    #    order: near the end of a drive, or next to the exclusion window, the best may have none)
    points, pixels, used_views, used_neighbours = [], [], [], []
    for _, i, pairs in views:
        if len(used_views) == params.n_views:
            break
        neighbours = neighbours_of(i, retrieval.search_area, geometry.T_world_camera, params)
        if not neighbours:
            continue
        structure, ms = view_structure(geometry, i, neighbours, params, cache)
        structure_ms += ms
        used_views.append(i)
        used_neighbours.extend(neighbours)
        for q_row, d_row in pairs.tolist():
            X = structure.get(d_row)
            if X is not None:
                points.append(X)
                pixels.append(query_xy[q_row])
    base = dict(n_verified_inliers=best_inliers, candidate_inliers=inliers_of, view_indices=tuple(used_views),
                neighbour_indices=tuple(used_neighbours))
    if not used_views:
        return fallback(f"no database neighbour {list(params.neighbour_gaps)} frames from the verified views is "
                        f"allowed and at least {params.min_baseline_m:g} m away (car stopped?)", **base)

    # 3. the query camera's pose, then its vehicle's reference point
    pnp = solve_pnp(np.array(points), np.array(pixels), query_camera.K, reprojection_px=params.pnp_px,
                    iterations=params.pnp_iterations, seed=params.seed, min_inliers=params.min_pnp_inliers)
    base["n_correspondences_3d"] = len(points)
    if isinstance(pnp, str):
        return fallback(pnp, **base)
    T_world_imu = imu_pose_from_camera(pnp.T_world_camera, query_camera.T_camera_imu)
    east_north = T_world_imu[:2, 3].copy()
    anchor = used_views[0]
    offset_m = float(np.linalg.norm(east_north - np.asarray(db_east_north_m[anchor], float)))
    if not np.all(np.isfinite(east_north)) or offset_m > params.max_offset_m:
        return fallback(f"PnP pose {offset_m:.1f} m from the geotag of view {anchor} (limit "
                        f"{params.max_offset_m:g} m)", n_pnp_inliers=len(pnp.inliers), **base)

    # 4. covariance: PnP's, plus the floor for what residuals cannot see
    cov = imu_east_north_covariance(pnp, query_camera.T_camera_imu) + params.sigma_floor_m**2 * np.eye(2)
    return Measurement(
        east_north, cov, GEOMETRY, fallback_reason=None, db_index=anchor, n_pnp_inliers=len(pnp.inliers),
        reprojection_rms_px=pnp.reprojection_rms_px, up_m=float(T_world_imu[2, 3]),
        heading_deg=heading_deg_of(T_world_imu), compute_ms=(time.perf_counter() - start) * 1000.0,
        structure_ms=structure_ms, **base,
    )


def filter_measurements(measurements: Sequence[Measurement], filter_params, *, gate_chi2: float = 0.0):
    """Re-run only the filter over measurements already made (cheap: no image work).

    Each measurement's own covariance is used where it has one, the filter's R
    (``filter_params.meas_var_m2``) otherwise; change R, Q or P0 through
    ``filter_params`` and the gate through ``gate_chi2`` (0 = off). Returns one
    ``FilterStep`` per measurement.
    """
    from visloc.tracking import run_filter

    return run_filter([m.east_north_m for m in measurements], filter_params,
                      covariances_m2=[m.cov_m2 for m in measurements], gate_chi2=gate_chi2)
