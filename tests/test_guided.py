"""Guided matching (visloc.pose.guided): a pose's 3D points projected into the query, matched near where they land."""

import numpy as np

from visloc.pose.guided import QueryKeypoints, guided_matches, project_points

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
    pairs, _ = guided_matches(uv, front, point_desc, QueryKeypoints(query_xy, query_desc), radius_px=4.0, ratio=0.9,
                              max_distance=1e9)
    assert len(pairs) >= 195
    assert np.array_equal(pairs[:, 0], pairs[:, 1])  # point k matched query row k, never a distractor
    assert len(np.unique(pairs[:, 1])) == len(pairs)


def test_ambiguous_far_and_behind_points_are_not_matched():
    rng = np.random.default_rng(1)
    points, point_desc = _scene(rng, 3)
    uv, front = project_points(points, np.eye(4), K)
    query_xy = np.r_[uv[:1], uv[:1] + [1.5, 0], uv[1:2] + [10, 0], uv[2:3]]
    query_desc = np.r_[point_desc[:1] + 1, point_desc[:1] + 1.05, point_desc[1:2], point_desc[2:3] + 50]
    query = QueryKeypoints(query_xy, query_desc)
    found, _ = guided_matches(uv, front, point_desc, query, radius_px=4.0, ratio=0.9, max_distance=100.0)
    # point 0: two near-equal candidates (ratio); point 1: its keypoint 10 px off; point 2: too far in descriptor
    assert len(found) == 0
    behind = front.copy()
    behind[:] = False
    assert len(guided_matches(uv, behind, point_desc, query, radius_px=4.0, ratio=0.9, max_distance=1e9)[0]) == 0


def _rule_point_by_point(uv, usable, point_desc, query_xy, query_desc, radius_px, ratio, max_distance):
    """guided_matches' rule written out one point at a time: (point row, query row, distance) of every match."""
    best = {}  # query row -> (distance, point row)
    for point in range(len(uv)):
        if not (usable[point] and np.all(np.isfinite(uv[point]))):
            continue
        candidates = np.flatnonzero(((query_xy - uv[point]) ** 2).sum(axis=1) <= radius_px**2)
        if not len(candidates):
            continue
        d = np.linalg.norm(query_desc[candidates].astype(np.float32) - point_desc[point].astype(np.float32), axis=1)
        order = np.argsort(d, kind="stable")  # of equal distances, the first query row
        d1 = float(d[order[0]])
        if d1 > max_distance or (len(order) > 1 and not d1 < ratio * float(d[order[1]])):
            continue
        q = int(candidates[order[0]])
        if q not in best or d1 < best[q][0]:  # of equal claims, the first point row
            best[q] = (d1, point)
    return sorted((point, q, d) for q, (d, point) in best.items())


def test_matching_all_points_at_once_takes_what_the_rule_takes_point_by_point_ties_included():
    """Random scenes where ties are common (descriptors of a few levels, keypoints stacked on the same pixel,
    points sharing a descriptor): the vectorised matching returns exactly the rule's pairs and distances, and
    breaks ties as it says (the first query row, the first point row)."""
    for seed in range(12):
        rng = np.random.default_rng(seed)
        n_points, n_query = int(rng.integers(1, 80)), int(rng.integers(1, 120))
        uv = np.c_[rng.uniform(0, 200, n_points), rng.uniform(0, 60, n_points)]
        uv[rng.random(n_points) < 0.05] = np.nan  # a few project nowhere
        usable = rng.random(n_points) < 0.9
        query_xy = np.c_[rng.uniform(0, 200, n_query), rng.uniform(0, 60, n_query)]
        stacked = rng.random(n_query) < 0.3
        query_xy[stacked] = query_xy[rng.integers(0, n_query, stacked.sum())]  # several keypoints on one pixel
        levels = int(rng.integers(2, 5))
        query_desc = rng.integers(0, levels, (n_query, 128)).astype(np.uint8) * 40
        point_desc = rng.integers(0, levels, (n_points, 128)).astype(np.uint8) * 40
        point_desc[rng.random(n_points) < 0.3] = point_desc[0]  # points sharing a descriptor claim alike
        for radius_px, ratio, max_distance in ((6.0, 0.8, np.inf), (15.0, 1.0, 500.0), (30.0, 0.9, 300.0)):
            pairs, distances = guided_matches(uv, usable, point_desc, QueryKeypoints(query_xy, query_desc),
                                              radius_px=radius_px, ratio=ratio, max_distance=max_distance)
            expected = _rule_point_by_point(uv, usable, point_desc, query_xy, query_desc, radius_px, ratio,
                                            max_distance)
            got = [(int(p), int(q), float(d)) for (p, q), d in zip(pairs, distances)]
            assert got == expected, (seed, radius_px)


def test_pairs_ordered_by_one_key_as_by_three_and_distances_exact():
    """The pairs' order (point, distance, query row) from one 64-bit key is lexsort's, ties included, and so is
    it where the indices are too large for one key; the distances are numpy's float32 norms to the bit."""
    from visloc.pose.guided import _by_point_distance_query, _pair_distances

    rng = np.random.default_rng(3)
    for p_max, q_max in ((50, 40), (3000, 9000), (2**31, 2**31)):  # the last: no room in 64 bits
        pi = rng.integers(0, p_max, 2000)
        qi = rng.permutation(np.arange(2000) * (q_max // 2000 + 1))  # unique, as pairs are
        dist = (rng.integers(0, 5, 2000) * 40).astype(np.float32)  # many equal distances
        assert np.array_equal(_by_point_distance_query(pi, dist, qi), np.lexsort((qi, dist, pi)))
    a = rng.integers(0, 256, (300, 128)).astype(np.float32)
    b = rng.integers(0, 256, (200, 128)).astype(np.float32)
    ia, ib = rng.integers(0, 300, 5000), rng.integers(0, 200, 5000)
    assert np.array_equal(_pair_distances(a, b, ia, ib), np.linalg.norm(a[ia] - b[ib], axis=1))
