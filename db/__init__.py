"""visloc's SQLite store: geotags and SIFT features of images, never the images.

This package is the only place in the project that speaks SQL. It knows nothing
about SIFT or Kalman filters: it stores numpy arrays and plain metadata and hands
them back. ``store`` holds ``FeatureStore``, ``schema`` the tables and migrations,
``records`` the plain records and errors, ``structures`` the table of triangulated points, ``vectors`` global vectors and named arrays, ``selfchecks`` the database's self-checks.
"""

from visloc.db.records import (
    CameraRecord,
    DamagedStoreError,
    EmptyStoreError,
    ImageRecord,
    NotAStoreError,
    SelfCheckRecord,
    SettingsMismatchError,
    SkippedFrame,
    StoredImage,
    StoreError,
    StructureRecord,
)
from visloc.db.schema import SCHEMA_VERSION
from visloc.db.selfchecks import SelfCheckTable
from visloc.db.store import FeatureStore
from visloc.db.structures import StructureTable
from visloc.db.vectors import VectorTable

__all__ = [
    "SCHEMA_VERSION",
    "CameraRecord",
    "DamagedStoreError",
    "EmptyStoreError",
    "FeatureStore",
    "ImageRecord",
    "NotAStoreError",
    "SelfCheckRecord",
    "SelfCheckTable",
    "SettingsMismatchError",
    "SkippedFrame",
    "StoreError",
    "StoredImage",
    "StructureRecord",
    "StructureTable",
    "VectorTable",
]
