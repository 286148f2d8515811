"""visloc's SQLite store: geotags and SIFT features of images, never the images.

This package is the only place in the project that speaks SQL. It knows nothing
about SIFT or Kalman filters: it stores numpy arrays and plain metadata and hands
them back. ``store`` holds ``FeatureStore``, ``schema`` the tables and migrations,
``records`` the plain records and errors, ``structures`` the table of triangulated points, ``vectors`` global vectors and named arrays, ``selfchecks`` the database's self-checks.
"""

import sys as _sys

if "pandas" not in _sys.modules:
    # sqlite-utils imports pandas when it can, only to map pandas.Timestamp to a column type; the store never
    # passes pandas objects. Importing sqlite-utils with pandas hidden saves every visloc command about 0.2 s of
    # start-up; pandas itself stays importable afterwards (a Dask cluster imports it for its own use).
    _sys.modules["pandas"] = None  # an import of it now raises ImportError, which sqlite-utils catches
    try:
        import sqlite_utils  # noqa: F401
    finally:
        del _sys.modules["pandas"]

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
