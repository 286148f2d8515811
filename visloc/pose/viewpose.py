"""Posing a query against database views whose keypoints carry 3D points (steps 3-5 of ``visloc.pose.refined``).

``pose_from_views`` is shared by the exact refined path (structure triangulated as it is needed)
and the fast one (structure read from the store): given the same correspondences and structure,
both give the same measurement.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from visloc.errors import InputError
from visloc.geometry.projective import (CameraModel, PnPResult, heading_deg_of, heading_difference_deg,
                                        imu_east_north_covariance, imu_pose_from_camera, refine_pose, solve_pnp)
from visloc.params import RefinedParams
from visloc.pose.guided import guided_pairs
from visloc.pose.uncertainty import (DEFAULT_LEVER_GAIN, LeverGain, unstated_geotag_covariance_m2,
                                     unstated_geotags)


@dataclass(frozen=True)
class DatabaseGeometry:
    """The database as the refined mode needs it, in arrays.

    T_world_camera: (N, 4, 4) pose of each database camera in the local ENU frame,
    NaN where the image's attitude is unknown; camera: intrinsics and extrinsics of
    the database camera, or None with ``unavailable_reason`` saying why; geotag_sigma_m:
    the stated accuracy of each geotag (standard deviation per axis, metres; NaN or None
    where the source states none); heading_spread_rad: how far the database's headings stray from
    its course over ground (``visloc.geometry.bundle.heading_spread_rad``; None where it cannot be told);
    lever_gain: what the database's poses get wrong per metre of lever (``visloc.pose.uncertainty``),
    as its self-check measured it (None: ``DEFAULT_LEVER_GAIN``).
    """

    T_world_camera: np.ndarray
    keypoints_xy_px: Sequence[np.ndarray]
    descriptors_u8: Sequence[np.ndarray]
    camera: CameraModel | None
    unavailable_reason: str | None = None
    geotag_sigma_m: np.ndarray | None = None  # (N,) stated accuracy of each geotag, per axis, NaN if unknown
    heading_spread_rad: float | None = None
    lever_gain: LeverGain | None = None  # measured by the store's self-check; None: DEFAULT_LEVER_GAIN

    @cached_property
    def unstated_geotags(self) -> np.ndarray:
        """(N,) bool: geotags with no accuracy of their own among others that state one (``unstated_geotags``)."""
        return unstated_geotags(self.geotag_sigma_m)


def require_calibrated(geometry: DatabaseGeometry, query_camera: CameraModel | None, query_what: str) -> None:
    """Refuse a refined measurer without what a pose needs, naming what is missing."""
    if geometry.camera is None:
        raise InputError(f"the refined method needs a calibrated database: {geometry.unavailable_reason}")
    if query_camera is None:
        raise InputError(f"the refined method needs a calibrated query camera: {query_what} has no intrinsics "
                         "and extrinsics")


@dataclass(frozen=True)
class _Views:
    """2D-3D correspondences of the query against some views: which view each comes from."""

    points_world: np.ndarray  # (M, 3)
    points_cov: np.ndarray  # (M, 3, 3)
    pixels: np.ndarray  # (M, 2)
    view_of: np.ndarray  # (M,) database index of the view
    rows: np.ndarray  # (M, 2) (query row, keypoint row of the view)


def _correspondences(chosen: list[int], pairs_of: dict[int, np.ndarray], structure_of: dict[int, dict],
                     query_xy: np.ndarray) -> _Views:
    points, covs, pixels, view_of, rows = [], [], [], [], []
    for i in chosen:
        structure = structure_of[i]
        for q_row, d_row in pairs_of[i].tolist():
            found = structure.get(d_row)
            if found is not None:
                points.append(found[0])
                covs.append(found[1])
                pixels.append(query_xy[q_row])
                view_of.append(i)
                rows.append((q_row, d_row))
    return _Views(np.array(points).reshape(-1, 3), np.array(covs).reshape(-1, 3, 3), np.array(pixels).reshape(-1, 2),
                  np.array(view_of, np.int64), np.array(rows, np.int64).reshape(-1, 2))


def side_of(view_centre: np.ndarray, T_world_camera_query: np.ndarray) -> int:
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


def _both_sides(usable: list[int], T_world_camera_query: np.ndarray, geometry: "DatabaseGeometry",
                params: RefinedParams) -> tuple[dict[int, int], list[int]]:
    """Each usable view's side of the query camera at ``T_world_camera_query`` (+1 ahead, -1 behind), and as many
    views on each side as the database has, best first and alternating (empty when all lie on one side)."""
    side = {i: side_of(geometry.T_world_camera[i][:3, 3], T_world_camera_query) for i in usable}
    behind, ahead = [i for i in usable if side[i] < 0], [i for i in usable if side[i] > 0]
    if not (behind and ahead):
        return side, []
    return side, [i for pair in zip(behind, ahead) for i in pair][: max(params.n_views, 2)]


def _far_views(positions: dict[int, np.ndarray], limit_m: float) -> list[int]:
    """Among three or more views' own positions, those farther than ``limit_m`` from their median (none when
    every view is, or fewer than three)."""
    if len(positions) < 3:
        return []
    centre = np.median(np.array(list(positions.values())), axis=0)
    far = [i for i, p in positions.items() if np.linalg.norm(p - centre) > limit_m]
    return far if len(far) < len(positions) else []


def agreeing_majority(positions: dict[int, np.ndarray], limit_m: float) -> list[int]:
    """The views whose own positions lie within half ``limit_m`` of their median (so within ``limit_m`` of each
    other), in their order in ``positions``, when they are more than half of the views; else empty."""
    centre = np.median(np.array(list(positions.values())), axis=0)
    near = [i for i, p in positions.items() if np.linalg.norm(p - centre) <= limit_m / 2.0]
    return near if 2 * len(near) > len(positions) else []


def _disagreement(positions: dict[int, np.ndarray], limit_m: float) -> str | None:
    """Why the views' own positions cannot make one measurement (they lie more than ``limit_m`` apart), or None."""
    spread_m = _spread_m(list(positions.values()))
    if spread_m > limit_m:
        return f"views {sorted(positions)} disagree: their own poses lie {spread_m:.1f} m apart (limit {limit_m:g} m)"
    return None


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


@dataclass
class PosedViews:
    """What ``pose_from_views`` found: a pose (``reason`` None) or why there is none.

    support: view_indices, neighbour_indices, n_correspondences_3d and n_pnp_inliers (Measurement fields).
    cov_m2 is the relative covariance (``visloc.pose.uncertainty``): the sum of ``cov_terms_m2`` ("pnp", "views",
    "lever", "geotags"; the exact path adds "views_round": ``visloc.pose.refined.round_spread``); side: "both" or
    "one" (the views' sides of the pose); lever_m: the distance from the pose to its nearest view's geotag;
    absolute_sigma_m: the views' geotags' stated accuracy."""

    reason: str | None
    support: dict
    structure_ms: float = 0.0
    east_north_m: np.ndarray | None = None
    cov_m2: np.ndarray | None = None
    anchor: int | None = None
    reprojection_rms_px: float | None = None
    up_m: float | None = None
    heading_deg: float | None = None
    cov_terms_m2: dict | None = None
    side: str | None = None
    lever_m: float | None = None
    absolute_sigma_m: float | None = None
    inliers: "MapCorrespondences | None" = None  # the PnP inliers, what a tracker follows to the next frame
    thin_support: bool = False  # posed at thin_support_pnp_px with thin_support_min_inliers (``thin_support_params``)
    views_posed_apart: int = 0  # the views' own positions the "views" term's spread comes from (fewer than 2: none)


@dataclass(frozen=True)
class MapCorrespondences:
    """A posed frame's 2D-3D inliers: the map points it saw and where.

    query_rows: (M,) rows of the query's keypoints; view_of, view_rows: (M,) the database view and keypoint row
    each point belongs to; points_world: (M, 3) m; points_cov: (M, 3, 3) m^2; T_world_camera: (4, 4) the pose;
    neighbours: view -> the database images its structure was triangulated with."""

    query_rows: np.ndarray
    view_of: np.ndarray
    view_rows: np.ndarray
    points_world: np.ndarray
    points_cov: np.ndarray
    T_world_camera: np.ndarray
    neighbours: dict = None  # view -> the database images its structure was triangulated with
    view_structure: dict = None  # view -> {keypoint row: (world point, covariance)}: all of its structure


def pose_from_views(query_xy: np.ndarray, usable: list[int], pairs_of: dict[int, np.ndarray],
                    structure_of, neighbours_used: dict[int, Sequence[int]], db_east_north_m: np.ndarray,
                    geometry: DatabaseGeometry, query_camera: CameraModel, params: RefinedParams,
                    query_descriptors: np.ndarray | None = None) -> PosedViews:
    """Steps 3-5 of the module docstring: the query posed against views (best first in ``usable``).

    pairs_of[i]: (M, 2) pairs (query row, keypoint row of view i); structure_of(i) -> (keypoint row ->
    (world point, covariance), milliseconds spent building it); neighbours_used[i]: the database images
    view i's structure was triangulated with. Shared by the exact path (structure built as needed)
    and the fast path (structure read from the store). With ``query_descriptors`` (and
    ``params.guided_radius_px`` above 0) the first pose's views are matched again, guided by it
    (``guided_pairs``), and the query posed on both."""
    spent = {"structure_ms": 0.0}
    if params.fuse_views:
        fused, spent["structure_ms"] = _views_fused(query_xy, usable, pairs_of, structure_of, neighbours_used,
                                                    db_east_north_m, geometry, query_camera, params, query_descriptors)
        if fused is not None:
            return fused
    structures: dict[int, dict] = {}
    support: dict = {}

    def solve(chosen: list[int], pairs: dict[int, np.ndarray] = pairs_of) -> tuple[PnPResult | str, _Views]:
        for i in chosen:
            if i not in structures:
                structures[i], ms = structure_of(i)
                spent["structure_ms"] += ms
        views = _correspondences(chosen, pairs, structures, query_xy)
        return _solve(views, query_camera, params), views

    def describe(chosen: list[int], views: _Views) -> None:
        support.update(view_indices=tuple(chosen), n_correspondences_3d=len(views.points_world),
                       neighbour_indices=tuple(j for i in chosen for j in neighbours_used[i]))

    def failed(reason: str) -> PosedViews:
        return PosedViews(reason, support, spent["structure_ms"])

    # 3. pose against the best views, then against views on both sides of it where the database has them
    chosen = usable[: params.n_views]
    pnp, views = solve(chosen)
    if params.both_sides and not isinstance(pnp, str):
        _, balanced_choice = _both_sides(usable, pnp.T_world_camera, geometry, params)
        if balanced_choice and set(balanced_choice) != set(chosen):
            balanced, balanced_views = solve(balanced_choice)
            if not isinstance(balanced, str):
                pnp, views, chosen = balanced, balanced_views, balanced_choice
    if (not isinstance(pnp, str) and query_descriptors is not None and params.guided_radius_px > 0):
        guided = guided_pairs(pnp, views, chosen, structures, query_xy, query_descriptors, geometry, query_camera,
                              params)
        again, again_views = solve(chosen, guided)
        if not isinstance(again, str) and len(again.inliers) >= len(pnp.inliers):
            pnp, views, pairs_of = again, again_views, guided
    describe(chosen, views)
    if isinstance(pnp, str):
        if params.thin_support_pnp_px > 0:  # thin support: pose again, looser, before giving up
            thin = pose_from_views(query_xy, usable, pairs_of, structure_of, neighbours_used, db_east_north_m,
                                   geometry, query_camera, thin_support_params(params), query_descriptors)
            thin.structure_ms += spent["structure_ms"]
            thin.thin_support = True
            return thin
        return failed(pnp)

    # 4. each view alone: drop a view that disagrees with the others, reject if they still disagree
    min_points = max(6, params.min_pnp_inliers // 2)
    per_view = _per_view_positions(pnp, views, query_camera, min_points)
    far = _far_views(per_view, params.max_view_spread_m)
    if far:
        kept = [i for i in chosen if i not in far]
        again, again_views = solve(kept, pairs_of)
        if not isinstance(again, str):
            pnp, views, chosen = again, again_views, kept
            describe(chosen, views)
            per_view = _per_view_positions(pnp, views, query_camera, min_points)
    support.update(n_pnp_inliers=len(pnp.inliers))
    disagree = _disagreement(per_view, params.max_view_spread_m)
    if disagree:
        return failed(disagree)
    T_world_imu = imu_pose_from_camera(pnp.T_world_camera, query_camera.T_camera_imu)
    k = pnp.inliers
    inliers = MapCorrespondences(views.rows[k, 0], views.view_of[k], views.rows[k, 1], views.points_world[k],
                                 views.points_cov[k], pnp.T_world_camera,
                                 {i: tuple(neighbours_used[i]) for i in chosen}, {i: structures[i] for i in chosen})
    return _finish(T_world_imu[:2, 3].copy(), T_world_imu, chosen[0], chosen, per_view,
                   imu_east_north_covariance(pnp, query_camera.T_camera_imu), pnp.reprojection_rms_px, inliers,
                   support, spent["structure_ms"], db_east_north_m, geometry, params)


def thin_support_params(params: RefinedParams) -> RefinedParams:
    """The settings of a second pose where support is thin: PnP at ``thin_support_pnp_px`` needing
    ``thin_support_min_inliers`` (never stricter than ``params``), and no third attempt. True inliers of a
    query's 2D-3D matches scatter a pixel or two (more for large keypoints) beyond ``pnp_px``; where many
    matches exist the strict threshold loses little, where a few exist it leaves fewer than a pose needs."""
    return params.replace(pnp_px=max(params.pnp_px, params.thin_support_pnp_px),
                          min_pnp_inliers=min(params.min_pnp_inliers, params.thin_support_min_inliers),
                          thin_support_pnp_px=0.0)


def _finish(east_north: np.ndarray, T_world_imu: np.ndarray, anchor: int, chosen: list[int],
            per_view: dict[int, np.ndarray], pnp_cov_m2: np.ndarray, reprojection_rms_px: float,
            inliers: MapCorrespondences, support: dict, structure_ms: float, db_east_north_m: np.ndarray,
            geometry: DatabaseGeometry, params: RefinedParams) -> PosedViews:
    """The checks of step 4 that need the pose, and step 5's covariance: a posed ``PosedViews``, or why not.
    ``T_world_imu``: the query vehicle's pose (its heading and height); ``east_north`` its position;
    ``per_view``: the views' own poses (``east_north`` is their mean where they were posed apart)."""
    offset_m = float(np.linalg.norm(east_north - np.asarray(db_east_north_m[anchor], float)))
    if not np.all(np.isfinite(east_north)) or offset_m > params.max_offset_m:
        return PosedViews(f"PnP pose {offset_m:.1f} m from the geotag of view {anchor} (limit "
                          f"{params.max_offset_m:g} m)", support, structure_ms)
    heading = heading_deg_of(T_world_imu)
    view_heading = heading_deg_of(geometry.T_world_camera[anchor] @ geometry.camera.T_camera_imu)
    turn_deg = heading_difference_deg(heading, view_heading)
    if turn_deg > params.max_heading_diff_deg:
        return PosedViews(f"PnP pose faces {turn_deg:.0f} deg away from view {anchor} (limit "
                          f"{params.max_heading_diff_deg:g} deg)", support, structure_ms)

    # 5. covariance (visloc.pose.uncertainty): relative to the map, PnP's + the views' spread + what the
    #    database's poses get wrong over the lever to the nearest view + the views' geotags that are no fix;
    #    the geotags' stated accuracy apart
    sides = {side_of(geometry.T_world_camera[i][:3, 3], inliers.T_world_camera) for i in chosen}
    side = "both" if len(sides) == 2 else "one"
    lever_m = float(min(np.linalg.norm(east_north - np.asarray(db_east_north_m[i], float)) for i in chosen))
    gain = geometry.lever_gain if geometry.lever_gain is not None else DEFAULT_LEVER_GAIN
    terms = {"pnp": pnp_cov_m2, "views": _mean_covariance(list(per_view.values())),
             "lever": gain.covariance_m2(side, lever_m, heading)}
    terms["geotags"] = unstated_geotag_covariance_m2(inliers.neighbours or {}, geometry.unstated_geotags,
                                                     params.geotag_sigma_m)
    cov = sum(terms.values())
    absolute_sigma_m = float(np.sqrt(np.mean([_geotag_sigma_m(geometry, i, params) ** 2 for i in chosen])))
    return PosedViews(None, support, structure_ms, east_north, cov, anchor, reprojection_rms_px,
                      float(T_world_imu[2, 3]), heading, terms, side, lever_m, absolute_sigma_m, inliers,
                      views_posed_apart=len(per_view))


def _solve(views: _Views, query_camera: CameraModel, params: RefinedParams) -> PnPResult | str:
    return solve_pnp(views.points_world, views.pixels, query_camera.K, reprojection_px=params.pnp_px,
                     iterations=params.pnp_iterations, seed=params.seed, min_inliers=params.min_pnp_inliers,
                     points_cov=views.points_cov)


def _pose_alone(i: int, pairs: np.ndarray, structure: dict, query_xy: np.ndarray, query_descriptors: np.ndarray | None,
                geometry: DatabaseGeometry, query_camera: CameraModel,
                params: RefinedParams) -> tuple[PnPResult | str, _Views]:
    """The query posed against view ``i`` alone: PnP on its correspondences, then guided matching from that pose
    (as ``pose_from_views`` does for the pooled views), kept when it finds at least as many inliers."""
    views = _correspondences([i], {i: pairs}, {i: structure}, query_xy)
    pnp = _solve(views, query_camera, params)
    if not isinstance(pnp, str) and query_descriptors is not None and params.guided_radius_px > 0:
        guided = guided_pairs(pnp, views, [i], {i: structure}, query_xy, query_descriptors, geometry, query_camera,
                              params)
        again_views = _correspondences([i], guided, {i: structure}, query_xy)
        again = _solve(again_views, query_camera, params)
        if not isinstance(again, str) and len(again.inliers) >= len(pnp.inliers):
            pnp, views = again, again_views
    return pnp, views


def _views_fused(query_xy: np.ndarray, usable: list[int], pairs_of: dict[int, np.ndarray], structure_of,
                 neighbours_used: dict[int, Sequence[int]], db_east_north_m: np.ndarray, geometry: DatabaseGeometry,
                 query_camera: CameraModel, params: RefinedParams,
                 query_descriptors: np.ndarray | None) -> tuple[PosedViews | None, float]:
    """``pose_from_views`` with ``params.fuse_views``: the query posed against each view alone, and the mean of
    those positions, with the milliseconds spent building structure. None (one PnP over every view's points
    decides) when fewer than two views pose the query alone: where each view has too few points for a pose of
    its own, their points together may still make one. Views are chosen as for one PnP (the best, then as many
    on each side of the best view's pose as the database has); a view farther than ``max_view_spread_m`` from
    the others' median is dropped; where the rest still disagree, those that agree are kept when they are most of
    them (``agreeing_majority``), and the measurement is rejected otherwise. Covariance: the
    views' PnP covariances summed over the square of their number (independent poses), the covariance of their
    mean from their spread, and the lever term, what the views share beyond their spread (the gain is measured
    on such means: ``visloc.pose.selfcheck``). The
    inliers a tracker follows are every kept view's, with the pose of the best verified view."""
    spent = 0.0
    structures: dict[int, dict] = {}
    alone: dict[int, tuple[PnPResult | str, _Views]] = {}

    def pose_alone(i: int) -> PnPResult | str:
        nonlocal spent
        if i not in alone:
            if i not in structures:
                structures[i], ms = structure_of(i)
                spent += ms
            alone[i] = _pose_alone(i, pairs_of[i], structures[i], query_xy, query_descriptors, geometry,
                                   query_camera, params)
        return alone[i][0]

    def posed(views: list[int]) -> list[int]:
        return [i for i in views if not isinstance(pose_alone(i), str)]

    chosen = usable[: params.n_views]
    kept = posed(chosen)
    if params.both_sides and kept:
        reference = alone[max(kept, key=lambda i: len(alone[i][0].inliers))][0].T_world_camera
        side, balanced_choice = _both_sides(usable, reference, geometry, params)
        if balanced_choice and set(balanced_choice) != set(chosen):
            balanced = posed(balanced_choice)
            if len({side[i] for i in balanced}) == 2:
                chosen, kept = balanced_choice, balanced
    if len(kept) < 2:
        return None, spent

    positions = {i: imu_pose_from_camera(alone[i][0].T_world_camera, query_camera.T_camera_imu)[:2, 3].copy()
                 for i in kept}
    far = _far_views(positions, params.max_view_spread_m)
    kept = [i for i in kept if i not in far]
    positions = {i: positions[i] for i in kept}
    if _disagreement(positions, params.max_view_spread_m):  # the views that agree, where most of them do
        kept = agreeing_majority(positions, params.max_view_spread_m) or kept
        positions = {i: positions[i] for i in kept}
    pnps = [alone[i][0] for i in kept]
    support = dict(view_indices=tuple(kept), neighbour_indices=tuple(j for i in kept for j in neighbours_used[i]),
                   n_correspondences_3d=sum(len(alone[i][1].points_world) for i in kept),
                   n_pnp_inliers=sum(len(p.inliers) for p in pnps))
    disagree = _disagreement(positions, params.max_view_spread_m)
    if disagree:
        return PosedViews(disagree, support, spent), spent
    anchor = kept[0]  # the best verified, as for one PnP
    T_world_imu = imu_pose_from_camera(alone[anchor][0].T_world_camera, query_camera.T_camera_imu)
    T_world_imu[2, 3] = float(np.mean([imu_pose_from_camera(p.T_world_camera, query_camera.T_camera_imu)[2, 3]
                                       for p in pnps]))
    pnp_cov_m2 = sum(imu_east_north_covariance(p, query_camera.T_camera_imu) for p in pnps) / len(pnps) ** 2
    rms_px = float(np.sqrt(sum(len(p.inliers) * p.reprojection_rms_px ** 2 for p in pnps)
                           / sum(len(p.inliers) for p in pnps)))
    parts = [(alone[i][1], alone[i][0].inliers) for i in kept]
    inliers = MapCorrespondences(np.concatenate([v.rows[k, 0] for v, k in parts]),
                                 np.concatenate([v.view_of[k] for v, k in parts]),
                                 np.concatenate([v.rows[k, 1] for v, k in parts]),
                                 np.concatenate([v.points_world[k] for v, k in parts]),
                                 np.concatenate([v.points_cov[k] for v, k in parts]),
                                 alone[anchor][0].T_world_camera, {i: tuple(neighbours_used[i]) for i in kept},
                                 {i: structures[i] for i in kept})
    east_north = np.mean(np.array(list(positions.values())), axis=0)
    return _finish(east_north, T_world_imu, anchor, kept, positions, pnp_cov_m2, rms_px, inliers, support, spent,
                   db_east_north_m, geometry, params), spent


def _geotag_sigma_m(geometry: DatabaseGeometry, i: int, params: RefinedParams) -> float:
    stated = None if geometry.geotag_sigma_m is None else float(geometry.geotag_sigma_m[i])
    return stated if stated is not None and np.isfinite(stated) else params.geotag_sigma_m
