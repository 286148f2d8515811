"""The refined method's measurement: a metric position of the query from the database alone.

For a query whose retrieval has ranked the database candidates by correspondence count:

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

Whenever a stage fails for one query (too few inliers, no neighbour with a baseline
because the car stood still, an image without attitude, PnP failure, an implausible
pose) the measurement falls back to the paper's: the geotag of the best match by count,
with the filter's own R, and ``fallback_reason`` says why. Without calibrated cameras
there is nothing to pose: ``PoseMeasurer`` refuses to be built.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from visloc.errors import InputError
from visloc.features import Query
from visloc.geometry import (CameraModel, essential_inliers, heading_deg_of, imu_east_north_covariance,
                             imu_pose_from_camera, solve_pnp, triangulate)
from visloc.matching import correspondences
from visloc.measurement import GEOMETRY, GEOTAG, Measurement, geotag_measurement
from visloc.params import MatchParams, RefinedParams
from visloc.retrieval import Retrieval


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


def pose_measurement(
    query_keypoints_f32: np.ndarray | None,
    query_descriptors_u8: np.ndarray,
    retrieval: Retrieval,
    db_east_north_m: np.ndarray,
    geometry: DatabaseGeometry,
    query_camera: CameraModel,
    params: RefinedParams = RefinedParams(),
    cache: StructureCache | None = None,
) -> Measurement:
    """The refined measurement of one query and its retrieval (see the module docstring), or the
    geotag of the best match with the reason geometry failed.

    ``geometry`` must have its camera (see ``PoseMeasurer``). ``query_keypoints_f32`` is (N, 6) or
    (N, 2) with pixel x, y first. Pass a ``StructureCache`` to reuse database structure across queries.
    """
    start = time.perf_counter()
    if retrieval.best_index is None:
        return geotag_measurement(retrieval, db_east_north_m, "no database image has a correspondence")

    structure_ms = 0.0

    def fallback(reason: str, **extra) -> Measurement:
        m = geotag_measurement(retrieval, db_east_north_m, reason)
        return Measurement(m.east_north_m, None, GEOTAG, fallback_reason=reason, db_index=m.db_index,
                           compute_ms=(time.perf_counter() - start) * 1000.0, structure_ms=structure_ms, **extra)

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


class PoseMeasurer:
    """The refined method's measurer. Refuses to be built without what a pose needs: the database
    camera's calibration and attitudes (``geometry``) and the query camera's calibration."""

    def __init__(self, db_east_north_m: np.ndarray, geometry: DatabaseGeometry, query_camera: CameraModel | None,
                 params: RefinedParams, *, structures: StructureCache | None = None, query_what: str = "the query camera"):
        if geometry.camera is None:
            raise InputError(f"the refined method needs a calibrated database: {geometry.unavailable_reason}")
        if query_camera is None:
            raise InputError(f"the refined method needs a calibrated query camera: {query_what} has no intrinsics "
                             "and extrinsics")
        self.db_east_north_m = np.asarray(db_east_north_m, float)
        self.geometry = geometry
        self.query_camera = query_camera
        self.params = params
        self.structures = structures if structures is not None else StructureCache()

    def measure(self, query: Query, retrieval: Retrieval) -> Measurement:
        return pose_measurement(query.keypoints_f32, query.descriptors_u8, retrieval, self.db_east_north_m,
                                self.geometry, self.query_camera, self.params, self.structures)

