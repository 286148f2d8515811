"""Opening a store file: for writing (created when asked), or for reading only.

A reader never changes the file: it opens SQLite's read-only mode, and where even that needs
a side file it cannot create (a WAL store on a read-only medium) it opens the file as
immutable. Writers wait for each other's locks (``BUSY_TIMEOUT_S``) instead of failing with
"database is locked".
"""

from __future__ import annotations

import contextlib
import sqlite3
from collections.abc import Iterator
from pathlib import Path

import sqlite_utils

from visloc.db.records import NotAStoreError

BUSY_TIMEOUT_S = 60.0  # how long a writer waits for another writer's lock


def _probe(conn: sqlite3.Connection) -> None:
    conn.execute("SELECT name FROM sqlite_master LIMIT 1").fetchall()


def connect(path: Path, label: str, *, read_only: bool) -> sqlite3.Connection:
    """A connection to ``path``; ``NotAStoreError`` naming ``label`` if the file is no SQLite database."""
    try:
        if not read_only:
            conn = sqlite3.connect(str(path), timeout=BUSY_TIMEOUT_S)
            _probe(conn)
            return conn
        uri = Path(path).absolute().as_uri()
        try:
            conn = sqlite3.connect(uri + "?mode=ro", uri=True, timeout=BUSY_TIMEOUT_S)
            _probe(conn)
            return conn
        except sqlite3.OperationalError:
            # a WAL store whose side files cannot be created (read-only medium): read it as immutable
            conn = sqlite3.connect(uri + "?immutable=1", uri=True)
            _probe(conn)
            return conn
    except sqlite3.DatabaseError as exc:
        raise NotAStoreError(f"{label}: not a SQLite database, or a damaged one ({exc})") from None


class Database(sqlite_utils.Database):
    """sqlite-utils' database whose transactions take the write lock when they begin.

    A transaction that first reads and only then writes (as sqlite-utils' inserts do: they look
    up the table first) cannot wait for another writer in WAL mode: once its snapshot is stale,
    SQLite refuses the write at once with "database is locked". ``BEGIN IMMEDIATE`` waits for
    the lock (up to the busy timeout) before reading anything.
    """

    @contextlib.contextmanager
    def atomic(self) -> Iterator["Database"]:
        if self.conn.in_transaction:  # nested: sqlite-utils' savepoints
            with super().atomic():
                yield self
            return
        self.conn.execute("BEGIN IMMEDIATE")
        try:
            yield self
        except BaseException:
            self.conn.rollback()
            raise
        self.conn.execute("COMMIT")


def sqlite_error_line(label: str, exc: sqlite3.Error) -> str:
    """One line for an error SQLite raised on the store ``label``, saying what it means for the user."""
    text = str(exc)
    if "malformed" in text or "not a database" in text:
        return (f"{label}: the store file is damaged (SQLite: {text}); 'visloc check --db {label}' says more; "
                "ingest its drives into a new store")
    if "disk I/O error" in text or "disk is full" in text:
        return (f"{label}: cannot write the store (SQLite: {text}): the disk is full or a file-size limit is "
                "reached; every image committed before is kept: make room and run the same command again to go on")
    return f"{label}: SQLite: {text}"
