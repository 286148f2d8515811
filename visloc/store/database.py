"""A geotagged database and a set of queries, as arrays for the engine (``visloc.store.workspace`` loads them)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from visloc.db import CameraRecord, StoredImage
from visloc.features.sift import Query, at_contrast_threshold
from visloc.geometry.bundle import heading_spread_rad
from visloc.geo import LocalFrame
from visloc.geometry.projective import CameraModel, imu_poses, invert
from visloc.pose.uncertainty import LeverGain
from visloc.pose.viewpose import DatabaseGeometry


@dataclass(frozen=True)
class GeoDatabase:
    """Images of one (source, camera) in time order, with features and positions.

    ``frame`` is the local metric frame: origin at the first image's geotag. ``up_m``
    is altitude minus the first image's (NaN when unknown); ``rpy_rad`` (N, 3) the
    attitude of each geotag's reference frame (NaN when unknown, e.g. a schema-1 store
    or a CSV without attitude columns); ``geotag_sigma_m`` (N,) each geotag's stated accuracy,
    the standard deviation per horizontal axis in metres (NaN when the source states none).
    """

    source: str
    camera: str
    images: tuple[StoredImage, ...]
    timestamps_s: np.ndarray  # (N,)
    lat_deg: np.ndarray  # (N,)
    lon_deg: np.ndarray  # (N,)
    east_north_m: np.ndarray  # (N, 2)
    keypoints_f32: Sequence[np.ndarray]  # a tuple, or read from a sharded store's tiles when asked for
    descriptors_u8: Sequence[np.ndarray]
    calibration: CameraRecord | None
    frame: LocalFrame
    up_m: np.ndarray | None = None  # (N,)
    rpy_rad: np.ndarray | None = None  # (N, 3)
    geotag_sigma_m: np.ndarray | None = None  # (N,) stated geotag accuracy, sigma per axis, m; NaN if unknown
    lever_gain: LeverGain | None = None  # measured by the store's self-check (visloc.pose.uncertainty); None: default
    # the camera-rate path's, measured by its own self-check on the stored structure; None: ``lever_gain``
    camera_rate_lever_gain: LeverGain | None = None
    # the SIFT contrast threshold the store's features were selected at, higher than the one they were extracted
    # with (``visloc.features.sift.contrast_kept``); None: the features as stored
    selected_contrast: float | None = None
    # the threshold retrieval counts correspondences at (the paper's retrieval and the exact refined mode's; the
    # camera-rate path counts matches to stored structure), where it is higher than the one the features were
    # described with: the paper's, on a store described at a lower one (``retrieval_descriptors_u8``); None: all
    retrieval_contrast: float | None = None
    octave_layers: int = 3  # SIFT's layers per octave the features were described with

    def as_retrieved(self, keypoints_f32: np.ndarray, descriptors_u8: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One image's features (this database's, or a query's of the same store) as retrieval counts them: those
        SIFT keeps at ``retrieval_contrast`` (all of them where that is None)."""
        return at_contrast_threshold(keypoints_f32, descriptors_u8, self.retrieval_contrast, self.octave_layers)

    @cached_property
    def retrieval_descriptors_u8(self) -> Sequence[np.ndarray]:
        """Each image's descriptors that retrieval counts correspondences with: those of its keypoints SIFT keeps
        at ``retrieval_contrast`` (all of them where that is None). A query's are chosen alike (``at_contrast``)."""
        if self.retrieval_contrast is None:
            return self.descriptors_u8
        if not isinstance(self.keypoints_f32, tuple):  # a sharded store's: read when asked for
            return self.keypoints_f32.selected(self.descriptors_u8, self.retrieval_contrast, self.octave_layers)
        return tuple(self.as_retrieved(k, d)[1] for k, d in zip(self.keypoints_f32, self.descriptors_u8))

    def __len__(self) -> int:
        return len(self.images)

    @property
    def frames(self) -> np.ndarray:
        return np.array([im.frame for im in self.images])

    def T_world_imu(self) -> np.ndarray:
        """(N, 4, 4) pose of each geotag's reference frame in the local ENU frame (NaN where unknown)."""
        n = len(self)
        up = self.up_m if self.up_m is not None else np.full(n, np.nan)
        rpy = self.rpy_rad if self.rpy_rad is not None else np.full((n, 3), np.nan)
        return imu_poses(np.c_[self.east_north_m, up], rpy)

    def geometry(self, camera_rate: bool = False) -> DatabaseGeometry:
        """What the refined method needs; ``camera`` is None (with the reason) when calibration is missing.
        ``camera_rate``: with the camera-rate path's lever gain (the refined path's where the store has none)."""
        camera, reason = camera_model(self.calibration, f"database {self.source}/{self.camera}")
        T_world_imu = self.T_world_imu()
        if camera is not None and not np.isfinite(T_world_imu).all(axis=(1, 2)).any():
            camera, reason = None, (f"database {self.source}/{self.camera} has no attitudes (a store from before "
                                    "schema 2, or a CSV without roll_deg, pitch_deg and heading): run 'visloc "
                                    "ingest' on the drive to fill them")
        T_world_camera = T_world_imu @ invert(camera.T_camera_imu) if camera is not None else T_world_imu
        return DatabaseGeometry(T_world_camera=T_world_camera,
                                keypoints_xy_px=(tuple(map(_xy_f64, self.keypoints_f32))
                                                 if isinstance(self.keypoints_f32, tuple)
                                                 else self.keypoints_f32.map(_xy_f64)),  # read when asked
                                descriptors_u8=self.descriptors_u8, camera=camera, unavailable_reason=reason,
                                geotag_sigma_m=self.geotag_sigma_m,
                                heading_spread_rad=(heading_spread_rad(self.east_north_m, self.rpy_rad[:, 2])
                                                    if self.rpy_rad is not None else None),
                                lever_gain=(self.camera_rate_lever_gain or self.lever_gain) if camera_rate
                                else self.lever_gain)


def _xy_f64(keypoints_f32: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(keypoints_f32[:, :2], dtype=np.float64)


def camera_model(record: CameraRecord | None, what: str) -> tuple[CameraModel | None, str | None]:
    """A ``CameraModel`` from a stored camera, or None and the reason it cannot be built."""
    if record is None or record.P_rect is None:
        return None, f"{what}: no intrinsics (P_rect) in the store (a CSV drive needs a calibration.json)"
    if record.T_camera_imu is None:
        return None, (f"{what}: no extrinsics (T_camera_imu) in the store: run 'visloc ingest' on the drive "
                      "to fill them")
    return CameraModel.from_projection(record.P_rect, record.T_camera_imu), None


@dataclass(frozen=True)
class QuerySet:
    """Query images of one camera with their ground truth, in time order."""

    source: str
    camera: str
    frames: np.ndarray  # (N,) frame numbers
    timestamps_s: np.ndarray  # (N,)
    lat_deg: np.ndarray  # (N,) ground truth
    lon_deg: np.ndarray
    descriptors_u8: Sequence[np.ndarray]  # a tuple, or read from a sharded store's tiles when asked for
    sift_ms: np.ndarray  # (N,) time SIFT took on each query image, ms (NaN if unknown)
    image_ids: tuple[int, ...] = ()  # store ids, keys of cached correspondence counts
    paths: tuple[str, ...] = ()  # original image files (may be unreachable)
    keypoints_f32: Sequence[np.ndarray] = ()  # (N, 6) per image: x_px, y_px, size, angle, response, octave
    heading_deg: np.ndarray | None = None  # (N,) ground-truth compass heading, NaN if unknown
    calibration: CameraRecord | None = None
    truth_sigma_m: np.ndarray | None = None  # (N,) the ground truth's stated accuracy, sigma per axis, m; NaN if unknown
    selected_contrast: float | None = None  # as ``GeoDatabase.selected_contrast``

    def __len__(self) -> int:
        return len(self.frames)

    def truth_sigma(self, index: int) -> float | None:
        """Stated accuracy of query ``index``'s ground-truth geotag (sigma per axis, m), None if unknown."""
        if self.truth_sigma_m is None or not np.isfinite(self.truth_sigma_m[index]):
            return None
        return float(self.truth_sigma_m[index])

    @property
    def name(self) -> str:
        return f"{self.source}/{self.camera}"

    def key(self, index: int) -> int:
        return self.image_ids[index] if self.image_ids else index

    def query(self, index: int) -> Query:
        """Query ``index`` as the localizer sees it: stored features, its time, the SIFT time measured at ingest."""
        sift_ms = float(self.sift_ms[index]) if np.isfinite(self.sift_ms[index]) else 0.0
        return Query(self.descriptors_u8[index], float(self.timestamps_s[index]), key=self.key(index),
                     keypoints_f32=self.keypoints_f32[index] if self.keypoints_f32 else None, sift_ms=sift_ms)

    @property
    def camera_model(self) -> CameraModel | None:
        """The query camera's calibration, None when the store has none."""
        return camera_model(self.calibration, f"queries {self.name}")[0]


SAME_DRIVE_WITHIN_S = 0.5  # a database image this close in time to a query ...
SAME_DRIVE_WITHIN_M = 25.0  # ... and this close in place (0.5 s at 180 km/h) was taken on the query's drive


def same_drive(db: GeoDatabase, timestamps_s: np.ndarray, lat_deg: np.ndarray, lon_deg: np.ndarray) -> bool:
    """True when the database holds an image of the queries' own drive: one taken within
    ``SAME_DRIVE_WITHIN_S`` of a query and within ``SAME_DRIVE_WITHIN_M`` of where it was taken (its
    stereo partner, the query's own image, or a copy of either under another name, as a CSV made
    from a KITTI drive). Such a database geotags its images with the queries' own receiver: a query
    must not be posed from its own image or its twin (the exclusion window), and its ground truth
    shares the map's absolute error (``visloc.pose.uncertainty``)."""
    t_db = np.asarray(db.timestamps_s, float)
    t_q = np.asarray(timestamps_s, float)
    if t_db.size == 0 or t_q.size == 0:
        return False
    order = np.argsort(t_db)
    sorted_t = t_db[order]
    pos = np.clip(np.searchsorted(sorted_t, t_q), 1, max(len(sorted_t) - 1, 1))
    before, after = order[pos - 1], order[np.minimum(pos, len(order) - 1)]
    nearest = np.where(np.abs(t_db[before] - t_q) <= np.abs(t_db[after] - t_q), before, after)
    close_in_time = np.abs(t_db[nearest] - t_q) <= SAME_DRIVE_WITHIN_S
    if not close_in_time.any():
        return False
    query_m = db.frame.to_local(np.asarray(lat_deg, float)[close_in_time], np.asarray(lon_deg, float)[close_in_time])
    apart_m = np.linalg.norm(np.asarray(query_m).reshape(-1, 2) - db.east_north_m[nearest[close_in_time]], axis=1)
    return bool(np.any(apart_m <= SAME_DRIVE_WITHIN_M))
