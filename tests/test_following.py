"""Following map points between full localizations, its pure parts: image tracks flowed once, the same map points
linked across the database's views, and the exclusion window over a track's views."""

from __future__ import annotations

from types import SimpleNamespace

import cv2
import numpy as np

from visloc.pose.flowtrack import TrackedPoints, follow, linked, merged
from visloc.pose.measurement import Measurement
from visloc.pose.structure import ViewStructure
from visloc.tracking.viewwindow import ViewWindow


def _points(pixels, tracks, views, rows, xyz, neighbours=None, T=None) -> TrackedPoints:
    n = len(tracks)
    return TrackedPoints(np.asarray(pixels, np.float32).reshape(n, 2), np.asarray(tracks, np.int64),
                         np.asarray(views, np.int64), np.asarray(rows, np.int64), np.asarray(xyz, float).reshape(n, 3),
                         np.tile(np.eye(3) * 1e-4, (n, 1, 1)), dict(neighbours or {}),
                         np.eye(4) if T is None else T, np.zeros(2))


def _descriptor(seed: int) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 60, 128).astype(np.uint8)


def test_a_followed_point_is_linked_to_the_same_map_point_of_another_view_and_to_nothing_else():
    """Camera at the origin looking down +z. Track 0 has its point 0.2 m from a point of view 1 with the same
    descriptor: linked. Track 1 has one nearby with a descriptor far from its own: not linked. Track 2 has two
    nearby whose descriptors are about as near as each other: ambiguous, not linked. Track 3's nearest point of
    view 1 lies farther than the radius (6 % of 20 m): not linked."""
    own = np.stack([_descriptor(k) for k in range(4)])
    ambiguous = own[2].astype(int)
    other = np.stack([own[0], _descriptor(99), np.clip(ambiguous + 3, 0, 255), np.clip(ambiguous - 3, 0, 255),
                      own[3]]).astype(np.uint8)
    xyz = np.array([[0.0, 0.0, 20.0], [5.0, 0.0, 20.0], [-5.0, 0.0, 20.0], [0.0, 4.0, 20.0]])
    points = _points([[600, 180], [800, 180], [400, 180], [600, 320]], [0, 1, 2, 3], [0] * 4, range(4), xyz,
                     neighbours={0: (5,)})
    view = (np.array([10, 11, 12, 13, 14]),
            np.array([[0.2, 0.0, 20.0], [5.1, 0.0, 20.0], [-5.0, 0.1, 20.0], [-5.0, -0.1, 20.0], [0.0, 4.0, 22.0]]),
            np.tile(np.eye(3) * 1e-4, (5, 1, 1)))
    db_descriptors = {0: own, 1: np.concatenate([np.zeros((10, 128), np.uint8), other])}
    out = linked(points, {1: view}, db_descriptors, neighbours={1: (2, 3)})
    assert len(out) == 5
    new = out.subset(np.arange(4, 5))
    assert new.track_of.tolist() == [0] and new.view_of.tolist() == [1] and new.view_rows.tolist() == [10]
    np.testing.assert_allclose(new.pixels_px, [[600, 180]])  # the same image track: its pixel, not the view's
    np.testing.assert_allclose(new.points_world, [[0.2, 0.0, 20.0]])  # the view's own point
    assert out.neighbours == {0: (5,), 1: (2, 3)}
    # linked again: the track already has its point in view 1, and the others still fail
    assert len(linked(out, {1: view}, db_descriptors, neighbours={1: (2, 3)})) == 5


def test_a_view_point_claimed_by_two_tracks_goes_to_the_nearer_descriptor():
    own = np.stack([_descriptor(1), _descriptor(1)]).astype(int)
    own[1] = np.clip(own[1] + 20, 0, 255)
    points = _points([[500, 100], [510, 100]], [7, 8], [0, 0], [0, 1], [[0, 0, 20.0], [0.1, 0, 20.0]])
    view = (np.array([3]), np.array([[0.05, 0.0, 20.0]]), np.eye(3)[None] * 1e-4)
    out = linked(points, {2: view}, {0: own.astype(np.uint8), 2: np.stack([_descriptor(9)] * 3 + [_descriptor(1)])})
    assert out.subset(np.arange(2, len(out))).track_of.tolist() == [7]


def test_points_of_one_image_track_are_flowed_once_and_keep_one_pixel(kitti_root):
    """A real frame moved 3 px right and 2 px up: every track's points (the same keypoint in two views' structure)
    end on one pixel, where the image moved."""
    from helpers import DRIVE_0005
    from visloc.sources.drives import load_gray
    from visloc.sources.opening import open_source

    seq = open_source(kitti_root, drive=DRIVE_0005, camera="image_00")
    gray = load_gray(seq.frames[0].image_path)
    moved = cv2.warpAffine(gray, np.float32([[1, 0, 3.0], [0, 1, -2.0]]), (gray.shape[1], gray.shape[0]))
    corners = cv2.goodFeaturesToTrack(gray, 100, 0.01, 10).reshape(-1, 2)
    corners = corners[(corners[:, 0] > 30) & (corners[:, 1] > 30) & (corners[:, 0] < gray.shape[1] - 30)
                      & (corners[:, 1] < gray.shape[0] - 30)]
    n = len(corners)
    twice = np.concatenate([corners, corners])
    points = _points(twice, np.r_[np.arange(n), np.arange(n)], np.r_[np.zeros(n), np.ones(n)], np.r_[np.arange(n),
                     np.arange(n)], np.zeros((2 * n, 3)))
    out = follow(points, gray, moved, seq.camera_model.K, None)
    assert len(out) > 1.8 * n and len(out) % 2 == 0
    by_track = {}
    for track, pixel in zip(out.track_of.tolist(), out.pixels_px.tolist()):
        by_track.setdefault(track, []).append(pixel)
    assert all(len(p) == 2 and p[0] == p[1] for p in by_track.values())
    first = np.array([p[0] for p in by_track.values()])
    np.testing.assert_allclose(np.median(first - corners[list(by_track)], axis=0), [3.0, -2.0], atol=0.05)


def test_the_window_drops_points_whose_view_or_neighbours_a_frame_may_not_use_and_offers_the_nearest_views():
    t = np.arange(40) * 0.1  # ten views a second, 1 m apart
    en = np.c_[np.arange(40, dtype=float), np.zeros(40)]

    def structure(view: int, variant: str, neighbours: tuple) -> ViewStructure:
        return ViewStructure(view, variant, neighbours, np.array([0]), np.zeros((1, 3)), np.eye(3)[None])

    # no structure stored for views 7-10: the nearest views behind that have some are 5 and 6
    stored = {v: {"before": structure(v, "before", (v - 2,)), "after": structure(v, "after", (v + 2,))}
              for v in range(2, 38) if not 7 <= v <= 10}
    window = ViewWindow(en, t, 1.0, stored)
    # a frame at 2.0 s may use the views of 1.0 s and before, 3.0 s and after
    points = _points(np.zeros((3, 2)), [0, 1, 2], [5, 30, 12], [0, 0, 0], np.zeros((3, 3)),
                     neighbours={5: (3,), 30: (32,), 12: (10,)})
    assert window.allowed(points, 2.0).view_of.tolist() == [5, 30]  # view 12 (1.2 s) is inside the window
    # a view whose neighbour lies inside goes too
    assert window.allowed(_points(np.zeros((1, 2)), [0], [9], [0], np.zeros((1, 3)), {9: (11,)}), 2.0).view_of.size == 0
    nearest = window.nearest_views(en[20], 2.0, 0.0, 4, 40.0)
    assert sorted(nearest) == [5, 6, 30, 31]  # two on each side, the nearest the window allows
    # both variants of views 5 and 6 are allowed: the neighbours on the side away from the frame are taken
    assert nearest[5].variant == nearest[6].variant == "before"
    assert nearest[30].variant == "after" and nearest[31].variant == "after"  # its "before" neighbour is inside
    assert window.nearest_view_m(en[20], 2.0) == 10.0
    assert window.nearest_views(en[20], 2.0, 0.0, 4, 12.0).keys() == {30, 31}  # within 12 m: those ahead only


def test_a_followed_frame_keeps_the_two_nearest_views_on_each_side_that_hold_points():
    """Views 1 m apart, the frame at 20 m (2.0 s): behind it views 8 (12 m away, 30 points), 9 (11 m, 5 points) and
    10 (10 m, 12 points); ahead 31 (11 m, 40 points) and 35 (15 m, 40 points) and 36 (16 m, 3 points). Behind, the
    two nearest holding ten points or more are 10 and 8, and 9 between them stays; ahead, 31 and 35, and 36 beyond
    them goes."""

    t = np.arange(40) * 0.1
    en = np.c_[np.arange(40, dtype=float), np.zeros(40)]
    counts = {8: 30, 9: 5, 10: 12, 31: 40, 35: 40, 36: 3}
    views = np.concatenate([np.full(n, v) for v, n in counts.items()])
    n = len(views)
    points = _points(np.zeros((n, 2)), np.arange(n), views, np.zeros(n), np.zeros((n, 3)))
    window = ViewWindow(en, t, 1.0, None)
    kept = window.nearest_views_only(points, en[20], 2.0, 2, 10)
    assert sorted(set(kept.view_of.tolist())) == [8, 9, 10, 31, 35]
    assert len(kept) == n - 3
    # with fewer than two views holding ten points on a side, every view there stays
    few = points.subset(np.isin(points.view_of, [9, 10, 36]))
    assert sorted(set(window.nearest_views_only(few, en[20], 2.0, 2, 10).view_of.tolist())) == [9, 10, 36]


def test_a_followed_frame_is_posed_on_its_nearest_views_and_carries_the_farther_ones(monkeypatch):
    """The frame at 20 m (2.0 s), points in views 10 and 11 behind it (10 and 9 m away), 29, 30 and 33 ahead (9, 10
    and 13 m). It is posed on the two nearest views on each side that hold ten points (10, 11, 29, 30), not on 33;
    it keeps its pose's inliers and carries view 33's points on, but for the image track its pose refused."""
    import visloc.tracking.follower as follower_module
    from visloc.pose.viewpose import MapCorrespondences
    from visloc.tracking.follower import PointFollower

    t = np.arange(40) * 0.1
    en = np.c_[np.arange(40, dtype=float), np.zeros(40)]
    views = np.repeat([10, 11, 29, 30, 33], 12)
    tracks = np.tile(np.arange(12), 5)  # each image track in every view's structure
    n = len(views)
    points = _points(np.zeros((n, 2)), tracks, views, np.arange(n), np.zeros((n, 3)))
    posed_on = []

    def pose_tracked(posed, px, *args):
        posed_on.append(sorted(set(posed.view_of.tolist())))
        inliers = np.flatnonzero(posed.track_of != 5)  # track 5 followed wrongly
        T = np.eye(4)
        T[:3, :3] = [[0, 0, 1], [-1, 0, 0], [0, -1, 0]]  # looking east, along the road
        T[:2, 3] = [20.0, 0.5]
        corr = MapCorrespondences(inliers, posed.view_of[inliers], posed.view_rows[inliers],
                                  posed.points_world[inliers], posed.points_cov[inliers], T)
        return Measurement(np.array([20.0, 0.5]), np.eye(2) * 0.01, "geometry"), corr

    monkeypatch.setattr(follower_module, "pose_tracked", pose_tracked)
    follower = PointFollower.__new__(PointFollower)
    follower.db_east_north_m, follower.stored = en, {"stored": True}
    follower.window = ViewWindow(en, t, 1.0, None)
    cameras = np.repeat(np.eye(4)[None], 40, axis=0)
    cameras[:, :2, 3] = en  # each view's camera where its geotag is
    follower.geometry, follower.pose = SimpleNamespace(T_world_camera=cameras), None
    follower.camera = type("Camera", (), {"K": np.eye(3)})()
    follower.relocalizer = SimpleNamespace(undistort=lambda px: np.asarray(px, np.float32))  # no distortion
    m, kept, views_ahead = PointFollower._pose(follower, points, 2.0, en[20])  # the points posed at 0; moved 20 m
    assert posed_on == [[10, 11, 29, 30]] and views_ahead  # views 29 and 30 lie ahead, along the camera's axis
    assert sorted(set(kept.view_of.tolist())) == [10, 11, 29, 30, 33]
    assert 5 not in kept.track_of.tolist() and len(kept) == n - 5
    np.testing.assert_allclose(kept.east_north_m, [20.0, 0.5])  # every point kept at the frame's pose
    looking_east = kept.T_world_camera
    assert not follower._rests_ahead(np.array([10, 11]), looking_east)
    looking_west = looking_east @ np.diag([-1.0, 1.0, -1.0, 1.0])  # turned about its vertical (y) axis
    assert follower._rests_ahead(np.array([10, 11]), looking_west)


def test_a_view_the_points_left_comes_back_in_the_variant_it_returns_with():
    """View 13 was ahead of the vehicle, its structure triangulated with the images after it (14); its points left
    with it. Back as a view behind the vehicle, triangulated with the images before it (11), its points are judged by
    those: a frame at 2.4 s may use them (the stale variant's neighbour 14 lies inside its window). A view the points
    still hold in one variant does not take another's points."""
    from visloc.pose.flowtrack import appended

    t = np.arange(40) * 0.1
    en = np.c_[np.arange(40, dtype=float), np.zeros(40)]
    ahead = _points(np.zeros((3, 2)), [0, 1, 2], [13, 13, 36], [0, 1, 2], np.zeros((3, 3)),
                    neighbours={13: (14,), 36: (37,)})
    left = ahead.subset(ahead.view_of == 36)
    assert left.neighbours == {36: (37,)}
    behind = _points(np.zeros((2, 2)), [5, 6], [13, 13], [3, 4], np.zeros((2, 3)), neighbours={13: (11,)})
    back = appended(left, behind)
    assert back.neighbours == {36: (37,), 13: (11,)}
    assert ViewWindow(en, t, 1.0, None).allowed(back, 2.4).view_of.tolist() == [36, 13, 13]
    held = appended(ahead, behind)  # view 13 still held in its first variant: the other's points stay out
    assert held.neighbours[13] == (14,) and len(held) == len(ahead)


def test_points_merged_keep_the_current_ones_and_add_the_fresh_ones_they_lack():
    current = _points([[1, 1], [2, 2]], [0, 1], [0, 0], [0, 1], np.ones((2, 3)), neighbours={0: (3,)})
    fresh = _points([[9, 9], [5, 5]], [7, 8], [0, 1], [1, 5], np.zeros((2, 3)), neighbours={0: (4,), 1: (2,)},
                    T=np.diag([2.0, 2.0, 2.0, 1.0]))
    out = merged(current, fresh)
    assert list(zip(out.view_of.tolist(), out.view_rows.tolist())) == [(0, 0), (0, 1), (1, 5)]
    np.testing.assert_allclose(out.pixels_px, [[1, 1], [2, 2], [5, 5]])  # the current pixel where both have the point
    assert out.track_of.tolist() == [0, 1, 8] and out.neighbours == {0: (3,), 1: (2,)}
    np.testing.assert_allclose(out.T_world_camera, np.eye(4))  # at the current points' pose
    assert merged(None, fresh) is fresh


def test_sift_near_describes_what_sift_finds_near_the_given_pixels_and_nothing_else(kitti_root):
    """A real frame at the camera-rate path's scale: the keypoints SIFT finds near a few pixels are exactly those of
    the whole image's SIFT (every keypoint, same place, same descriptor) that lie there, and none lies elsewhere."""
    from visloc.features.sift import extract_sift, sift_near
    from visloc.params import SiftParams

    gray = cv2.imread(str(next((kitti_root / "2011_09_26" / "2011_09_26_drive_0001_sync" / "image_00" / "data")
                               .glob("*.png"))), cv2.IMREAD_GRAYSCALE)
    params = SiftParams(contrast_threshold=0.02, image_scale=0.75)
    everything = extract_sift(gray, params)
    near_px = everything.xy_px[::40] + 3.0  # near every 40th keypoint, 3 px off it
    radius_px = 6.0
    found = sift_near(gray, params, near_px, radius_px)
    distance = np.linalg.norm(found.xy_px[:, None] - near_px[None], axis=2).min(axis=1)
    # the mask lies on the pixel grid of the image SIFT sees (at 0.75): a keypoint and the disc's centre each round
    assert 0 < len(found) < len(everything) / 4 and distance.max() <= radius_px + 2.5
    # a keypoint is its place, size and orientation (SIFT gives one place several orientations), with its descriptor
    def by_keypoint(f):
        return {tuple(np.round(k[:4], 3).tolist()): d.tobytes() for k, d in zip(f.keypoints_f32, f.descriptors_u8)}

    whole, near = by_keypoint(everything), by_keypoint(found)
    assert all(whole.get(k) == d for k, d in near.items())
    inside = np.linalg.norm(everything.xy_px[:, None] - near_px[None], axis=2).min(axis=1) <= radius_px - 1.5
    assert {tuple(np.round(k[:4], 3).tolist()) for k in everything.keypoints_f32[inside]} <= set(near)
    assert len(sift_near(gray, params, np.zeros((0, 2)), radius_px)) == 0


def test_guided_matching_takes_no_lone_keypoint_whose_descriptor_is_far():
    """A map point with one keypoint near where it projects: taken when its descriptor is near the view's, not when
    it is farther than the bound (with the pose as the only other evidence, that keypoint is no match)."""
    from visloc.pose.flowtrack import guided_view_matches

    K = np.array([[700.0, 0, 600], [0, 700.0, 180], [0, 0, 1]])
    view_desc = np.zeros((2, 128), np.uint8)
    view_desc[0, :64], view_desc[1, 64:] = 40, 40
    view_points = {0: (np.array([0, 1]), np.array([[0.0, 0, 10], [1.0, 0, 10]]), np.repeat(np.eye(3)[None], 2, 0))}
    query_xy = np.array([[601.0, 180], [671.0, 181]])
    query_desc = view_desc.copy()
    query_desc[1] = 0
    query_desc[1, 64:96] = 40  # half of point 1's descriptor: L2 distance 226 from it
    found = guided_view_matches(view_points, [view_desc], query_xy, query_desc, np.eye(4), K, (376, 1241),
                                radius_px=8.0)
    assert sorted(found.query_rows.tolist()) == [0, 1]
    bounded = guided_view_matches(view_points, [view_desc], query_xy, query_desc, np.eye(4), K, (376, 1241),
                                  radius_px=8.0, max_distance=200.0)
    assert bounded.query_rows.tolist() == [0] and bounded.view_rows.tolist() == [0]


def _guided_by_brute_force(view_points, view_descs, query_xy, query_desc, K, shape, radius_px, ratio, max_distance):
    """guided_view_matches' rule, written out pair by pair: (query row, view, view row) of every match."""
    from visloc.pose.guided import project_points

    h, w = shape
    claims = {}  # query row -> (distance, view, view row)
    for view, (rows, points, _) in view_points.items():
        uv, front = project_points(points, np.eye(4), K)
        for p, (u, v) in enumerate(uv):
            if not (front[p] and 0 <= u <= w - 1 and 0 <= v <= h - 1):
                continue
            near = np.flatnonzero(((query_xy - (u, v)) ** 2).sum(axis=1) <= radius_px**2)
            if not len(near):
                continue
            d = np.linalg.norm(query_desc[near].astype(float) - view_descs[view][rows[p]].astype(float), axis=1)
            order = np.argsort(d, kind="stable")
            second = d[order[1]] if len(order) > 1 else np.inf
            if d[order[0]] < ratio * second and d[order[0]] <= max_distance:
                q = int(near[order[0]])
                if q not in claims or d[order[0]] < claims[q][0]:
                    claims[q] = (d[order[0]], view, int(rows[p]))
    return sorted((q, v, r) for q, (_, v, r) in claims.items())


def test_guided_matching_takes_what_the_rule_says_pair_by_pair():
    """Random views' points and keypoints, some planted where points project with their descriptors a little
    changed: the vectorised matching finds exactly the matches the rule finds pair by pair, at a small and a wide
    radius."""
    from visloc.pose.flowtrack import guided_view_matches

    rng = np.random.default_rng(7)
    K = np.array([[700.0, 0, 600], [0, 700.0, 180], [0, 0, 1]])
    shape = (376, 1241)
    query_xy = np.c_[rng.uniform(0, 1240, 400), rng.uniform(0, 375, 400)]
    query_desc = rng.integers(0, 120, (400, 128)).astype(np.uint8)
    view_points, view_descs = {}, []
    for view in range(3):
        view_descs.append(rng.integers(0, 120, (300, 128)).astype(np.uint8))
        rows = rng.choice(300, 120, replace=False)
        uv = np.c_[rng.uniform(-50, 1290, 120), rng.uniform(-20, 395, 120)]
        depth = rng.uniform(3, 40, 120) * np.where(rng.random(120) < 0.1, -1, 1)  # a few behind the camera
        points = np.c_[(uv - K[:2, 2]) / 700.0 * depth[:, None], depth]
        view_points[view] = (rows, points, np.repeat(np.eye(3)[None], 120, 0))
        for p in range(0, 120, 4):  # planted: a keypoint near where the point lands, its descriptor a little off
            q = int(rng.integers(400))
            query_xy[q] = uv[p] + rng.normal(0, 2, 2)
            query_desc[q] = np.clip(view_descs[view][rows[p]].astype(int) + rng.integers(-8, 9, 128), 0, 255)
    for radius_px in (4.0, 24.0):
        found = guided_view_matches(view_points, view_descs, query_xy, query_desc, np.eye(4), K, shape,
                                    radius_px=radius_px, max_distance=250.0)
        got = sorted(zip(found.query_rows.tolist(), found.view_of.tolist(), found.view_rows.tolist()))
        expected = _guided_by_brute_force(view_points, view_descs, query_xy, query_desc, K, shape, radius_px, 0.8,
                                          250.0)
        assert got == expected and len(got) >= 40, (radius_px, len(got), len(expected))
