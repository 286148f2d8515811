"""Geometry of the refined mode on a synthetic scene with known poses.

A street of random 3D points, database cameras at known poses along it, a query camera
between them; pixels are projections with a KITTI-like K plus small noise. The
triangulation, the PnP pose and the whole measurement must give back the known answer.
"""

from dataclasses import replace

import numpy as np
import pytest

from visloc.geometry.projective import (CameraModel, essential_inliers, imu_east_north_covariance, imu_pose_from_camera,
                             imu_poses, invert, project, rotation_from_rpy, solve_pnp, triangulate)
from visloc.protocols.drive import filter_measurements
from visloc.errors import InputError
from visloc.features.sift import Query
from visloc.pose.measurement import GEOMETRY, GEOTAG, geotag_measurement
from visloc.params import FilterParams, MatchParams, RefinedParams
from visloc.pose.refined import PoseMeasurer, StructureCache, pose_measurement
from visloc.pose.selfcheck import self_check_params
from visloc.pose.viewpose import DatabaseGeometry, agreeing_majority
from visloc.retrieval.retrievers import Retrieval
from visloc.retrieval.matching import correspondences
from visloc.tracking.kalman import run_filter
from visloc.pose.uncertainty import DEFAULT_LEVER_GAIN, LeverGain

K = np.array([[721.5377, 0.0, 609.5593], [0.0, 721.5377, 172.854], [0.0, 0.0, 1.0]])
WIDTH_PX, HEIGHT_PX = 1242, 375
# imu: x forward, y left, z up; camera: x right, y down, z forward, 1.1 m ahead of the imu and 0.7 m above it
R_CAMERA_IMU = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
T_CAMERA_IMU = np.eye(4)
T_CAMERA_IMU[:3, :3] = R_CAMERA_IMU
T_CAMERA_IMU[:3, 3] = -R_CAMERA_IMU @ np.array([1.1, 0.3, 0.7])
CAMERA = CameraModel(K, T_CAMERA_IMU)


def street(n_points=1500, seed=0):
    """Points on two facades and the road ahead of an eastbound car (world ENU, metres)."""
    rng = np.random.default_rng(seed)
    east = rng.uniform(5.0, 60.0, n_points)
    side = rng.choice([-1.0, 1.0], n_points)
    north = side * rng.uniform(4.0, 9.0, n_points)
    up = rng.uniform(-1.5, 6.0, n_points)
    return np.stack([east, north, up], axis=1)


def camera_pose(east_m, north_m=0.0, up_m=0.0, yaw_rad=0.0, pitch_rad=0.0, roll_rad=0.0):
    T_world_imu = imu_poses(np.array([[east_m, north_m, up_m]]), np.array([[roll_rad, pitch_rad, yaw_rad]]))[0]
    return T_world_imu @ invert(T_CAMERA_IMU), T_world_imu


def observe(points, T_world_camera, noise_px=0.0, rng=None):
    """Pixels and a visibility mask (in front, inside the image)."""
    uv, depth = project(K, T_world_camera, points)
    visible = (depth > 1.0) & (uv[:, 0] >= 0) & (uv[:, 0] < WIDTH_PX) & (uv[:, 1] >= 0) & (uv[:, 1] < HEIGHT_PX)
    if noise_px:
        uv = uv + (rng or np.random.default_rng(1)).normal(scale=noise_px, size=uv.shape)
    return uv, visible


def test_rotation_follows_the_oxts_convention():
    # yaw 90 degrees: the car's forward axis (imu x) points north, its left axis (imu y) west
    R = rotation_from_rpy(0.0, 0.0, np.pi / 2)
    np.testing.assert_allclose(R @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(R @ [0, 1, 0], [-1, 0, 0], atol=1e-12)
    # positive pitch is "front down" in OXTS: forward axis gets a negative up component
    assert (rotation_from_rpy(0.0, 0.1, 0.0) @ [1, 0, 0])[2] < 0
    # positive roll is "left side up"
    assert (rotation_from_rpy(0.1, 0.0, 0.0) @ [0, 1, 0])[2] > 0
    T = imu_poses(np.array([[1.0, 2.0, 3.0]]), np.array([[0.1, 0.2, 0.3]]))[0]
    np.testing.assert_allclose(invert(T) @ T, np.eye(4), atol=1e-12)


def test_triangulation_recovers_points_and_rejects_tiny_parallax():
    points = street()
    Ta, _ = camera_pose(0.0)
    Tb, _ = camera_pose(3.0, north_m=0.1, yaw_rad=0.02)
    xa, va = observe(points, Ta)
    xb, vb = observe(points, Tb)
    both = va & vb
    exact = triangulate(K, Ta, xa[both], K, Tb, xb[both], max_reprojection_px=1.0, min_parallax_deg=1.0)
    assert exact.keep.sum() > 300
    assert np.abs(exact.points_world[exact.keep] - points[both][exact.keep]).max() < 1e-6
    # 0.2 px of noise: with a forward baseline depth is the weak direction, its error grows with distance
    rng = np.random.default_rng(2)
    xa_noisy = xa + rng.normal(scale=0.2, size=xa.shape)
    xb_noisy = xb + rng.normal(scale=0.2, size=xb.shape)
    tri = triangulate(K, Ta, xa_noisy[both], K, Tb, xb_noisy[both], max_reprojection_px=1.0, min_parallax_deg=1.0)
    assert tri.keep.sum() > 300
    err = np.linalg.norm(tri.points_world[tri.keep] - points[both][tri.keep], axis=1)
    distance = np.linalg.norm(points[both][tri.keep] - Ta[:3, 3], axis=1)
    assert np.median(err / distance) < 0.01
    assert np.all(tri.parallax_deg[tri.keep] >= 1.0)
    # the same views with no baseline: nothing has parallax, nothing is kept
    zero = triangulate(K, Ta, xa[va], K, Ta, xa[va], min_parallax_deg=0.5)
    assert zero.keep.sum() == 0


@pytest.mark.parametrize("noise_px", [0.0, 0.3])
def test_pnp_gives_back_the_query_position_within_centimetres(noise_px):
    points = street(seed=3)
    T_query_camera, T_query_imu = camera_pose(-6.0, north_m=0.4, up_m=0.05, yaw_rad=0.03, pitch_rad=0.01)
    xq, vq = observe(points, T_query_camera, noise_px, np.random.default_rng(4))
    outliers = np.flatnonzero(vq)[:40]  # 40 wrong 2D-3D pairs, RANSAC must drop them
    xq[outliers] += np.random.default_rng(5).uniform(30, 200, (40, 2))
    pnp = solve_pnp(points[vq], xq[vq], K, reprojection_px=2.0, seed=0, min_inliers=15)
    assert not isinstance(pnp, str), pnp
    T_imu = imu_pose_from_camera(pnp.T_world_camera, T_CAMERA_IMU)
    assert np.linalg.norm(T_imu[:3, 3] - T_query_imu[:3, 3]) < 0.02
    assert not set(np.flatnonzero(vq)[pnp.inliers]) & set(outliers)


def test_pnp_where_most_pairs_are_wrong_keeps_the_right_ones_and_its_inliers_settle():
    """60 % of the pairs wrong, as on a retrieval's correspondences: the pose within centimetres, no wrong pair
    kept unless it fits by chance, most right ones kept, and the inliers exactly those that fit the final pose
    (selected again until they no longer change)."""
    points = street(n_points=200, seed=11)
    T_query_camera, T_query_imu = camera_pose(-6.0, north_m=0.3, yaw_rad=0.02)
    xq, vq = observe(points, T_query_camera, 1.0, np.random.default_rng(12))  # 1 px: pairs near the threshold
    X, x = points[vq], xq[vq].copy()
    rng = np.random.default_rng(13)
    wrong = rng.choice(len(x), int(0.6 * len(x)), replace=False)
    x[wrong] = rng.uniform([0, 0], [WIDTH_PX, HEIGHT_PX], (len(wrong), 2))  # anywhere in the image
    pnp = solve_pnp(X, x, K, reprojection_px=2.0, seed=0, min_inliers=15)
    assert not isinstance(pnp, str), pnp
    T_imu = imu_pose_from_camera(pnp.T_world_camera, T_CAMERA_IMU)
    assert np.linalg.norm(T_imu[:3, 3] - T_query_imu[:3, 3]) < 0.05
    right = np.setdiff1d(np.arange(len(x)), wrong)
    uv_true, _ = project(K, T_query_camera, X)
    near_true = np.linalg.norm(uv_true - x, axis=1) <= 2.0
    assert near_true[np.intersect1d(pnp.inliers, wrong)].all()  # a wrong pair kept only where it fits by chance
    assert len(np.intersect1d(pnp.inliers, right)) >= 0.8 * len(right)  # 1 px noise puts ~14 % beyond 2 px
    uv, _ = project(K, pnp.T_world_camera, X)
    np.testing.assert_array_equal(np.flatnonzero(np.linalg.norm(uv - x, axis=1) <= 2.0), pnp.inliers)


def test_pnp_covariance_matches_the_scatter_of_repeated_noisy_solutions():
    """With exact 3D points and pixel noise, PnP's propagated covariance should describe its own errors."""
    points = street(n_points=300, seed=6)
    T_query_camera, T_query_imu = camera_pose(-6.0, north_m=0.4, yaw_rad=0.03)
    nees = []
    for seed in range(40):
        xq, vq = observe(points, T_query_camera, 1.0, np.random.default_rng(100 + seed))
        pnp = solve_pnp(points[vq], xq[vq], K, reprojection_px=4.0, seed=0)
        e = imu_pose_from_camera(pnp.T_world_camera, T_CAMERA_IMU)[:2, 3] - T_query_imu[:2, 3]
        cov = imu_east_north_covariance(pnp, T_CAMERA_IMU)
        assert np.all(np.linalg.eigvalsh(cov) > 0)
        nees.append(e @ np.linalg.solve(cov, e))
    # chi-square with 2 dof has mean 2; 40 draws put the sample mean within about +-0.7
    assert 1.2 < np.mean(nees) < 3.0, np.mean(nees)


def test_pnp_with_too_few_points_says_why():
    points = street(n_points=8)
    T, _ = camera_pose(0.0)
    x, v = observe(points, T)
    reason = solve_pnp(points[v], x[v], K, min_inliers=15)
    assert isinstance(reason, str) and "2D-3D correspondences" in reason


def test_essential_inliers_reject_wrong_matches_and_need_five_points():
    points = street(seed=7)
    Ta, _ = camera_pose(0.0)
    Tb, _ = camera_pose(4.0, yaw_rad=0.05)
    xa, va = observe(points, Ta, 0.2)
    xb, vb = observe(points, Tb, 0.2)
    both = np.flatnonzero(va & vb)
    ya, yb = xa[both].copy(), xb[both].copy()
    wrong = np.arange(0, len(both), 5)
    yb[wrong] = np.random.default_rng(8).uniform([0, 0], [WIDTH_PX, HEIGHT_PX], (len(wrong), 2))
    mask = essential_inliers(ya, yb, K, K, threshold_px=1.0, seed=0)
    right = np.setdiff1d(np.arange(len(both)), wrong)
    assert mask[right].mean() > 0.95 and mask[wrong].mean() < 0.1
    np.testing.assert_array_equal(mask, essential_inliers(ya, yb, K, K, threshold_px=1.0, seed=0))  # seeded
    assert not essential_inliers(ya[:4], yb[:4], K, K).any()


# -- the whole measurement -------------------------------------------------------------

def synthetic_database(db_east_m, query_east_m=-2.0, n_points=1500, noise_px=0.3, seed=11, geotag_sigma_m=0.01,
                       lever_gain=None, yaw_error_rad=None, north_error_m=None):
    """Database images at the given eastings (all heading east), a query, and descriptors per 3D point;
    the geotags state ``geotag_sigma_m`` as their accuracy, the database's self-check measured
    ``lever_gain`` (None: none, the default applies). ``yaw_error_rad`` (one per image): how far each
    database camera's recorded yaw is off the true one (the images are taken at the true poses);
    ``north_error_m`` (one per image): how far each image's geotag and recorded pose lie north of the truth."""
    rng = np.random.default_rng(seed)
    points = street(n_points=n_points, seed=seed)
    descriptors = rng.integers(0, 256, (n_points, 128)).astype(np.uint8)
    poses, kps, descs = [], [], []
    for east in db_east_m:
        T, _ = camera_pose(east)
        x, v = observe(points, T, noise_px, rng)
        poses.append(T)
        kps.append(x[v])
        descs.append(descriptors[v])
    Tq, Tq_imu = camera_pose(query_east_m, north_m=0.3, yaw_rad=0.02)
    xq, vq = observe(points, Tq, noise_px, rng)
    recorded = poses if yaw_error_rad is None else [camera_pose(east, yaw_rad=err)[0]
                                                    for east, err in zip(db_east_m, yaw_error_rad)]
    geometry = DatabaseGeometry(T_world_camera=np.array(recorded), keypoints_xy_px=tuple(kps),
                                descriptors_u8=tuple(descs), camera=CAMERA, geotag_sigma_m=np.full(len(poses), geotag_sigma_m),
                                lever_gain=lever_gain,
                                heading_spread_rad=None if yaw_error_rad is None else float(np.std(yaw_error_rad)))
    if north_error_m is not None:
        recorded = [camera_pose(east, north_m=err)[0] for east, err in zip(db_east_m, north_error_m)]
        geometry = replace(geometry, T_world_camera=np.array(recorded))
    imu_positions = np.array([(T @ T_CAMERA_IMU)[:2, 3] for T in (poses if north_error_m is None else recorded)])
    return geometry, imu_positions, xq[vq], descriptors[vq], Tq_imu[:2, 3]


def retrieval_over(n):
    """Every database image a candidate; counts favour the middle image."""
    counts = np.full(n, 50, np.int64)
    counts[n // 2] = 80
    return Retrieval(candidates=np.arange(n), counts=counts, best_index=n // 2)


def test_measurement_gives_back_the_known_query_position_within_centimetres():
    geometry, geotags, xq, dq, truth = synthetic_database([3.0, 6.0, 9.0, 12.0, 15.0], lever_gain=LeverGain(0.0, 0.0))
    params = RefinedParams(neighbour_baselines_m=(2.0, 5.0), max_neighbour_gap=2, n_views=2)
    cache = StructureCache()
    m = pose_measurement(xq, dq, retrieval_over(5), geotags, geometry, CAMERA, params, cache)
    assert m.source == GEOMETRY and m.fallback_reason is None, m.fallback_reason
    assert np.linalg.norm(m.east_north_m - truth) < 0.05
    assert m.n_pnp_inliers > 100 and m.sigma_m < 0.1 and m.heading_deg == pytest.approx(90 - np.degrees(0.02), abs=0.2)
    assert not m.thin_support  # plenty of support: posed at pnp_px
    assert len(cache) > 0
    # the exact path verifies: its count is essential-matrix inliers, the camera-rate path's count stays unset
    assert m.n_verified_inliers == max(m.candidate_inliers.values()) >= params.min_verified_inliers
    assert m.n_structure_matches is None and m.candidate_structure_matches == {}
    # the paper's measurement of the same retrieval is the best match's geotag, 5 m off here
    paper = geotag_measurement(retrieval_over(5), geotags)
    assert paper.source == GEOTAG and paper.cov_m2 is None
    assert paper.n_verified_inliers is None and paper.n_structure_matches is None  # nothing verified or matched
    np.testing.assert_array_equal(paper.east_north_m, geotags[2])
    # deterministic: the same inputs give the same measurement, with or without the cache
    again = PoseMeasurer(geotags, geometry, CAMERA, params).measure(Query(dq, 0.0, keypoints_f32=xq), retrieval_over(5))
    np.testing.assert_array_equal(again.east_north_m, m.east_north_m)
    np.testing.assert_array_equal(again.cov_m2, m.cov_m2)


def test_a_pair_is_matched_once_for_both_its_ways_and_the_cache_keeps_the_last_pairs():
    geometry, *_ = synthetic_database([3.0, 6.0, 9.0])
    params = RefinedParams()
    match = MatchParams(tau1=params.ratio, tau2=-1.0)
    d = geometry.descriptors_u8
    cache = StructureCache(max_pairs=2)
    np.testing.assert_array_equal(cache.pairs(geometry, 0, 1, params), correspondences(d[0], d[1], match))
    np.testing.assert_array_equal(cache.pairs(geometry, 1, 0, params), correspondences(d[1], d[0], match))
    assert cache.pairs_matched == 1  # the second way came with the first
    cache.pairs(geometry, 2, 1, params)  # two more pairs kept: (0, 1) and (1, 0) are let go
    cache.pairs(geometry, 0, 1, params)
    assert cache.pairs_matched == 3


def test_views_are_taken_on_both_sides_of_the_query_when_the_database_has_both():
    geometry, geotags, xq, dq, truth = synthetic_database([-12.0, -9.0, -6.0, 6.0, 9.0, 12.0], query_east_m=0.0)
    counts = np.array([60, 70, 80, 50, 45, 40])  # the best by count are all behind the query
    retrieval = Retrieval(candidates=np.arange(6), counts=counts, best_index=2)
    params = RefinedParams(neighbour_baselines_m=(3.0,), max_neighbour_gap=2, n_views=2)
    m = pose_measurement(xq, dq, retrieval, geotags, geometry, CAMERA, params)
    assert m.source == GEOMETRY, m.fallback_reason
    east_of_views = geotags[list(m.view_indices), 0]
    assert east_of_views.min() < truth[0] < east_of_views.max()
    assert np.linalg.norm(m.east_north_m - truth) < 0.05
    # with both_sides off, the same retrieval is posed from behind only
    one_side = pose_measurement(xq, dq, retrieval, geotags, geometry, CAMERA, params.replace(both_sides=False))
    assert (geotags[list(one_side.view_indices), 0] < truth[0]).all()


def test_images_behind_the_pose_are_verified_when_the_best_candidates_all_lie_ahead():
    # a fast car: the retrieval's best candidates by count all lie ahead of the query, and verifying only the top
    # three of them leaves the images behind it, which see the same scene, unverified
    geometry, geotags, xq, dq, truth = synthetic_database([-12.0, -9.0, -6.0, 6.0, 9.0, 12.0], query_east_m=0.0)
    retrieval = Retrieval(candidates=np.arange(6), counts=np.array([10, 20, 30, 80, 70, 60]), best_index=3)
    params = RefinedParams(neighbour_baselines_m=(3.0,), max_neighbour_gap=2, n_views=2, top_k=3)
    m = pose_measurement(xq, dq, retrieval, geotags, geometry, CAMERA, params)
    assert m.source == GEOMETRY and m.side == "both", m.fallback_reason
    east_of_views = geotags[list(m.view_indices), 0]
    assert east_of_views.min() < truth[0] < east_of_views.max()
    assert np.linalg.norm(m.east_north_m - truth) < 0.05
    # the nearest behind the pose were verified, the farthest not
    assert {1, 2} <= set(m.candidate_inliers) and 0 not in m.candidate_inliers
    # without the search, the same retrieval is posed from ahead only
    ahead = pose_measurement(xq, dq, retrieval, geotags, geometry, CAMERA, params.replace(other_side_candidates=0))
    assert ahead.source == GEOMETRY and ahead.side == "one" and (geotags[list(ahead.view_indices), 0] > truth[0]).all()
    # images behind that face far from the query's heading (a turn) are not searched
    turned = synthetic_database([-12.0, -9.0, -6.0, 6.0, 9.0, 12.0], query_east_m=0.0,
                                yaw_error_rad=[0.4, 0.4, 0.4, 0.0, 0.0, 0.0])
    m = pose_measurement(turned[2], turned[3], retrieval, turned[1], turned[0], CAMERA, params)
    assert m.source == GEOMETRY and m.side == "one" and set(m.candidate_inliers) == {3, 4, 5}
    loose = pose_measurement(turned[2], turned[3], retrieval, turned[1], turned[0], CAMERA,
                             params.replace(other_side_max_turn_deg=30.0))
    assert {1, 2} <= set(loose.candidate_inliers)  # 23 degrees away: searched under a looser limit
    # a retrieval whose search area holds nothing behind the pose: one side, as before
    only_ahead = Retrieval(candidates=np.arange(3, 6), counts=np.array([80, 70, 60]), best_index=3)
    m = pose_measurement(xq, dq, only_ahead, geotags, geometry, CAMERA, params)
    assert m.source == GEOMETRY and m.side == "one" and set(m.candidate_inliers) == {3, 4, 5}


def test_views_posed_apart_and_averaged_keep_both_sides_where_their_geotags_disagree():
    # the images behind the query were geotagged 0.6 m north of where they were taken, those ahead exactly: each
    # side's structure is consistent in itself (the views' neighbours lie on their own side), the sides disagree
    east_m = [-18.0, -15.0, -12.0, -9.0, 9.0, 12.0, 15.0, 18.0]
    geometry, geotags, xq, dq, truth = synthetic_database(east_m, query_east_m=0.0, north_error_m=[0.6] * 4 + [0.0] * 4)
    retrieval = Retrieval(candidates=np.array([0, 1, 2, 5, 6, 7]), counts=np.array([50, 60, 80, 70, 55, 45]),
                          best_index=2)
    params = RefinedParams(neighbour_baselines_m=(3.0,), max_neighbour_gap=1, n_views=2)
    pooled = pose_measurement(xq, dq, retrieval, geotags, geometry, CAMERA, params.replace(fuse_views=False))
    fused = pose_measurement(xq, dq, retrieval, geotags, geometry, CAMERA, params)  # the default
    assert pooled.source == fused.source == GEOMETRY, (pooled.fallback_reason, fused.fallback_reason)
    behind = geotags[:, 0] < truth[0]
    assert set(behind[list(pooled.view_indices)].tolist()) == set(behind[list(fused.view_indices)].tolist()) == {0, 1}
    # one PnP over both sides' points keeps one side's: the other's lie pixels off its pose
    assert len(set(behind[pooled.inliers.view_of].tolist())) == 1
    # each view posed alone: both sides count, and the measurement lies between them
    assert set(behind[fused.inliers.view_of].tolist()) == {0, 1}
    assert fused.n_pnp_inliers > 1.3 * pooled.n_pnp_inliers
    assert fused.east_north_m[1] - truth[1] == pytest.approx(0.3, abs=0.05)
    # and their disagreement is in its covariance: the spread of two poses 0.6 m apart, north
    assert fused.cov_terms_m2["views"][1, 1] == pytest.approx(0.3**2, rel=0.3)
    np.testing.assert_allclose(fused.cov_m2, sum(fused.cov_terms_m2.values()))
    # the spread came from the two views' own positions; one PnP kept one side's points, one view: no spread
    assert fused.views_posed_apart == 2
    # two views' spread lies on one line and says nothing across it: stated round, at its longest axis
    views = fused.cov_terms_m2["views"]
    np.testing.assert_allclose(views + fused.cov_terms_m2["views_round"], np.linalg.eigvalsh(views).max() * np.eye(2))
    assert pooled.views_posed_apart == 1 and not pooled.cov_terms_m2["views"].any()
    # where the geotags agree, the views posed apart give back the known position
    geometry, geotags, xq, dq, truth = synthetic_database(east_m, query_east_m=0.0)
    agreed = pose_measurement(xq, dq, retrieval, geotags, geometry, CAMERA, params)
    assert agreed.source == GEOMETRY and np.linalg.norm(agreed.east_north_m - truth) < 0.05


def test_where_views_disagree_most_of_them_that_agree_make_the_measurement():
    # two views behind, their geotags extrapolated 1.6 m off, against three ahead that agree (drive 0027's start)
    positions = {23: np.array([0.0, 0.0]), 0: np.array([-1.6, 0.1]), 24: np.array([0.2, 0.1]),
                 2: np.array([-1.5, 0.0]), 25: np.array([0.1, -0.2])}
    assert agreeing_majority(positions, 1.5) == [23, 24, 25]
    # no majority (two against two), or two sets of the same size: no measurement
    assert agreeing_majority({k: positions[k] for k in (23, 0, 24, 2)}, 1.5) == []
    assert agreeing_majority({1: np.array([0.0, 0.0]), 2: np.array([1.0, 0.0]), 3: np.array([2.0, 0.0])}, 1.5) == []
    assert agreeing_majority({1: np.array([0.0, 0.0]), 2: np.array([3.0, 0.0])}, 1.5) == []


def whole_lever(m, gain):
    """The lever term a measurement carries: (gain * lever)^2 per axis, whole, also for views posed apart (the gain
    is measured on means of views posed apart, so it is what they share beyond their spread)."""
    return (gain * m.lever_m) ** 2 * np.eye(2)


def test_the_covariance_is_relative_to_the_map_and_grows_with_the_lever_to_the_nearest_view():
    params = RefinedParams(neighbour_baselines_m=(2.0, 5.0), max_neighbour_gap=2, n_views=2)
    gain = LeverGain(both_sides=0.01, one_side=0.03)
    near = synthetic_database([3.0, 6.0, 9.0, 12.0, 15.0], query_east_m=2.0, geotag_sigma_m=0.3, lever_gain=gain)
    far = synthetic_database([3.0, 6.0, 9.0, 12.0, 15.0], query_east_m=-6.0, geotag_sigma_m=0.3, lever_gain=gain)
    m_near = pose_measurement(near[2], near[3], retrieval_over(5), near[1], near[0], CAMERA, params)
    m_far = pose_measurement(far[2], far[3], retrieval_over(5), far[1], far[0], CAMERA, params)
    assert m_near.source == m_far.source == GEOMETRY
    for m, truth in ((m_near, near[4]), (m_far, far[4])):
        # the parts, each named, add up to the covariance the filter takes
        np.testing.assert_allclose(m.cov_m2, sum(m.cov_terms_m2.values()))
        # (and on its two views, what their spread could not see across the line they lie on)
        assert set(m.cov_terms_m2) == {"pnp", "views", "lever", "geotags", "views_round"}
        assert not m.cov_terms_m2["geotags"].any()  # every geotag states its accuracy
        # every view lies ahead of these queries: one side, the lever to the nearest view's geotag
        assert m.side == "one"
        assert m.lever_m == pytest.approx(np.linalg.norm(near[1][list(m.view_indices)] - m.east_north_m, axis=1).min())
        np.testing.assert_allclose(m.cov_terms_m2["lever"], whole_lever(m, 0.03))
        # the geotags' stated accuracy is the map's own error: stated apart, not in the relative covariance
        assert m.absolute_sigma_m == pytest.approx(0.3)
        assert m.sigma_m < 0.3
    # the farther from its nearest view, the larger the lever and the covariance
    assert m_far.lever_m > m_near.lever_m + 5.0 and m_far.sigma_m > m_near.sigma_m
    # a database without a self-check takes the default gain; a geotag without a stated accuracy states
    # geotag_sigma_m as its absolute error
    unstated = replace(near[0], geotag_sigma_m=None, lever_gain=None)
    m = pose_measurement(near[2], near[3], retrieval_over(5), near[1], unstated, CAMERA, params.replace(geotag_sigma_m=2.0))
    np.testing.assert_allclose(m.cov_terms_m2["lever"], whole_lever(m, DEFAULT_LEVER_GAIN.one_side))
    assert m.absolute_sigma_m == pytest.approx(2.0)


def test_views_on_both_sides_use_the_both_sides_gain():
    geometry, geotags, xq, dq, truth = synthetic_database([-12.0, -9.0, -6.0, 6.0, 9.0, 12.0], query_east_m=0.0,
                                                          lever_gain=LeverGain(both_sides=0.01, one_side=0.05))
    counts = np.array([60, 70, 80, 50, 45, 40])
    retrieval = Retrieval(candidates=np.arange(6), counts=counts, best_index=2)
    m = pose_measurement(xq, dq, retrieval, geotags, geometry, CAMERA,
                         RefinedParams(neighbour_baselines_m=(3.0,), max_neighbour_gap=2, n_views=2))
    assert m.side == "both"
    np.testing.assert_allclose(m.cov_terms_m2["lever"], whole_lever(m, 0.01))
    assert m.lever_m == pytest.approx(np.linalg.norm(geotags[list(m.view_indices)] - m.east_north_m, axis=1).min())


def test_views_whose_geotags_are_no_fix_carry_their_error_in_the_covariance():
    """The first images' geotags were filled in (no position solution: no stated accuracy, 0.8 m off), the rest are
    fixes stated at 1 cm. Posed on the filled-in ones, the measurement is 0.8 m off: its covariance says so, where
    it claimed centimetres when every geotag was taken at its word."""
    east_m = [3.0, 6.0, 9.0, 12.0, 15.0, 18.0, 21.0, 24.0]
    geometry, geotags, xq, dq, truth = synthetic_database(east_m, north_error_m=[0.8] * 5 + [0.0] * 3,
                                                          lever_gain=LeverGain(0.0, 0.0))
    retrieval = Retrieval(candidates=np.arange(8), counts=np.array([60, 70, 80, 50, 45, 20, 20, 20]), best_index=2)
    params = RefinedParams(neighbour_baselines_m=(3.0,), max_neighbour_gap=1, n_views=2)
    filled = replace(geometry, geotag_sigma_m=np.array([np.nan] * 5 + [0.01] * 3))
    taken = pose_measurement(xq, dq, retrieval, geotags, geometry, CAMERA, params)
    said = pose_measurement(xq, dq, retrieval, geotags, filled, CAMERA, params)
    assert taken.source == said.source == GEOMETRY, (taken.fallback_reason, said.fallback_reason)
    np.testing.assert_allclose(said.east_north_m, taken.east_north_m)  # the same pose, another covariance
    assert {*said.view_indices, *said.neighbour_indices} <= set(range(5))
    np.testing.assert_allclose(said.cov_terms_m2["geotags"], params.geotag_sigma_m ** 2 * np.eye(2))
    np.testing.assert_allclose(said.cov_m2, sum(said.cov_terms_m2.values()))
    error = said.east_north_m - truth
    assert np.linalg.norm(error) > 0.6
    assert error @ np.linalg.solve(taken.cov_m2, error) > 100  # overconfident
    assert error @ np.linalg.solve(said.cov_m2, error) < 5.99  # inside its 95 % ellipse
    # a database that states no accuracy anywhere: its geotags are all alike, nothing is added
    alike = replace(geometry, geotag_sigma_m=np.full(8, np.nan))
    assert not pose_measurement(xq, dq, retrieval, geotags, alike, CAMERA, params).cov_terms_m2["geotags"].any()


def test_refined_database_poses_straighten_a_structure_built_on_wrong_headings():
    """Recorded yaws off by up to 0.8 degrees (as an INS in a turn): posing from the structure as
    recorded misplaces the query; the bundle adjustment finds the true headings from the images."""
    errors = np.radians([0.8, -0.5, 0.6, -0.7, 0.4, -0.6])
    args = dict(query_east_m=-4.0, noise_px=0.3, lever_gain=LeverGain(0.0, 0.0), yaw_error_rad=errors)
    geometry, geotags, xq, dq, truth = synthetic_database([3.0, 6.0, 9.0, 12.0, 15.0, 18.0], **args)
    params = RefinedParams(neighbour_baselines_m=(3.0, 6.0), max_neighbour_gap=3, n_views=2)
    refined = pose_measurement(xq, dq, retrieval_over(6), geotags, geometry, CAMERA, params)
    as_recorded = pose_measurement(xq, dq, retrieval_over(6), geotags, geometry, CAMERA,
                                   params.replace(refine_poses=False))
    assert refined.source == GEOMETRY, refined.fallback_reason
    error_refined = np.linalg.norm(refined.east_north_m - truth)
    error_recorded = np.inf if as_recorded.source != GEOMETRY else np.linalg.norm(as_recorded.east_north_m - truth)
    # what is left is the compromise with the priors: a 5 cm position prior over 3 m baselines lets the
    # track turn by about a degree, as far as the attitude prior lets the headings stay
    assert error_refined < 0.2 and error_recorded > 3 * error_refined, (error_refined, error_recorded)
    # a structure on poses that were right all along stays where it is
    right = synthetic_database([3.0, 6.0, 9.0, 12.0, 15.0, 18.0], query_east_m=-4.0, lever_gain=LeverGain(0.0, 0.0))
    m = pose_measurement(right[2], right[3], retrieval_over(6), right[1], right[0], CAMERA, params)
    assert np.linalg.norm(m.east_north_m - right[4]) < 0.03


def test_a_stopped_car_has_no_baseline_and_falls_back_to_the_geotag():
    geometry, geotags, xq, dq, _ = synthetic_database([5.0, 5.0, 5.0, 5.0, 5.0])
    m = pose_measurement(xq, dq, retrieval_over(5), geotags, geometry, CAMERA, RefinedParams(neighbour_baselines_m=(2.0, 5.0), max_neighbour_gap=2))
    assert m.source == GEOTAG and m.cov_m2 is None
    assert "car stopped" in m.fallback_reason
    np.testing.assert_array_equal(m.east_north_m, geotags[2])


def test_too_few_points_fall_back_with_the_reason():
    geometry, geotags, xq, dq, _ = synthetic_database([3.0, 6.0, 9.0], n_points=40)
    m = pose_measurement(xq, dq, retrieval_over(3), geotags, geometry, CAMERA,
                         RefinedParams(max_neighbour_gap=1, min_verified_inliers=60))
    assert m.source == GEOTAG and m.fallback_reason.startswith("verification: best candidate has")


def test_thin_support_is_posed_again_looser_and_says_so():
    # few points seen with 2 px of noise: at 2 px no pose keeps 15 inliers, at 4 px one keeps 10 or more
    geometry, geotags, xq, dq, truth = synthetic_database([3.0, 6.0, 9.0, 12.0, 15.0], n_points=30, noise_px=2.0)
    params = RefinedParams(neighbour_baselines_m=(2.0, 5.0), max_neighbour_gap=2, n_views=2, triangulation_px=5.0,
                           min_verified_inliers=8, essential_px=3.0)
    strict = pose_measurement(xq, dq, retrieval_over(5), geotags, geometry, CAMERA,
                              params.replace(thin_support_pnp_px=0.0))
    assert strict.source == GEOTAG and strict.fallback_reason.startswith("PnP RANSAC"), strict.fallback_reason
    m = pose_measurement(xq, dq, retrieval_over(5), geotags, geometry, CAMERA, params)
    assert m.source == GEOMETRY and m.thin_support, m.fallback_reason
    assert params.thin_support_min_inliers <= m.n_pnp_inliers
    error = m.east_north_m - truth
    assert np.linalg.norm(error) < 0.5
    assert error @ np.linalg.solve(m.cov_m2, error) < 13.82  # its looser pose says so: inside its 99.9 % ellipse
    # a store's self-check poses at the strict threshold only, so what it stored stays valid
    assert self_check_params(params).thin_support_pnp_px == 0.0


@pytest.mark.parametrize("what,reason", [
    ("keypoints", "query keypoints not given"),
    ("excluded_neighbours", "car stopped"),
])
def test_a_query_without_what_a_pose_needs_falls_back_with_the_reason(what, reason):
    geometry, geotags, xq, dq, _ = synthetic_database([3.0, 6.0, 9.0])
    retrieval = retrieval_over(3)
    if what == "keypoints":
        xq = None
    elif what == "excluded_neighbours":  # the retrieval allows only the view itself: no neighbour to triangulate with
        retrieval = Retrieval(candidates=np.array([1]), counts=np.array([80]), best_index=1)
    m = pose_measurement(xq, dq, retrieval, geotags, geometry, CAMERA, RefinedParams(max_neighbour_gap=1))
    assert m.source == GEOTAG and reason in m.fallback_reason
    np.testing.assert_array_equal(m.east_north_m, geotags[retrieval.best_index])


def test_the_pose_measurer_is_refused_without_calibrated_cameras():
    geometry, geotags, _, _, _ = synthetic_database([3.0, 6.0, 9.0])
    with pytest.raises(InputError, match="calibrated query camera: q/camera has no intrinsics"):
        PoseMeasurer(geotags, geometry, None, RefinedParams(), query_what="q/camera")
    uncalibrated = DatabaseGeometry(geometry.T_world_camera, geometry.keypoints_xy_px, geometry.descriptors_u8, None,
                                    "database x: no intrinsics (P_rect) in the store")
    with pytest.raises(InputError, match="calibrated database: database x: no intrinsics"):
        PoseMeasurer(geotags, uncalibrated, CAMERA, RefinedParams())


def test_no_match_gives_no_measurement_in_either_method():
    geometry, geotags, xq, dq, _ = synthetic_database([3.0, 6.0, 9.0])
    none = Retrieval(candidates=np.arange(3), counts=np.zeros(3, np.int64), best_index=None)
    for m in (geotag_measurement(none, geotags), pose_measurement(xq, dq, none, geotags, geometry, CAMERA)):
        assert m.source is None and m.east_north_m is None


def test_filter_measurements_uses_each_measurements_own_covariance():
    geometry, geotags, xq, dq, truth = synthetic_database([3.0, 6.0, 9.0, 12.0, 15.0])
    params = RefinedParams(neighbour_baselines_m=(2.0, 5.0), max_neighbour_gap=2)
    geo = pose_measurement(xq, dq, retrieval_over(5), geotags, geometry, CAMERA, params)
    paper = geotag_measurement(retrieval_over(5), geotags)
    fp = FilterParams()
    steps = filter_measurements([paper, geo], fp)
    expected = run_filter([paper.east_north_m, geo.east_north_m], fp, covariances_m2=[None, geo.cov_m2])
    np.testing.assert_allclose(steps[1].x, expected[1].x)
    np.testing.assert_allclose(steps[1].R, geo.cov_m2)
    np.testing.assert_allclose(steps[0].R, fp.meas_var_m2 * np.eye(2))
    # a centimetre-accurate measurement pulls the estimate onto itself
    assert np.linalg.norm(steps[1].x[:2] - geo.east_north_m) < 0.01


def test_neighbours_are_chosen_by_distance_so_a_stopped_car_finds_its_baseline_where_it_last_moved():
    from visloc.pose.refined import neighbours_of

    east = [0.0, 1.0, 2.0, 3.0, 4.0] + [5.0] * 20 + [6.0, 7.0, 8.0]  # stands still for 2 s at 5 m
    T = np.array([camera_pose(e)[0] for e in east])
    view = 15  # in the middle of the stop
    params = RefinedParams(neighbour_baselines_m=(2.0, 3.0), min_baseline_m=1.0, max_neighbour_gap=15)
    found = neighbours_of(view, np.arange(len(east)), T, params)
    baselines = sorted(abs(east[j] - east[view]) for j in found)
    assert found and min(baselines) >= 1.0  # none from the stop itself
    assert {east[j] for j in found} == {3.0, 2.0, 7.0, 8.0}
    # within the stop only (gap too small to leave it): no neighbour, the measurement falls back
    assert neighbours_of(view, np.arange(len(east)), T, params.replace(max_neighbour_gap=5)) == []
    # images the retrieval does not allow are never neighbours
    assert not set(neighbours_of(view, np.arange(20), T, params)) & set(range(20, len(east)))


def test_structure_settings_name_the_cap_on_adjusted_points_only_where_it_is_set():
    """A store built before the cap existed holds structure made on every point: the default (0) writes the
    settings as they were written then, so that structure stays valid; a cap is named, and made anew."""
    import json

    from visloc.pose.structure import STRUCTURE_SETTINGS, structure_settings_json

    default = json.loads(structure_settings_json(RefinedParams()))
    assert set(default) == set(STRUCTURE_SETTINGS) - {"max_adjusted_points"}
    capped = json.loads(structure_settings_json(RefinedParams(max_adjusted_points=400)))
    assert capped == {**default, "max_adjusted_points": 400}
