"""A geotagged database loaded from the store into arrays for the engine."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from db import CameraRecord, EmptyStoreError, FeatureStore, StoredImage
from visloc.geo import LocalFrame
from visloc.ingest import check_sift_settings
from visloc.params import SiftParams


@dataclass(frozen=True)
class GeoDatabase:
    """Images of one (source, camera) in time order, with features and positions.

    ``frame`` is the local metric frame: origin at the first image's geotag.
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

    def __len__(self) -> int:
        return len(self.images)

    @property
    def frames(self) -> np.ndarray:
        return np.array([im.frame for im in self.images])


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
    return GeoDatabase(
        source=source, camera=camera, images=images,
        timestamps_s=np.array([im.timestamp_s for im in images]),
        lat_deg=lat, lon_deg=lon, east_north_m=frame.to_local(lat, lon),
        keypoints_f32=keypoints, descriptors_u8=descriptors,
        calibration=store.get_camera(source, camera), frame=frame,
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
        keypoints_f32=keypoints,
        heading_deg=np.array([np.nan if im.heading_deg is None else im.heading_deg for im in images]),
    )
