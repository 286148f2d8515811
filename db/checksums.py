"""Which column holds the CRC-32 of which BLOB, and the checksums of a store upgraded from a version
that had none (schema version 5 brought them)."""

from __future__ import annotations

import sqlite_utils

from visloc.db.blobs import crc32

# table -> ((BLOB column, its CRC-32 column), ...)
BLOB_CHECKSUMS: dict[str, tuple[tuple[str, str], ...]] = {
    "images": (("keypoints_f32", "keypoints_crc32"), ("descriptors_u8", "descriptors_crc32")),
    "structures": (("rows_i32", "rows_crc32"), ("points_f64", "points_crc32"), ("cov_f64", "cov_crc32")),
    "global_vectors": (("vector_f32", "vector_crc32"),),
    "arrays": (("data", "data_crc32"),),
}


def fill_checksums(db: sqlite_utils.Database) -> int:
    """Compute the CRC-32 of every BLOB that has none, inside the caller's transaction; returns how many.
    The checksums vouch for the bytes as they are now: damage from before cannot be told apart."""
    filled = 0
    tables = set(db.table_names())
    for table, pairs in BLOB_CHECKSUMS.items():
        if table not in tables:
            continue
        for blob_column, crc_column in pairs:
            rowids = [r[0] for r in db.execute(f"SELECT rowid FROM [{table}] WHERE [{crc_column}] IS NULL AND "
                                               f"[{blob_column}] IS NOT NULL")]
            for start in range(0, len(rowids), 256):  # a chunk of BLOBs in memory at a time
                chunk = rowids[start : start + 256]
                rows = db.execute(f"SELECT rowid, [{blob_column}] FROM [{table}] "
                                  f"WHERE rowid IN ({','.join('?' * len(chunk))})", chunk).fetchall()
                db.conn.executemany(f"UPDATE [{table}] SET [{crc_column}] = ? WHERE rowid = ?",
                                    [(crc32(blob), rowid) for rowid, blob in rows])
            filled += len(rowids)
    return filled
