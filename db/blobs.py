"""Arrays kept as BLOBs: read back only when the BLOB holds exactly the array its row describes."""

from __future__ import annotations

import numpy as np

from visloc.db.records import StoreError


def array_from_blob(blob: object, dtype: type | np.dtype, shape: tuple[int, ...], what: str) -> np.ndarray:
    """A writable ``dtype`` array of ``shape`` from ``blob``; ``StoreError`` naming ``what`` (the store,
    the row, the column) when the BLOB is NULL or its size does not fit the shape its row states."""
    dtype = np.dtype(dtype)
    if not isinstance(blob, bytes | bytearray | memoryview):
        raise StoreError(f"{what}: missing (NULL) where {int(np.prod(shape))} values are expected; the store is "
                         "damaged: ingest this drive into a new store")
    expected = int(np.prod(shape)) * dtype.itemsize
    if len(blob) != expected:
        raise StoreError(f"{what}: holds {len(blob)} bytes but its row states shape {shape} ({expected} bytes); the "
                         "store is damaged: ingest this drive into a new store")
    return np.frombuffer(blob, dtype).reshape(shape).copy()
