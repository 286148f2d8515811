"""A track at camera rate: follow the map's points from frame to frame, localize in full only when needed.

``PointFollower.steps`` runs a drive's frames in order through a ``Localizer`` (the refined method):

* **Tracked frames.** The map points the last posed frame saw are followed into this frame by optical flow and the
  frame is posed against those of its nearest views (``visloc.pose.flowtrack``), with the full measurement's own
  PnP, checks and covariance, on at least ``min_pnp_inliers`` image tracks (a keypoint in several views' structure
  counts once). No SIFT, no retrieval. How far one view's pose strays, which the spread of the one or two views a
  followed frame rests on hardly says, comes from the run's poses on several views posed apart as well
  (``visloc.pose.trackedcov.ViewScatter``). Points whose view (or the views it was triangulated with) lies inside
  the exclusion window of this frame are dropped, as the full path would not use them. The points of a few farther
  views are carried on unposed: with the window on, the nearest view ahead leaves it every frame or two, and its
  points would leave with it, where the carried ones take over without a full localization.
* **Relocalization.** The full path (SIFT, retrieval, structure, PnP) runs when the followed points no longer
  serve (``visloc.pose.flowtrack.needs_relocalization``), or, with ``guided_relocalization``, a relocalization
  guided by the tracked pose of the frame that asked (``visloc.tracking.relocalize``). With ``background_relocalization`` it runs in a
  thread beside the tracker on the frame that asked, and its points are followed from that frame into the
  frame where it arrives and joined to the tracked ones (replacing them if its pose disagrees with the
  tracked pose of the same frame); unpaced (``pace_hz`` None), the next frame is read once it has come.
  Without, the frame that asked waits for it (reproducible runs).
* **No frame waits long.** With the relocalization beside the tracker, a frame whose followed points give no pose
  (too few left, or a pose the checks refuse) waits at most ``max_lost_wait_ms`` for the one under way. If it has
  not come, the frame is not posed: the filter predicts it (kind "predicted"), a full localization of it starts
  beside the tracker unless one is under way, and its measurement takes that frame's place in the filter when it
  comes. Only a frame with no track to predict (the first) is localized in full at once, as is, without the
  background thread, every frame with nothing to follow.
* **A first fix.** A track's first measurement is the start of everything after it, so a first frame that
  only gets the geotag of its best candidate (no pose) takes the median geotag of its best candidates
  instead when the best one lies far from the others (``visloc.tracking.localizer.first_fix``).

Each step carries its kind ("tracked", "predicted" or "relocalized") and its latency: the wall time from its image
read to its filter step done (flow and pose, or SIFT, retrieval and measurement). A background relocalization's
own cost is on another core.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor, wait
from dataclasses import dataclass, replace

import numpy as np

from visloc.features.sift import Query, make_sift
from visloc.geometry.projective import CameraModel
from visloc.params import RefinedParams, SiftParams, TrackParams
from visloc.pose.flowtrack import (TrackedPoints, appended, disagree, follow, grid_cells_occupied, linked, merged,
                                   needs_relocalization, pose_tracked, predicted_camera)
from visloc.pose.measurement import GEOMETRY, Measurement
from visloc.pose.trackedcov import ViewRuns, ViewScatter, shared_map_error
from visloc.pose.viewpose import DatabaseGeometry, side_of
from visloc.retrieval.matching import MatchCancelled
from visloc.retrieval.retrievers import Retrieval
from visloc.sources.drives import Drive, load_gray
from visloc.tracking.localizer import Localizer, StepResult, first_fix
from visloc.tracking.relocalize import EXTRA_VIEW_RADIUS_M, GUIDED, NO_RETRIEVAL, Relocalization, Relocalizer
from visloc.tracking.viewwindow import ViewWindow

TRACKED = "tracked"
RELOCALIZED = "relocalized"
PREDICTED = "predicted"  # no pose from the followed points and a full localization under way: the filter predicts
LINKED_VIEWS = 4  # a followed frame takes on the same map points in this many views nearest it, half on each side
POSED_VIEWS = 2  # ... is posed on the views no farther away than the POSED_VIEWS nearest on each side that hold
POSED_VIEW_MIN_POINTS = 10  # ... this many points
CARRIED_VIEWS = 4  # ... and carries on the points of the views up to the CARRIED_VIEWS nearest on each side, for when
# the exclusion window takes the nearest views away
HISTORY_FRAMES = 50  # a relocalization that arrives later than this many frames is not fused in its frame's place


@dataclass(frozen=True)
class FollowedStep:
    """One frame of a followed track. latency_ms: see the module docstring; flow_ms: following the points;
    followed_points: how many were posed against (tracked frames) or found (relocalized);
    relocalize_reason: why this frame asked for a full localization (None: it did not); merged: a background
    relocalization's points joined the followed ones at this frame ("joined" or "replaced")."""

    result: StepResult
    latency_ms: float
    kind: str
    flow_ms: float = 0.0
    followed_points: int = 0
    relocalize_reason: str | None = None
    merged: str | None = None
    relocalization_ms: dict | None = None  # the relocalization this frame used (its own or one from beside), by stage
    relocalized_by: str | None = None  # ... how it was made: "full" or "guided" (visloc.tracking.relocalize)


def _moved_to(points: TrackedPoints, displacement_m: np.ndarray | None) -> np.ndarray:
    """Where the vehicle is: the points' pose moved by ``displacement_m`` (None: not moved), east, north m."""
    return points.east_north_m + (0.0 if displacement_m is None else np.asarray(displacement_m, float))


def _at_pose(points: TrackedPoints, T_world_camera: np.ndarray, east_north_m: np.ndarray) -> TrackedPoints:
    return replace(points, T_world_camera=np.asarray(T_world_camera, float),
                   east_north_m=np.asarray(east_north_m, float))


class PointFollower:
    """Steps a localizer through a drive's frames, following map points between full localizations."""

    def __init__(self, localizer: Localizer, db_east_north_m: np.ndarray, db_timestamps_s: np.ndarray,
                 geometry: DatabaseGeometry, query_camera: CameraModel, pose: RefinedParams, sift: SiftParams,
                 params: TrackParams, distortion: np.ndarray | None = None, stored: dict | None = None):
        self.localizer = localizer
        self.db_east_north_m = np.asarray(db_east_north_m, float)
        self.geometry = geometry
        self.camera = query_camera
        self.pose = pose
        self.sift = sift
        self.params = params
        self.stored = stored or {}
        self.window = ViewWindow(db_east_north_m, db_timestamps_s, params.exclusion_s, self.stored)
        self.relocalizer = Relocalizer(localizer, db_east_north_m, geometry, query_camera, pose, sift, self.window,
                                       distortion, self.stored)
        # per view structure (view, its neighbours): the first image track not yet linked into it
        self._linked_from: dict[tuple, int] = {}
        self._trees: dict = {}  # each view structure's k-d tree over its points, for linking
        # Guided matching's k-d trees come from scipy.spatial, which the CLI imports only when asked (a few tenths
        # of a second): imported here, before the first frame is read, it does not delay that frame, so a run paced
        # at the camera's rate does not start that far behind and hurry through the frames that came meanwhile
        # faster than its relocalizations arrive (6-11 frames of each shared drive were left predicted, not posed).
        import scipy.spatial  # noqa: F401

    def _rests_ahead(self, views: np.ndarray, T_world_camera: np.ndarray) -> bool:
        """Whether one of the database ``views`` lies ahead of a camera posed at ``T_world_camera``."""
        return any(side_of(self.geometry.T_world_camera[v][:3, 3], T_world_camera) > 0 for v in np.unique(views))

    def _linked(self, points: TrackedPoints, timestamp_s: float, displacement_m: np.ndarray | None) -> TrackedPoints:
        """``points`` on the views a frame at ``timestamp_s`` takes on: each image track linked into the structure
        of the ``LINKED_VIEWS`` views nearest the frame that it may use where it has no point there yet
        (``visloc.pose.flowtrack.linked``: the same map points in the database's other views), then without the
        views farther away than the ``CARRIED_VIEWS`` nearest on each side that hold ``POSED_VIEW_MIN_POINTS``
        points. As the vehicle moves on, the views it passes and those the exclusion window takes away hand their
        map points on to the views it nears, and the frames stay posed on the nearest views (``_pose``) without a
        full localization. ``displacement_m``: how far the vehicle moved since the
        points' pose."""
        if not self.stored or not len(points):
            return points
        east_north_m = _moved_to(points, displacement_m)
        out = points
        for v, st in self.window.nearest_views(east_north_m, timestamp_s, 0.0, LINKED_VIEWS,
                                               EXTRA_VIEW_RADIUS_M).items():
            key = (v, tuple(st.neighbours))
            newer = out.track_of >= self._linked_from.get(key, 0)  # the tracks not tried in this view yet
            self._linked_from[key] = int(out.track_of.max()) + 1  # tracks are numbered in the order they come
            if newer.any():
                tried = out.subset(newer)
                more = linked(tried, {v: (st.rows, st.points_world, st.cov_world)}, self.geometry.descriptors_u8,
                              neighbours={v: tuple(st.neighbours)}, trees=self._trees)
                if len(more) > len(tried):
                    out = appended(out, more.subset(np.arange(len(tried), len(more))))
        return self.window.nearest_views_only(out, east_north_m, timestamp_s, CARRIED_VIEWS, POSED_VIEW_MIN_POINTS)

    @staticmethod
    def _direction(seq: Drive) -> float:
        t = seq.timestamps_s
        return 1.0 if len(t) < 2 or t[-1] >= t[0] else -1.0

    def _pose(self, points: TrackedPoints, timestamp_s: float,
              displacement_m: np.ndarray | None) -> tuple[Measurement, TrackedPoints | None, bool]:
        """A frame posed on the followed points of its nearest views (``POSED_VIEWS`` on each side: the error grows
        with the distance to the views), the points it keeps (None: no pose): its inliers at its pose, and the
        points of the farther views it carries on (``CARRIED_VIEWS``), but for the image tracks its pose found wrong,
        and whether a view its pose rests on lies ahead of it (along the camera's axis). The carried views are the
        ones that serve once the exclusion window has taken the nearest away.
        ``displacement_m``: how far the vehicle moved since the points' pose."""
        t1 = time.perf_counter()
        posed = (self.window.nearest_views_only(points, _moved_to(points, displacement_m), timestamp_s, POSED_VIEWS,
                                                POSED_VIEW_MIN_POINTS) if self.stored else points)
        m, inliers = pose_tracked(posed, self.relocalizer.undistort(posed.pixels_px)[:, :2], self.db_east_north_m,
                                  self.geometry, self.camera, self.pose)
        m = replace(m, compute_ms=(time.perf_counter() - t1) * 1000.0)
        if inliers is None:
            return m, None, False
        kept = posed.subset(inliers.query_rows)
        views_ahead = self._rests_ahead(kept.view_of, inliers.T_world_camera)
        outliers = np.setdiff1d(posed.track_of, kept.track_of)
        carried = points.subset(~np.isin(points.view_of, np.unique(posed.view_of))
                                & ~np.isin(points.track_of, outliers))
        if len(carried):
            kept = appended(kept, carried)
        return m, _at_pose(kept, inliers.T_world_camera, m.east_north_m), views_ahead

    def _relocalize(self, gray: np.ndarray, timestamp_s: float, prediction, engines: tuple, name: str,
                    posed: TrackedPoints | None = None) -> Relocalization:
        """The frame relocalized: guided by ``posed``, its tracked points at its pose, when it has them and the guided
        points give a pose (``visloc.tracking.relocalize``), else in full. ``engines``: SIFT for the full path and for
        the guided one (all keypoints near the map's points), each used by one thread only."""
        if posed is not None and self.stored and self.params.guided_relocalization:
            done = self.relocalizer.guided(gray, timestamp_s, posed.T_world_camera, posed.east_north_m, engines[1],
                                           lambda points: self._pose(points, timestamp_s, None)[:2])
            if done is not None:
                return done
        return self.relocalizer.relocalize(gray, timestamp_s, prediction, engines[0], name)

    def steps(self, seq: Drive, indices: Iterable[int],
              cancelled: Callable[[], bool] | None = None) -> Iterator[FollowedStep]:
        """The frames ``indices`` of ``seq`` in order, from the localizer's current state (see the module
        docstring); ``cancelled()`` is asked after each frame and raises ``MatchCancelled`` when true."""
        p, K = self.params, self.camera.K
        self.window.direction = self._direction(seq)

        def engines() -> tuple:  # SIFT for the full path and, when asked for, the guided one: one pair per thread
            return (make_sift(self.sift),
                    make_sift(self.sift.replace(n_features=0)) if p.guided_relocalization else None)
        engine = engines()
        pool = ThreadPoolExecutor(1, thread_name_prefix="relocalize") if p.background_relocalization else None
        background_engine = engines() if pool else None
        points: TrackedPoints | None = None
        points_t_s = 0.0  # the time of the frame the points were last seen in
        previous_gray = None
        # a background relocalization: its future, the tracked measurement of its frame, the frame's number
        pending: tuple[Future, Measurement, int] | None = None
        since_full = 0
        on_points = 0  # frames posed on the points since fresh ones last came
        min_points = max(6, self.pose.min_pnp_inliers)
        scatter = ViewScatter()  # one view's scatter, from this run's poses on several views posed apart
        view_runs = ViewRuns()  # how many tracked frames in a row each view has been posed on
        full_ahead = [False]  # whether the last full localization was posed on a view ahead of the vehicle

        def learn(done: Relocalization) -> Measurement:
            """From a relocalization: the view scatter, whether it found a view ahead; its measurement for the filter
            (a guided one states the view scatter, as a followed frame's does)."""
            m = done.full.measurement
            scatter.add(m)
            full_ahead[0] = (m.source == GEOMETRY and m.inliers is not None
                             and self._rests_ahead(m.inliers.view_of, m.inliers.T_world_camera))
            return scatter.stated(m) if done.how == GUIDED else m
        started = time.perf_counter()

        def moved_m(since_s: float) -> np.ndarray | None:
            v = self.localizer.velocity_m_s
            return None if v is None else v * (t_s - since_s)

        history: list[list] = []  # [frame number, filter before its measurement, the measurement], the last ones

        def fuse(query: Query, retrieval: Retrieval, m: Measurement, retrieval_ms: float = 0.0,
                 measurement_ms: float = 0.0) -> StepResult:
            history.append([n, self.localizer.snapshot(), m])
            del history[:-HISTORY_FRAMES]
            return self.localizer.fuse(query, retrieval, m, retrieval_ms, measurement_ms)

        def refuse_from(n_then: int, m: Measurement) -> None:
            """Frame ``n_then``'s measurement replaced by ``m`` (a relocalization of it that arrived late) and every
            later one fused again: the filter goes on as if it had had ``m`` in time."""
            at = [k for k, h in enumerate(history) if h[0] == n_then]
            if not at or m.source != GEOMETRY:
                return
            self.localizer.restore(history[at[0]][1])
            history[at[0]][2] = m
            for h in history[at[0]:]:
                h[1] = self.localizer.snapshot()
                self.localizer.fuse(Query(np.zeros((0, 128), np.uint8), 0.0), NO_RETRIEVAL, h[2])

        def take(done: Relocalization, tracked_then: Measurement | None, current: TrackedPoints | None,
                 n_then: int):
            """The points a relocalization brings, followed into this frame and joined to ``current``; its
            measurement takes the place of the tracked one of its frame in the filter."""
            m = learn(done)
            refuse_from(n_then, m)
            used[0] = done
            if done.points is None:
                return current, None
            fresh = follow(done.points, done.full.gray, gray, K, moved_m(done.full.query.timestamp_s))
            if current is None or not len(current):
                return fresh, "joined"
            replaced = tracked_then is not None and disagree(m, tracked_then)
            return (fresh, "replaced") if replaced else (merged(current, fresh), "joined")

        try:
            for n, i in enumerate(indices):
                if p.pace_hz:
                    time.sleep(max(0.0, started + n / p.pace_hz - time.perf_counter()))
                elif p.pace_hz is None and pending is not None:  # as fast as the full localizations keep up
                    wait([pending[0]])
                frame = seq.frames[i]
                gray = load_gray(frame.image_path)
                t_s = frame.timestamp_s
                t0 = time.perf_counter()
                used: list[Relocalization | None] = [None]  # the relocalization whose result this frame used
                tracked, kept, reason, joined, n_followed, flow_ms = None, None, None, None, 0, 0.0
                followed = None
                if points is not None and previous_gray is not None:
                    followed = follow(points, previous_gray, gray, K, moved_m(points_t_s))
                if pending is not None and pending[0].done():
                    followed, joined = take(pending[0].result(), pending[1], followed, pending[2])
                    pending = None
                if followed is not None:
                    followed = self.window.allowed(self._linked(followed, t_s, moved_m(points_t_s)), t_s)
                if (pending is not None and (followed is None or followed.n_tracks < min_points)
                        and wait([pending[0]], max(0.0, p.max_lost_wait_ms / 1000.0 - (time.perf_counter() - t0))).done):
                    followed, joined = take(pending[0].result(), None, followed, pending[2])  # lost: the one under way
                    pending = None
                    if followed is not None:
                        followed = self.window.allowed(followed, t_s)
                if followed is not None:
                    n_followed, n_tracks = len(followed), followed.n_tracks  # a keypoint in several views: one track
                    flow_ms = (time.perf_counter() - t0) * 1000.0
                    if n_tracks >= min_points:
                        tracked, kept, views_ahead = self._pose(followed, t_s, moved_m(points_t_s))
                        reason = None if kept is not None else tracked.fallback_reason
                    else:
                        reason = f"{n_tracks} image tracks followed"
                if kept is not None:
                    on_points = 1 if joined else on_points + 1
                    scatter.add(tracked)
                    repeated = view_runs.frames(tracked.view_indices, on_points)  # frames on the same map
                    tracked = shared_map_error(scatter.stated(tracked), repeated)
                    result = fuse(Query(np.zeros((0, 128), np.uint8), t_s), NO_RETRIEVAL, tracked, 0.0,
                                  tracked.compute_ms)
                    points, points_t_s, kind = kept, t_s, TRACKED
                    since_full += 1
                    sigma_m = float(np.sqrt(max(np.linalg.eigvalsh(result.filter.P[:2, :2]).max(), 0.0)))
                    # the image tracks the frame was posed on: the next frames link them into the views they near
                    reason = needs_relocalization(
                        points.n_tracks, grid_cells_occupied(points.pixels_px, gray.shape), tracked.lever_m, sigma_m,
                        since_full, min_points=p.min_followed_points, min_cells=p.min_followed_cells,
                        max_lever_m=p.max_followed_lever_m, max_sigma_m=p.max_followed_sigma_m,
                        every_frames=p.relocalize_every, views_ahead=views_ahead,
                        # posed on views behind only where the last full localization found one ahead
                        behind_only_every_frames=p.relocalize_behind_only_every if full_ahead[0] else 0,
                        nearest_view_m=self.window.nearest_view_m(tracked.east_north_m, t_s),
                        max_lever_excess_m=p.max_followed_lever_excess_m)
                    if reason is not None and pending is None:
                        since_full = 0
                        if pool is not None:
                            pending = (pool.submit(self._relocalize, gray, t_s, self.localizer.prediction(),
                                                   background_engine, str(frame.image_path), points), tracked, n)
                        else:  # the frame waits, and is measured by the relocalization: its own image, nothing to follow
                            done = self._relocalize(gray, t_s, self.localizer.prediction(), engine,
                                                    str(frame.image_path), points)
                            used[0] = done
                            m = learn(done)
                            if done.points is not None:
                                replaced = disagree(m, tracked)
                                points = done.points if replaced else merged(points, done.points)
                                joined = "replaced" if replaced else "joined"
                                self.localizer.restore(history.pop()[1])
                                result = fuse(done.full.query, done.full.retrieval, m, done.full.retrieval_ms,
                                              done.full.measurement_ms)
                            kind = RELOCALIZED
                elif pool is not None and self.localizer.started:  # no pose from its points: predicted, no wait
                    if pending is None:  # a full localization of this frame, beside the tracker
                        pending = (pool.submit(self._relocalize, gray, t_s, self.localizer.prediction(),
                                               background_engine, str(frame.image_path)), None, n)
                        since_full = 0
                    reason = reason or "no points to follow"
                    m = tracked or Measurement(None, None, None, fallback_reason=reason)
                    result = fuse(Query(np.zeros((0, 128), np.uint8), t_s), NO_RETRIEVAL, m)
                    at_m = np.asarray(result.filter.x[:2], float)
                    # too few points are followed on from the predicted pose; points that gave no pose are dropped
                    points = None if followed is None or tracked is not None else _at_pose(
                        followed, predicted_camera(followed.T_world_camera, followed.east_north_m, at_m), at_m)
                    points_t_s, kind = t_s, PREDICTED
                else:  # nothing to follow, or it no longer poses, and no track to predict: localize in full now
                    if pending is not None:
                        pending[0].cancel()
                        pending = None
                    done = self._relocalize(gray, t_s, self.localizer.prediction(), engine, str(frame.image_path))
                    used[0] = done
                    m = learn(done)
                    if not self.localizer.started:
                        m = first_fix(m, done.full.retrieval, self.db_east_north_m)
                    result = fuse(done.full.query, done.full.retrieval, m, done.full.retrieval_ms,
                                  done.full.measurement_ms)
                    points, points_t_s, kind = done.points, t_s, RELOCALIZED
                    on_points = 0
                    since_full = 0
                    n_followed = 0 if points is None else len(points)
                    reason = reason or ("first frame" if n == 0 else "no points to follow")
                latency = (time.perf_counter() - t0) * 1000.0
                step = FollowedStep(result, latency, kind, flow_ms, n_followed, reason, joined,
                                    None if used[0] is None else used[0].stages_ms,
                                    None if used[0] is None else used[0].how)
                previous_gray = gray
                if cancelled is not None and cancelled():
                    raise MatchCancelled()
                yield step
        finally:
            if pool is not None:
                pool.shutdown(wait=True, cancel_futures=True)
