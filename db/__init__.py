"""visloc's SQLite store: geotags and SIFT features of images, never the images.

This package is the only place in the project that speaks SQL. It knows nothing
about SIFT or Kalman filters: it stores numpy arrays and plain metadata and hands
them back. ``store`` holds ``FeatureStore``, ``schema`` the tables and migrations,
``records`` the plain records and errors, ``structures`` the table of triangulated points.
"""

from visloc.db.records import (
    CameraRecord,
    EmptyStoreError,
    ImageRecord,
    NotAStoreError,
    SettingsMismatchError,
    StoredImage,
    StoreError,
    StructureRecord,
)
from visloc.db.schema import SCHEMA_VERSION
from visloc.db.store import FeatureStore
from visloc.db.structures import StructureTable

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
    "StructureRecord",
    "StructureTable",
]
