"""The refined method's measurement: a metric position of the query from the database alone.

For a query whose retrieval has ranked the database candidates by correspondence count:

1. **Verification.** The ``top_k`` candidates are matched to the query again (Lowe's
   ratio alone) and re-ranked by their inliers under an essential matrix (RANSAC,
   both cameras' intrinsics).
2. **Structure.** Each verified candidate used as a *view* is triangulated with its
   nearest database neighbours, up to ``neighbours_per_side`` before and after it within
   ``max_neighbour_gap`` frames, among the images the retrieval allows (so the exclusion
   window holds for them too) and at least ``min_baseline_m`` away. Their poses come from
   the geotags and attitudes, their scale from the geotags: no query information.
3. **Views on both sides.** The query is posed against the ``n_views`` best views; if
   they all lie on one side of that first pose (all behind it, or all ahead) and a
   verified candidate lies on the other side, the weakest view is swapped for it and the
   query posed again. Posing from one side extrapolates the geotags' local errors (their
   scale and drift between the views and their neighbours) over the distance to the
   query; views on both sides interpolate them.
4. **Pose.** PnP RANSAC and Levenberg-Marquardt over every view's 2D-3D correspondences
   give the query camera's pose, and the query camera's extrinsics give the pose of the
   query vehicle's geotag reference point (its IMU): the measurement is its east/north.
   The query is also posed against each view alone (from the pooled pose, on that view's
   inliers): a view whose pose lies more than ``max_view_spread_m`` from the others' is
   dropped, and a measurement whose views still disagree, that faces away from its views,
   or lies far from them, is rejected with the reason.
5. **Uncertainty**, the sum of three parts, none fitted to a drive: the PnP covariance
   (residual variance times the inverse normal matrix) propagated to east/north; the
   spread of the per-view poses (the covariance of their mean: what one view's geotags
   and structure get wrong and another's do not); and the views' geotags' own stated
   accuracy (OXTS ``pos_accuracy``, or ``geotag_sigma_m`` where the source states none),
   since the pose is tied to those geotags.

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
from visloc.geometry import (CameraModel, PnPResult, essential_inliers, heading_deg_of, imu_east_north_covariance,
                             imu_pose_from_camera, refine_pose, solve_pnp)
from visloc.multiview import triangulate_tracks
from visloc.matching import correspondences
from visloc.measurement import GEOMETRY, GEOTAG, Measurement, geotag_measurement
from visloc.params import MatchParams, RefinedParams
from visloc.retrieval import Retrieval


@dataclass(frozen=True)
class DatabaseGeometry:
    """The database as the refined mode needs it, in arrays.

    T_world_camera: (N, 4, 4) pose of each database camera in the local ENU frame,
    NaN where the image's attitude is unknown; camera: intrinsics and extrinsics of
    the database camera, or None with ``unavailable_reason`` saying why; geotag_sigma_m:
    the stated accuracy of each geotag (standard deviation per axis, metres; NaN or None
    where the source states none).
    """

    T_world_camera: np.ndarray
    keypoints_xy_px: Sequence[np.ndarray]
    descriptors_u8: Sequence[np.ndarray]
    camera: CameraModel | None
    unavailable_reason: str | None = None
    geotag_sigma_m: np.ndarray | None = None  # (N,) stated accuracy of each geotag, per axis, NaN if unknown


class StructureCache:
    """Memoised structure per (view, neighbours) and matches per database pair: database-side work,
    reusable across queries."""

    def __init__(self) -> None:
        self._views: dict[tuple[int, tuple[int, ...]], dict[int, np.ndarray]] = {}
        self._pairs: dict[tuple[int, int], np.ndarray] = {}
        self.build_ms = 0.0

    def get(self, key: tuple[int, tuple[int, ...]]) -> dict[int, np.ndarray] | None:
        return self._views.get(key)

    def put(self, key: tuple[int, tuple[int, ...]], value: dict[int, np.ndarray], ms: float) -> None:
        self._views[key] = value
        self.build_ms += ms

    def pairs(self, geometry: "DatabaseGeometry", a: int, b: int, params: RefinedParams) -> np.ndarray:
        if (a, b) not in self._pairs:
            match = MatchParams(tau1=params.ratio, tau2=-1.0)
            self._pairs[(a, b)] = correspondences(geometry.descriptors_u8[a], geometry.descriptors_u8[b], match)
        return self._pairs[(a, b)]

    def __len__(self) -> int:
        return len(self._views)


def build_view_structure(geometry: DatabaseGeometry, view: int, neighbours: Sequence[int], params: RefinedParams,
                         cache: StructureCache) -> dict[int, np.ndarray]:
    """keypoint row of ``view`` -> (world point, its 3x3 covariance), triangulated from every neighbour
    that sees it."""
    tracks: dict[int, dict[int, np.ndarray]] = {}
    for c, j in enumerate(neighbours, 1):
        pairs = cache.pairs(geometry, view, j, params)
        for d_row, n_row in pairs.tolist():
            tracks.setdefault(d_row, {})[c] = geometry.keypoints_xy_px[j][n_row]
    rows = np.array(sorted(tracks), np.int64)
    xy = np.full((len(rows), len(neighbours) + 1, 2), np.nan)
    for m, d_row in enumerate(rows.tolist()):
        xy[m, 0] = geometry.keypoints_xy_px[view][d_row]
        for c, pixel in tracks[d_row].items():
            xy[m, c] = pixel
    T = geometry.T_world_camera[[view, *neighbours]]
    tri = triangulate_tracks(geometry.camera.K, T, xy, max_reprojection_px=params.triangulation_px,
                             min_parallax_deg=params.min_parallax_deg, max_depth_m=params.max_depth_m)
    return {int(k): (X, S) for k, X, S in zip(rows[tri.keep].tolist(), tri.points_world[tri.keep],
                                               tri.cov_world[tri.keep])}


def view_structure(geometry: DatabaseGeometry, view: int, neighbours: Sequence[int], params: RefinedParams,
                   cache: StructureCache | None) -> tuple[dict[int, np.ndarray], float]:
    """keypoint row of ``view`` -> world point over its neighbours, and the milliseconds spent
    building it (0 when cached)."""
    cache = cache if cache is not None else StructureCache()
    key = (view, tuple(neighbours))
    found = cache.get(key)
    if found is not None:
        return found, 0.0
    t0 = time.perf_counter()
    structure = build_view_structure(geometry, view, neighbours, params, cache)
    ms = (time.perf_counter() - t0) * 1000.0
    cache.put(key, structure, ms)
    return structure, ms


def neighbours_of(view: int, allowed: np.ndarray, T_world_camera: np.ndarray, params: RefinedParams) -> list[int]:
    """For each of ``neighbour_baselines_m``, the database image before ``view`` and the one after
    it (within ``max_neighbour_gap`` frames, allowed and posed) whose distance from the view is
    nearest that baseline and at least ``min_baseline_m``."""
    allowed_set = set(int(i) for i in allowed)
    centre = T_world_camera[view][:3, 3]
    out: list[int] = []
    for direction in (-1, 1):
        near = []
        for gap in range(1, params.max_neighbour_gap + 1):
            j = view + direction * gap
            if not 0 <= j < len(T_world_camera):
                break
            if j in allowed_set and np.all(np.isfinite(T_world_camera[j])):
                baseline_m = float(np.linalg.norm(T_world_camera[j][:3, 3] - centre))
                if baseline_m >= params.min_baseline_m:
                    near.append((baseline_m, j))
        for target_m in params.neighbour_baselines_m:
            if near:
                j = min(near, key=lambda bj: abs(bj[0] - target_m))[1]
                if j not in out:
                    out.append(j)
    return out


@dataclass(frozen=True)
class _Views:
    """2D-3D correspondences of the query against some views: which view each comes from."""

    points_world: np.ndarray  # (M, 3)
    points_cov: np.ndarray  # (M, 3, 3)
    pixels: np.ndarray  # (M, 2)
    view_of: np.ndarray  # (M,) database index of the view


def _correspondences(chosen: list[int], pairs_of: dict[int, np.ndarray], structure_of: dict[int, dict],
                     query_xy: np.ndarray) -> _Views:
    points, covs, pixels, view_of = [], [], [], []
    for i in chosen:
        structure = structure_of[i]
        for q_row, d_row in pairs_of[i].tolist():
            found = structure.get(d_row)
            if found is not None:
                points.append(found[0])
                covs.append(found[1])
                pixels.append(query_xy[q_row])
                view_of.append(i)
    return _Views(np.array(points).reshape(-1, 3), np.array(covs).reshape(-1, 3, 3), np.array(pixels).reshape(-1, 2),
                  np.array(view_of, np.int64))


def _east_north(pnp: PnPResult, query_camera: CameraModel) -> np.ndarray:
    return imu_pose_from_camera(pnp.T_world_camera, query_camera.T_camera_imu)[:2, 3].copy()


def _side(view_centre: np.ndarray, T_world_camera_query: np.ndarray) -> int:
    """+1 if a view's camera lies ahead of the query camera (along its optical axis), -1 behind."""
    forward = T_world_camera_query[:3, 2]
    return 1 if float(np.dot(view_centre - T_world_camera_query[:3, 3], forward)) >= 0 else -1


def _per_view_positions(pnp: PnPResult, views: _Views, query_camera: CameraModel,
                        min_points: int) -> dict[int, np.ndarray]:
    """East/north of the query posed against each view alone, from the pooled pose on that view's
    inliers (views with fewer than ``min_points`` inliers are left out)."""
    out = {}
    inlier_views = views.view_of[pnp.inliers]
    for i in np.unique(inlier_views).tolist():
        rows = pnp.inliers[inlier_views == i]
        if len(rows) < min_points:
            continue
        T_world_camera = refine_pose(views.points_world[rows], views.pixels[rows], query_camera.K, pnp)
        out[int(i)] = imu_pose_from_camera(T_world_camera, query_camera.T_camera_imu)[:2, 3].copy()
    return out


def _mean_covariance(positions: list[np.ndarray]) -> np.ndarray:
    """Covariance of the mean of independent estimates, from their spread (zero for fewer than two)."""
    if len(positions) < 2:
        return np.zeros((2, 2))
    P = np.array(positions)
    d = P - P.mean(axis=0)
    return d.T @ d / (len(P) * (len(P) - 1))


def _spread_m(positions: list[np.ndarray]) -> float:
    P = np.array(positions)
    return float(max(np.linalg.norm(a - b) for a in P for b in P)) if len(P) > 1 else 0.0


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

    spent = {"structure_ms": 0.0}

    def fallback(reason: str, **extra) -> Measurement:
        m = geotag_measurement(retrieval, db_east_north_m, reason)
        return Measurement(m.east_north_m, None, GEOTAG, fallback_reason=reason, db_index=m.db_index,
                           compute_ms=(time.perf_counter() - start) * 1000.0, structure_ms=spent["structure_ms"],
                           **extra)

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
    candidates = [(i, pairs) for n, i, pairs in verified if n >= params.min_verified_inliers
                  and np.all(np.isfinite(geometry.T_world_camera[i]))]
    if not candidates:
        return fallback(f"database image {verified[0][1]} has no attitude (re-run 'visloc ingest' to fill it)",
                        n_verified_inliers=best_inliers, candidate_inliers=inliers_of)

    # 2. the verified candidates that have allowed neighbours; a view's structure is built when it is chosen
    pairs_of, structure_of, neighbours_used = {}, {}, {}
    for i, pairs in candidates:
        neighbours = neighbours_of(i, retrieval.search_area, geometry.T_world_camera, params)
        if neighbours:
            pairs_of[i], neighbours_used[i] = pairs, neighbours
    usable = list(pairs_of)  # in inlier order
    base = dict(n_verified_inliers=best_inliers, candidate_inliers=inliers_of)
    if not usable:
        return fallback(f"no database neighbour within {params.max_neighbour_gap} frames of the verified views is "
                        f"allowed and at least {params.min_baseline_m:g} m away (car stopped?)", **base)

    def solve(chosen: list[int]) -> tuple[PnPResult | str, _Views]:
        for i in chosen:
            if i not in structure_of:
                structure_of[i], ms = view_structure(geometry, i, neighbours_used[i], params, cache)
                spent["structure_ms"] += ms
        views = _correspondences(chosen, pairs_of, structure_of, query_xy)
        pnp = solve_pnp(views.points_world, views.pixels, query_camera.K, reprojection_px=params.pnp_px,
                        iterations=params.pnp_iterations, seed=params.seed, min_inliers=params.min_pnp_inliers,
                        points_cov=views.points_cov)
        return pnp, views

    def describe(chosen: list[int], views: _Views) -> None:
        base.update(view_indices=tuple(chosen), n_correspondences_3d=len(views.points_world),
                    neighbour_indices=tuple(j for i in chosen for j in neighbours_used[i]))

    # 3. pose against the best views, then against views on both sides of it where the database has them
    chosen = usable[: params.n_views]
    pnp, views = solve(chosen)
    if params.both_sides and not isinstance(pnp, str):
        side = {i: _side(geometry.T_world_camera[i][:3, 3], pnp.T_world_camera) for i in usable}
        behind, ahead = [i for i in usable if side[i] < 0], [i for i in usable if side[i] > 0]
        if behind and ahead:  # as many views on each side, best first
            balanced_choice = [i for pair in zip(behind, ahead) for i in pair][: max(params.n_views, 2)]
            if set(balanced_choice) != set(chosen):
                balanced, balanced_views = solve(balanced_choice)
                if not isinstance(balanced, str):
                    pnp, views, chosen = balanced, balanced_views, balanced_choice
    describe(chosen, views)
    if isinstance(pnp, str):
        return fallback(pnp, **base)

    # 4. each view alone: drop a view that disagrees with the others, reject if they still disagree
    min_points = max(6, params.min_pnp_inliers // 2)
    per_view = _per_view_positions(pnp, views, query_camera, min_points)
    if len(per_view) >= 3:
        centre = np.median(np.array(list(per_view.values())), axis=0)
        far = [i for i, p in per_view.items() if np.linalg.norm(p - centre) > params.max_view_spread_m]
        if far and len(far) < len(per_view):
            kept = [i for i in chosen if i not in far]
            again, again_views = solve(kept)
            if not isinstance(again, str):
                pnp, views, chosen = again, again_views, kept
                describe(chosen, views)
                per_view = _per_view_positions(pnp, views, query_camera, min_points)
    spread_m = _spread_m(list(per_view.values()))
    base.update(n_pnp_inliers=len(pnp.inliers))
    if spread_m > params.max_view_spread_m:
        return fallback(f"views {sorted(per_view)} disagree: their own poses lie {spread_m:.1f} m apart "
                        f"(limit {params.max_view_spread_m:g} m)", **base)
    T_world_imu = imu_pose_from_camera(pnp.T_world_camera, query_camera.T_camera_imu)
    east_north = T_world_imu[:2, 3].copy()
    anchor = chosen[0]
    offset_m = float(np.linalg.norm(east_north - np.asarray(db_east_north_m[anchor], float)))
    if not np.all(np.isfinite(east_north)) or offset_m > params.max_offset_m:
        return fallback(f"PnP pose {offset_m:.1f} m from the geotag of view {anchor} (limit "
                        f"{params.max_offset_m:g} m)", **base)
    heading = heading_deg_of(T_world_imu)
    view_heading = heading_deg_of(geometry.T_world_camera[anchor] @ geometry.camera.T_camera_imu)
    turn_deg = abs((heading - view_heading + 180.0) % 360.0 - 180.0)
    if turn_deg > params.max_heading_diff_deg:
        return fallback(f"PnP pose faces {turn_deg:.0f} deg away from view {anchor} (limit "
                        f"{params.max_heading_diff_deg:g} deg)", **base)

    # 5. covariance: PnP's + the views' spread + the views' geotags' stated accuracy + the scale of
    #    each view's structure, which its geotags' accuracy over its baselines leaves uncertain
    geotag_var = np.nanmean([_geotag_sigma_m(geometry, i, params) ** 2 for i in chosen])
    scale_cov = np.zeros((2, 2))
    for i in chosen:
        scale_cov += _scale_covariance(geometry, i, neighbours_used[i], east_north, params) / len(chosen) ** 2
    cov = (imu_east_north_covariance(pnp, query_camera.T_camera_imu) + _mean_covariance(list(per_view.values()))
           + geotag_var * np.eye(2) + scale_cov)
    return Measurement(
        east_north, cov, GEOMETRY, fallback_reason=None, db_index=anchor,
        reprojection_rms_px=pnp.reprojection_rms_px, up_m=float(T_world_imu[2, 3]),
        heading_deg=heading, compute_ms=(time.perf_counter() - start) * 1000.0,
        structure_ms=spent["structure_ms"], **base,
    )


def _scale_covariance(geometry: DatabaseGeometry, view: int, neighbours: Sequence[int], east_north_m: np.ndarray,
                      params: RefinedParams) -> np.ndarray:
    """Covariance (2x2, m^2) of a pose from one view's structure due to that structure's scale.

    The scale comes from the baselines between the view and its neighbours; errors of s per axis in
    the two geotags of a baseline b make its length uncertain by about sqrt(2) s, a relative scale
    error sqrt(2) s / b (the longest baseline dominates). A query d metres from the view is placed
    d times that scale, along the line from the view to the query.
    """
    centre = geometry.T_world_camera[view][:3, 3]
    baseline_m = max(float(np.linalg.norm(geometry.T_world_camera[j][:3, 3] - centre)) for j in neighbours)
    sigma_m = np.sqrt(np.mean([_geotag_sigma_m(geometry, k, params) ** 2 for k in (view, *neighbours)]))
    offset = np.asarray(east_north_m, float) - centre[:2]
    # the camera, not the geotag's reference point, is the centre of the scaling; the difference
    # (the camera's lever arm, about a metre) is small against the offsets this term matters for
    return (np.sqrt(2.0) * sigma_m / baseline_m) ** 2 * np.outer(offset, offset)


def _geotag_sigma_m(geometry: DatabaseGeometry, i: int, params: RefinedParams) -> float:
    stated = None if geometry.geotag_sigma_m is None else float(geometry.geotag_sigma_m[i])
    return stated if stated is not None and np.isfinite(stated) else params.geotag_sigma_m


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

