"""A followed track's relocalizations: the map points a frame is given afresh, by the full path or guided by its pose.

* **In full** (``Relocalizer.relocalize``): SIFT over the whole frame, retrieval, the refined measurement, and the
  map points it hands the tracker: its pose's inliers, widened by the structure of its views and of the views that
  keep serving (``visloc.pose.flowtrack.guided_view_matches``), posed again to keep the consistent ones. What a frame with
  no pose to go on (the first, one the tracker lost) needs.
* **Guided by a pose** (``Relocalizer.guided``): a frame the tracker has posed already knows where the map's points
  should lie in it. No retrieval (the views nearest its pose that it may use), SIFT describes only the keypoints near
  where their points project (``visloc.features.sift.sift_near``), and every one of those points is found by its
  projection and descriptor, then the frame is posed on them as a followed frame is. It finds more of the map than
  the full path hands on, for a fraction of its cost.

Each carries what it cost by stage (``Relocalization.stages_ms``); relocalizations run in a thread beside the
tracker, so both are safe from another thread (the image track numbers they hand out are taken under a lock).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, replace

import cv2
import numpy as np

from visloc.features.sift import Query, extract_sift, sift_near, undistort_keypoints
from visloc.geometry.projective import CameraModel
from visloc.params import RefinedParams, SiftParams
from visloc.pose.flowtrack import TrackedPoints, guided_view_matches, points_of, pose_tracked
from visloc.pose.guided import project_points
from visloc.pose.measurement import GEOMETRY, Measurement
from visloc.pose.viewpose import DatabaseGeometry
from visloc.retrieval.retrievers import Retrieval
from visloc.tracking.localizer import Localizer
from visloc.tracking.viewwindow import ViewWindow

LOOKAHEAD_S = 0.5  # a relocalization also takes on the points of views that still serve this much later
EXTRA_VIEWS = 4  # ... this many of them
EXTRA_VIEW_RADIUS_M = 40.0
GUIDED_VIEWS = 8  # a relocalization guided by a pose looks for the points of this many views nearest it
GUIDED_LOOKAHEAD_S = 0.0  # ... among those the frame may use now: the views just ahead that the exclusion window
# takes in a few frames are the nearest that see what it sees, and their points serve until then, as the full path's do
GUIDED_RADIUS_PX = 24.0  # a map point is found among the keypoints within this distance of where it projects: a
# tracked pose 0.3 m off moves a point 10 m away by 20 px, and within a narrower radius (8 px) only the points of
# the views it was posed on were found (they agree with its error), so a pose on the views behind it stayed there,
# its bias with it (drive 0005's S-bend)
GUIDED_MAX_DESCRIPTOR_DISTANCE = 250.0  # ... and its descriptor this near its view keypoint's (L2, uint8 SIFT): with
# the pose as the only other evidence, a lone keypoint near a projection is no match (else a pose a little off finds
# keypoints that agree with it, and the track drifts with its own relocalizations)
GUIDED_MASK_RADIUS_PX = 5.0  # SIFT describes the keypoints this near a projection: eight views' projections lie so
# dense that a keypoint farther than this from its own point's projection is mostly near another's; against 10 px
# it took a tenth less processor paced at 10 Hz for the same accuracy, and at 3 px drive 0005 erred by a tenth
# more (docs/performance.md)
NO_RETRIEVAL = Retrieval(np.zeros(0, np.int64), np.zeros(0, np.int64), None)
FULL, GUIDED = "full", "guided"


@dataclass(frozen=True)
class Localized:
    """A relocalized frame: its image, its features, retrieval (none when guided) and measurement."""

    gray: np.ndarray
    query: Query
    raw_px: np.ndarray  # (N, 2) its keypoints in the image as read
    retrieval: Retrieval
    measurement: Measurement
    retrieval_ms: float
    measurement_ms: float


@dataclass(frozen=True)
class Relocalization:
    """A relocalization's result: the frame localized, the map points it hands the tracker (None: none), how it
    was made (``FULL`` or ``GUIDED``: a guided measurement is a followed frame's, its views' scatter still to be
    stated by the run) and what widening and posing its points took."""

    full: Localized
    points: TrackedPoints | None
    points_ms: float = 0.0
    how: str = FULL

    @property
    def stages_ms(self) -> dict[str, float]:
        """What it cost, by stage, ms."""
        f = self.full
        return {"sift_ms": f.query.sift_ms, "retrieval_ms": f.retrieval_ms, "measurement_ms": f.measurement.query_side_ms,
                "points_ms": self.points_ms}


class Relocalizer:
    """Relocalizes frames of a followed track against a database (see the module docstring)."""

    def __init__(self, localizer: Localizer, db_east_north_m: np.ndarray, geometry: DatabaseGeometry,
                 query_camera: CameraModel, pose: RefinedParams, sift: SiftParams, window: ViewWindow,
                 distortion: np.ndarray | None = None, stored: dict | None = None):
        self.localizer = localizer
        self.db_east_north_m = np.asarray(db_east_north_m, float)
        self.geometry = geometry
        self.camera = query_camera
        self.pose = pose
        self.sift = sift
        self.window = window
        self.distortion = distortion
        self.stored = stored or {}
        # every keypoint of a relocalized frame starts an image track of its own: the first number the next one takes
        self._next_track = 0
        self._track_lock = threading.Lock()

    def _tracks(self, n: int) -> int:
        """The first of ``n`` image track numbers no other frame has."""
        with self._track_lock:
            first, self._next_track = self._next_track, self._next_track + n
        return first

    def undistort(self, px: np.ndarray) -> np.ndarray:
        """Pixels of the image as read, moved to the pinhole camera (as they are without a distortion)."""
        return undistort_keypoints(np.asarray(px, np.float32), self.camera.K, self.distortion)

    def _full(self, gray: np.ndarray, timestamp_s: float, prediction, engine, name: str) -> Localized:
        t0 = time.perf_counter()
        features = extract_sift(gray, self.sift, sift=engine, name=name)
        keypoints = self.undistort(features.keypoints_f32)
        query = Query(features.descriptors_u8, timestamp_s, keypoints_f32=keypoints,
                      sift_ms=(time.perf_counter() - t0) * 1000.0)
        retrieval, m, r_ms, m_ms = self.localizer.measure(query, prediction)
        return Localized(gray, query, features.keypoints_f32[:, :2], retrieval, m, r_ms, m_ms)

    def _view_points(self, view: int, neighbours: tuple, structure: dict) -> tuple:
        """(rows, points_world, points_cov) of a view's structure: the stored arrays when the store has this
        variant, else made from the measurement's own (row -> (point, covariance))."""
        for s in self.stored.get(view, {}).values():
            if tuple(s.neighbours) == tuple(neighbours):
                return s.rows, s.points_world, s.cov_world
        rows = np.fromiter(structure, np.int64, len(structure))
        return (rows, np.array([structure[r][0] for r in rows.tolist()], float).reshape(-1, 3),
                np.array([structure[r][1] for r in rows.tolist()], float).reshape(-1, 3, 3))

    def _points(self, full: Localized) -> TrackedPoints | None:
        """The map points a fully localized frame hands the tracker: its pose's inliers, widened by the structure
        of its views and of views that keep serving (``guided_view_matches``), posed again to keep the consistent ones."""
        m = full.measurement
        if m.source != GEOMETRY or m.inliers is None:
            return None
        inliers = m.inliers
        neighbours = dict(inliers.neighbours or {})
        first_track = self._tracks(len(full.raw_px))
        base = points_of(inliers, full.raw_px, m.east_north_m, neighbours, first_track)
        if not inliers.view_structure:
            return base
        view_points = {v: self._view_points(v, neighbours.get(v, ()), structure)
                       for v, structure in inliers.view_structure.items()}
        for view, s in self.window.nearest_views(m.east_north_m, full.query.timestamp_s, LOOKAHEAD_S, EXTRA_VIEWS,
                                                 EXTRA_VIEW_RADIUS_M).items():
            if view not in view_points:
                view_points[view], neighbours[view] = (s.rows, s.points_world, s.cov_world), tuple(s.neighbours)
        guided = guided_view_matches(view_points, self.geometry.descriptors_u8, full.query.keypoints_f32[:, :2],
                                full.query.descriptors_u8, inliers.T_world_camera, self.camera.K, full.gray.shape)
        wide = points_of(guided, full.raw_px, m.east_north_m, neighbours, first_track)
        if len(wide) <= len(base):
            return base
        posed, kept = pose_tracked(wide, full.query.keypoints_f32[guided.query_rows, :2], self.db_east_north_m,
                                   self.geometry, self.camera, self.pose)
        if kept is None or len(kept.query_rows) <= len(base):
            return base
        return replace(wide.subset(kept.query_rows), T_world_camera=np.asarray(kept.T_world_camera, float),
                       east_north_m=np.asarray(posed.east_north_m, float))

    def relocalize(self, gray: np.ndarray, timestamp_s: float, prediction, engine, name: str) -> Relocalization:
        """The frame localized in full, and the map points it hands the tracker."""
        full = self._full(gray, timestamp_s, prediction, engine, name)
        t0 = time.perf_counter()
        points = self._points(full)
        return Relocalization(full, points, (time.perf_counter() - t0) * 1000.0)

    def guided(self, gray: np.ndarray, timestamp_s: float, T_world_camera: np.ndarray, east_north_m: np.ndarray,
               engine, pose_points: Callable[[TrackedPoints], tuple]) -> Relocalization | None:
        """The frame, posed at ``T_world_camera`` (at ``east_north_m``) by the tracker, given the map points of the
        ``GUIDED_VIEWS`` views nearest it that it may use that SIFT finds where they
        project; posed on them by ``pose_points(points) -> (measurement, points kept or None)``. None when the
        points give no pose (the full path is then the one to ask)."""
        views = self.window.nearest_views(east_north_m, timestamp_s, GUIDED_LOOKAHEAD_S, GUIDED_VIEWS,
                                          EXTRA_VIEW_RADIUS_M)
        if not views:
            return None
        t0 = time.perf_counter()
        view_points = {v: (s.rows, s.points_world, s.cov_world) for v, s in views.items()}
        h, w = gray.shape[:2]
        projected = []
        for _, points_world, _ in view_points.values():
            uv, front = project_points(points_world, T_world_camera, self.camera.K)
            projected.append(uv[front & (uv[:, 0] >= 0) & (uv[:, 1] >= 0) & (uv[:, 0] <= w - 1) & (uv[:, 1] <= h - 1)])
        near_px = self._distort(np.concatenate(projected))
        features = sift_near(gray, self.sift, near_px, GUIDED_MASK_RADIUS_PX, sift=engine)
        keypoints = self.undistort(features.keypoints_f32)
        query = Query(features.descriptors_u8, timestamp_s, keypoints_f32=keypoints,
                      sift_ms=(time.perf_counter() - t0) * 1000.0)
        if not len(features):
            return None
        t1 = time.perf_counter()
        found = guided_view_matches(view_points, self.geometry.descriptors_u8, keypoints[:, :2], features.descriptors_u8,
                               T_world_camera, self.camera.K, gray.shape, radius_px=GUIDED_RADIUS_PX,
                               max_distance=GUIDED_MAX_DESCRIPTOR_DISTANCE)
        neighbours = {v: tuple(s.neighbours) for v, s in views.items()}
        points = points_of(found, features.keypoints_f32[:, :2], east_north_m, neighbours, self._tracks(len(features)))
        m, kept = pose_points(points)
        if kept is None:
            return None
        m = replace(m, compute_ms=(time.perf_counter() - t1) * 1000.0, structure_ms=0.0)
        full = Localized(gray, query, features.keypoints_f32[:, :2], NO_RETRIEVAL, m, 0.0, m.compute_ms)
        return Relocalization(full, kept, 0.0, GUIDED)

    def _distort(self, undistorted_px: np.ndarray) -> np.ndarray:
        """Pixels of the pinhole camera moved into the image as read (as is without a distortion)."""
        if self.distortion is None or not len(undistorted_px):
            return undistorted_px
        K = np.asarray(self.camera.K, float)
        rays = np.c_[(undistorted_px - K[:2, 2]) / np.diag(K)[:2], np.ones(len(undistorted_px))]
        px, _ = cv2.projectPoints(rays.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, np.asarray(self.distortion, float))
        return px.reshape(-1, 2)
