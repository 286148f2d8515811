"""The store's schema has one history (``visloc.db.schema.HISTORY``): a new store, a store written to
through every path, and an older store upgraded all hold exactly what applying that history makes."""

from __future__ import annotations

import hashlib
import re
import sqlite3

import numpy as np
import pytest

from helpers import REPO
from helpers import features, make_version_1_store
from visloc.db import (CameraRecord, DamagedStoreError, FeatureStore, ImageRecord, SelfCheckRecord, SelfCheckTable, SkippedFrame,
                       StructureRecord, StructureTable, VectorTable)
from visloc.db.connection import Database
from visloc.db.schema import HISTORY, SCHEMA_VERSION, Column, Index, Table, upgrade

# ``images`` as every store made before the schema was kept as a history laid it out (and as
# out/results/visloc.sqlite holds it), with the columns of later versions in their places: before the BLOBs
IMAGES_SQL = ('CREATE TABLE "images" (\n   "id" INTEGER PRIMARY KEY,\n   "source" TEXT NOT NULL,\n'
              '   "camera" TEXT NOT NULL,\n   "frame" INTEGER NOT NULL,\n   "path" TEXT,\n'
              '   "source_sha256" TEXT,\n   "source_bytes" INTEGER,\n'
              '   "timestamp_s" REAL NOT NULL,\n   "lat_deg" REAL NOT NULL,\n   "lon_deg" REAL NOT NULL,\n'
              '   "alt_m" REAL,\n   "heading_deg" REAL,\n   "width_px" INTEGER,\n   "height_px" INTEGER,\n'
              '   "sift_ms" REAL,\n   "roll_rad" REAL,\n   "pitch_rad" REAL,\n   "yaw_rad" REAL,\n'
              '   "position_accuracy_m" REAL,\n   "n_keypoints" INTEGER NOT NULL,\n   "keypoints_crc32" INTEGER,\n'
              '   "descriptors_crc32" INTEGER,\n   "keypoints_f32" BLOB,\n   "descriptors_u8" BLOB,\n'
              '   "created_at" TEXT\n)')
TABLES = {"visloc_schema", "settings", "cameras", "images", "pair_counts", "structures", "global_vectors", "arrays",
          "skipped_frames", "self_checks", "selected_pair_counts"}


def _affinity(declared: str) -> str:
    """SQLite's type affinity of a declared type (FLOAT and REAL are one type to SQLite)."""
    t = declared.upper()
    if "INT" in t:
        return "INTEGER"
    if any(k in t for k in ("CHAR", "CLOB", "TEXT")):
        return "TEXT"
    if not t or "BLOB" in t:
        return "BLOB"
    if any(k in t for k in ("REAL", "FLOA", "DOUB")):
        return "REAL"
    return "NUMERIC"


def normalized(conn: sqlite3.Connection) -> dict:
    """Every table's columns (name, affinity, NOT NULL, primary-key position) and indexes (name, unique,
    columns), independent of column order and of how the SQL was written."""
    out = {}
    for (table,) in conn.execute("SELECT name FROM sqlite_master WHERE type = 'table' ORDER BY name"):
        columns = sorted((name, _affinity(declared), bool(notnull), pk)
                         for _, name, declared, notnull, _, pk in conn.execute(f'PRAGMA table_info("{table}")'))
        indexes = sorted((name, bool(unique), tuple(r[2] for r in conn.execute(f'PRAGMA index_info("{name}")')))
                         for _, name, unique, *_ in conn.execute(f'PRAGMA index_list("{table}")'))
        out[table] = (columns, indexes)
    return out


def master(conn: sqlite3.Connection) -> set[tuple]:
    return set(conn.execute("SELECT type, name, tbl_name, sql FROM sqlite_master"))


def history_applied(step_by_step: bool) -> sqlite3.Connection:
    """An empty database with the history applied: in one run, or one version at a time."""
    db = Database(memory=True)
    if step_by_step:
        for target in range(1, SCHEMA_VERSION + 1):
            with db.atomic():
                upgrade(db, target - 1, target)
    else:
        with db.atomic():
            upgrade(db, 0)
    return db.conn


def written_through_every_path(path) -> None:
    """A new store, written to by every writer the store has."""
    kp, desc = features(8, 1)
    with FeatureStore(path, create=True) as store:
        store.require_setting("sift", {"n_features": 0})
        store.set_camera(CameraRecord("drive", "image_01", np.eye(3, 4), 64, 32, T_camera_imu=np.eye(4)))
        store.add_images([(ImageRecord("drive", "image_01", 0, "/x/0.png", 100.0, 49.0, 8.4), kp, desc)],
                         skipped=[SkippedFrame("drive", "image_01", 1, "/x/1.png", "unreadable")])
        store.set_attitudes("drive", "image_01", {0: (0.0, 0.0, 1.0)})
        store.set_position_accuracies("drive", "image_01", {0: 0.5})
        store.add_pair_counts({(1, 1): (5, 2.0)}, 0.8, 0.97)
        StructureTable(store).add([StructureRecord(1, "all", "{}", (), np.zeros(0, np.int32), np.zeros((0, 3)),
                                                   np.zeros((0, 3, 3)), "no neighbour")])
        vectors = VectorTable(store)
        vectors.add_global_vectors("vlad", [1], np.ones((1, 4), np.float32))
        vectors.put_array("vlad_codebook", np.ones((2, 2), np.float32))
        SelfCheckTable(store).add([SelfCheckRecord(1, "{}", 0.1, 0.2, 1.0, 0.0, 1.0, 3.0, "both")])


def test_the_history_defines_each_table_column_and_index_once():
    changes = [c for step in HISTORY for c in step]
    tables = [c.name for c in changes if isinstance(c, Table)]
    columns = ([(t.name, name) for t in changes if isinstance(t, Table) for name, _ in t.columns]
               + [(c.table, c.name) for c in changes if isinstance(c, Column)])
    indexes = [c.name for c in changes if isinstance(c, Index)]
    assert len(set(tables)) == len(tables) and set(tables) == TABLES
    assert len(set(columns)) == len(columns) and len(set(indexes)) == len(indexes)
    assert SCHEMA_VERSION == len(HISTORY) == 7


def test_every_blob_of_the_schema_is_a_declared_stored_array_with_its_checksum_column():
    """A BLOB column is read, written, checked and upgraded from its declaration in visloc.db.arrays: one
    added to the schema without a declaration (and so without its CRC-32) fails here."""
    from visloc.db.arrays import STORED_ARRAYS

    changes = [c for step in HISTORY for c in step]
    typed = ({(t.name, name): kind for t in changes if isinstance(t, Table) for name, kind in t.columns}
             | {(c.table, c.name): c.sql_type for c in changes if isinstance(c, Column)})
    blobs = {key for key, kind in typed.items() if "BLOB" in kind.upper()}
    assert blobs == {(a.table, a.blob) for a in STORED_ARRAYS}
    for a in STORED_ARRAYS:
        assert "INTEGER" in typed[(a.table, a.crc)].upper(), a
        assert a.count is None or (a.table, a.count) in typed, a


def test_a_new_store_written_through_every_path_holds_exactly_what_the_history_makes(tmp_path):
    """A table or index made anywhere but the history (a second CREATE, a table sqlite-utils makes when
    an insert finds none) shows up here as a difference."""
    path = tmp_path / "new.sqlite"
    written_through_every_path(path)
    conn = sqlite3.connect(path)
    in_one_run = history_applied(step_by_step=False)
    assert master(conn) == master(in_one_run)  # the very same SQL text
    assert normalized(conn) == normalized(history_applied(step_by_step=True))
    assert {name for (name,) in conn.execute("SELECT name FROM sqlite_master WHERE type = 'table'")} == TABLES
    assert conn.execute("SELECT version FROM visloc_schema").fetchall() == [(SCHEMA_VERSION,)]
    assert conn.execute("PRAGMA journal_mode").fetchone() == ("wal",)


def test_a_new_store_lays_its_images_out_as_stores_written_before(tmp_path):
    path = tmp_path / "new.sqlite"
    FeatureStore(path, create=True).close()
    conn = sqlite3.connect(path)
    assert conn.execute("SELECT sql FROM sqlite_master WHERE name = 'images'").fetchone() == (IMAGES_SQL,)
    assert set(conn.execute("SELECT name FROM sqlite_master WHERE type = 'index' AND sql IS NOT NULL")) == {
        ("idx_images_source_camera_frame",), ("idx_images_source_camera_timestamp_s",)}


def old_store(path, version: int) -> None:
    """A store of schema ``version`` holding one image: version 1 as it wrote its tables (by hand), later
    ones as the history's first steps make them."""
    if version == 1:
        make_version_1_store(path)
        return
    db = Database(sqlite3.connect(path))
    with db.atomic():
        upgrade(db, 0, version)
        kp, desc = features(7, 3)
        db["images"].insert({"source": "drive", "camera": "image_01", "frame": 0, "timestamp_s": 100.0,
                             "lat_deg": 49.0, "lon_deg": 8.4, "n_keypoints": 7, "keypoints_f32": kp.tobytes(),
                             "descriptors_u8": desc.tobytes()})
    db.close()


@pytest.mark.parametrize("version", range(1, SCHEMA_VERSION))
def test_an_upgraded_store_has_the_schema_of_a_new_one(tmp_path, version):
    path = tmp_path / f"v{version}.sqlite"
    old_store(path, version)
    with FeatureStore(path) as store:  # opening for writing upgrades
        assert store.migrated_from == version
        assert len(store.images()) == 1
    new = tmp_path / "new.sqlite"
    FeatureStore(new, create=True).close()
    assert normalized(sqlite3.connect(path)) == normalized(sqlite3.connect(new))
    assert sqlite3.connect(path).execute("SELECT version FROM visloc_schema").fetchall() == [(SCHEMA_VERSION,)]


def test_a_store_that_lost_tables_is_refused_as_damaged_when_read_and_rebuilt_when_written(tmp_path):
    """A store of this version holds every table the history makes: one without some (lost, or a
    version 4 store written when two were made only when first needed and not upgraded since) is
    damaged. Reading it says so and writes nothing; opening it for writing (ingest) makes them again."""
    path = tmp_path / "lost.sqlite"
    written_through_every_path(path)
    conn = sqlite3.connect(path)
    conn.execute("DROP TABLE skipped_frames")
    conn.execute("DROP TABLE self_checks")
    conn.commit()
    conn.close()
    before = hashlib.sha256(path.read_bytes()).hexdigest()
    with pytest.raises(DamagedStoreError, match=r"lost.sqlite: damaged visloc store: missing table skipped_frames, "
                                                r"table self_checks; 'visloc ingest' of its drives rebuilds"):
        FeatureStore(path, read_only=True)
    assert hashlib.sha256(path.read_bytes()).hexdigest() == before
    with FeatureStore(path) as store:
        assert store.migrated_from is None  # same version: nothing to report
    assert master(sqlite3.connect(path)) == master(history_applied(step_by_step=False))
    with FeatureStore(path, read_only=True) as store:
        assert store.skipped_frames() == [] and store.image_count() == 1


def test_no_table_or_index_is_made_outside_the_schema_history():
    making = re.compile(r"CREATE\s+(UNIQUE\s+)?(TABLE|INDEX)|ALTER\s+TABLE|DROP\s+(TABLE|INDEX)|executescript|"
                        r"\]\s*\.\s*(create|create_index|add_column|transform|drop)\s*\(|\.create_table\s*\(",
                        re.IGNORECASE)
    offenders = []
    for folder in ("db", "visloc", "dashboard", "bench", "scripts", "benchmarks"):
        for path in sorted((REPO / folder).rglob("*.py")):
            if path == REPO / "db" / "schema.py":
                continue
            offenders += [f"{path.relative_to(REPO)}:{n}" for n, line in enumerate(path.read_text().splitlines(), 1)
                          if making.search(line)]
    assert offenders == []
