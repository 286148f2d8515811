"""The refined method's measurement: a metric position of the query from the database alone.

For a query whose retrieval has ranked the database candidates by correspondence count:

1. **Verification.** The ``top_k`` candidates are matched to the query again (Lowe's
   ratio alone) and re-ranked by their inliers under an essential matrix (RANSAC,
   both cameras' intrinsics).
2. **Structure.** Each verified candidate used as a *view* is triangulated with database
   neighbours before and after it: on each side, for each of ``neighbour_baselines_m``, the
   image whose distance from the view is nearest that baseline (``neighbours_of``), within
   ``max_neighbour_gap`` frames, among the images the retrieval allows (so the exclusion
   window holds for them too), posed, and at least ``min_baseline_m`` away. Their poses come
   from the geotags and attitudes, their scale from the geotags: no query information.
3. **Views on both sides.** The query is posed against the ``n_views`` best views; if
   they all lie on one side of that first pose (all behind it, or all ahead) and a
   verified candidate lies on the other side, the weakest view is swapped for it and the
   query posed again. Where none of the verified candidates lies there (a fast car's
   best candidates by count often all lie ahead of it), the ``other_side_candidates``
   allowed images nearest the pose on the other side, facing within
   ``other_side_max_turn_deg`` of its heading, are verified and the query posed again
   with them, kept when it then has views on both sides. Posing
   from one side extrapolates the geotags' local errors (their scale and drift between
   the views and their neighbours) over the distance to the query; views on both sides
   interpolate them.
4. **Pose.** PnP RANSAC and Levenberg-Marquardt over every view's 2D-3D correspondences
   give the query camera's pose, and the query camera's extrinsics give the pose of the
   query vehicle's geotag reference point (its IMU): the measurement is its east/north.
   The query is also posed against each view alone (from the pooled pose, on that view's
   inliers): a view whose pose lies more than ``max_view_spread_m`` from the others' is
   dropped, and a measurement whose views still disagree, that faces away from its views,
   or lies far from them, is rejected with the reason. With ``fuse_views`` the query is posed against each
   view alone instead (its own RANSAC and guided matching) and the measurement is the mean of those poses:
   views whose separately adjusted structures disagree by more than the PnP threshold then all count.
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
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import replace

import numpy as np
from threadpoolctl import threadpool_limits

from visloc.geometry.bundle import PosePriors, refine_database_poses
from visloc.features.sift import Query
from visloc.geometry.projective import CameraModel, essential_inliers, heading_deg_of, heading_difference_deg
from visloc.geometry.multiview import triangulate_tracks
from visloc.retrieval.matching import correspondences, correspondences_both_ways
from visloc.pose.measurement import Measurement, MeasurementEnd, query_pixels
from visloc.params import MatchParams, RefinedParams
from visloc.retrieval.retrievers import Retrieval
from visloc.pose.viewpose import DatabaseGeometry, PosedViews, pose_from_views, require_calibrated, side_of


class StructureCache:
    """Memoised structure per (view, neighbours) and matches per database pair: database-side work,
    reusable across queries. A pair's matches are found both ways from one product of the two images'
    descriptors (``correspondences_both_ways``): a view's neighbour is mostly a neighbour's view too. The
    last ``max_pairs`` pairs asked for are kept: a drive's views are built in time order, so those are the ones
    asked again."""

    def __init__(self, max_pairs: int = 4096) -> None:
        self._views: dict[tuple[int, tuple[int, ...]], dict[int, np.ndarray]] = {}
        self._pairs: OrderedDict[tuple[int, int, float], np.ndarray] = OrderedDict()
        self._max_pairs = max_pairs
        self.pairs_matched = 0  # descriptor products made so far: one per pair, for both its ways
        self.build_ms = 0.0

    def get(self, key: tuple[int, tuple[int, ...]]) -> dict[int, np.ndarray] | None:
        return self._views.get(key)

    def put(self, key: tuple[int, tuple[int, ...]], value: dict[int, np.ndarray], ms: float) -> None:
        self._views[key] = value
        self.build_ms += ms

    def share_pairs(self, other: "StructureCache") -> None:
        """Keep the database pairs' matches in ``other``'s store of them: what either matched, both have."""
        self._pairs, self._max_pairs = other._pairs, other._max_pairs

    def pairs(self, geometry: "DatabaseGeometry", a: int, b: int, params: RefinedParams) -> np.ndarray:
        """(M, 2) rows of database images ``a`` and ``b`` whose descriptors pass the ratio test from ``a``'s side."""
        key = (a, b, params.ratio)
        if key in self._pairs:
            self._pairs.move_to_end(key)
            return self._pairs[key]
        match = MatchParams(tau1=params.ratio, tau2=-1.0)
        a_to_b, b_to_a = correspondences_both_ways(geometry.descriptors_u8[a], geometry.descriptors_u8[b], match)
        self.pairs_matched += 1
        self._pairs[(b, a, params.ratio)] = b_to_a
        self._pairs[key] = a_to_b
        while len(self._pairs) > self._max_pairs:
            self._pairs.popitem(last=False)
        return a_to_b

    def __len__(self) -> int:
        return len(self._views)


def build_view_structure(geometry: DatabaseGeometry, view: int, neighbours: Sequence[int], params: RefinedParams,
                         cache: StructureCache) -> dict[int, np.ndarray]:
    """keypoint row of ``view`` -> (world point, its 3x3 covariance), triangulated from every neighbour
    that sees it. Made with one BLAS thread (``one_blas_thread``): the same bits at ingest, on a
    cluster's workers and at query time."""
    with one_blas_thread():
        return _view_structure(geometry, view, neighbours, params, cache)


def one_blas_thread():
    """A context in which BLAS runs one thread. BLAS sums in another order with another number of
    threads; what a store keeps (structure, self-checks) is made in it, so that a store built by one
    process, by the workers of a cluster or on another machine holds the same bits, and the exact path
    rebuilds a view's structure as the store holds it."""
    return threadpool_limits(1, user_api="blas")


def _view_structure(geometry: DatabaseGeometry, view: int, neighbours: Sequence[int], params: RefinedParams,
                    cache: StructureCache) -> dict[int, np.ndarray]:
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
    if params.refine_poses:
        T = refined_poses(geometry, T, xy, params)
    tri = triangulate_tracks(geometry.camera.K, T, xy, max_reprojection_px=params.triangulation_px,
                             min_parallax_deg=params.min_parallax_deg, max_depth_m=params.max_depth_m)
    return {int(k): (X, S) for k, X, S in zip(rows[tri.keep].tolist(), tri.points_world[tri.keep],
                                               tri.cov_world[tri.keep])}


def pose_priors(geometry: DatabaseGeometry, params: RefinedParams, n_images: int,
                sigma_pos_m: float | None = None) -> PosePriors:
    """The priors of ``n_images`` poses in a bundle adjustment: ``relative_geotag_sigma_m`` (or
    ``sigma_pos_m``) on the horizontal position, twice that (at least 0.2 m) on the height, which
    GNSS gets worse, and ``attitude_prior_per_heading_spread`` times the database's heading spread, at
    least ``min_attitude_prior_deg``, on the attitude."""
    sigma = params.relative_geotag_sigma_m if sigma_pos_m is None else sigma_pos_m
    spread = geometry.heading_spread_rad
    attitude = max(np.radians(params.min_attitude_prior_deg),
                   params.attitude_prior_per_heading_spread * spread if spread is not None else 0.0)
    return PosePriors(sigma_pos_m=np.full(n_images, sigma), sigma_up_m=max(0.2, 2.0 * sigma), sigma_rot_rad=attitude)


def refined_poses(geometry: DatabaseGeometry, T: np.ndarray, xy: np.ndarray, params: RefinedParams) -> np.ndarray:
    """``T`` (C, 4, 4), the poses of a view and its neighbours, refined by bundle adjustment on their
    observations ``xy`` (M, C, 2). Where the images move the positions much farther than the prior
    allows (a jittery track), the adjustment is run again with the prior loosened to the RMS of those
    moves: the images, not the prior, then decide the track's shape. ``T`` itself when too few points
    start an adjustment."""
    used = np.all(np.isfinite(xy), axis=2)
    priors = pose_priors(geometry, params, len(T))
    refined = refine_database_poses(geometry.camera.K, T, xy, used, priors, max_points=params.max_adjusted_points)
    if refined is None:
        return T
    moved_rms_m = float(np.sqrt(np.mean(refined.moved_m**2) / 3.0))
    if moved_rms_m > 3.0 * params.relative_geotag_sigma_m:
        again = refine_database_poses(geometry.camera.K, T, xy, used, pose_priors(geometry, params, len(T), moved_rms_m),
                                      max_points=params.max_adjusted_points)
        refined = again if again is not None else refined
    return refined.T_world_camera


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


def neighbours_of(view: int, allowed: np.ndarray, T_world_camera: np.ndarray, params: RefinedParams,
                  directions: tuple[int, ...] = (-1, 1)) -> list[int]:
    """For each of ``neighbour_baselines_m``, the database image before ``view`` and the one after
    it (within ``max_neighbour_gap`` frames, allowed and posed) whose distance from the view is
    nearest that baseline and at least ``min_baseline_m``. ``directions``: (-1,) before only,
    (1,) after only."""
    allowed_set = set(int(i) for i in allowed)
    centre = T_world_camera[view][:3, 3]
    out: list[int] = []
    for direction in directions:
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
    end = MeasurementEnd(retrieval, db_east_north_m)
    if retrieval.best_index is None:
        return end.no_match()
    fallback = end.fallback
    query_xy = query_pixels(query_keypoints_f32, query_descriptors_u8)
    if query_xy is None:
        return fallback(end.NO_KEYPOINTS)

    # 1. verification: re-rank the top-k candidates by essential-matrix inliers
    order = np.argsort(-retrieval.counts, kind="stable")[: params.top_k]
    order = [k for k in order if retrieval.counts[k] > 0]
    verified = _verified([int(retrieval.candidates[k]) for k in order], query_xy, query_descriptors_u8, geometry,
                         query_camera, params)
    inliers_of = {i: n for n, i, _ in verified}
    best_inliers = verified[0][0] if verified else 0
    if best_inliers < params.min_verified_inliers:
        return fallback(f"verification: best candidate has {best_inliers} essential-matrix inliers "
                        f"(need {params.min_verified_inliers})", n_verified_inliers=best_inliers,
                        candidate_inliers=inliers_of)
    if not any(np.all(np.isfinite(geometry.T_world_camera[i])) for n, i, _ in verified
               if n >= params.min_verified_inliers):
        return fallback(f"database image {verified[0][1]} has no attitude (re-run 'visloc ingest' to fill it)",
                        n_verified_inliers=best_inliers, candidate_inliers=inliers_of)

    # 2. the verified candidates that have allowed neighbours; a view's structure is built when it is chosen
    pairs_of, neighbours_used = {}, {}

    def use(more_verified: list[tuple[int, int, np.ndarray]]) -> list[int]:
        """The views among ``more_verified`` that pass and have allowed neighbours (in inlier order)."""
        added = []
        for n, i, pairs in more_verified:
            if n < params.min_verified_inliers or not np.all(np.isfinite(geometry.T_world_camera[i])):
                continue
            neighbours = neighbours_of(i, retrieval.search_area, geometry.T_world_camera, params)
            if neighbours:
                pairs_of[i], neighbours_used[i] = pairs, neighbours
                added.append(i)
        return added

    usable = use(verified)
    base = dict(n_verified_inliers=best_inliers, candidate_inliers=inliers_of)
    if not usable:
        return fallback(f"no database neighbour within {params.max_neighbour_gap} frames of the verified views is "
                        f"allowed and at least {params.min_baseline_m:g} m away (car stopped?)", **base)

    def structure_of(i: int) -> tuple[dict[int, np.ndarray], float]:
        return view_structure(geometry, i, neighbours_used[i], params, cache)

    def pose(views: list[int]) -> PosedViews:
        return pose_from_views(query_xy, views, pairs_of, structure_of, neighbours_used, db_east_north_m, geometry,
                               query_camera, params, query_descriptors=query_descriptors_u8)

    posed = pose(usable)
    # 3. every view on one side: the images nearest the pose on the other side, verified, and the query posed again
    if params.both_sides and params.other_side_candidates > 0 and posed.reason is None and posed.side == "one":
        other = other_side_images(posed, retrieval.search_area, set(inliers_of), db_east_north_m, geometry, params)
        more = _verified(other, query_xy, query_descriptors_u8, geometry, query_camera, params)
        inliers_of.update({i: n for n, i, _ in more})
        added = use(more)
        if added:
            again = pose(usable + added)
            if again.reason is None and again.side == "both":
                again.structure_ms += posed.structure_ms
                posed = again
            else:
                posed.structure_ms += again.structure_ms
    return end.posed(round_spread(posed), **base)


SHAPED_SPREAD_VIEWS = 4  # fewer views posed apart: their spread tells the views term's size, not its shape


def round_spread(posed: PosedViews) -> PosedViews:
    """``posed`` with the spread of its two or three views posed apart stated round, at its longest axis (the part
    added is the term "views_round"): two positions lie on one line and say nothing across it, and three say little
    more (``benchmarks/nees_tails.py`` measures what shaped ellipses on so few views held). The exact path's: its
    self-check's poses are stated so too, and its lever gain fitted beyond them. The camera-rate path poses every
    frame on two views, its self-check's poses too, so its gain already holds what their spread cannot see, and a
    followed frame states that spread from the run's pooled scatter (``visloc.pose.trackedcov``)."""
    if posed.reason is not None or not 2 <= posed.views_posed_apart < SHAPED_SPREAD_VIEWS:
        return posed
    views = np.asarray(posed.cov_terms_m2["views"], float)
    extra = float(np.linalg.eigvalsh(views).max()) * np.eye(2) - views
    return replace(posed, cov_m2=posed.cov_m2 + extra, cov_terms_m2={**posed.cov_terms_m2, "views_round": extra})


def _verified(indices: Sequence[int], query_xy: np.ndarray, query_descriptors_u8: np.ndarray,
              geometry: DatabaseGeometry, query_camera: CameraModel,
              params: RefinedParams) -> list[tuple[int, int, np.ndarray]]:
    """(essential-matrix inliers, database index, pairs (query row, keypoint row)) of each of ``indices``, matched
    with Lowe's ratio alone, most inliers first (ties keep the order of ``indices``)."""
    match = MatchParams(tau1=params.ratio, tau2=-1.0)
    verified = []
    for i in indices:
        pairs = correspondences(query_descriptors_u8, geometry.descriptors_u8[i], match)
        mask = essential_inliers(query_xy[pairs[:, 0]], geometry.keypoints_xy_px[i][pairs[:, 1]],
                                 query_camera.K, geometry.camera.K, threshold_px=params.essential_px,
                                 seed=params.seed)
        verified.append((int(mask.sum()), int(i), pairs))
    verified.sort(key=lambda v: -v[0])
    return verified


def other_side_images(posed: PosedViews, allowed: np.ndarray, exclude: set[int], db_east_north_m: np.ndarray,
                      geometry: DatabaseGeometry, params: RefinedParams) -> list[int]:
    """The ``other_side_candidates`` images of ``allowed`` (not in ``exclude``) nearest the pose of ``posed`` on the
    other side of it from its views, facing within ``other_side_max_turn_deg`` of its heading and at most
    ``max_offset_m`` from it, nearest first."""
    T_query = posed.inliers.T_world_camera
    views_side = side_of(geometry.T_world_camera[posed.anchor][:3, 3], T_query)
    found = []
    for j in np.asarray(allowed, int).tolist():
        T = geometry.T_world_camera[j]
        if j in exclude or not np.all(np.isfinite(T)) or side_of(T[:3, 3], T_query) == views_side:
            continue
        distance_m = float(np.linalg.norm(np.asarray(db_east_north_m[j], float) - posed.east_north_m))
        turn_deg = heading_difference_deg(heading_deg_of(T @ geometry.camera.T_camera_imu), posed.heading_deg)
        if distance_m <= params.max_offset_m and turn_deg <= params.other_side_max_turn_deg:
            found.append((distance_m, j))
    return [j for _, j in sorted(found)[: params.other_side_candidates]]


class PoseMeasurer:
    """The refined method's measurer. Refuses to be built without what a pose needs: the database
    camera's calibration and attitudes (``geometry``) and the query camera's calibration."""

    def __init__(self, db_east_north_m: np.ndarray, geometry: DatabaseGeometry, query_camera: CameraModel | None,
                 params: RefinedParams, *, structures: StructureCache | None = None, query_what: str = "the query camera"):
        require_calibrated(geometry, query_camera, query_what)
        self.db_east_north_m = np.asarray(db_east_north_m, float)
        self.geometry = geometry
        self.query_camera = query_camera
        self.params = params
        self.structures = structures if structures is not None else StructureCache()

    def measure(self, query: Query, retrieval: Retrieval) -> Measurement:
        return pose_measurement(query.keypoints_f32, query.descriptors_u8, retrieval, self.db_east_north_m,
                                self.geometry, self.query_camera, self.params, self.structures)

