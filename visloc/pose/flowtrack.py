"""Following the map's points from frame to frame: a pose at camera rate without SIFT or retrieval.

A frame posed by the refined measurement knows which of its pixels are the database's triangulated
points (``visloc.pose.viewpose.MapCorrespondences``). The next frame, a tenth of a second later, sees
mostly the same points a few pixels away. ``follow_points`` finds them again by pyramidal
Lucas-Kanade optical flow, each started where the predicted pose projects its 3D point, and keeps only
those the flow finds again when run backwards. ``pose_tracked`` then poses the frame exactly as the
full measurement does (``visloc.pose.viewpose.pose_from_views``: PnP RANSAC, the per-view check, the
same covariance model), against the same 3D points. The points are the map's, not the previous frame's
estimate, so the pose stays tied to the map and does not drift as visual odometry does; the points
only thin out, and ``needs_relocalization`` says when the full path must find new ones.

Pure functions over numpy arrays (OpenCV for the flow).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from visloc.geometry.projective import CameraModel
from visloc.params import RefinedParams
from visloc.pose.guided import QueryKeypoints, guided_matches, project_points
from visloc.pose.measurement import Measurement, posed_measurement
from visloc.pose.viewpose import DatabaseGeometry, MapCorrespondences, pose_from_views
from visloc.stats import CHI2_2DOF_999

FLOW_WINDOW_PX = 21  # Lucas-Kanade's window side
FLOW_LEVELS = 3  # pyramid levels above the image: follows motions of up to about 2^3 windows
FLOW_CRITERIA = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 20, 0.03)
GRID_CELLS = 4  # the image is cut into GRID_CELLS x GRID_CELLS cells to tell how points are spread


@dataclass(frozen=True)
class TrackedPoints:
    """Map points seen in one frame, as the tracker follows them.

    pixels_px: (M, 2) where they lie in the frame's image as read (before any undistortion);
    track_of: (M,) the image track each point's pixel follows: one keypoint of a fully localized frame, followed
    from frame to frame; the same map point in several views' structure is one track, flowed once;
    view_of, view_rows: (M,) the database view and keypoint row of each; points_world: (M, 3) m;
    points_cov: (M, 3, 3) m^2; neighbours: view -> the database images its structure was triangulated with;
    T_world_camera: (4, 4) the frame's pose; east_north_m: (2,) the frame's posed position."""

    pixels_px: np.ndarray
    track_of: np.ndarray
    view_of: np.ndarray
    view_rows: np.ndarray
    points_world: np.ndarray
    points_cov: np.ndarray
    neighbours: dict
    T_world_camera: np.ndarray
    east_north_m: np.ndarray

    def __len__(self) -> int:
        return len(self.pixels_px)

    @property
    def n_tracks(self) -> int:
        """How many image tracks the points lie on (a keypoint seen in several views' structure counts once)."""
        return int(len(np.unique(self.track_of)))

    def subset(self, keep: np.ndarray, pixels_px: np.ndarray | None = None) -> "TrackedPoints":
        """The points ``keep`` (bool or index), optionally at new pixels (already subset)."""
        px = self.pixels_px[keep] if pixels_px is None else pixels_px
        view_of = self.view_of[keep]
        return TrackedPoints(px, self.track_of[keep], view_of, self.view_rows[keep], self.points_world[keep],
                             self.points_cov[keep], _present(self.neighbours, view_of), self.T_world_camera,
                             self.east_north_m)


def _present(neighbours: dict, view_of: np.ndarray) -> dict:
    """``neighbours`` of the views in ``view_of`` only: a view the points no longer hold may come back later in
    another variant of its structure (a view ahead of the vehicle, triangulated with the images after it, is
    later a view behind it, triangulated with those before)."""
    views = set(np.unique(view_of).tolist())
    return {v: n for v, n in neighbours.items() if v in views}


def points_of(inliers: MapCorrespondences, raw_pixels_px: np.ndarray, east_north_m: np.ndarray,
              neighbours: dict, first_track: int = 0) -> TrackedPoints:
    """What a posed frame hands the tracker: its inliers at the pixels they have in the image as read
    (``raw_pixels_px``: (N, 2) of every query keypoint, before undistortion); keypoint row r follows track
    ``first_track + r``."""
    return TrackedPoints(np.asarray(raw_pixels_px, np.float32)[inliers.query_rows].reshape(-1, 2),
                         first_track + np.asarray(inliers.query_rows, np.int64),
                         inliers.view_of, inliers.view_rows, inliers.points_world, inliers.points_cov,
                         dict(neighbours), np.asarray(inliers.T_world_camera, float),
                         np.asarray(east_north_m, float))


def predicted_camera(T_world_camera: np.ndarray, from_east_north_m: np.ndarray,
                     to_east_north_m: np.ndarray) -> np.ndarray:
    """The camera pose moved by the vehicle's predicted displacement (same attitude)."""
    T = np.array(T_world_camera, float)
    T[:2, 3] += np.asarray(to_east_north_m, float) - np.asarray(from_east_north_m, float)
    return T


def follow_points(previous_gray: np.ndarray, gray: np.ndarray, previous_px: np.ndarray, guess_px: np.ndarray,
                  *, max_backward_px: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (M, 2) of ``previous_px`` found in ``gray`` by pyramidal Lucas-Kanade started at ``guess_px``,
    and (M,) bool: found, inside the image and found again within ``max_backward_px`` of where it was when
    the flow is run back."""
    if len(previous_px) == 0:
        return np.zeros((0, 2), np.float32), np.zeros(0, bool)
    p0 = np.ascontiguousarray(previous_px, np.float32).reshape(-1, 1, 2)
    guess = np.ascontiguousarray(guess_px, np.float32).reshape(-1, 1, 2)
    lk = dict(winSize=(FLOW_WINDOW_PX, FLOW_WINDOW_PX), maxLevel=FLOW_LEVELS, criteria=FLOW_CRITERIA,
              flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
    p1, found, _ = cv2.calcOpticalFlowPyrLK(previous_gray, gray, p0, guess.copy(), **lk)
    back, found_back, _ = cv2.calcOpticalFlowPyrLK(gray, previous_gray, p1, p0.copy(), **lk)
    p1, back = p1.reshape(-1, 2), back.reshape(-1, 2)
    h, w = gray.shape[:2]
    ok = (found.ravel() == 1) & (found_back.ravel() == 1)
    ok &= np.linalg.norm(back - p0.reshape(-1, 2), axis=1) <= max_backward_px
    ok &= (p1[:, 0] >= 0) & (p1[:, 1] >= 0) & (p1[:, 0] <= w - 1) & (p1[:, 1] <= h - 1)
    return p1, ok


def follow(points: TrackedPoints, previous_gray: np.ndarray, gray: np.ndarray, K: np.ndarray,
           displacement_m: np.ndarray | None, *, max_backward_px: float = 1.0) -> TrackedPoints:
    """``points`` found again in ``gray`` (those lost are dropped), each flow started where its point
    projects once the camera has moved by ``displacement_m`` (east, north) from the points' pose (at its
    previous pixel without a displacement, or behind the camera)."""
    guess = np.asarray(points.pixels_px, float).copy()
    if displacement_m is not None and len(points):
        T = predicted_camera(points.T_world_camera, points.east_north_m,
                             points.east_north_m + np.asarray(displacement_m, float))
        uv, front = project_points(points.points_world, T, K)
        # the projection carries the motion; the offset of each point's last pixel from its own projection
        # under the last pose carries what the model misses (lens distortion, the point's own error)
        last, last_front = project_points(points.points_world, points.T_world_camera, K)
        use = front & last_front
        guess[use] = uv[use] + (points.pixels_px[use] - last[use])
    # each track flowed once, from where its points project on average
    tracks, first, of = np.unique(points.track_of, return_index=True, return_inverse=True)
    track_guess = np.zeros((len(tracks), 2))
    np.add.at(track_guess, of, guess)
    track_guess /= np.bincount(of, minlength=len(tracks))[:, None]
    px, ok = follow_points(previous_gray, gray, points.pixels_px[first], track_guess, max_backward_px=max_backward_px)
    keep = ok[of]
    return points.subset(keep, px[of][keep])


def grid_cells_occupied(pixels_px: np.ndarray, image_shape: tuple[int, int], cells: int = GRID_CELLS) -> int:
    """How many of the image's ``cells`` x ``cells`` cells hold at least one of the pixels."""
    if len(pixels_px) == 0:
        return 0
    h, w = image_shape[:2]
    cx = np.clip((np.asarray(pixels_px)[:, 0] * cells // w).astype(int), 0, cells - 1)
    cy = np.clip((np.asarray(pixels_px)[:, 1] * cells // h).astype(int), 0, cells - 1)
    return int(len(np.unique(cy * cells + cx)))


def pose_tracked(points: TrackedPoints, undistorted_px: np.ndarray, db_east_north_m: np.ndarray,
                 geometry: DatabaseGeometry, query_camera: CameraModel,
                 params: RefinedParams) -> tuple[Measurement, MapCorrespondences | None]:
    """The frame posed against the followed points, by the full measurement's own ``pose_from_views`` (views
    ranked by how many of their points were followed), each view alone and their positions averaged (each view's
    structure is adjusted on its own, so the same map point lies a little apart in two views' structure, and the
    followed points come from several views: ``linked``), or a measurement with no position and the reason."""
    views, counts = np.unique(points.view_of, return_counts=True)
    usable = [int(v) for v in views[np.argsort(-counts, kind="stable")]]
    rows = np.arange(len(points))
    pairs_of = {i: np.stack([rows[points.view_of == i], points.view_rows[points.view_of == i]], axis=1)
                for i in usable}
    lookup = {i: {int(r): (p, c) for r, p, c in zip(points.view_rows[points.view_of == i],
                                                      points.points_world[points.view_of == i],
                                                      points.points_cov[points.view_of == i])} for i in usable}
    neighbours = {i: tuple(points.neighbours.get(i, ())) for i in usable}
    # every view the points come from, not only the best few: they are already the map's points this frame saw
    posed = pose_from_views(np.asarray(undistorted_px, float), usable, pairs_of, lambda i: (lookup[i], 0.0),
                            neighbours, db_east_north_m, geometry, query_camera,
                            params.replace(n_views=max(params.n_views, len(usable)), fuse_views=True))
    if posed.reason is not None:
        return Measurement(None, None, None, fallback_reason=f"tracked points: {posed.reason}", **posed.support), None
    # a keypoint followed into several views' structure constrains the pose once: a pose on a handful of image
    # tracks, each repeated in many views, passes a count of 2D-3D inliers and claims an ellipse it has not earned
    n_tracks = int(len(np.unique(points.track_of[posed.inliers.query_rows])))
    if n_tracks < params.min_pnp_inliers:
        return Measurement(None, None, None, fallback_reason=f"tracked points: {n_tracks} image tracks among the PnP "
                                                             f"inliers (fewer than {params.min_pnp_inliers})",
                           **posed.support), None
    m = posed_measurement(posed)
    return m, posed.inliers


def disagree(a: Measurement, b: Measurement) -> bool:
    """Two positions farther apart than the 99.9 % ellipse of their summed covariances."""
    if a.cov_m2 is None or b.cov_m2 is None or a.east_north_m is None or b.east_north_m is None:
        return False
    d = np.asarray(a.east_north_m, float) - np.asarray(b.east_north_m, float)
    return float(d @ np.linalg.solve(np.asarray(a.cov_m2) + np.asarray(b.cov_m2), d)) > CHI2_2DOF_999


def needs_relocalization(n_points: int, cells_occupied: int, lever_m: float | None, estimate_sigma_m: float,
                         frames_since_full: int, *, min_points: int, min_cells: int, max_lever_m: float,
                         max_sigma_m: float, every_frames: int, nearest_view_m: float = np.inf,
                         max_lever_excess_m: float = np.inf, views_ahead: bool = True,
                         behind_only_every_frames: int = 0) -> str | None:
    """Why the full path should find new points now (None: the tracked points still serve). ``nearest_view_m``:
    how far the nearest database view the frame may use is; a frame whose points' nearest view (``lever_m``) lies
    more than ``max_lever_excess_m`` farther asks for the nearer views' points (the error grows with the
    distance to the views). ``views_ahead``: whether a view the frame was posed on lies ahead of it; posed on
    views behind it only, it asks once ``behind_only_every_frames`` frames have passed (0: never)."""
    if n_points < min_points:
        return f"{n_points} points followed (fewer than {min_points})"
    if cells_occupied < min_cells:
        return f"points in {cells_occupied} of {GRID_CELLS * GRID_CELLS} image cells (fewer than {min_cells})"
    if lever_m is not None and lever_m > max_lever_m:
        return f"{lever_m:.1f} m from the nearest view (more than {max_lever_m:g} m)"
    if lever_m is not None and lever_m > nearest_view_m + max_lever_excess_m:
        return (f"{lever_m:.1f} m from the nearest view of its points, a view it may use {nearest_view_m:.1f} m away "
                f"(more than {max_lever_excess_m:g} m nearer)")
    if estimate_sigma_m > max_sigma_m:
        return f"estimate sigma {estimate_sigma_m:.2f} m (more than {max_sigma_m:g} m)"
    if not views_ahead and 0 < behind_only_every_frames <= frames_since_full:
        return f"posed on views behind it only, {frames_since_full} frames since the last full localization"
    if every_frames > 0 and frames_since_full >= every_frames:
        return f"{frames_since_full} frames since the last full localization"
    return None


def merged(current: TrackedPoints | None, fresh: TrackedPoints) -> TrackedPoints:
    """``current`` points and the ``fresh`` ones they lack (same view and keypoint row: the current one is kept),
    at ``current``'s pose (``fresh`` alone when there are no current points)."""
    if current is None or not len(current):
        return fresh
    have = set(zip(current.view_of.tolist(), current.view_rows.tolist()))
    new = np.array([(v, r) not in have for v, r in zip(fresh.view_of.tolist(), fresh.view_rows.tolist())], bool)
    return appended(current, fresh.subset(new))


# Two views' points are the same map point (``linked``) when they lie within LINK_RADIUS_FRACTION of the point's depth
# of each other (at least LINK_MIN_RADIUS_M), among the LINK_CANDIDATES nearest, and their descriptors lie at most
# LINK_MAX_DESCRIPTOR_DISTANCE apart (L2, uint8 SIFT) and closer than LINK_RATIO times the next candidate's
LINK_RADIUS_FRACTION = 0.06
LINK_MIN_RADIUS_M = 0.3
LINK_CANDIDATES = 4
LINK_MAX_DESCRIPTOR_DISTANCE = 250.0
LINK_RATIO = 0.8


def linked(points: TrackedPoints, view_points: dict, db_descriptors_u8, *, neighbours: dict | None = None,
           trees: dict | None = None,
           radius_fraction: float = LINK_RADIUS_FRACTION, min_radius_m: float = LINK_MIN_RADIUS_M,
           max_distance: float = LINK_MAX_DESCRIPTOR_DISTANCE, ratio: float = LINK_RATIO) -> TrackedPoints:
    """``points`` with the points of other views that are the same map points: what lets a followed frame go on
    from views it can no longer use (the exclusion window, or views it has left far behind) to nearer ones
    without a full localization.

    Each view's structure is triangulated on its own (its poses adjusted on its own), so one map point lies at
    slightly different places in two views' structures: on the shared drives 1 % of its depth apart in median,
    2-3 % at the upper quartile. A followed point takes, in each view of ``view_points`` (view -> (rows (K,),
    points_world (K, 3), points_cov (K, 3, 3))) where its track has no point yet, the point among the
    ``LINK_CANDIDATES`` nearest its own 3D point and within ``radius_fraction`` of its distance from the camera
    (at least ``min_radius_m``) whose descriptor in that view lies nearest its descriptor in its own view, when
    at most ``max_distance`` and below ``ratio`` times the next one's; a point of the view taken by several
    keeps the nearest. The database alone links them, as a map's multi-view tracks do: the frame's own image is not
    compared with the views. The new points follow the same image tracks as the points they were linked from.
    ``neighbours``: view -> the database images its structure was triangulated with, for the views of
    ``view_points``; ``trees``: a cache of each view's k-d tree over its points ((view, its neighbours) ->
    ``cKDTree``)."""
    from scipy.spatial import cKDTree  # here: scipy.spatial costs every command's start-up about 0.2 s

    if not len(points) or not view_points:
        return points
    tracks, first = np.unique(points.track_of, return_index=True)
    source_xyz = points.points_world[first]
    source_desc = np.empty((len(first), 128), np.float32)
    source_views = points.view_of[first]
    for v in np.unique(source_views).tolist():
        at = source_views == v
        source_desc[at] = np.asarray(db_descriptors_u8[v])[points.view_rows[first][at]]
    depth_m = np.linalg.norm(source_xyz - np.asarray(points.T_world_camera, float)[:3, 3], axis=1)
    radius_m = np.maximum(min_radius_m, radius_fraction * depth_m)
    parts = []
    for view, (rows, xyz, cov) in view_points.items():
        if not len(rows):
            continue
        key = (view, tuple((neighbours or {}).get(view, ())))  # a view's structure differs with its neighbours
        tree = None if trees is None else trees.get(key)
        if tree is None:
            tree = cKDTree(np.asarray(xyz, float))
            if trees is not None:
                trees[key] = tree
        untaken = ~np.isin(tracks, points.track_of[points.view_of == view])  # tracks without a point in the view
        if not untaken.any():
            continue
        k = min(LINK_CANDIDATES, len(rows))
        dist_m, nearest = tree.query(source_xyz[untaken], k=k, distance_upper_bound=radius_m[untaken].max())
        dist_m, nearest = dist_m.reshape(-1, k), nearest.reshape(-1, k)
        within = dist_m <= radius_m[untaken][:, None]
        if not within.any():
            continue
        si = np.flatnonzero(untaken)[np.nonzero(within)[0]]  # (pairs,) source track index, view point index
        pi = nearest[within]
        view_desc = np.asarray(db_descriptors_u8[view])[rows[pi]].astype(np.float32)
        dist = np.linalg.norm(view_desc - source_desc[si], axis=1)
        order = np.lexsort((dist, si))
        si, pi, dist = si[order], pi[order], dist[order]
        starts = np.flatnonzero(np.r_[True, si[1:] != si[:-1]])
        second = np.full(len(starts), np.inf)
        has_second = np.r_[starts[1:], len(si)] - starts > 1
        second[has_second] = dist[starts[has_second] + 1]
        ok = starts[(dist[starts] <= max_distance) & (dist[starts] < ratio * second)]
        if not ok.size:
            continue
        by_point = ok[np.lexsort((dist[ok], pi[ok]))]  # a view's point claimed by several tracks: the nearest
        _, keep = np.unique(pi[by_point], return_index=True)
        ok = by_point[keep]
        parts.append((first[si[ok]], np.full(ok.size, view, np.int64), rows[pi[ok]], xyz[pi[ok]], cov[pi[ok]]))
    if not parts:
        return points
    source, view_of, view_rows, xyz, cov = (np.concatenate(x) for x in zip(*parts))
    return appended(points, TrackedPoints(points.pixels_px[source], points.track_of[source], view_of, view_rows, xyz,
                                          cov, dict(neighbours or {}), points.T_world_camera, points.east_north_m))


def appended(points: TrackedPoints, more: TrackedPoints) -> TrackedPoints:
    """``points`` and then ``more`` (points it lacks), at ``points``' pose; ``more``'s points of a view that
    ``points`` holds in another variant of its structure (other neighbours: other 3D points) are left out."""
    own = _present(points.neighbours, points.view_of)
    clash = [v for v, n in more.neighbours.items() if v in own and tuple(own[v]) != tuple(n)]
    if clash:
        more = more.subset(~np.isin(more.view_of, clash))
    cat = np.concatenate
    return TrackedPoints(cat([points.pixels_px, more.pixels_px]), cat([points.track_of, more.track_of]),
                         cat([points.view_of, more.view_of]), cat([points.view_rows, more.view_rows]),
                         cat([points.points_world, more.points_world]), cat([points.points_cov, more.points_cov]),
                         {**_present(more.neighbours, more.view_of), **own}, points.T_world_camera,
                         points.east_north_m)


def guided_view_matches(view_points: dict, db_descriptors_u8, query_xy_px: np.ndarray,
                        query_descriptors_u8: np.ndarray, T_world_camera: np.ndarray, K: np.ndarray,
                        image_shape: tuple[int, int], *, radius_px: float = 4.0, ratio: float = 0.8,
                        max_distance: float = np.inf) -> MapCorrespondences:
    """Every structure point of some views found among the query's keypoints by its projection: each point
    projected into the image by the pose takes the query keypoint within ``radius_px`` whose descriptor is nearest
    its view keypoint's, if nearer than ``ratio`` times the next one within the radius (the guided matching of
    ``visloc.pose.guided.guided_matches``, view by view), one point per query keypoint over all the views: the
    nearest (of equals, the first view's). Far more of the map than descriptor matching alone finds: what a
    tracker follows.

    view_points: view -> (rows (M,), points_world (M, 3), points_cov (M, 3, 3)) of its structure;
    ``query_xy_px``: (N, 2) undistorted keypoints. Returns the matches (``T_world_camera`` as given)."""
    h, w = image_shape[:2]
    parts = []
    query = QueryKeypoints(query_xy_px, query_descriptors_u8)  # made once for every view
    for view, (rows, points, covs) in view_points.items():
        if not len(rows):
            continue
        uv, front = project_points(points, T_world_camera, K)
        with np.errstate(invalid="ignore"):  # a point behind the camera may project to nowhere
            inside = front & (uv[:, 0] >= 0) & (uv[:, 1] >= 0) & (uv[:, 0] <= w - 1) & (uv[:, 1] <= h - 1)
        pairs, dist = guided_matches(uv, inside, np.asarray(db_descriptors_u8[view])[rows], query,
                                     radius_px=radius_px, ratio=ratio, max_distance=max_distance)
        k = pairs[:, 0]
        parts.append((dist, pairs[:, 1], np.full(len(k), view, np.int64), rows[k], points[k], covs[k]))
    if not parts:
        return MapCorrespondences(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64),
                                  np.zeros((0, 3)), np.zeros((0, 3, 3)), np.asarray(T_world_camera, float))
    dist, qi, view_of, rows, points, covs = (np.concatenate(x) for x in zip(*parts))
    order = np.argsort(dist, kind="stable")
    _, first = np.unique(qi[order], return_index=True)  # one point per query keypoint: the nearest
    keep = order[np.sort(first)]
    return MapCorrespondences(qi[keep], view_of[keep], rows[keep], points[keep], covs[keep],
                              np.asarray(T_world_camera, float))
