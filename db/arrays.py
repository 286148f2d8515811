"""Every array a store keeps as a BLOB, declared once: its table, BLOB column, CRC-32 column, dtype and
the shape of one counted item. Writing (``fields``), reading (``read``), checking (``problem``,
``visloc check``), filling the checksums of an upgraded store (``visloc.db.checksums``) and the schema's
test are derived from ``STORED_ARRAYS``; a BLOB column of the schema that is not declared here fails
that test. ``chunks`` is the one way to look rows up by a long list of ids.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import numpy as np

from visloc.db.blobs import array_from_blob, blob_of, blob_problem
from visloc.db.records import DESCRIPTOR_DIM, KEYPOINT_COLUMNS

CHUNK_IDS = 500  # ids in one "IN (?, ...)" lookup: well under SQLite's limit on bound parameters


@dataclass(frozen=True)
class StoredArray:
    """One BLOB column and the CRC-32 column beside it.

    table, blob, crc: where it lives
    dtype:            its element type; None where each row states it (the named arrays)
    item_shape:       the shape of one item; the row's ``count`` column says how many items
                      (None: the size is stated elsewhere, per name or per row)
    count:            the column that holds the number of items, or None
    what:             how a message names it ("keypoints", "points", ...)
    """

    table: str
    blob: str
    crc: str
    dtype: str | None
    item_shape: tuple[int, ...] | None
    count: str | None
    what: str

    def shape(self, n: int) -> tuple[int, ...]:
        """The array's shape when its row counts ``n`` items."""
        assert self.item_shape is not None, self.blob
        return (n, *self.item_shape)

    def nbytes(self, n: int) -> int:
        """The size of the BLOB of ``n`` items, bytes."""
        return math.prod(self.shape(n)) * np.dtype(self.dtype).itemsize

    def fields(self, array: np.ndarray) -> dict:
        """{BLOB column: the bytes of ``array`` as this dtype, CRC column: their CRC-32}, to store."""
        blob, crc = blob_of(array, np.dtype(self.dtype) if self.dtype else np.asarray(array).dtype)
        return {self.blob: blob, self.crc: crc}

    def read(self, row: dict, n: int, name: str, label: str) -> np.ndarray:
        """The array of ``row`` (which holds both columns) with ``n`` items, checked against its size and
        checksum; ``DamagedStoreError`` naming ``name`` (the store and the row) and this array otherwise."""
        return array_from_blob(row[self.blob], np.dtype(self.dtype), self.shape(n), f"{name} {self.what}",
                               row[self.crc], label)

    def problem(self, row: dict, n: int) -> str | None:
        """What is wrong with ``row``'s BLOB of ``n`` items, as "what: problem"; None when nothing is."""
        found = blob_problem(row.get(self.blob), self.nbytes(n), row.get(self.crc))
        return None if found is None else f"{self.what}: {found}"


KEYPOINTS = StoredArray("images", "keypoints_f32", "keypoints_crc32", "float32", (KEYPOINT_COLUMNS,), "n_keypoints",
                        "keypoints")
DESCRIPTORS = StoredArray("images", "descriptors_u8", "descriptors_crc32", "uint8", (DESCRIPTOR_DIM,), "n_keypoints",
                          "descriptors")
STRUCTURE_ROWS = StoredArray("structures", "rows_i32", "rows_crc32", "int32", (), "n_points", "rows")
STRUCTURE_POINTS = StoredArray("structures", "points_f64", "points_crc32", "float64", (3,), "n_points", "points")
STRUCTURE_COVARIANCES = StoredArray("structures", "cov_f64", "cov_crc32", "float64", (3, 3), "n_points",
                                    "covariances")
# a global vector's length is its encoder's (every vector of a name has the first one's)
GLOBAL_VECTOR = StoredArray("global_vectors", "vector_f32", "vector_crc32", "float32", None, None, "global vector")
# a named array's dtype and shape are in its row (dtype, shape_json)
NAMED_ARRAY = StoredArray("arrays", "data", "data_crc32", None, None, None, "array")

STORED_ARRAYS = (KEYPOINTS, DESCRIPTORS, STRUCTURE_ROWS, STRUCTURE_POINTS, STRUCTURE_COVARIANCES, GLOBAL_VECTOR,
                 NAMED_ARRAY)


def arrays_of(table: str) -> tuple[StoredArray, ...]:
    """The stored arrays of ``table``, in declaration order."""
    return tuple(a for a in STORED_ARRAYS if a.table == table)


def chunks(ids: Sequence, size: int = CHUNK_IDS) -> Iterator[tuple[list, str]]:
    """(``size`` of ``ids`` at a time, their placeholders "?,?,..." for an ``IN (...)``)."""
    ids = list(ids)
    for start in range(0, len(ids), size):
        chunk = ids[start : start + size]
        yield chunk, ",".join("?" * len(chunk))
