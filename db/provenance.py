"""What each stored image was made from (the SHA-256 and size of its file), and replacing an image's
features in place when that file changed or its BLOBs were damaged: the row keeps its id, so the
store then holds exactly what a fresh ingest of the same files holds."""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from visloc.db.records import ImageRecord, StoreError
from visloc.db.arrays import DESCRIPTORS, KEYPOINTS
from visloc.db.store import FeatureStore, image_row


class StoredSource(NamedTuple):
    """What a stored image was made from, and the checksums of its features."""

    image_id: int
    source_sha256: str | None  # None: stored before sources were recorded
    source_bytes: int | None
    keypoints_crc32: int | None
    descriptors_crc32: int | None


def stored_sources(store: FeatureStore, source: str, camera: str) -> dict[int, StoredSource]:
    """frame -> ``StoredSource`` of each stored image of (source, camera)."""
    rows = store.db.execute("SELECT frame, id, source_sha256, source_bytes, keypoints_crc32, descriptors_crc32 "
                            "FROM images WHERE source = ? AND camera = ?", [source, camera])
    return {frame: StoredSource(*rest) for frame, *rest in rows}


def replace_images(store: FeatureStore, batch: Sequence[tuple[ImageRecord, np.ndarray, np.ndarray]]) -> list[int]:
    """Overwrite the stored images of the records' (source, camera, frame) with these features and
    metadata, in one transaction, keeping each row's id. Returns the ids replaced."""
    ids = []
    with store.db.atomic():
        for record, keypoints, descriptors in batch:
            row = image_row(record, keypoints, descriptors)
            key = [row.pop("source"), row.pop("camera"), row.pop("frame")]
            columns = ", ".join(f"[{c}] = ?" for c in row)
            found = store.db.execute("SELECT id FROM images WHERE source = ? AND camera = ? AND frame = ?",
                                     key).fetchone()
            if found is None:
                raise StoreError(f"{store.label}: {record.source}/{record.camera} frame {record.frame}: not stored, "
                                 "nothing to replace")
            store.db.execute(f"UPDATE images SET {columns} WHERE id = ?", [*row.values(), found[0]])
            ids.append(found[0])
    return ids


def record_sources(store: FeatureStore, source: str, camera: str, digests: dict[int, tuple[str, int]]) -> int:
    """Record frame -> (source_sha256, source_bytes) of stored images whose features were found to be
    what their file gives today, in one transaction. Returns rows changed."""
    changed = 0
    with store.db.atomic():
        for frame, (sha, size) in digests.items():
            changed += store.db.execute("UPDATE images SET source_sha256 = ?, source_bytes = ? "
                                        "WHERE source = ? AND camera = ? AND frame = ?",
                                        [sha, int(size), source, camera, int(frame)]).rowcount
    return changed


def same_checksums(stored: StoredSource, keypoints: np.ndarray, descriptors: np.ndarray) -> bool:
    """Do these features give the checksums stored for the image? (Then they are the bytes first written.)"""
    return (KEYPOINTS.fields(keypoints)[KEYPOINTS.crc] == stored.keypoints_crc32
            and DESCRIPTORS.fields(descriptors)[DESCRIPTORS.crc] == stored.descriptors_crc32)
