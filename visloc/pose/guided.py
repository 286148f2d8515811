"""Guided matching: once a query is posed, its views' 3D points are projected into it and matched to the
query keypoints near where they land.

Matching a query to a database image by descriptors alone (Lowe's ratio over the whole image) drops
every keypoint whose nearest neighbour is not clearly better than its second: on repeated texture
(fences, windows, road markings) and low contrast, most of them. A pose narrows each point's
candidates to the few query keypoints within a few pixels of its projection, and among those the
ratio test passes far more often. This is the step COLMAP's and ORB-SLAM's localization take
after a first pose; here it gathers support from the views' stored structure, which the descriptor
matching left unused.

Pure functions over numpy arrays.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from visloc.geometry.projective import CameraModel, PnPResult
    from visloc.params import RefinedParams


def project_points(points_world: np.ndarray, T_world_camera: np.ndarray, K: np.ndarray,
                   min_depth_m: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """(M, 2) pixels of ``points_world`` (M, 3) seen from the camera at ``T_world_camera``, and (M,) bool:
    which lie in front of it (depth above ``min_depth_m``)."""
    R, t = T_world_camera[:3, :3], T_world_camera[:3, 3]
    p_camera = (np.asarray(points_world, float) - t) @ R
    depth = p_camera[:, 2]
    front = depth > min_depth_m
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = (p_camera @ K.T)[:, :2] / p_camera[:, 2:3]
    return uv, front


def _pair_distances(a: np.ndarray, b: np.ndarray, ia: np.ndarray, ib: np.ndarray, chunk: int = 2048) -> np.ndarray:
    """(K,) L2 distances between rows ``a[ia]`` and ``b[ib]`` (float32 arrays), a cache-sized chunk at a time.

    The squares are summed by ``einsum`` on the difference made in place: about four times faster than
    ``np.linalg.norm`` of the difference, and as exact. For descriptors that
    hold whole numbers (uint8 SIFT) every partial sum is a whole number below 2**24, exact in float32 in any
    order, so the distances are the same to the bit."""
    out = np.empty(len(ia), np.float32)
    for s in range(0, len(ia), chunk):
        d = a[ia[s:s + chunk]]
        d -= b[ib[s:s + chunk]]
        out[s:s + chunk] = np.einsum("ij,ij->i", d, d)
    return np.sqrt(out, out=out)


class QueryKeypoints:
    """A query's keypoints made ready for guided matching against many views: a k-d tree over their pixels
    (``xy_px`` (N, 2)) and their descriptors as float32, made once and shared by every view's points."""

    def __init__(self, xy_px: np.ndarray, descriptors: np.ndarray):
        from scipy.spatial import cKDTree  # here: scipy.spatial costs every command's start-up about 0.2 s

        self.n = len(xy_px)
        self.tree = cKDTree(np.asarray(xy_px, float)) if self.n else None
        self.descriptors_f32 = np.asarray(descriptors, np.float32)


def _by_point_distance_query(pi: np.ndarray, dist: np.ndarray, qi: np.ndarray) -> np.ndarray:
    """The order of pairs by point, then descriptor distance, then query row: ``np.lexsort((qi, dist, pi))``,
    made by one sort of a 64-bit key where the three fit in one (the pairs are unique, so the order is the same;
    a distance is never negative, and a non-negative float32's bits order as the float does), three to four
    times faster."""
    p_bits, q_bits = int(pi.max()).bit_length(), int(qi.max()).bit_length()
    if p_bits + 32 + q_bits > 64:
        return np.lexsort((qi, dist, pi))
    key = ((pi.astype(np.uint64) << np.uint64(32 + q_bits)) | (dist.view(np.uint32).astype(np.uint64) << np.uint64(q_bits))
           | qi.astype(np.uint64))
    return np.argsort(key)


def guided_matches(points_uv_px: np.ndarray, usable: np.ndarray, point_descriptors: np.ndarray,
                   query: QueryKeypoints, *, radius_px: float, ratio: float,
                   max_distance: float) -> tuple[np.ndarray, np.ndarray]:
    """(K, 2) int64 pairs (point row, query row), by point row, and (K,) float32 their descriptor distances: for
    each ``usable`` point (in front of the camera, say; a non-finite projection never is), the query keypoint
    within ``radius_px`` of its projection whose descriptor is nearest the point's (of equals, the first query
    row), kept when that distance is at most ``max_distance`` and below ``ratio`` times the second nearest's
    within the radius (a lone candidate passes on the distance alone). A query keypoint claimed by several
    points goes to the nearest in descriptor distance (of equals, the first point row).

    Every (projection, keypoint) pair within the radius comes from a k-d tree at once, and only the usable
    points' descriptors are made float. ``query``: the query's keypoints (``QueryKeypoints``), made once for
    every view whose points are matched to them."""
    rows = np.flatnonzero(np.asarray(usable, bool) & np.all(np.isfinite(points_uv_px), axis=1))
    none = np.zeros((0, 2), np.int64), np.zeros(0, np.float32)
    if len(rows) == 0 or query.n == 0:
        return none
    from scipy.spatial import cKDTree

    near = cKDTree(np.asarray(points_uv_px, float)[rows]).sparse_distance_matrix(query.tree, radius_px,
                                                                                 output_type="ndarray")
    pi, qi = near["i"].astype(np.int64), near["j"].astype(np.int64)
    if not pi.size:
        return none
    dist = _pair_distances(np.asarray(point_descriptors)[rows].astype(np.float32), query.descriptors_f32, pi, qi)
    order = _by_point_distance_query(pi, dist, qi)  # by point, nearest first, then by query row
    pi, qi, dist = pi[order], qi[order], dist[order]
    starts = np.flatnonzero(np.r_[True, pi[1:] != pi[:-1]])
    nearest = dist[starts].astype(np.float64)  # the tests in double precision, as a Python float would make them
    second = np.full(len(starts), np.inf)
    has_second = np.r_[starts[1:], len(pi)] - starts > 1
    second[has_second] = dist[starts[has_second] + 1]
    ok = starts[(nearest <= max_distance) & (nearest < ratio * second)]
    point_rows, query_rows, dist = rows[pi[ok]], qi[ok], dist[ok]
    claims = np.lexsort((point_rows, dist))  # a query row's claims, nearest (then first point) first
    _, first = np.unique(query_rows[claims], return_index=True)
    keep = np.sort(claims[first])  # by point row, as the points came
    return np.c_[point_rows[keep], query_rows[keep]], dist[keep]


def descriptor_distances(query_descriptors: np.ndarray, view_descriptors: np.ndarray,
                         pairs: np.ndarray) -> np.ndarray:
    """(M,) L2 distances of the descriptors of ``pairs`` (query row, view row)."""
    return _pair_distances(np.asarray(query_descriptors, np.float32), np.asarray(view_descriptors, np.float32),
                           pairs[:, 0], pairs[:, 1])


def guided_pairs(pnp: "PnPResult", views, chosen: list[int], structures: dict[int, dict], query_xy: np.ndarray,
                 query_descriptors: np.ndarray, geometry, query_camera: "CameraModel",
                 params: "RefinedParams") -> dict[int, np.ndarray]:
    """Each chosen view's pairs (query row, keypoint row) that the pose ``pnp`` kept as inliers among ``views``
    (the correspondences it was solved on: their ``rows`` and ``view_of``), with those guided matching adds
    (``guided_matches``): the view's other 3D points, projected by the pose and
    matched to the query keypoints within ``guided_radius_px`` of where they land, by Lowe's ratio
    ``guided_ratio`` among those, and no farther in descriptor space than the farthest of the pose's
    own inliers (a match the first pose confirmed). The first pose's outliers are dropped: the points they
    claimed are matched again. ``geometry``: the database (``visloc.pose.viewpose.DatabaseGeometry``)."""
    k = pnp.inliers
    distances = np.concatenate([descriptor_distances(query_descriptors, geometry.descriptors_u8[i],
                                                     views.rows[k][views.view_of[k] == i]) for i in chosen])
    max_distance = float(distances.max()) if len(distances) else 0.0
    query = QueryKeypoints(query_xy, query_descriptors)
    out = {}
    for i in chosen:
        pairs = views.rows[k][views.view_of[k] == i]  # the first pose's inliers: its outliers free their points
        d_rows = np.array(sorted(structures[i]), np.int64)
        if len(d_rows) == 0:
            out[i] = pairs
            continue
        points = np.array([structures[i][r][0] for r in d_rows.tolist()])
        uv, front = project_points(points, pnp.T_world_camera, query_camera.K)
        found, _ = guided_matches(uv, front, geometry.descriptors_u8[i][d_rows], query,
                                  radius_px=params.guided_radius_px, ratio=params.guided_ratio,
                                  max_distance=max_distance)
        new = np.c_[found[:, 1], d_rows[found[:, 0]]]
        taken_q, taken_d = set(pairs[:, 0].tolist()), set(pairs[:, 1].tolist())
        new = np.array([(q, d) for q, d in new.tolist() if q not in taken_q and d not in taken_d], np.int64)
        out[i] = np.concatenate([pairs, new.reshape(-1, 2)]) if len(new) else pairs
    return out
