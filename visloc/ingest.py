"""Build or extend a store: SIFT on every image of a sequence, geotags beside the features.

Idempotent and resumable: frames already in the store are skipped, features are
committed in small batches, and an interruption (Ctrl-C) commits the images that
were finished before re-raising. A killed process loses at most the batch in
flight; SQLite's journal guarantees that no half-written image remains.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace

import cv2
import numpy as np

from visloc.db import CameraRecord, EmptyStoreError, FeatureStore, ImageRecord
from visloc.errors import InputError
from visloc.features import extract_sift, make_sift, undistort_keypoints
from visloc.params import SiftParams
from visloc.sources import Frame, Sequence, load_gray

SIFT_SETTINGS_KEY = "sift"


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

    @property
    def images_per_s(self) -> float:
        return self.n_added / self.seconds if self.seconds > 0 else 0.0


def require_sift_settings(store: FeatureStore, params: SiftParams) -> None:
    """Record the SIFT settings in a new store; refuse a store built with others."""
    store.require_setting(SIFT_SETTINGS_KEY, params.as_dict(), what="SIFT settings")


def check_sift_settings(store: FeatureStore, params: SiftParams) -> None:
    """Refuse to read features extracted with other SIFT settings (read-only check)."""
    stored = store.get_setting(SIFT_SETTINGS_KEY)
    if stored is None:
        raise EmptyStoreError(f"{store.label}: no features yet (build it with 'visloc ingest')")
    if stored != params.as_dict():
        store.require_setting(SIFT_SETTINGS_KEY, params.as_dict(), what="SIFT settings")  # raises, naming the diff


def stored_sift_params(store: FeatureStore) -> SiftParams | None:
    stored = store.get_setting(SIFT_SETTINGS_KEY)
    return None if stored is None else SiftParams(**stored)


_worker_sift = None


def _init_worker(params: SiftParams, single_thread: bool = True) -> None:
    global _worker_sift
    if single_thread:
        cv2.setNumThreads(1)  # in worker processes: parallelism comes from the processes
    _worker_sift = make_sift(params)


# one work item: the frame, the SIFT settings, and the pinhole K (3x3) and distortion coefficients to
# undistort its keypoints with (None, None: stored as detected)
WorkItem = tuple[Frame, SiftParams, np.ndarray | None, np.ndarray | None]


def _extract_frame(item: WorkItem) -> tuple[Frame, np.ndarray, np.ndarray, float, tuple[int, int]]:
    frame, params, K, distortion = item
    gray = load_gray(frame.image_path)
    start = time.perf_counter()
    features = extract_sift(gray, params, sift=_worker_sift, name=str(frame.image_path))
    sift_ms = (time.perf_counter() - start) * 1000.0
    keypoints = features.keypoints_f32 if distortion is None else undistort_keypoints(features.keypoints_f32, K,
                                                                                       distortion)
    return frame, keypoints, features.descriptors_u8, sift_ms, (gray.shape[1], gray.shape[0])


def _undistortion(sequence: Sequence) -> tuple[np.ndarray | None, np.ndarray | None]:
    if sequence.distortion is None:
        return None, None
    if sequence.P_rect is None:
        raise InputError(f"{sequence.name}: distortion coefficients without intrinsics (P_rect)")
    return np.asarray(sequence.P_rect, float)[:, :3], np.asarray(sequence.distortion, float)


def _extracted(todo: list[Frame], params: SiftParams, workers: int, sequence: Sequence) -> Iterator[tuple]:
    K, distortion = _undistortion(sequence)
    items = [(f, params, K, distortion) for f in todo]
    if workers <= 1 or len(todo) <= 1:
        _init_worker(params, single_thread=False)  # in this process: leave OpenCV's threading alone
        yield from map(_extract_frame, items)
        return
    ctx = mp.get_context("spawn")  # fork after OpenCV has started threads can deadlock
    with ctx.Pool(workers, initializer=_init_worker, initargs=(params,)) as pool:
        yield from pool.imap(_extract_frame, items, chunksize=1)


def ingest(
    store: FeatureStore,
    sequence: Sequence,
    params: SiftParams,
    *,
    workers: int | None = None,
    batch_size: int = 8,
    progress: Callable[[int, int], None] | None = None,
    limit: int | None = None,
) -> IngestReport:
    """Add every frame of ``sequence`` missing from ``store``. ``progress(done, total)`` is told of
    the start (0 done) and of each image done.

    ``limit`` stops after that many new images (for sampling and tests).
    """
    start = time.perf_counter()
    require_sift_settings(store, params)
    _refuse_mixed_undistortion(store, sequence)
    stored = store.stored_frames(sequence.source, sequence.camera)
    missing = [f for f in sequence.frames if f.frame not in stored]
    todo = missing if limit is None else missing[:limit]
    workers = workers or min(os.cpu_count() or 1, 8)
    pending: list[tuple[ImageRecord, np.ndarray, np.ndarray]] = []
    added = 0
    size_px = sequence.image_size_px
    if progress:
        progress(0, len(todo))
    try:
        for done, (frame, keypoints, descriptors, sift_ms, size) in enumerate(
                _extracted(todo, params, workers, sequence), 1):
            if sequence.image_size_px is not None and tuple(size) != tuple(sequence.image_size_px):
                raise InputError(f"{frame.image_path}: image is {size[0]}x{size[1]} px but the calibration of "
                                 f"{sequence.name} is for {sequence.image_size_px[0]}x{sequence.image_size_px[1]}")
            size_px = size
            record = ImageRecord(
                source=sequence.source, camera=sequence.camera, frame=frame.frame, path=str(frame.image_path),
                timestamp_s=frame.timestamp_s, lat_deg=frame.lat_deg, lon_deg=frame.lon_deg, alt_m=frame.alt_m,
                heading_deg=frame.heading_deg, width_px=size_px[0], height_px=size_px[1], sift_ms=sift_ms,
                roll_rad=frame.roll_rad, pitch_rad=frame.pitch_rad, yaw_rad=frame.yaw_rad,
                position_accuracy_m=frame.position_accuracy_m,
            )
            pending.append((record, keypoints, descriptors))
            if len(pending) >= batch_size:
                added += store.add_images(pending)
                pending = []
            if progress:
                progress(done, len(todo))
    finally:
        # Commit what finished, also on Ctrl-C or on a bad image further on.
        if pending:
            added += store.add_images(pending)
        if size_px is not None and (added or store.get_camera(sequence.source, sequence.camera) is None):
            store.set_camera(CameraRecord(sequence.source, sequence.camera, sequence.P_rect, *size_px,
                                          T_camera_imu=sequence.T_camera_imu))
    filled = backfill_poses(store, sequence)
    return IngestReport(sequence.source, sequence.camera, len(sequence), len(sequence) - len(missing), added,
                        time.perf_counter() - start, n_attitudes_filled=filled,
                        n_accuracies_filled=backfill_accuracies(store, sequence))


def _refuse_mixed_undistortion(store: FeatureStore, sequence: Sequence) -> None:
    """Keypoints stored without calibration were not undistorted: refuse to add undistorted ones beside
    them (or to give them a pinhole calibration they do not fit)."""
    if sequence.distortion is None:
        return
    camera = store.get_camera(sequence.source, sequence.camera)
    if camera is not None and camera.P_rect is None and store.stored_frames(sequence.source, sequence.camera):
        raise InputError(f"{store.label}: {sequence.name} was stored without calibration, so its keypoints are "
                         "not undistorted; ingest it into a new store to use the calibration's distortion")


def backfill_accuracies(store: FeatureStore, sequence: Sequence) -> int:
    """Fill the stated geotag accuracy that a store built before schema version 3 lacks, from
    ``sequence``; features are untouched. Returns the number of images filled."""
    lacking = store.frames_without_accuracy(sequence.source, sequence.camera)
    accuracies = {f.frame: f.position_accuracy_m for f in sequence.frames
                  if f.frame in lacking and f.position_accuracy_m is not None}
    return store.set_position_accuracies(sequence.source, sequence.camera, accuracies) if accuracies else 0


def backfill_poses(store: FeatureStore, sequence: Sequence) -> int:
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
