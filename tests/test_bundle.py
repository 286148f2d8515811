"""Bundle adjustment of posed database cameras with priors on their poses (visloc.geometry.bundle)."""

from types import SimpleNamespace

import numpy as np
import pytest

from visloc.geometry.bundle import PosePriors, bundle_adjust, refine_database_poses, rotation_exp, rotation_log
from visloc.geometry.multiview import triangulate_tracks
from visloc.geometry.projective import project, rotation_from_rpy
from visloc.params import REFINED
from visloc.pose.refined import refined_poses

K = np.array([[721.5, 0.0, 609.6], [0.0, 721.5, 172.9], [0.0, 0.0, 1.0]])
R_IMU_CAMERA = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # camera z forward = imu x


def camera_pose(east_m, yaw_rad=0.0):
    """World <- camera of a camera 1.5 m up, looking along a car heading ``yaw_rad`` from east."""
    T = np.eye(4)
    T[:3, :3] = rotation_from_rpy(0.0, 0.0, yaw_rad) @ R_IMU_CAMERA
    T[:3, 3] = [east_m, 0.0, 1.5]
    return T


def street(n_points, seed):
    rng = np.random.default_rng(seed)
    side = rng.choice([-1.0, 1.0], n_points)
    return np.stack([rng.uniform(5.0, 60.0, n_points), side * rng.uniform(4.0, 9.0, n_points),
                     rng.uniform(-1.0, 6.0, n_points)], axis=1)


def observe(points, T, noise_px, rng):
    uv, depth = project(K, T, points)
    visible = (depth > 1.0) & (uv[:, 0] >= 0) & (uv[:, 0] < 1242) & (uv[:, 1] >= 0) & (uv[:, 1] < 375)
    return uv + rng.normal(scale=noise_px, size=uv.shape), visible


def test_rotation_vectors_round_trip():
    rng = np.random.default_rng(0)
    w = rng.normal(scale=0.5, size=(50, 3))
    np.testing.assert_allclose(rotation_log(rotation_exp(w)), w, atol=1e-10)
    R = rotation_exp(w)
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    np.testing.assert_allclose(rotation_log(np.eye(3)), np.zeros(3), atol=1e-15)


def _scene(yaw_errors_deg, noise_px=0.3, seed=5, sideways_m=0.0):
    """Cameras 2 m apart heading east with recorded yaws off by ``yaw_errors_deg`` and recorded positions off
    sideways by ``sideways_m`` (a jittery GPS); each point observed by every camera that sees it."""
    rng = np.random.default_rng(seed)
    points = street(n_points=800, seed=seed)
    east = 2.0 * np.arange(len(yaw_errors_deg))
    true = np.array([camera_pose(e) for e in east])
    recorded = np.array([camera_pose(e, yaw_rad=np.radians(d)) for e, d in zip(east, yaw_errors_deg)])
    recorded[:, 1, 3] += sideways_m
    xy = np.full((len(points), len(east), 2), np.nan)
    for c, T in enumerate(true):
        uv, visible = observe(points, T, noise_px, rng)
        xy[visible, c] = uv[visible]
    keep = np.sum(np.isfinite(xy[..., 0]), axis=1) >= 2
    return true, recorded, xy[keep]


def _yaw_error_deg(T_estimated, T_true):
    return np.degrees(np.linalg.norm(rotation_log(T_estimated[:, :3, :3] @ np.swapaxes(T_true[:, :3, :3], 1, 2)),
                                     axis=1))


def test_the_images_correct_headings_the_prior_holds_loosely():
    errors = [0.3, 0.4, 0.5, 0.6, 0.5, 0.4, 0.3]  # an INS heading off by a few tenths, drifting
    true, recorded, xy = _scene(errors)
    used = np.all(np.isfinite(xy), axis=2)
    priors = PosePriors(sigma_pos_m=np.full(len(true), 0.02), sigma_up_m=0.05, sigma_rot_rad=np.radians(2.0))
    result = refine_database_poses(K, recorded, xy, used, priors)
    assert result is not None and result.iterations >= 1
    before, after = _yaw_error_deg(recorded, true), _yaw_error_deg(result.T_world_camera, true)
    assert before.max() > 0.5 and after.max() < 0.05, after
    # what the images disagreed with the recorded attitudes by, in the priors' units
    assert result.prior_chi2 > 0 and np.degrees(result.turned_rad).max() > 0.4
    np.testing.assert_allclose(result.moved_m, np.linalg.norm(result.T_world_camera[:, :3, 3] - recorded[:, :3, 3],
                                                               axis=1))


def test_right_poses_stay_put_and_a_tight_prior_wins_over_the_images():
    true, recorded, xy = _scene([0.0] * 6)
    used = np.all(np.isfinite(xy), axis=2)
    priors = PosePriors(sigma_pos_m=np.full(len(true), 0.05), sigma_up_m=0.1, sigma_rot_rad=np.radians(1.0))
    result = refine_database_poses(K, recorded, xy, used, priors)
    assert _yaw_error_deg(result.T_world_camera, true).max() < 0.05 and result.moved_m.max() < 0.01
    # recorded poses off by half a degree, with a prior far tighter than that: they barely move
    _, wrong, xy2 = _scene([0.5] * 6)
    tight = PosePriors(sigma_pos_m=np.full(6, 1e-4), sigma_up_m=1e-4, sigma_rot_rad=np.radians(1e-3))
    held = refine_database_poses(K, wrong, xy2, np.all(np.isfinite(xy2), axis=2), tight)
    assert np.degrees(held.turned_rad).max() < 0.01


def test_too_few_points_to_start_an_adjustment():
    true, recorded, xy = _scene([0.0] * 3)
    used = np.all(np.isfinite(xy), axis=2)
    priors = PosePriors(sigma_pos_m=np.full(3, 0.05), sigma_up_m=0.1, sigma_rot_rad=0.01)
    assert refine_database_poses(K, recorded, xy[:10], used[:10], priors) is None
    # points without two observations are left out of the adjustment and come back NaN
    X = np.full((len(xy), 3), np.nan)
    result = bundle_adjust(K, recorded, X, xy, used, priors)
    assert np.isnan(result.points_world).all() and result.moved_m.max() == pytest.approx(0.0)


def test_a_few_hundred_of_the_most_seen_points_find_the_headings_as_every_point_does():
    true, recorded, xy = _scene([0.3, 0.4, 0.5, 0.6, 0.5, 0.4, 0.3])
    used = np.all(np.isfinite(xy), axis=2)
    priors = PosePriors(sigma_pos_m=np.full(len(true), 0.02), sigma_up_m=0.05, sigma_rot_rad=np.radians(2.0))
    every = refine_database_poses(K, recorded, xy, used, priors)
    capped = refine_database_poses(K, recorded, xy, used, priors, max_points=100)
    adjusted = np.all(np.isfinite(capped.points_world), axis=1)
    assert adjusted.sum() == 100 and np.all(np.isfinite(every.points_world), axis=1).sum() > 300
    # the adjusted points are those most cameras see
    assert used[adjusted].sum(axis=1).min() >= used[~adjusted].sum(axis=1).max() - 1
    assert _yaw_error_deg(capped.T_world_camera, true).max() < 0.05
    np.testing.assert_allclose(capped.T_world_camera[:, :3, 3], every.T_world_camera[:, :3, 3], atol=0.01)


def test_where_the_most_seen_points_start_too_few_every_point_is_tried():
    true, recorded, xy = _scene([0.3, 0.4, 0.5, 0.6, 0.5, 0.4, 0.3])
    used = np.all(np.isfinite(xy), axis=2)
    # the 40 points seen most often are mismatched (each observation 60-120 px off): none starts it
    most = np.lexsort((np.arange(len(used)), -used.sum(axis=1)))[:40]
    rng = np.random.default_rng(3)
    xy = xy.copy()
    xy[most] += rng.choice([-1.0, 1.0], xy[most].shape) * rng.uniform(60.0, 120.0, xy[most].shape)
    assert triangulate_tracks(K, recorded, xy[most], max_reprojection_px=4.0, min_parallax_deg=0.3).keep.sum() < 20
    priors = PosePriors(sigma_pos_m=np.full(len(true), 0.02), sigma_up_m=0.05, sigma_rot_rad=np.radians(2.0))
    capped = refine_database_poses(K, recorded, xy, used, priors, max_points=20)
    assert capped is not None and np.all(np.isfinite(capped.points_world), axis=1).sum() == 20
    assert _yaw_error_deg(capped.T_world_camera, true).max() < 0.1


@pytest.mark.parametrize("relative_geotag_sigma_m", [0.05, 0.005])
def test_the_images_not_the_prior_shape_a_jittery_track(relative_geotag_sigma_m):
    """Geotags off sideways by up to 0.2 m from one image to the next: the structure's poses follow the
    images, whatever the position prior, because a prior the images move the poses well beyond is loosened
    to what they moved (held at 5 mm, the poses would stay 0.14 m off)."""
    true, recorded, xy = _scene([0.0] * 6, seed=7, sideways_m=np.array([0.0, 0.2, -0.15, 0.175, -0.2, 0.15]))
    geometry = SimpleNamespace(camera=SimpleNamespace(K=K), heading_spread_rad=None)

    def sideways_error_m(T):  # each camera's sideways offset from the first, against the truth's
        return np.abs((T[:, 1, 3] - T[0, 1, 3]) - (true[:, 1, 3] - true[0, 1, 3])).max()

    refined = refined_poses(geometry, recorded, xy, REFINED.replace(relative_geotag_sigma_m=relative_geotag_sigma_m))
    assert sideways_error_m(recorded) > 0.15 and sideways_error_m(refined) < 0.03, sideways_error_m(refined)
