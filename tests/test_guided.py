"""Guided matching (visloc.pose.guided): a pose's 3D points projected into the query, matched near where they land."""

import numpy as np

from visloc.pose.guided import guided_matches, project_points

K = np.array([[700.0, 0, 600], [0, 700.0, 180], [0, 0, 1]])


def _scene(rng, n=200):
    points = np.c_[rng.uniform(-10, 10, n), rng.uniform(-3, 3, n), rng.uniform(5, 40, n)]
    descriptors = rng.integers(0, 120, (n, 128)).astype(np.float32)
    return points, descriptors


def test_projection_matches_a_pinhole_and_marks_points_behind_the_camera():
    T = np.eye(4)
    T[:3, 3] = [1.0, 0.0, -2.0]  # camera 2 m behind the origin, looking along +z
    uv, front = project_points(np.array([[1.0, 0.0, 8.0], [0.0, 0.0, -5.0]]), T, K)
    assert np.allclose(uv[0], [600, 180])
    assert front.tolist() == [True, False]


def test_every_point_finds_its_own_keypoint_among_distractors():
    rng = np.random.default_rng(0)
    points, point_desc = _scene(rng)
    uv, front = project_points(points, np.eye(4), K)
    # the query: each point's keypoint 1 px off with a slightly changed descriptor, plus far-off distractors
    query_xy = np.r_[uv + rng.normal(0, 0.7, uv.shape), rng.uniform(0, 1200, (300, 2))]
    query_desc = np.r_[point_desc + rng.normal(0, 3, point_desc.shape), rng.integers(0, 120, (300, 128))]
    pairs = guided_matches(uv, front, point_desc, query_xy, query_desc, radius_px=4.0, ratio=0.9, max_distance=1e9)
    assert len(pairs) >= 195
    assert np.array_equal(pairs[:, 0], pairs[:, 1])  # point k matched query row k, never a distractor
    assert len(np.unique(pairs[:, 1])) == len(pairs)


def test_ambiguous_far_and_behind_points_are_not_matched():
    rng = np.random.default_rng(1)
    points, point_desc = _scene(rng, 3)
    uv, front = project_points(points, np.eye(4), K)
    query_xy = np.r_[uv[:1], uv[:1] + [1.5, 0], uv[1:2] + [10, 0], uv[2:3]]
    query_desc = np.r_[point_desc[:1] + 1, point_desc[:1] + 1.05, point_desc[1:2], point_desc[2:3] + 50]
    found = guided_matches(uv, front, point_desc, query_xy, query_desc, radius_px=4.0, ratio=0.9, max_distance=100.0)
    # point 0: two near-equal candidates (ratio); point 1: its keypoint 10 px off; point 2: too far in descriptor
    assert len(found) == 0
    behind = front.copy()
    behind[:] = False
    assert len(guided_matches(uv, behind, point_desc, query_xy, query_desc, radius_px=4.0, ratio=0.9,
                              max_distance=1e9)) == 0
