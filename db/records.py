"""What the store holds, as plain records, and the errors it raises (no SQL here)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

KEYPOINT_COLUMNS = 6  # x_px, y_px, size_px, angle_deg, response, octave
DESCRIPTOR_DIM = 128


class StoreError(Exception):
    """Base class for every error the store raises; its message is one line."""


class NotAStoreError(StoreError):
    """The file is not SQLite, or is SQLite but not a visloc store."""


class EmptyStoreError(StoreError):
    """The store exists but holds no images (or no images of the requested camera)."""


class DamagedStoreError(StoreError):
    """A BLOB fails its checksum or its row, a table or a column the schema needs is missing: the store
    is damaged. The message names the store and the image, and how to find and repair the rest."""


class SettingsMismatchError(StoreError):
    """Features were requested or added with SIFT settings other than the store's."""


@dataclass(frozen=True)
class ImageRecord:
    """Metadata of one image, as it goes into the store."""

    source: str  # drive or dataset name, e.g. "2011_09_26_drive_0001_sync"
    camera: str  # e.g. "image_01"
    frame: int  # index of the image within (source, camera)
    path: str  # original image file, for display only; the store never reads it
    timestamp_s: float  # seconds since the Unix epoch
    lat_deg: float
    lon_deg: float
    alt_m: float | None = None
    heading_deg: float | None = None  # compass: 0 = north, clockwise
    width_px: int = 0
    height_px: int = 0
    sift_ms: float | None = None  # time SIFT took on this image when it was ingested
    # attitude of the geotag's reference frame (KITTI: the OXTS/IMU unit, x forward, y left,
    # z up), radians, as OXTS records give it: roll about x, pitch about y, yaw about z with
    # 0 = east and counter-clockwise positive. None when the source has none (CSV).
    roll_rad: float | None = None
    pitch_rad: float | None = None
    yaw_rad: float | None = None
    # stated accuracy of the geotag: standard deviation per horizontal axis, metres (KITTI: the OXTS
    # record's pos_accuracy; CSV: the accuracy_m column). None when the source states none.
    position_accuracy_m: float | None = None
    # what the features were made from: the SHA-256 (hex) of the image file's bytes and their count.
    # None in images stored before schema version 5 until ingest has read their files again.
    source_sha256: str | None = None
    source_bytes: int | None = None


@dataclass(frozen=True)
class StoredImage(ImageRecord):
    """An image row read back from the store (metadata only, no arrays)."""

    image_id: int = 0
    n_keypoints: int = 0


@dataclass(frozen=True)
class CameraRecord:
    source: str
    camera: str
    P_rect: np.ndarray | None  # (3, 4) float64, pixels
    width_px: int
    height_px: int
    T_camera_imu: np.ndarray | None = None  # (4, 4) float64, metres: X_camera = T_camera_imu @ X_imu


@dataclass(frozen=True)
class StructureRecord:
    """One database image's triangulated points, as the store keeps them.

    variant:        which neighbours it was triangulated with ("both", "before", "after")
    params_json:    the settings that made it (JSON); structure made with other settings is not used
    neighbour_ids:  image ids of those neighbours
    rows_i32:       (M,) keypoint row of the image that observes each point
    points_f64:     (M, 3) world points, metres (the engine's local frame of the image's source)
    cov_f64:        (M, 3, 3) their covariances, m^2
    reason:         why there are no points (no neighbour, no attitude, ...), None otherwise
    """

    image_id: int
    variant: str
    params_json: str
    neighbour_ids: tuple[int, ...]
    rows_i32: np.ndarray
    points_f64: np.ndarray
    cov_f64: np.ndarray
    reason: str | None = None
    build_ms: float = 0.0


@dataclass(frozen=True)
class SkippedFrame:
    """A frame that ingest left out because it could not be described, and why."""

    source: str
    camera: str
    frame: int
    path: str
    reason: str


@dataclass(frozen=True)
class SelfCheckRecord:
    """One database image posed from its neighbours as a query would be (``visloc.pose.selfcheck``).

    params_json:    the settings it was made with (JSON); a self-check made with other settings is not used
    error_*_m:      the pose minus the image's own geotag, metres east and north (None: no pose, see reason)
    cov_*_m2:       the pose's covariance without the lever term (PnP and views), m^2
    lever_m:        distance from the pose to its nearest view's geotag, metres
    side:           "both" (views before and after it) or "one"
    reason:         why there is no pose, None otherwise
    views_posed_apart: how many views the pose is the mean of (None: not recorded, a row of an older store)
    """

    image_id: int
    params_json: str
    error_east_m: float | None
    error_north_m: float | None
    cov_ee_m2: float | None
    cov_en_m2: float | None
    cov_nn_m2: float | None
    lever_m: float | None
    side: str | None
    reason: str | None = None
    views_posed_apart: int | None = None
