"""A drive run of the camera-rate method as ``visloc track`` makes it: following points on the queries' images.

``match_drive`` measures every query from its stored features alone. A vehicle at the camera's rate does
what ``visloc track`` does instead: it reads each frame, localizes in full now and then, and poses the frames
between on the map points it follows by optical flow (``visloc.tracking.follower``). ``follow_drive`` makes
that run over a store's query series, from the series' own images (``open_series`` reads them again from
where they were stored from), and hands it back as ``DriveMatches``, so that the dashboard scrubs it and
re-runs only the filter when R, Q or P0 change, as it does a matched run.

The frames are read as ``visloc track`` reads them by default: each once the full localization asked for
before it has come, so the run is the same every time (``TrackParams.pace_hz``).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np

from visloc.errors import InputError
from visloc.features.vlad import GlobalIndex
from visloc.params import PAPER_MATCH, TRACK, FilterParams, MatchParams, RetrievalParams, SiftParams, TrackParams
from visloc.params.methods import REFINED_FAST_METHOD, Method
from visloc.pose.refined import one_blas_thread
from visloc.protocols.drive import DriveMatches
from visloc.protocols.track import one_opencv_thread
from visloc.sources.drives import Drive, default_data_root
from visloc.sources.logs import is_log
from visloc.sources.opening import open_source
from visloc.store.database import GeoDatabase, QuerySet
from visloc.tracking.follower import PointFollower
from visloc.tracking.methods import build_localizer

MAX_TIME_DIFFERENCE_S = 1e-3  # a frame of the drive read again is the stored query if their times agree this well


def open_series(path: Path | str | None, source: str, camera: str) -> Drive:
    """The images of the store's series ``source``/``camera``, read again from ``path``: a KITTI raw root that
    holds the drive (None: the data root, ``default_data_root()``), or the CSV or log it was stored from.
    ``InputError`` (one line, naming the path) when they cannot be read or are another series."""
    path = default_data_root() if path is None else Path(path)
    if is_log(path):
        drive = open_source(path, camera=camera)
    elif path.suffix.lower() == ".csv":
        drive = open_source(path)
    else:
        drive = open_source(path, drive=source, camera=camera)
    if (drive.source, drive.camera) != (source, camera):
        raise InputError(f"{path}: holds {drive.name}, not {source}/{camera}")
    return drive


def drive_indices(drive: Drive, queries: QuerySet) -> np.ndarray:
    """The index in ``drive`` of each query of ``queries``, found by frame number and time; ``InputError``
    naming the drive when one is missing or at another time (the images are not those of the store)."""
    by_frame = {f.frame: i for i, f in enumerate(drive.frames)}
    out = np.empty(len(queries.frames), np.int64)
    for k, (frame, t_s) in enumerate(zip(queries.frames, queries.timestamps_s)):
        i = by_frame.get(int(frame))
        if i is None or abs(drive.frames[i].timestamp_s - float(t_s)) > MAX_TIME_DIFFERENCE_S:
            raise InputError(f"{drive.name}: has no frame {int(frame)} at {float(t_s):.3f} s as the store's "
                             f"{queries.name} does: these images are not the ones stored")
        out[k] = i
    return out


def follows_points(method: Method, query_indices: Sequence[int]) -> bool:
    """Whether a drive run of ``method`` over ``query_indices`` follows points: the camera-rate method does, at
    the camera's own rate (every frame: points are followed from one frame to the next); below it, each query is
    localized in full."""
    indices = np.asarray(query_indices, np.int64)
    return method.camera_rate and len(indices) > 0 and bool(np.all(np.diff(indices) == 1))


def follow_drive(drive: Drive, queries: QuerySet, db: GeoDatabase, sift: SiftParams,
                 retrieval_params: RetrievalParams, query_indices: Sequence[int], *,
                 method: Method = REFINED_FAST_METHOD, match_params: MatchParams = PAPER_MATCH,
                 filter_params: FilterParams = FilterParams(), stored: dict | None = None,
                 shortlist_index: GlobalIndex | None = None, track: TrackParams = TRACK,
                 progress: Callable[[int, int], None] | None = None, cancelled: Callable[[], bool] | None = None,
                 on_step: Callable[[DriveMatches], None] | None = None) -> DriveMatches:
    """The queries ``query_indices`` of ``queries`` localized in order from ``drive``'s images (the same series:
    ``drive_indices``) by the camera-rate ``method``, following points between full localizations.

    ``sift``: the store's SIFT settings; each frame is described at ``track``'s query scale and keypoint cap,
    as ``visloc track`` describes it. ``stored`` and ``shortlist_index``: the database's stored structure and
    global vectors (``Workspace.load_structure``, ``Workspace.load_database_index``). The exclusion window is
    ``retrieval_params``'. ``progress``, ``cancelled`` and ``on_step``: as ``match_drive``'s. The measurements are
    those the follower fused; a step posed on followed points has no retrieval (``DriveMatches.kinds`` says
    how each step was measured)."""
    if not method.camera_rate:
        raise InputError(f"following points is the camera-rate method's; {method.name} measures every query in full")
    if drive.camera_model is None:
        raise InputError(f"{drive.name}: no calibration: following points needs the camera's intrinsics")
    indices = np.asarray(query_indices, np.int64)
    if not follows_points(method, indices):
        raise InputError("following points needs every frame, in order: points are followed from one frame to "
                         "the next (below the camera's rate, localize each query in full with match_drive)")
    frames = drive_indices(drive, queries)[indices]
    params = replace(track, exclusion_s=retrieval_params.exclusion_s, follow_points=True, pace_hz=None)
    localizer = build_localizer(method, db, match_params, retrieval_params, filter_params,
                                query_camera=drive.camera_model, query_what=drive.name, stored=stored,
                                shortlist_index=shortlist_index)
    localizer.reset()
    frame_sift = sift.replace(image_scale=params.query_image_scale, n_features=params.query_max_keypoints)
    follower = PointFollower(localizer, db.east_north_m, db.timestamps_s, db.geometry(camera_rate=True),
                             drive.camera_model, method.pose, frame_sift, params, drive.distortion, stored=stored)
    done: list = []

    def matches_of(steps: Sequence) -> DriveMatches:
        return DriveMatches(indices[:len(steps)], tuple(s.result.retrieval for s in steps),
                            tuple(s.result.measurement for s in steps), match_params, retrieval_params, method,
                            np.array([s.latency_ms for s in steps], float), kinds=tuple(s.kind for s in steps))

    # one BLAS and one OpenCV thread, as visloc track follows (visloc.protocols.track.run_track says why)
    with one_blas_thread(), one_opencv_thread():
        for step in follower.steps(drive, [int(i) for i in frames], cancelled=cancelled):
            done.append(step)
            if progress:
                progress(len(done), len(indices))
            if on_step:
                on_step(matches_of(done))
    return matches_of(done)
