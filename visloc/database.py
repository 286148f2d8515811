"""A geotagged database loaded from the store into arrays for the engine."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from db import CameraRecord, EmptyStoreError, FeatureStore, StoredImage
from visloc.geo import LocalFrame
from visloc.geometry import CameraModel, imu_poses, invert
from visloc.ingest import check_sift_settings
from visloc.params import SiftParams
from visloc.refined import DatabaseGeometry


@dataclass(frozen=True)
class GeoDatabase:
    """Images of one (source, camera) in time order, with features and positions.

    ``frame`` is the local metric frame: origin at the first image's geotag. ``up_m``
    is altitude minus the first image's (NaN when unknown); ``rpy_rad`` (N, 3) the
    attitude of each geotag's reference frame (NaN when unknown, e.g. a schema-1 store
    or a CSV source).
    """

    source: str
    camera: str
    images: tuple[StoredImage, ...]
    timestamps_s: np.ndarray  # (N,)
    lat_deg: np.ndarray  # (N,)
    lon_deg: np.ndarray  # (N,)
    east_north_m: np.ndarray  # (N, 2)
    keypoints_f32: tuple[np.ndarray, ...]
    descriptors_u8: tuple[np.ndarray, ...]
    calibration: CameraRecord | None
    frame: LocalFrame
    up_m: np.ndarray | None = None  # (N,)
    rpy_rad: np.ndarray | None = None  # (N, 3)

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

    def geometry(self) -> DatabaseGeometry:
        """What the refined mode needs; ``camera`` is None (with the reason) when calibration is missing."""
        camera, reason = camera_model(self.calibration, f"database {self.source}/{self.camera}")
        T_world_imu = self.T_world_imu()
        if camera is not None and not np.isfinite(T_world_imu).all(axis=(1, 2)).any():
            camera, reason = None, (f"database {self.source}/{self.camera} has no attitudes (a store from before "
                                    "schema 2 or a CSV source): run 'visloc ingest' on the KITTI drive to fill them")
        T_world_camera = T_world_imu @ invert(camera.T_camera_imu) if camera is not None else T_world_imu
        return DatabaseGeometry(T_world_camera=T_world_camera,
                                keypoints_xy_px=tuple(np.ascontiguousarray(k[:, :2], dtype=np.float64)
                                                      for k in self.keypoints_f32),
                                descriptors_u8=self.descriptors_u8, camera=camera, unavailable_reason=reason)


def camera_model(record: CameraRecord | None, what: str) -> tuple[CameraModel | None, str | None]:
    """A ``CameraModel`` from a stored camera, or None and the reason it cannot be built."""
    if record is None or record.P_rect is None:
        return None, f"{what}: no intrinsics (P_rect) in the store"
    if record.T_camera_imu is None:
        return None, (f"{what}: no extrinsics (T_camera_imu) in the store: run 'visloc ingest' on the KITTI drive "
                      "to fill them")
    return CameraModel.from_projection(record.P_rect, record.T_camera_imu), None


def load_images(store: FeatureStore, source: str, camera: str, sift: SiftParams
                ) -> tuple[tuple[StoredImage, ...], tuple[np.ndarray, ...], tuple[np.ndarray, ...]]:
    """Stored images of (source, camera) in time order with their keypoints and descriptors."""
    check_sift_settings(store, sift)
    images = tuple(store.images(source, camera))
    if not images:
        have = ", ".join(f"{s['source']}/{s['camera']}" for s in store.sources()) or "nothing"
        raise EmptyStoreError(f"{store.label}: no images of {source}/{camera} (it holds {have})")
    features = store.features(im.image_id for im in images)
    keypoints = tuple(features[im.image_id][0] for im in images)
    descriptors = tuple(features[im.image_id][1] for im in images)
    return images, keypoints, descriptors


def load_database(store: FeatureStore, source: str, camera: str, sift: SiftParams,
                  frame: LocalFrame | None = None) -> GeoDatabase:
    """Load (source, camera) from ``store``; refuse a store built with other SIFT settings."""
    images, keypoints, descriptors = load_images(store, source, camera, sift)
    lat = np.array([im.lat_deg for im in images])
    lon = np.array([im.lon_deg for im in images])
    frame = frame or LocalFrame(float(lat[0]), float(lon[0]))
    alt = np.array([np.nan if im.alt_m is None else im.alt_m for im in images], float)
    rpy = np.array([[np.nan if v is None else v for v in (im.roll_rad, im.pitch_rad, im.yaw_rad)] for im in images],
                   float).reshape(-1, 3)
    return GeoDatabase(
        source=source, camera=camera, images=images,
        timestamps_s=np.array([im.timestamp_s for im in images]),
        lat_deg=lat, lon_deg=lon, east_north_m=frame.to_local(lat, lon),
        keypoints_f32=keypoints, descriptors_u8=descriptors,
        calibration=store.get_camera(source, camera), frame=frame, up_m=alt - alt[0], rpy_rad=rpy,
    )


@dataclass(frozen=True)
class QuerySet:
    """Query images of one camera with their ground truth, in time order."""

    source: str
    camera: str
    frames: np.ndarray  # (N,) frame numbers
    timestamps_s: np.ndarray  # (N,)
    lat_deg: np.ndarray  # (N,) ground truth
    lon_deg: np.ndarray
    descriptors_u8: tuple[np.ndarray, ...]
    sift_ms: np.ndarray  # (N,) time SIFT took on each query image, ms (NaN if unknown)
    image_ids: tuple[int, ...] = ()  # store ids, keys of cached correspondence counts
    paths: tuple[str, ...] = ()  # original image files (may be unreachable)
    keypoints_f32: tuple[np.ndarray, ...] = ()  # (N, 6) per image: x_px, y_px, size, angle, response, octave
    heading_deg: np.ndarray | None = None  # (N,) ground-truth compass heading, NaN if unknown
    calibration: CameraRecord | None = None

    def key(self, index: int) -> int:
        return self.image_ids[index] if self.image_ids else index


def load_query_set(store: FeatureStore, source: str, camera: str, sift: SiftParams) -> QuerySet:
    """Stored images of (source, camera) as queries, with their geotags as ground truth."""
    images, keypoints, descriptors = load_images(store, source, camera, sift)
    return QuerySet(
        source=source, camera=camera, frames=np.array([im.frame for im in images]),
        timestamps_s=np.array([im.timestamp_s for im in images]), lat_deg=np.array([im.lat_deg for im in images]),
        lon_deg=np.array([im.lon_deg for im in images]), descriptors_u8=descriptors,
        sift_ms=np.array([np.nan if im.sift_ms is None else im.sift_ms for im in images]),
        image_ids=tuple(im.image_id for im in images), paths=tuple(im.path for im in images),
        keypoints_f32=keypoints, calibration=store.get_camera(source, camera),
        heading_deg=np.array([np.nan if im.heading_deg is None else im.heading_deg for im in images]),
    )
