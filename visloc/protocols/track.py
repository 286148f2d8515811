"""``visloc track``: localize every frame of a drive in order, at the camera's rate, as a vehicle would.

Each frame is read, described by SIFT, retrieved, measured (the refined method) and fused by
the constant-velocity filter, whose time step is the frame interval. ``track_localizer``
composes the path (``TrackParams.fast``: the camera-rate path of ``visloc.pose.fastpose`` on the
structure and global vectors the store keeps; else the exact refined path with the paper's
retrieval), ``run_track`` runs it and ``TrackRun`` holds what happened: per frame the timings,
the measurement and the estimate against the frame's own geotag, and the run's summary.

Latency counts what a live system spends on a frame once its image is decoded: SIFT,
retrieval, the query side of the measurement and the filter step (``visloc.tracking.runs.latency_ms``).
``sustained_hz`` is frames per second of wall time over the whole run, reading included.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace

import numpy as np

from visloc.store.database import GeoDatabase
from visloc.protocols.records import QueryTruth, nees_against_truth, truth_extra_m2
from visloc.errors import InputError
from visloc.geo import geodesic_distance_m
from visloc.geometry.projective import CameraModel
from visloc.tracking.localizer import Localizer, StepResult
from visloc.pose.measurement import GEOMETRY
from visloc.params.methods import REFINED_FAST_METHOD, REFINED_METHOD, Method
from visloc.tracking.methods import build_localizer
from visloc.params import (MAX_DT_S, MIN_DT_S, PAPER_FILTER, PAPER_MATCH, REFINED, TRACK, FilterParams, RefinedParams,
                           RetrievalParams, SiftParams, TrackParams)
from visloc.sources.queries import extract_queries
from visloc.pose.refined import one_blas_thread
from visloc.pose.structure import seeded_structure_cache
from visloc.tracking.follower import FollowedStep, PointFollower
from visloc.tracking.localizer import first_fix
from visloc.tracking.runs import steps_of
from visloc.sources.drives import Drive
from visloc.pose.uncertainty import SIDES, calibration
from visloc.stats import LATENCY_FIGURES, summary_of
from visloc.store.workspace import Workspace

WINDOW_S = 20.0  # the exact path's retrieval window, the paper's


def track_filter(seq: Drive, params: TrackParams, base: FilterParams = PAPER_FILTER) -> FilterParams:
    """``base`` with the time step of one localized frame: the median frame interval times the stride."""
    t = seq.timestamps_s
    if len(t) < 2:
        raise InputError(f"{seq.name}: a track needs at least 2 frames")
    dt_s = float(np.median(np.diff(t))) * params.stride
    if not MIN_DT_S <= dt_s <= MAX_DT_S:
        raise InputError(f"{seq.name}: its median frame interval times --stride {params.stride} is {dt_s:g} s, the "
                         f"filter's time step; it must be in [{MIN_DT_S:g}, {MAX_DT_S:g}] s (check the timestamps)")
    return base.replace(dt_s=dt_s)


def track_localizer(ws: Workspace, db: GeoDatabase, query_camera: CameraModel | None, filter_params: FilterParams,
                    params: TrackParams = TRACK, method: Method | None = None, *,
                    query_what: str = "the query camera") -> tuple[Localizer, SiftParams]:
    """The localizer of a track over ``db`` and the SIFT settings its frames are described with.

    ``method``: the refined method to run, a preset with the user's changes (default: refined-fast when
    ``params.fast``, else refined)."""
    method = method or (REFINED_FAST_METHOD if params.fast else REFINED_METHOD)
    store_sift = ws.sift_params
    structures = ws.load_structure(db, method.pose)
    retrieval = RetrievalParams(window_s=WINDOW_S, exclusion_s=params.exclusion_s)
    if not method.camera_rate:
        loc = build_localizer(method, db, PAPER_MATCH, retrieval, filter_params, query_camera=query_camera,
                              query_what=query_what, structures=seeded_structure_cache(structures))
        return loc, store_sift
    loc = build_localizer(method, db, PAPER_MATCH, retrieval, filter_params, query_camera=query_camera,
                          query_what=query_what, stored=structures,
                          shortlist_index=ws.global_vectors.load_database_index(db, method.shortlist))
    return loc, store_sift.replace(image_scale=params.query_image_scale, n_features=params.query_max_keypoints)


@dataclass(frozen=True)
class TrackFrame:
    """One localized frame. Positions are (east_m, north_m) in the database's local frame."""

    frame: int
    timestamp_s: float
    truth_m: tuple[float, float]
    estimate_m: tuple[float, float]
    estimate_sigma_m: float
    error_m: float  # estimate vs the frame's geotag, geodesic
    measurement_m: tuple[float, float] | None
    measurement_sigma_m: float | None
    measurement_error_m: float | None
    measurement_source: str | None  # "geometry", "geotag" or None
    fallback_reason: str | None
    gated: bool
    restarted: bool
    view_frames: tuple[int, ...]
    n_pnp_inliers: int
    sift_ms: float
    retrieval_ms: float
    geometry_ms: float
    filter_ms: float
    latency_ms: float
    estimate_cov_m2: list[list[float]] | None = None  # 2x2 east/north position covariance, m^2
    measurement_cov_m2: list[list[float]] | None = None  # the measurement's own covariance, m^2
    # e' C^-1 e of the measurement's and the estimate's errors (visloc.protocols.records.step_record's rule: C alone when
    # the frame's geotag comes from the map's own receiver, else with the map's and the truth's accuracy added)
    measurement_nees: float | None = None
    estimate_nees: float | None = None
    measurement_side: str | None = None  # refined: "both" or "one" (the views' sides of the pose)
    absolute_sigma_m: float | None = None  # refined: the map's own error, m per axis
    maneuver: bool = False  # the filter applied the measurement with its maneuver prediction
    retracted_previous: bool = False  # the filter took the previous frame's measurement out
    # following points (visloc.tracking.follower): "tracked" (posed against followed points), "predicted" (no pose
    # from its points, a relocalization under way: the filter predicted it), "relocalized" (localized in full on
    # this frame), or "full" (a run that localizes every frame in full)
    kind: str = "full"
    flow_ms: float = 0.0  # following the points into this frame
    followed_points: int = 0
    relocalize_reason: str | None = None  # why this frame asked for a full localization
    merged: str | None = None  # a background relocalization's points "joined" (or "replaced") the followed ones
    relocalization_ms: dict | None = None  # the relocalization this frame used, its cost by stage (any thread), ms
    relocalized_by: str | None = None  # ... how it was made: "full" or "guided" by the frame's tracked pose


def _latency(values: list[float]) -> dict | None:
    return summary_of(values, LATENCY_FIGURES) if len(values) else None


def _relocalizations(costs: list[dict], wall_s: float, guided: int = 0) -> dict | None:
    """Relocalizations a run that follows points made: how many (``guided`` of them guided by a tracked pose), per
    second of wall time, median cost by stage."""
    if not costs:
        return None
    return {"n": len(costs), "guided": guided, "per_s": len(costs) / wall_s if wall_s > 0 else None,
            "stages_ms": {k: float(np.median([c[k] for c in costs])) for k in costs[0]},
            "total_ms": float(np.median([sum(c.values()) for c in costs]))}


@dataclass
class TrackRun:
    queries: str
    database: str
    path: str  # "fast" or "exact"
    params: dict
    frames: list[TrackFrame] = field(default_factory=list)
    wall_s: float = 0.0
    frame_origin_deg: tuple[float, float] | None = None  # (lat, lon) of the local frame of every *_m position
    cpu_s: float = 0.0  # processor time of the whole process over the run (every thread), s
    pace_hz: float = 0.0  # frames were read at this rate (0: as fast as possible)

    def summary(self) -> dict:
        f = self.frames
        n_geometry = sum(x.measurement_source == "geometry" for x in f)
        return {
            "queries": self.queries, "database": self.database, "path": self.path, "frames": len(f),
            "latency_ms": _latency([x.latency_ms for x in f]),
            "kinds": {kind: {"frames": n, "share": n / len(f), "latency_ms": _latency([x.latency_ms for x in f
                                                                                      if x.kind == kind])}
                      for kind in sorted({x.kind for x in f}) for n in [sum(x.kind == kind for x in f)]},
            "relocalizations": _relocalizations([x.relocalization_ms for x in f if x.relocalization_ms], self.wall_s,
                                                sum(x.relocalized_by == "guided" for x in f)),
            "tracked_stages_ms": {k: float(np.median([getattr(x, k) for x in f if x.kind == "tracked"]))
                                  for k in ("flow_ms", "geometry_ms", "filter_ms")}
            if any(x.kind == "tracked" for x in f) else None,
            "cpu_s": self.cpu_s, "cpu_share_of_one_core": self.cpu_s / self.wall_s if self.wall_s > 0 else None,
            "pace_hz": self.pace_hz,
            "stages_ms": {k: float(np.median([getattr(x, k) for x in f])) if f else None
                          for k in ("sift_ms", "retrieval_ms", "geometry_ms", "filter_ms")},
            "error_m": summary_of([x.error_m for x in f], count=True),
            "measurement_error_m": summary_of([x.measurement_error_m for x in f], count=True),
            "geometry_measurement_error_m": summary_of([x.measurement_error_m for x in f
                                                       if x.measurement_source == "geometry"], count=True),
            "geometry_fraction": n_geometry / len(f) if f else None,
            "gated": sum(x.gated for x in f), "restarts": sum(x.restarted for x in f),
            "maneuvers": sum(x.maneuver for x in f), "retracted": sum(x.retracted_previous for x in f),
            "calibration": {"all": calibration([x.measurement_nees for x in f if x.measurement_source == GEOMETRY])
                            .as_dict(),
                            **{side: calibration([x.measurement_nees for x in f if x.measurement_source == GEOMETRY
                                                  and x.measurement_side == side]).as_dict() for side in SIDES}},
            "estimate_calibration": calibration([x.estimate_nees for x in f]).as_dict(),
            "wall_s": self.wall_s, "sustained_hz": len(f) / self.wall_s if self.wall_s > 0 else None,
            "params": self.params, "frame_origin_deg": self.frame_origin_deg,
        }

    def as_json(self) -> dict:
        out = self.summary()
        out["per_frame"] = [dict(x.__dict__) for x in self.frames]
        return out


def _frame_record(seq: Drive, i: int, r: StepResult, latency: float, db: GeoDatabase,
                  truths: QueryTruth) -> TrackFrame:
    fr, m = seq.frames[i], r.measurement
    truth = (fr.lat_deg, fr.lon_deg)
    truth_m = np.asarray(db.frame.to_local(*truth), float)
    extra_m2 = truth_extra_m2(m.absolute_sigma_m, truths.sigma(i), truths.shares_map_at(i))

    def error(en: np.ndarray) -> float:
        lat, lon = db.frame.to_geo(np.asarray(en, float))
        return float(geodesic_distance_m(float(lat), float(lon), *truth))

    est = r.filter.position_m
    P = np.asarray(r.filter.P, float)[:2, :2]
    m_sigma = None
    R = m.cov_m2 if m.cov_m2 is not None else r.filter.R  # the measurement's own covariance
    if m.east_north_m is not None and R is not None:
        m_sigma = float(np.sqrt(np.linalg.eigvalsh(np.asarray(R, float)).max()))
    return TrackFrame(
        frame=fr.frame, timestamp_s=fr.timestamp_s, truth_m=tuple(float(v) for v in db.frame.to_local(*truth)),
        estimate_m=(float(est[0]), float(est[1])), estimate_sigma_m=float(np.sqrt(np.linalg.eigvalsh(P).max())),
        error_m=error(est),
        measurement_m=None if m.east_north_m is None else (float(m.east_north_m[0]), float(m.east_north_m[1])),
        measurement_sigma_m=m_sigma,
        measurement_error_m=None if m.east_north_m is None else error(m.east_north_m),
        measurement_source=m.source, fallback_reason=m.fallback_reason, gated=bool(r.filter.gated),
        restarted=bool(r.filter.restarted), view_frames=tuple(int(db.images[v].frame) for v in m.view_indices),
        n_pnp_inliers=int(m.n_pnp_inliers), sift_ms=float(r.query.sift_ms), retrieval_ms=float(r.timings.retrieval_ms),
        geometry_ms=float(m.query_side_ms), filter_ms=float(r.timings.filter_ms), latency_ms=float(latency),
        estimate_cov_m2=P.tolist(),
        measurement_cov_m2=None if m_sigma is None else np.asarray(R, float).tolist(),
        measurement_nees=nees_against_truth(m.east_north_m, R if m_sigma is not None else None, truth_m, extra_m2),
        estimate_nees=nees_against_truth(est, P, truth_m, extra_m2), measurement_side=m.side, absolute_sigma_m=m.absolute_sigma_m,
        maneuver=bool(r.filter.maneuver), retracted_previous=bool(r.filter.retracted_previous))


def _stored_structure(localizer: Localizer) -> Mapping | None:
    """The store's structure the camera-rate measurer reads (view -> variant -> structure); None for the exact
    path, whose measurer keeps a cache of structure triangulated as needed instead."""
    stored = getattr(localizer.measurer, "structures", None)
    return stored if isinstance(stored, Mapping) else None  # a sharded store's reads its tiles as asked


def run_track(localizer: Localizer, seq: Drive, sift: SiftParams, db: GeoDatabase, params: TrackParams, *,
              indices: list[int] | None = None, path_params: dict | None = None,
              progress: Callable[[int, int], None] | None = None,
              cancelled: Callable[[], bool] | None = None, pose: RefinedParams | None = None) -> TrackRun:
    """Localize the frames ``indices`` of ``seq`` (default: every ``params.stride``-th) in order, from a fresh track.

    ``pose``: the refined method's settings; with ``params.follow_points`` the frames between full localizations
    follow the map's points (``visloc.tracking.follower``), else every frame is localized in full."""
    indices = list(range(0, len(seq), params.stride)) if indices is None else list(indices)
    if params.follow_points is None:  # the camera-rate path follows from frame to frame, the exact one does not
        params = params.replace(follow_points=params.fast and params.stride == 1)
    following = params.follow_points and pose is not None
    if params.pace_hz is None and not following:  # following, None reads frames as the full localizations keep up
        params = params.replace(pace_hz=0.0)
    run = TrackRun(seq.name, f"{db.source}/{db.camera}", "fast" if params.fast else "exact",
                   {"track": params.as_dict(), "query_sift": sift.as_dict(), "filter": localizer.filter_params.as_dict(),
                    **(path_params or {})},
                   frame_origin_deg=(db.frame.origin_lat_deg, db.frame.origin_lon_deg), pace_hz=params.pace_hz or 0.0)
    localizer.reset()
    truths = QueryTruth.of_drive(seq, db, (pose or REFINED).geotag_sigma_m)
    start, cpu_start = time.perf_counter(), time.process_time()
    if following:
        follower = PointFollower(localizer, db.east_north_m, db.timestamps_s, db.geometry(camera_rate=params.fast),
                                 seq.camera_model, pose, sift, params, seq.distortion,
                                 stored=_stored_structure(localizer))
        steps = follower.steps(seq, indices, cancelled=cancelled)
    else:
        steps = (FollowedStep(s.result, s.latency_ms, "full") for s in
                 steps_of(localizer, extract_queries(seq, indices, sift, paced_hz=params.pace_hz), cancelled=cancelled,
                          first=lambda m, retrieval: first_fix(m, retrieval, db.east_north_m)))
    # The camera-rate path's products are small (a frame's keypoints against a few views' structure, 3x3 and 6x6
    # covariances): with BLAS's own threads it was no faster, and their waiting between frames took 0.4-0.7 of a
    # core beside a 10 Hz run (benchmarks/track_following.py). The exact path shares its matching among threads of
    # its own, as many as BLAS has, so it keeps them. Following points, the full localizations run in a thread beside
    # the tracker: OpenCV's own threads on top of the two took a tenth of a core more at 10 Hz.
    with one_blas_thread() if params.fast else contextlib.nullcontext(), \
            one_opencv_thread() if params.fast and params.follow_points else contextlib.nullcontext():
        _record_steps(run, seq, indices, steps, db, truths, start, cpu_start, progress)
    return run


@contextlib.contextmanager
def one_opencv_thread():
    """A context in which OpenCV runs its functions on the calling thread only; the process's setting is handed back."""
    import cv2

    before = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        yield
    finally:
        cv2.setNumThreads(before)


def _record_steps(run: TrackRun, seq: Drive, indices: list[int], steps, db: GeoDatabase, truths, start: float,
                  cpu_start: float, progress: Callable[[int, int], None] | None) -> None:
    for n, (i, step) in enumerate(zip(indices, steps), 1):
        record = _frame_record(seq, i, step.result, step.latency_ms, db, truths)
        run.frames.append(replace(record, kind=step.kind, flow_ms=step.flow_ms, followed_points=step.followed_points,
                                  relocalize_reason=step.relocalize_reason, merged=step.merged,
                                  relocalization_ms=step.relocalization_ms, relocalized_by=step.relocalized_by))
        run.wall_s = time.perf_counter() - start
        run.cpu_s = time.process_time() - cpu_start
        if progress:
            progress(n, len(indices))
