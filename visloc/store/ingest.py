"""Build or extend a store: SIFT on every image of a sequence, geotags beside the features.

Idempotent and resumable: frames already in the store are skipped, features are
committed in small batches, and an interruption (Ctrl-C) commits the images that
were finished before re-raising. A killed process loses at most the batch in
flight; SQLite's journal guarantees that no half-written image remains.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import signal
import time
from collections import deque
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, replace

import cv2
import numpy as np

from visloc.db import (CameraRecord, DamagedStoreError, EmptyStoreError, FeatureStore, ImageRecord,
                       SettingsMismatchError, SkippedFrame)
from visloc.db.blobs import repair_hint
from visloc.db.integrity import forget_damage, forget_derived, move_geotags, scan
from visloc.db.provenance import StoredSource, record_sources, replace_images, same_checksums, stored_sources
from visloc.errors import InputError
from visloc.features.sift import extract_sift, make_sift, undistort_keypoints
from visloc.sources.imagesize import DEFAULT_MAX_IMAGE_MP, check_image_size, header_size_px, require_max_image_mp
from visloc.params import SiftParams
from visloc.sources.drives import Frame, Drive, file_digest, read_image
from visloc.store.processes import stop_now, wait_or_broken

SIFT_SETTINGS_KEY = "sift"
GEOTAG_TOLERANCE_DEG = 1e-9  # about 0.1 mm: a stored geotag farther from its source's is taken again


@dataclass(frozen=True)
class IngestReport:
    source: str
    camera: str
    n_frames: int
    n_skipped: int  # already stored
    n_added: int
    seconds: float
    n_attitudes_filled: int = 0  # stored images whose missing attitude this run filled in (schema-1 stores)
    n_accuracies_filled: int = 0  # stored images whose missing geotag accuracy this run filled in (schema < 3)
    n_geotags_moved: int = 0  # stored images whose geotag the source now states otherwise (structure rebuilt)
    n_bad_skipped: int = 0  # frames the store records as skipped because they could not be described
    n_repaired: int = 0  # stored images whose BLOBs failed their checksum, described again from their files
    n_source_changed: int = 0  # stored images whose file changed since, described again
    n_sources_recorded: int = 0  # stored images from before sources were recorded, found unchanged
    n_derived_repaired: int = 0  # damaged rows of structure, global vectors or encoders, dropped to be rebuilt

    @property
    def images_per_s(self) -> float:
        """Images described per second (added, repaired or described again)."""
        described = self.n_added + self.n_repaired + self.n_source_changed
        return described / self.seconds if self.seconds > 0 else 0.0


def require_sift_settings(store: FeatureStore, params: SiftParams) -> None:
    """Record the SIFT settings in a new store; refuse a store built with others."""
    try:
        store.require_setting(SIFT_SETTINGS_KEY, params.as_dict(), what="SIFT settings")
    except SettingsMismatchError:
        raise SettingsMismatchError(_sift_difference(store, params)) from None


def check_sift_settings(store: FeatureStore, params: SiftParams) -> float | None:
    """Refuse to read features extracted with other SIFT settings (read-only check). A store built with a
    lower contrast threshold and every other setting the same (keeping every keypoint) serves a higher one:
    the returned threshold is the one to select its features at (``visloc.features.sift.contrast_kept``);
    None: read them as they are."""
    stored = store.get_setting(SIFT_SETTINGS_KEY)
    if stored is None:
        raise EmptyStoreError(f"{store.label}: no features yet (build it with 'visloc ingest')")
    if stored == params.as_dict():
        return None
    theirs = stored_sift_params(store)
    if (theirs is not None and theirs.n_features == 0
            and replace(theirs, contrast_threshold=params.contrast_threshold) == params
            and params.contrast_threshold > theirs.contrast_threshold):
        return params.contrast_threshold
    raise SettingsMismatchError(_sift_difference(store, params))


def _sift_difference(store: FeatureStore, params: SiftParams) -> str:
    """"STORE: built with other SIFT settings (name: store X, asked Y; ...)", each setting as it takes
    effect (a setting the store does not record has its default, e.g. image_scale 1.0)."""
    stored = store.get_setting(SIFT_SETTINGS_KEY)
    try:
        theirs = SiftParams(**stored).__dict__
    except (TypeError, ValueError):
        theirs = dict(stored) if isinstance(stored, dict) else {}
    ours = params.__dict__
    diffs = "; ".join(f"{k}: store {theirs.get(k)!r}, asked {ours.get(k)!r}" for k in sorted(set(ours) | set(theirs))
                      if theirs.get(k) != ours.get(k))
    return f"{store.label}: built with other SIFT settings ({diffs})"


def stored_sift_params(store: FeatureStore) -> SiftParams | None:
    stored = store.get_setting(SIFT_SETTINGS_KEY)
    return None if stored is None else SiftParams(**stored)


_worker_sift = None
_worker_sift_params: SiftParams | None = None


def _init_worker(params: SiftParams, single_thread: bool = True) -> None:
    global _worker_sift, _worker_sift_params
    if single_thread:
        cv2.setNumThreads(1)  # in worker processes: parallelism comes from the processes
        signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the main process's to handle
    _worker_sift, _worker_sift_params = make_sift(params), params


def _extract_on_cluster(item: "WorkItem") -> "Extracted | InputError":
    """``_extract_frame`` in a worker of a distributed engine: the detector is made at its first task
    (and again if the settings change), with the OpenCV threads the engine gave the worker. A frame
    that cannot be described gives back the ``InputError`` saying why (a result, not a failed task)."""
    global _worker_sift, _worker_sift_params
    if _worker_sift is None or _worker_sift_params != item[1]:
        _worker_sift, _worker_sift_params = make_sift(item[1]), item[1]
    try:
        return _extract_frame(item)
    except InputError as exc:
        return exc


# one work item: the frame, the SIFT settings, the pinhole K (3x3) and distortion coefficients to
# undistort its keypoints with (None, None: stored as detected), the size the calibration states
# (None: any), and the image size limit in megapixels
WorkItem = tuple[Frame, SiftParams, np.ndarray | None, np.ndarray | None, tuple[int, int] | None, float]
Extracted = tuple[Frame, np.ndarray, np.ndarray, float, tuple[int, int], tuple[str, int]]


def _extract_frame(item: WorkItem) -> Extracted:
    """SIFT of one frame; ``InputError`` naming the frame's file when it cannot be described."""
    frame, params, K, distortion, calibrated_size, max_image_mp = item
    check_image_size(frame.image_path, header_size_px(frame.image_path), max_image_mp)
    gray, sha256, n_bytes = read_image(frame.image_path)
    size = (gray.shape[1], gray.shape[0])
    check_image_size(frame.image_path, size, max_image_mp)
    if calibrated_size is not None and size != tuple(calibrated_size):
        raise InputError(f"{frame.image_path}: image is {size[0]}x{size[1]} px but the calibration is for "
                         f"{calibrated_size[0]}x{calibrated_size[1]}")
    start = time.perf_counter()
    features = extract_sift(gray, params, sift=_worker_sift, name=str(frame.image_path))
    sift_ms = (time.perf_counter() - start) * 1000.0
    keypoints = features.keypoints_f32 if distortion is None else undistort_keypoints(features.keypoints_f32, K,
                                                                                       distortion)
    return frame, keypoints, features.descriptors_u8, sift_ms, size, (sha256, n_bytes)


def _undistortion(sequence: Drive) -> tuple[np.ndarray | None, np.ndarray | None]:
    if sequence.distortion is None:
        return None, None
    if sequence.P_rect is None:
        raise InputError(f"{sequence.name}: distortion coefficients without intrinsics (P_rect)")
    return np.asarray(sequence.P_rect, float)[:, :3], np.asarray(sequence.distortion, float)


class WorkerDiedError(InputError):
    """A SIFT worker process ended without a result (killed, or out of memory)."""


def _extracted(todo: list[Frame], params: SiftParams, workers: int, sequence: Drive,
               max_image_mp: float, cluster=None) -> Iterator[tuple[Frame, Extracted | InputError]]:
    """(frame, its extraction or the ``InputError`` that says why it has none), in ``todo``'s order.

    With several workers, at most two frames per worker are in flight, and a worker that dies ends
    the iteration with ``WorkerDiedError`` instead of waiting for a result that never comes.
    ``cluster``: a client of a distributed engine (``visloc.store.cluster``) whose workers describe the
    frames instead; a worker that dies there has its frames described again by another.
    """
    K, distortion = _undistortion(sequence)
    items = [(f, params, K, distortion, sequence.image_size_px, max_image_mp) for f in todo]
    if cluster is not None:
        yield from cluster.extracted(_extract_on_cluster, items, sequence.name)
        return
    if workers <= 1 or len(todo) <= 1:
        _init_worker(params, single_thread=False)  # in this process: leave OpenCV's threading alone
        for item in items:
            try:
                yield item[0], _extract_frame(item)
            except InputError as exc:
                yield item[0], exc
        return
    ctx = mp.get_context("spawn")  # fork after OpenCV has started threads can deadlock
    pool = ProcessPoolExecutor(workers, mp_context=ctx, initializer=_init_worker, initargs=(params,))
    in_flight: deque[tuple[Frame, Future]] = deque()
    pending = iter(items)
    def died(frame: Frame) -> WorkerDiedError:
        return WorkerDiedError(
            f"{sequence.name}: a SIFT worker process died (killed, or out of memory) while describing "
            f"{frame.image_path} or a frame after it; the images finished before are stored. Run the same "
            "command again to go on; if memory is short, lower --workers or --max-image-mp")

    refused: Frame | None = None  # the first frame the pool refused: a worker had died before it was handed out
    try:
        while True:
            while refused is None and len(in_flight) < 2 * workers and (item := next(pending, None)) is not None:
                try:
                    in_flight.append((item[0], pool.submit(_extract_frame, item)))
                except BrokenProcessPool:  # the frames in flight come back first, then this one is said
                    refused = item[0]
            if not in_flight:
                if refused is not None:
                    raise died(refused)
                break
            frame, future = in_flight.popleft()
            try:
                wait_or_broken(pool, {future})
                yield frame, future.result()
            except InputError as exc:
                yield frame, exc
            except BrokenProcessPool:
                raise died(frame) from None
    except BaseException:  # a worker died, an error, an interruption: the frames in flight are not waited for
        stop_now(pool)
        raise
    pool.shutdown(wait=True)


def ingest(
    store: FeatureStore,
    sequence: Drive,
    params: SiftParams,
    *,
    workers: int | None = None,
    batch_size: int = 8,
    progress: Callable[[int, int], None] | None = None,
    limit: int | None = None,
    skip_bad_frames: bool = False,
    max_image_mp: float = DEFAULT_MAX_IMAGE_MP,
    repair: bool = False,
    cluster=None,
) -> IngestReport:
    """Add every frame of ``sequence`` missing from ``store``. ``progress(done, total)`` is told of
    the start (0 done) and of each image done.

    A frame that cannot be described (unreadable, too large, of another size than the calibration,
    no keypoints) stops the ingest with an ``InputError`` naming it, keeping every image finished
    before; with ``skip_bad_frames`` it is recorded in the store as skipped, with the reason, and the
    ingest goes on. A frame recorded as skipped by an earlier run is tried again and, if still bad,
    skipped again. ``limit`` stops after that many new images (for sampling and tests).

    A stored frame whose image file changed since (or that was stored before files were recorded and
    now describes otherwise) is described again, in place. A stored frame whose features fail their
    checksum is described again with ``repair`` (and the damaged structure, global vectors and encoders
    of the camera dropped, for the build steps to make again); without it, the first damage found
    stops the ingest with a ``DamagedStoreError`` naming it.
    """
    start = time.perf_counter()
    max_image_mp = require_max_image_mp(max_image_mp)
    require_sift_settings(store, params)
    _refuse_mixed_undistortion(store, sequence)
    stored = stored_sources(store, sequence.source, sequence.camera)
    redo = _stale(store, sequence, stored, repair)
    skipped_before = {f.frame for f in store.skipped_frames(sequence.source, sequence.camera)}
    missing = [f for f in sequence.frames if f.frame not in stored]
    todo = [f for f in sequence.frames if f.frame in redo.frames] + (missing if limit is None else missing[:limit])
    workers = workers or min(os.cpu_count() or 1, 8)
    pending: list[tuple[ImageRecord, np.ndarray, np.ndarray]] = []
    replacing: list[tuple[ImageRecord, np.ndarray, np.ndarray]] = []
    added, bad, recorded, differed = 0, [], {}, 0
    size_px = sequence.image_size_px
    if progress:
        progress(0, len(todo))
    try:
        for done, (frame, result) in enumerate(_extracted(todo, params, workers, sequence, max_image_mp, cluster), 1):
            if isinstance(result, InputError):
                if not (skip_bad_frames or frame.frame in skipped_before) or frame.frame in stored:
                    raise InputError(f"{result} (frame {frame.frame} of {sequence.name}); the images before it "
                                     "are stored. Fix or remove that frame, or ingest with --skip-bad-frames to "
                                     "skip such frames (the store records which)") from None
                bad.append(SkippedFrame(sequence.source, sequence.camera, frame.frame, str(frame.image_path),
                                        str(result)))
            else:
                _, keypoints, descriptors, sift_ms, size_px, (sha256, n_bytes) = result
                record = ImageRecord(
                    source=sequence.source, camera=sequence.camera, frame=frame.frame, path=str(frame.image_path),
                    timestamp_s=frame.timestamp_s, lat_deg=frame.lat_deg, lon_deg=frame.lon_deg,
                    alt_m=frame.alt_m, heading_deg=frame.heading_deg, width_px=size_px[0], height_px=size_px[1],
                    sift_ms=sift_ms, roll_rad=frame.roll_rad, pitch_rad=frame.pitch_rad, yaw_rad=frame.yaw_rad,
                    position_accuracy_m=frame.position_accuracy_m, source_sha256=sha256, source_bytes=n_bytes,
                )
                if frame.frame not in stored:
                    pending.append((record, keypoints, descriptors))
                elif frame.frame in redo.unrecorded and _same_features(store, stored[frame.frame].image_id,
                                                                       keypoints, descriptors):
                    recorded[frame.frame] = (sha256, n_bytes)
                else:
                    differed += frame.frame in redo.unrecorded
                    # a repair that gives back the very bytes first written leaves what was made from them
                    restored = frame.frame in redo.damaged and same_checksums(stored[frame.frame], keypoints,
                                                                              descriptors)
                    replacing.append((record, keypoints, descriptors, restored))
            if len(pending) >= batch_size or (bad and not pending):
                added += store.add_images(pending, skipped=bad)
                pending, bad = [], []
            if len(replacing) >= batch_size:
                _replace(store, sequence, replacing)
                replacing = []
            if progress:
                progress(done, len(todo))
    finally:
        # Commit what finished, also on Ctrl-C, on a bad image further on or on a dead worker.
        if pending or bad:
            added += store.add_images(pending, skipped=bad)
        if replacing:
            _replace(store, sequence, replacing)
        if recorded:
            record_sources(store, sequence.source, sequence.camera, recorded)
        if size_px is not None and (added or redo.frames or store.get_camera(sequence.source, sequence.camera) is None):
            store.set_camera(CameraRecord(sequence.source, sequence.camera, sequence.P_rect, *size_px,
                                          T_camera_imu=sequence.T_camera_imu))
    filled = backfill_poses(store, sequence)
    geotags_moved = backfill_geotags(store, sequence)
    n_skipped_bad = len(store.skipped_frames(sequence.source, sequence.camera))
    return IngestReport(sequence.source, sequence.camera, len(sequence), len(sequence) - len(missing), added,
                        time.perf_counter() - start, n_attitudes_filled=filled,
                        n_accuracies_filled=backfill_accuracies(store, sequence), n_bad_skipped=n_skipped_bad,
                        n_repaired=len(redo.damaged), n_source_changed=len(redo.changed) + differed,
                        n_sources_recorded=len(recorded), n_derived_repaired=redo.n_derived,
                        n_geotags_moved=geotags_moved)


@dataclass(frozen=True)
class _Stale:
    """Stored frames of a sequence to describe again: ``damaged`` (their BLOBs fail), ``changed``
    (their file is not the one they were made from), ``unrecorded`` (stored before files were
    recorded: described again and compared). ``n_derived``: damaged derived rows dropped."""

    damaged: frozenset[int]
    changed: frozenset[int]
    unrecorded: frozenset[int]
    n_derived: int

    @property
    def frames(self) -> frozenset[int]:
        return self.damaged | self.changed | self.unrecorded


def _stale(store: FeatureStore, sequence: Drive, stored: dict[int, StoredSource], repair: bool) -> _Stale:
    """Which stored frames of ``sequence`` must be described again; damaged structure, global vectors
    and encoders of its camera are dropped here (the build steps make them again)."""
    damage = list(scan(store, source=sequence.source, camera=sequence.camera))
    if damage and not repair:
        raise DamagedStoreError(f"{store.label}: {damage[0].image}: {damage[0].problem}; {repair_hint(store.label)}")
    derived = [d for d in damage if d.table != "images"]
    if derived:
        forget_damage(store, derived)
    damaged = {d.frame for d in damage if d.table == "images"}
    changed, unrecorded = set(), set()
    for f in sequence.frames:
        if f.frame not in stored or f.frame in damaged:
            continue
        known = stored[f.frame]
        if known.source_sha256 is None:
            unrecorded.add(f.frame)
        elif file_digest(f.image_path) not in (None, (known.source_sha256, known.source_bytes)):
            changed.add(f.frame)
    in_sequence = {f.frame for f in sequence.frames}
    return _Stale(frozenset(damaged & in_sequence), frozenset(changed), frozenset(unrecorded), len(derived))


def _same_features(store: FeatureStore, image_id: int, keypoints: np.ndarray, descriptors: np.ndarray) -> bool:
    stored_keypoints, stored_descriptors = store.features([image_id])[image_id]
    return (np.array_equal(stored_descriptors, descriptors)
            and np.array_equal(stored_keypoints, np.asarray(keypoints, np.float32)))


def _replace(store: FeatureStore, sequence: Drive, batch: list) -> None:
    """Replace stored images in place; drop what was made from those not ``restored`` to their first bytes."""
    ids = replace_images(store, [(record, keypoints, descriptors) for record, keypoints, descriptors, _ in batch])
    changed = [image_id for image_id, (*_, restored) in zip(ids, batch) if not restored]
    forget_derived(store, sequence.source, sequence.camera, changed)


def _refuse_mixed_undistortion(store: FeatureStore, sequence: Drive) -> None:
    """Keypoints stored without calibration were not undistorted: refuse to add undistorted ones beside
    them (or to give them a pinhole calibration they do not fit)."""
    if sequence.distortion is None:
        return
    camera = store.get_camera(sequence.source, sequence.camera)
    if camera is not None and camera.P_rect is None and store.stored_frames(sequence.source, sequence.camera):
        raise InputError(f"{store.label}: {sequence.name} was stored without calibration, so its keypoints are "
                         "not undistorted; ingest it into a new store to use the calibration's distortion")


def backfill_accuracies(store: FeatureStore, sequence: Drive) -> int:
    """Fill the stated geotag accuracy that a store built before schema version 3 lacks, from
    ``sequence``, and forget one the source no longer states (an OXTS record KITTI filled in, whose
    accuracy was once read as stated); features are untouched. Returns the number of images changed."""
    lacking = store.frames_without_accuracy(sequence.source, sequence.camera)
    accuracies = {f.frame: f.position_accuracy_m for f in sequence.frames
                  if f.frame in lacking and f.position_accuracy_m is not None}
    # a frame the store does not hold changes no row
    accuracies.update({f.frame: None for f in sequence.frames
                       if f.position_accuracy_m is None and f.frame not in lacking})
    return store.set_position_accuracies(sequence.source, sequence.camera, accuracies) if accuracies else 0


def backfill_geotags(store: FeatureStore, sequence: Drive) -> int:
    """Take the geotags ``sequence`` states for stored frames where they differ from the stored ones by more than
    ``GEOTAG_TOLERANCE_DEG`` (a KITTI drive stored before its geotags were taken at the image's time); the
    camera's structure and self-checks, made at the old geotags, are dropped for the build steps to make again.
    Features are untouched. Returns the number of images whose geotag changed."""
    stored = {im.frame: (im.lat_deg, im.lon_deg) for im in store.images(sequence.source, sequence.camera)}
    moved = {f.frame: (f.lat_deg, f.lon_deg) for f in sequence.frames if f.frame in stored
             and max(abs(f.lat_deg - stored[f.frame][0]), abs(f.lon_deg - stored[f.frame][1])) > GEOTAG_TOLERANCE_DEG}
    return move_geotags(store, sequence.source, sequence.camera, moved)


def backfill_poses(store: FeatureStore, sequence: Drive) -> int:
    """Fill attitudes and camera extrinsics that a store built before schema version 2 lacks (or that a
    CSV drive gained since it was stored).

    Reads them from ``sequence`` (the OXTS records and calibration files); features are
    untouched. Returns the number of images whose attitude was filled.
    """
    camera = store.get_camera(sequence.source, sequence.camera)
    if camera is not None and camera.T_camera_imu is None and sequence.T_camera_imu is not None:
        store.set_camera(replace(camera, T_camera_imu=sequence.T_camera_imu,
                                 P_rect=camera.P_rect if camera.P_rect is not None else sequence.P_rect))
    lacking = store.frames_without_attitude(sequence.source, sequence.camera)
    attitudes = {f.frame: (f.roll_rad, f.pitch_rad, f.yaw_rad) for f in sequence.frames
                 if f.frame in lacking and None not in (f.roll_rad, f.pitch_rad, f.yaw_rad)}
    return store.set_attitudes(sequence.source, sequence.camera, attitudes) if attitudes else 0
