"""The checksums of a store upgraded from a version that had none (schema version 5 brought them), for
every stored array ``visloc.db.arrays`` declares."""

from __future__ import annotations

import sqlite_utils

from visloc.db.arrays import STORED_ARRAYS, chunks
from visloc.db.blobs import crc32


def fill_checksums(db: sqlite_utils.Database) -> int:
    """Compute the CRC-32 of every BLOB that has none, inside the caller's transaction; returns how many.
    The checksums vouch for the bytes as they are now: damage from before cannot be told apart."""
    filled = 0
    tables = set(db.table_names())
    for array in STORED_ARRAYS:
        if array.table not in tables:
            continue
        table, blob_column, crc_column = array.table, array.blob, array.crc
        rowids = [r[0] for r in db.execute(f"SELECT rowid FROM [{table}] WHERE [{crc_column}] IS NULL AND "
                                           f"[{blob_column}] IS NOT NULL")]
        for chunk, marks in chunks(rowids, 256):  # a chunk of BLOBs in memory at a time
            rows = db.execute(f"SELECT rowid, [{blob_column}] FROM [{table}] WHERE rowid IN ({marks})",
                              chunk).fetchall()
            db.conn.executemany(f"UPDATE [{table}] SET [{crc_column}] = ? WHERE rowid = ?",
                                [(crc32(blob), rowid) for rowid, blob in rows])
        filled += len(rowids)
    return filled
