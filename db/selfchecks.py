"""The ``self_checks`` table: how well the database poses its own images (``visloc.pose.selfcheck``).

One row per (image, settings): the pose's error against the image's own geotag, its covariance
without the lever term, the lever, the side and how many views it is the mean of, or why there is no
pose. A store read as it is may lack the table (one written before it was part of the schema): its
measurements use the default lever gain until ``visloc ingest`` runs the self-check.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

from visloc.db.arrays import chunks
from visloc.db.records import SelfCheckRecord
from visloc.db.schema import now_iso
from visloc.db.store import FeatureStore

COLUMNS = ("image_id", "params_json", "error_east_m", "error_north_m", "cov_ee_m2", "cov_en_m2", "cov_nn_m2",
           "lever_m", "side", "views_posed_apart", "reason")


class SelfCheckTable:
    """Self-check rows of one open ``FeatureStore``."""

    def __init__(self, store: FeatureStore):
        self.db = store.db

    def add(self, records: Sequence[SelfCheckRecord]) -> None:
        """Store ``records`` in one transaction, replacing rows of the same image and settings."""
        if not records:
            return
        with self.db.atomic():
            self.db["self_checks"].insert_all(
                [{**{c: getattr(r, c) for c in COLUMNS}, "checked_at": now_iso()} for r in records], replace=True)

    def get(self, image_ids: Iterable[int], params_json: str) -> dict[int, SelfCheckRecord]:
        """image id -> record, for ``image_ids`` checked with settings ``params_json`` (empty when none are)."""
        if "self_checks" not in self.db.table_names():
            return {}
        ids = [int(i) for i in image_ids]
        out: dict[int, SelfCheckRecord] = {}
        for chunk, marks in chunks(ids):
            for r in self.db.query(f"SELECT {', '.join(COLUMNS)} FROM self_checks WHERE params_json = ? "
                                   f"AND image_id IN ({marks})", [params_json, *chunk]):
                out[int(r["image_id"])] = SelfCheckRecord(**r)
        return out
