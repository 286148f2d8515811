"""Arrays kept as BLOBs, each with a CRC-32 beside it: written together, and read back only when the
BLOB holds exactly the array its row describes and its bytes still give the CRC stored with them."""

from __future__ import annotations

import zlib

import numpy as np

from visloc.db.records import DamagedStoreError


def crc32(blob: bytes | bytearray | memoryview) -> int:
    """The CRC-32 of a BLOB's bytes, as stored beside it (an unsigned 32-bit integer)."""
    return zlib.crc32(blob) & 0xFFFFFFFF


def blob_of(array: np.ndarray, dtype: type | np.dtype) -> tuple[bytes, int]:
    """(the bytes of ``array`` as ``dtype``, C order; their CRC-32), to store side by side."""
    data = np.ascontiguousarray(array, dtype=dtype).tobytes()
    return data, crc32(data)


def repair_hint(label: str) -> str:
    return (f"the store is damaged: 'visloc check --db {label}' lists what is, and 'visloc ingest' of the drive "
            "repairs it")


def blob_problem(blob: object, expected_bytes: int, stored_crc32: object) -> str | None:
    """What is wrong with a BLOB that should hold ``expected_bytes`` bytes with CRC ``stored_crc32``;
    None when nothing is."""
    if not isinstance(blob, bytes | bytearray | memoryview):
        return "missing (NULL)"
    if len(blob) != expected_bytes:
        return f"holds {len(blob)} bytes where its row states {expected_bytes}"
    if not isinstance(stored_crc32, int):
        return "has no checksum"
    if crc32(blob) != stored_crc32:
        return "checksum mismatch (its bytes changed after they were written)"
    return None


def array_from_blob(blob: object, dtype: type | np.dtype, shape: tuple[int, ...], what: str, stored_crc32: object,
                    label: str) -> np.ndarray:
    """A writable ``dtype`` array of ``shape`` from ``blob``; ``DamagedStoreError`` naming ``what`` (the
    store, the row, the column) when the BLOB is NULL, its size does not fit the shape its row states,
    or its bytes fail the checksum ``stored_crc32`` stored with them. ``label`` names the store."""
    dtype = np.dtype(dtype)
    problem = blob_problem(blob, int(np.prod(shape)) * dtype.itemsize, stored_crc32)
    if problem is not None:
        raise DamagedStoreError(f"{what}: {problem}; {repair_hint(label)}")
    return np.frombuffer(blob, dtype).reshape(shape).copy()
