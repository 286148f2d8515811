"""Queries described now: read a sequence's images and run SIFT on them, timed, one at a time.

(Queries whose features were stored at ingest come from ``QuerySet.query``.)
"""

from __future__ import annotations

import time
from collections.abc import Iterable, Iterator

import cv2

from visloc.features.sift import Query, extract_sift, make_sift, undistort_keypoints
from visloc.params import SiftParams
from visloc.sources.drives import Drive, load_gray


def extract_queries(sequence: Drive, indices: Iterable[int], sift: SiftParams, *,
                    engine: "cv2.SIFT | None" = None, paced_hz: float = 0.0) -> Iterator[Query]:
    """The frames ``indices`` of ``sequence`` as queries, lazily: each image is read (not timed) and
    described by SIFT (timed: ``Query.sift_ms``) when the query is reached. Queries have no key.
    Keypoints are undistorted as ingest does when the sequence's calibration has distortion.
    ``paced_hz`` > 0: the n-th image is not read before n / paced_hz seconds from the first, as a live camera
    delivers them."""
    engine = engine or make_sift(sift)
    K = None if sequence.distortion is None else sequence.P_rect[:, :3]
    started = time.perf_counter()
    for n, i in enumerate(indices):
        if paced_hz > 0:
            time.sleep(max(0.0, started + n / paced_hz - time.perf_counter()))
        frame = sequence.frames[i]
        gray = load_gray(frame.image_path)
        t0 = time.perf_counter()
        features = extract_sift(gray, sift, sift=engine, name=str(frame.image_path))
        keypoints = undistort_keypoints(features.keypoints_f32, K, sequence.distortion)
        sift_ms = (time.perf_counter() - t0) * 1000.0
        yield Query(features.descriptors_u8, frame.timestamp_s, keypoints_f32=keypoints,
                    sift_ms=sift_ms)
