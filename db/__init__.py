"""visloc's SQLite store: geotags and SIFT features of images, never the images.

This package is the only place in the project that speaks SQL. It knows nothing
about SIFT or Kalman filters: it stores numpy arrays and plain metadata and hands
them back.
"""

from db.store import (
    SCHEMA_VERSION,
    CameraRecord,
    EmptyStoreError,
    FeatureStore,
    ImageRecord,
    NotAStoreError,
    SettingsMismatchError,
    StoreError,
    StoredImage,
)

__all__ = [
    "SCHEMA_VERSION",
    "CameraRecord",
    "EmptyStoreError",
    "FeatureStore",
    "ImageRecord",
    "NotAStoreError",
    "SettingsMismatchError",
    "StoreError",
    "StoredImage",
]
