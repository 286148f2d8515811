"""The ``structures`` table: each database image's triangulated points (schema version 4).

One row per (image, variant): the keypoint rows that carry a 3D point, the points and their
covariances as BLOBs, the neighbours they were triangulated with and the settings that made
them. A row with no points says why (``reason``), so an interrupted build resumes where it
stopped and never redoes an image.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Sequence


from visloc.db.arrays import STRUCTURE_COVARIANCES, STRUCTURE_POINTS, STRUCTURE_ROWS, chunks
from visloc.db.blobs import repair_hint
from visloc.db.records import DamagedStoreError, StructureRecord
from visloc.db.schema import now_iso
from visloc.db.store import FeatureStore


class StructureTable:
    """Structure rows of one open ``FeatureStore``."""

    def __init__(self, store: FeatureStore):
        self.db = store.db
        self.label = store.label

    def complete_ids(self, image_ids: Iterable[int], params_json: str, n_variants: int) -> set[int]:
        """Those of ``image_ids`` whose every variant is stored with settings ``params_json``."""
        ids = [int(i) for i in image_ids]
        done: set[int] = set()
        for chunk, marks in chunks(ids):
            rows = self.db.execute(
                f"SELECT image_id FROM structures WHERE params_json = ? AND image_id IN ({marks}) "
                "GROUP BY image_id HAVING count(*) = ?", [params_json, *chunk, n_variants])
            done.update(int(r[0]) for r in rows)
        return done

    def add(self, records: Sequence[StructureRecord]) -> None:
        """Store ``records`` in one transaction, replacing rows of the same image and variant."""
        rows = []
        for r in records:
            row = {"image_id": int(r.image_id), "variant": r.variant, "params_json": r.params_json,
                   "neighbour_ids_json": json.dumps([int(i) for i in r.neighbour_ids]), "n_points": int(len(r.rows_i32))}
            row.update(**STRUCTURE_ROWS.fields(r.rows_i32), **STRUCTURE_POINTS.fields(r.points_f64),
                       **STRUCTURE_COVARIANCES.fields(r.cov_f64))
            rows.append({**row, "reason": r.reason, "build_ms": float(r.build_ms), "created_at": now_iso()})
        if rows:
            with self.db.atomic():
                self.db["structures"].insert_all(rows, replace=True)

    def get(self, image_ids: Iterable[int], params_json: str, *, points: bool = True
            ) -> dict[tuple[int, str], StructureRecord]:
        """(image id, variant) -> record, for ``image_ids`` with settings ``params_json``. ``points=False``:
        without the points and covariances (``None``; a sharded store's catalogue has none), which a
        reader takes from the tile that owns the image."""
        ids = [int(i) for i in image_ids]
        out: dict[tuple[int, str], StructureRecord] = {}
        for chunk, marks in chunks(ids):
            for r in self.db.query(
                "SELECT s.image_id, s.variant, s.neighbour_ids_json, s.n_points, s.rows_crc32, s.points_crc32, "
                "s.cov_crc32, s.rows_i32, s.points_f64, s.cov_f64, s.reason, s.build_ms, i.source, i.camera, i.frame "
                "FROM structures s LEFT JOIN images i ON i.id = s.image_id "
                f"WHERE s.params_json = ? AND s.image_id IN ({marks})", [params_json, *chunk]
            ):
                n, what = r["n_points"], f"{self.label}: {structure_name(r)}"
                if not isinstance(n, int) or n < 0:
                    raise DamagedStoreError(f"{what}: point count {n!r} is not a count; {repair_hint(self.label)}")
                out[(r["image_id"], r["variant"])] = StructureRecord(
                    image_id=r["image_id"], variant=r["variant"], params_json=params_json,
                    neighbour_ids=tuple(json.loads(r["neighbour_ids_json"])),
                    rows_i32=STRUCTURE_ROWS.read(r, n, what, self.label),
                    points_f64=STRUCTURE_POINTS.read(r, n, what, self.label) if points else None,
                    cov_f64=STRUCTURE_COVARIANCES.read(r, n, what, self.label) if points else None,
                    reason=r["reason"], build_ms=r["build_ms"] or 0.0)
        return out


def structure_name(row: dict) -> str:
    """"drive/camera frame N structure (variant)" of a structures row joined with its image."""
    image = (f"{row['source']}/{row['camera']} frame {row['frame']}" if row.get("source") is not None
             else f"image id {row['image_id']}")
    return f"{image} structure ({row['variant']})"
