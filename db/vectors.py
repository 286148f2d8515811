"""Global vectors and named arrays of a store (schema version 4): one small float32 vector per image
under a name (the VLAD encoder that made it), for a shortlist search that never loads the
descriptors, and named numpy arrays (that encoder's codebook)."""

from __future__ import annotations

import json
from collections.abc import Sequence

import numpy as np

from visloc.db.arrays import GLOBAL_VECTOR, NAMED_ARRAY
from visloc.db.blobs import array_from_blob, blob_problem, repair_hint
from visloc.db.records import DamagedStoreError, StoreError
from visloc.db.store import FeatureStore


class VectorTable:
    """Global vectors and arrays of one open ``FeatureStore``."""

    def __init__(self, store: FeatureStore):
        self.db = store.db
        self.label = store.label

    def add_global_vectors(self, name: str, image_ids: Sequence[int], vectors_f32: np.ndarray) -> None:
        """Store one float32 vector per image under ``name`` (replacing what was there), one transaction."""
        v = np.ascontiguousarray(vectors_f32, np.float32)
        if v.ndim != 2 or v.shape[0] != len(image_ids):
            raise StoreError(f"{self.label}: global vectors must be ({len(image_ids)}, D), got {v.shape}")
        with self.db.atomic():
            self.db["global_vectors"].insert_all(
                ({"name": name, "image_id": int(i), **GLOBAL_VECTOR.fields(row)}
                 for i, row in zip(image_ids, v)), replace=True, batch_size=1000)

    def stored_vector_ids(self, name: str) -> list[int]:
        """Image ids that have a global vector under ``name``."""
        if "global_vectors" not in self.db.table_names():
            return []
        return [r[0] for r in self.db.execute("SELECT image_id FROM global_vectors WHERE name = ?", [name])]

    def global_vectors(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """(image ids (N,) int64, vectors (N, D) float32) stored under ``name``, ordered by image id.
        Reads row by row into one preallocated array (no per-row Python objects kept)."""
        if "global_vectors" not in self.db.table_names():
            raise StoreError(f"{self.label}: no global vectors (build them first)")
        n = self.db.execute("SELECT count(*) FROM global_vectors WHERE name = ?", [name]).fetchone()[0]
        if n == 0:
            raise StoreError(f"{self.label}: no global vectors named {name!r}")
        ids = np.empty(n, np.int64)
        out = None
        cur = self.db.execute("SELECT image_id, vector_crc32, vector_f32 FROM global_vectors WHERE name = ? "
                              "ORDER BY image_id", [name])
        for k, (image_id, stored_crc, blob) in enumerate(cur):
            if out is None:  # the first vector sets the size every other one must have
                size = len(blob) if isinstance(blob, bytes) and len(blob) % 4 == 0 else 0
            problem = blob_problem(blob, size, stored_crc) if size else "is not a float32 vector"
            if problem is not None:
                raise DamagedStoreError(f"{self.label}: {self._image_name(image_id)} global vector ({name}): "
                                        f"{problem}; {repair_hint(self.label)}")
            row = np.frombuffer(blob, np.float32)
            if out is None:
                out = np.empty((n, row.size), np.float32)
            ids[k], out[k] = image_id, row
        return ids, out

    def _image_name(self, image_id: int) -> str:
        row = self.db.execute("SELECT source, camera, frame FROM images WHERE id = ?", [image_id]).fetchone()
        return f"image id {image_id}" if row is None else f"{row[0]}/{row[1]} frame {row[2]}"

    def put_array(self, key: str, array: np.ndarray) -> None:
        a = np.ascontiguousarray(array)
        with self.db.atomic():
            self.db["arrays"].upsert({"key": key, "dtype": a.dtype.str, "shape_json": json.dumps(list(a.shape)),
                                      **NAMED_ARRAY.fields(a)}, pk="key")

    def get_array(self, key: str) -> np.ndarray | None:
        if "arrays" not in self.db.table_names():
            return None
        row = next(self.db.query("SELECT dtype, shape_json, data_crc32, data FROM arrays WHERE key = ?", [key]), None)
        if row is None:
            return None
        return array_from_blob(row["data"], np.dtype(row["dtype"]), tuple(json.loads(row["shape_json"])),
                               f"{self.label}: array {key}", row["data_crc32"], self.label)

