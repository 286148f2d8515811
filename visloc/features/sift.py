"""SIFT extraction (OpenCV), as pure functions over images held in numpy arrays, and a query
image's features as the localizer sees them (``Query``)."""

from __future__ import annotations

from collections.abc import Hashable
from dataclasses import dataclass, replace

import cv2
import numpy as np

from visloc.errors import InputError
from visloc.params import SiftParams

# visloc names an image it cannot decode in its own one-line error: OpenCV's decoder warnings on
# stderr ("IHDR chunk shall be first", ...) would only add lines to it
cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)  # failures raise or return None

KEYPOINT_COLUMNS = ("x_px", "y_px", "size_px", "angle_deg", "response", "octave")


@dataclass(frozen=True)
class Features:
    """SIFT features of one image.

    keypoints_f32:  (N, 6) float32, columns ``KEYPOINT_COLUMNS``.
    descriptors_u8: (N, 128) uint8. OpenCV's SIFT descriptors are whole numbers
                    0..255, so uint8 holds them exactly.
    """

    keypoints_f32: np.ndarray
    descriptors_u8: np.ndarray

    def __len__(self) -> int:
        return int(self.descriptors_u8.shape[0])

    @property
    def xy_px(self) -> np.ndarray:
        return self.keypoints_f32[:, :2]


@dataclass(frozen=True)
class Query:
    """One query image as the localizer sees it: its features and time, never its geotag.

    key:       identifies the image for caches (e.g. its store id); None when it has none.
    keypoints_f32: (N, 6) or (N, 2), pixel x, y first; the refined measurement needs them.
    sift_ms:   time its SIFT features took (measured now, or at ingest), ms; part of its latency.
    """

    descriptors_u8: np.ndarray  # (N, 128)
    timestamp_s: float
    key: Hashable = None
    keypoints_f32: np.ndarray | None = None
    sift_ms: float = 0.0


def make_sift(params: SiftParams) -> "cv2.SIFT":
    # Every argument by keyword: positionally, descriptorType lands in the wrong slot.
    return cv2.SIFT_create(
        nfeatures=params.n_features,
        nOctaveLayers=params.n_octave_layers,
        contrastThreshold=params.contrast_threshold,
        edgeThreshold=params.edge_threshold,
        sigma=params.sigma,
        descriptorType=cv2.CV_8U,
    )


def extract_sift(gray_u8: np.ndarray, params: SiftParams, *, sift: "cv2.SIFT | None" = None,
                 name: str = "image") -> Features:
    """SIFT keypoints and descriptors of a 2-D uint8 image.

    ``name`` only labels errors. Raises ``InputError`` when the image has no
    keypoints at all (blank, black or saturated).
    """
    if gray_u8.ndim != 2 or gray_u8.dtype != np.uint8:
        raise InputError(f"{name}: expected a 2-D uint8 gray image, got {gray_u8.dtype} {gray_u8.shape}")
    features = _detect_and_describe(gray_u8, params, sift or make_sift(params), None)
    if not len(features):
        raise InputError(f"{name}: no SIFT keypoints found (blank or featureless image)")
    return features


def _scaled(gray_u8: np.ndarray, scale: float) -> np.ndarray:
    """The image SIFT runs on: resized by ``scale`` (area interpolation), as it is at 1."""
    return gray_u8 if scale == 1.0 else cv2.resize(gray_u8, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)


def _detect_and_describe(gray_u8: np.ndarray, params: SiftParams, sift: "cv2.SIFT",
                         near: tuple[np.ndarray, float] | None) -> Features:
    """SIFT on the image at ``params.image_scale``, keypoints mapped back to full-resolution pixels; ``near``:
    (pixels (M, 2), radius px), only the keypoints within the radius of one of them are kept, and described (None:
    every keypoint). Empty when none is found."""
    scale = params.image_scale
    image = _scaled(gray_u8, scale)
    mask = None
    if near is not None:
        mask = np.zeros(image.shape[:2], np.uint8)
        centres = np.round((np.asarray(near[0], float).reshape(-1, 2) + 0.5) * scale - 0.5).astype(np.int32)
        inside = ((centres >= 0) & (centres < [image.shape[1], image.shape[0]])).all(axis=1)
        mask[centres[inside, 1], centres[inside, 0]] = 255
        side = 2 * max(1, int(np.ceil(near[1] * scale))) + 1
        mask = cv2.dilate(mask, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (side, side)))
    keypoints, descriptors = sift.detectAndCompute(image, mask)  # the mask drops keypoints before they are described
    if not keypoints:
        return Features(np.zeros((0, 6), np.float32), np.zeros((0, 128), np.uint8))
    kp = np.array(
        [(k.pt[0], k.pt[1], k.size, k.angle, k.response, k.octave) for k in keypoints], dtype=np.float32
    )
    if scale != 1.0:
        # pixel centres: x_full + 0.5 = (x_scaled + 0.5) / scale
        kp[:, :2] = (kp[:, :2] + 0.5) / scale - 0.5
        kp[:, 2] /= scale
    return Features(keypoints_f32=kp, descriptors_u8=np.ascontiguousarray(descriptors, dtype=np.uint8))


def sift_near(gray_u8: np.ndarray, params: SiftParams, near_xy_px: np.ndarray, radius_px: float, *,
              sift: "cv2.SIFT | None" = None) -> Features:
    """SIFT keypoints of a 2-D uint8 image that lie within ``radius_px`` of one of ``near_xy_px`` ((M, 2) pixels of
    the image as it is), with their descriptors: where a pose says the map's points should be seen. SIFT detects
    over the whole image (``params.image_scale`` as ``extract_sift``), but describes only the keypoints near those
    pixels, every one of them (no ``n_features`` cap: the cap keeps the strongest over the whole image, and a
    keypoint away from the map's points serves nothing here). Empty when none is found."""
    return _detect_and_describe(gray_u8, params, sift or make_sift(params.replace(n_features=0)),
                                (near_xy_px, radius_px))


def contrast_kept(keypoints_f32: np.ndarray, contrast_threshold: float, n_octave_layers: int) -> np.ndarray:
    """(N,) bool: which of these keypoints (N, 6), found with a lower contrast threshold, SIFT would have kept
    at ``contrast_threshold``. OpenCV drops an extremum whose contrast (the keypoint's ``response``) times the
    layers per octave falls below the threshold; a lower threshold only adds keypoints (a few, out of
    thousands, whose unrefined extremum the higher one would have skipped before refining it)."""
    response = np.asarray(keypoints_f32, np.float64)[:, 4]
    return response * int(n_octave_layers) >= float(contrast_threshold)


def at_contrast_threshold(keypoints_f32: np.ndarray, descriptors_u8: np.ndarray, contrast_threshold: float | None,
                          n_octave_layers: int) -> tuple[np.ndarray, np.ndarray]:
    """One image's keypoints and descriptors that SIFT keeps at ``contrast_threshold`` (``contrast_kept``); all
    of them when it is None."""
    if contrast_threshold is None:
        return keypoints_f32, descriptors_u8
    kept = contrast_kept(keypoints_f32, contrast_threshold, n_octave_layers)
    return keypoints_f32[kept], descriptors_u8[kept]


def at_contrast(query: Query, contrast_threshold: float, n_octave_layers: int) -> Query:
    """``query`` with only the features SIFT keeps at ``contrast_threshold``; as it is when its keypoints do not
    say their response."""
    keypoints = query.keypoints_f32
    if keypoints is None or keypoints.ndim != 2 or keypoints.shape[1] < 5:
        return query
    keypoints, descriptors = at_contrast_threshold(keypoints, query.descriptors_u8, contrast_threshold,
                                                   n_octave_layers)
    return replace(query, descriptors_u8=descriptors, keypoints_f32=keypoints)


def undistort_keypoints(keypoints_f32: np.ndarray, K: np.ndarray, distortion: np.ndarray | None) -> np.ndarray:
    """Keypoints (N, 6) with x, y moved from the distorted image to the pinhole camera ``K`` (3x3, pixels)
    by OpenCV's iterative undistortion (``distortion``: OpenCV's coefficients); the other columns are
    kept. ``distortion`` None: returned unchanged."""
    if distortion is None or len(keypoints_f32) == 0:
        return keypoints_f32
    K = np.asarray(K, np.float64)
    xy = np.ascontiguousarray(keypoints_f32[:, :2], dtype=np.float64).reshape(-1, 1, 2)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-10)
    undistorted = cv2.undistortPoints(xy, cameraMatrix=K, distCoeffs=np.asarray(distortion, np.float64), P=K,
                                      criteria=criteria)
    out = np.array(keypoints_f32, dtype=np.float32, copy=True)
    out[:, :2] = undistorted.reshape(-1, 2)
    return out


def to_gray_u8(image: np.ndarray, *, name: str = "image") -> np.ndarray:
    """Gray uint8 from a gray, BGR or BGRA image (8 or 16 bit)."""
    if image.dtype == np.uint16:
        image = (image >> 8).astype(np.uint8)
    if image.dtype != np.uint8:
        raise InputError(f"{name}: unsupported pixel type {image.dtype}")
    if image.ndim == 2:
        return image
    if image.ndim == 3 and image.shape[2] == 3:
        return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if image.ndim == 3 and image.shape[2] == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2GRAY)
    raise InputError(f"{name}: unsupported image shape {image.shape}")

