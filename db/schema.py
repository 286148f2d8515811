"""The store's schema, kept as its history: each table, column and index is defined once, in the
step of ``HISTORY`` that brought it, and ``upgrade`` is the one function that applies them.

``HISTORY[n - 1]`` takes a store from schema version n - 1 to n:

1  the first store: its schema version, settings, cameras, images and their two indexes, and the
   cache of correspondence counts (``pair_counts``; the very first stores of version 1 lacked it).
2  attitudes (images: roll_rad, pitch_rad, yaw_rad) and camera extrinsics (cameras:
   t_camera_imu_json), NULL in rows written before.
3  each image's stated geotag accuracy (images: position_accuracy_m), NULL in rows written before.
4  database structure (``structures``), global vectors (``global_vectors``, ``arrays``), the frames
   ingest skipped (``skipped_frames``) and self-checks (``self_checks``). The last two were once
   made when first needed, so a store of version 4 written then may lack them.
5  a CRC-32 beside every BLOB (images: keypoints_crc32, descriptors_crc32; structures: rows_crc32,
   points_crc32, cov_crc32; global_vectors: vector_crc32; arrays: data_crc32), written in the same
   transaction as the BLOB and checked whenever it is read; and what each image was made from
   (images: source_sha256, the SHA-256 of the image file, and source_bytes, its size). Upgrading
   a store of version 4 computes the checksums of the BLOBs as they are then (``visloc.db.checksums``);
   the sources stay NULL until ingest has read them again.
6  the cache of correspondence counts of features selected at a higher SIFT contrast threshold than the
   store's (``selected_pair_counts``: a store built at a lower threshold serves the paper's method its own
   features, whose counts are other than those of the features as stored).
7  how many views a self-check's pose was posed against apart (self_checks: views_posed_apart), NULL in rows
   written before.

A new store is the whole history applied to an empty file. Opening a store for writing applies
whatever of the history it lacks (a store of an older version: every later step; any store: a
table that was once made when first needed) and records ``SCHEMA_VERSION``; every row is kept.
A column added to an existing table is appended (``ALTER TABLE ... ADD COLUMN``); in a table made
in the same run it takes its place (``after``) in the ``CREATE TABLE``, so a new store's
tables read as they always have: the large BLOB columns last.
"""

from __future__ import annotations

import datetime as _dt
from dataclasses import dataclass

import sqlite_utils


@dataclass(frozen=True)
class Table:
    """A table: columns as (name, declaration) in order; ``key``: a primary key of several columns."""

    name: str
    columns: tuple[tuple[str, str], ...]
    key: tuple[str, ...] = ()


@dataclass(frozen=True)
class Column:
    """A column added to ``table`` (NULL in the rows it holds); placed after ``after`` (None: last)
    when the table is made in the same run."""

    table: str
    name: str
    sql_type: str
    after: str | None = None


@dataclass(frozen=True)
class Index:
    """An index of ``table`` over ``columns``, named as sqlite-utils names it."""

    table: str
    columns: tuple[str, ...]
    unique: bool = False

    @property
    def name(self) -> str:
        return f"idx_{self.table}_{'_'.join(self.columns)}"


Change = Table | Column | Index

HISTORY: tuple[tuple[Change, ...], ...] = (
    (  # 0 -> 1
        Table("visloc_schema", (("version", "INTEGER"), ("created_at", "TEXT"))),
        Table("settings", (("key", "TEXT PRIMARY KEY"), ("value_json", "TEXT"))),
        Table("cameras", (("source", "TEXT"), ("camera", "TEXT"), ("p_rect_json", "TEXT"), ("width_px", "INTEGER"),
                          ("height_px", "INTEGER")), key=("source", "camera")),
        Table("images", (("id", "INTEGER PRIMARY KEY"), ("source", "TEXT NOT NULL"), ("camera", "TEXT NOT NULL"),
                         ("frame", "INTEGER NOT NULL"), ("path", "TEXT"), ("timestamp_s", "REAL NOT NULL"),
                         ("lat_deg", "REAL NOT NULL"), ("lon_deg", "REAL NOT NULL"), ("alt_m", "REAL"),
                         ("heading_deg", "REAL"), ("width_px", "INTEGER"), ("height_px", "INTEGER"),
                         ("sift_ms", "REAL"), ("n_keypoints", "INTEGER NOT NULL"), ("keypoints_f32", "BLOB"),
                         ("descriptors_u8", "BLOB"), ("created_at", "TEXT"))),
        Table("pair_counts", (("query_image_id", "INTEGER"), ("db_image_id", "INTEGER"), ("tau1", "REAL"),
                              ("tau2", "REAL"), ("n_correspondences", "INTEGER"), ("match_ms", "REAL")),
              key=("query_image_id", "db_image_id", "tau1", "tau2")),
        Index("images", ("source", "camera", "frame"), unique=True),
        Index("images", ("source", "camera", "timestamp_s")),
    ),
    (  # 1 -> 2
        Column("images", "roll_rad", "REAL", after="sift_ms"),
        Column("images", "pitch_rad", "REAL", after="roll_rad"),
        Column("images", "yaw_rad", "REAL", after="pitch_rad"),
        Column("cameras", "t_camera_imu_json", "TEXT"),
    ),
    (  # 2 -> 3
        Column("images", "position_accuracy_m", "REAL", after="yaw_rad"),
    ),
    (  # 3 -> 4
        Table("structures", (("image_id", "INTEGER"), ("variant", "TEXT"), ("params_json", "TEXT"),
                             ("neighbour_ids_json", "TEXT"), ("n_points", "INTEGER"), ("rows_i32", "BLOB"),
                             ("points_f64", "BLOB"), ("cov_f64", "BLOB"), ("reason", "TEXT"), ("build_ms", "REAL"),
                             ("created_at", "TEXT")), key=("image_id", "variant")),
        Table("global_vectors", (("name", "TEXT"), ("image_id", "INTEGER"), ("vector_f32", "BLOB")),
              key=("name", "image_id")),
        Table("arrays", (("key", "TEXT PRIMARY KEY"), ("dtype", "TEXT"), ("shape_json", "TEXT"), ("data", "BLOB"))),
        Table("skipped_frames", (("source", "TEXT"), ("camera", "TEXT"), ("frame", "INTEGER"), ("path", "TEXT"),
                                 ("reason", "TEXT"), ("skipped_at", "TEXT")), key=("source", "camera", "frame")),
        Table("self_checks", (("image_id", "INTEGER"), ("params_json", "TEXT"), ("error_east_m", "REAL"),
                              ("error_north_m", "REAL"), ("cov_ee_m2", "REAL"), ("cov_en_m2", "REAL"),
                              ("cov_nn_m2", "REAL"), ("lever_m", "REAL"), ("side", "TEXT"), ("reason", "TEXT"),
                              ("checked_at", "TEXT")), key=("image_id", "params_json")),
    ),
    (  # 4 -> 5
        Column("images", "source_sha256", "TEXT", after="path"),
        Column("images", "source_bytes", "INTEGER", after="source_sha256"),
        Column("images", "keypoints_crc32", "INTEGER", after="n_keypoints"),
        Column("images", "descriptors_crc32", "INTEGER", after="keypoints_crc32"),
        Column("structures", "rows_crc32", "INTEGER", after="n_points"),
        Column("structures", "points_crc32", "INTEGER", after="rows_crc32"),
        Column("structures", "cov_crc32", "INTEGER", after="points_crc32"),
        Column("global_vectors", "vector_crc32", "INTEGER", after="image_id"),
        Column("arrays", "data_crc32", "INTEGER", after="shape_json"),
    ),
    (  # 5 -> 6
        Table("selected_pair_counts", (("query_image_id", "INTEGER"), ("db_image_id", "INTEGER"), ("tau1", "REAL"),
                                       ("tau2", "REAL"), ("contrast_threshold", "REAL"),
                                       ("n_correspondences", "INTEGER"), ("match_ms", "REAL")),
              key=("query_image_id", "db_image_id", "tau1", "tau2", "contrast_threshold")),
    ),
    (  # 6 -> 7
        Column("self_checks", "views_posed_apart", "INTEGER", after="side"),
    ),
)
SCHEMA_VERSION = len(HISTORY)
REQUIRED_TABLES = {"visloc_schema", "settings", "cameras", "images"}  # a store lacking one is damaged, never repaired


def now_iso() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def change_name(change: Change) -> str:
    """"table T", "column T.C" or "index I": a change as a user reads it."""
    if isinstance(change, Table):
        return f"table {change.name}"
    if isinstance(change, Column):
        return f"column {change.table}.{change.name}"
    return f"index {change.name}"


def missing_names(changes: list[Change]) -> list[str]:
    """The lacking ``changes`` as a user reads them (``change_name``), without the columns and indexes of a table
    that is itself lacking: its table says it."""
    tables = {c.name for c in changes if isinstance(c, Table)}
    return [change_name(c) for c in changes if isinstance(c, Table) or c.table not in tables]


def lacking(db: sqlite_utils.Database, target: int = SCHEMA_VERSION) -> list[Change]:
    """The changes of the history's first ``target`` steps that the store does not hold, in order."""
    tables = set(db.table_names())
    indexes = {r[0] for r in db.execute("SELECT name FROM sqlite_master WHERE type = 'index'")}
    columns: dict[str, set[str]] = {}

    def holds(change: Change) -> bool:
        if isinstance(change, Table):
            return change.name in tables
        if isinstance(change, Index):
            return change.name in indexes
        if change.table not in tables:
            return False
        if change.table not in columns:
            columns[change.table] = set(db[change.table].columns_dict)
        return change.name in columns[change.table]

    return [change for step in HISTORY[:target] for change in step if not holds(change)]


# A sharded store's manifest (``visloc.db.shards``): another kind of file than a store, with its own tables.
MANIFEST_TABLES: tuple[Change, ...] = (
    Table("grid", (("tile_schema_version", "INTEGER"), ("epsg", "INTEGER"), ("tile_m", "REAL"), ("halo_m", "REAL"),
                   ("created_at", "TEXT"))),
    Table("tiles", (("key", "TEXT PRIMARY KEY"), ("ix", "INTEGER"), ("iy", "INTEGER"), ("east_min_m", "REAL"),
                    ("north_min_m", "REAL"), ("east_max_m", "REAL"), ("north_max_m", "REAL"), ("file", "TEXT"),
                    ("n_images", "INTEGER"), ("n_owned", "INTEGER"), ("sha256", "TEXT"), ("rows_digest", "TEXT"),
                    ("published_at", "TEXT"))),
    Index("tiles", ("ix", "iy")),
    Table("tile_datasets", (("tile", "TEXT"), ("source", "TEXT"), ("camera", "TEXT"), ("n_owned", "INTEGER"),
                            ("first_timestamp_s", "REAL"), ("last_timestamp_s", "REAL")),
          key=("tile", "source", "camera")),
    Table("global_index", (("image_id", "INTEGER PRIMARY KEY"), ("source", "TEXT"), ("camera", "TEXT"),
                           ("frame", "INTEGER"), ("timestamp_s", "REAL"), ("east_m", "REAL"), ("north_m", "REAL"),
                           ("tile", "TEXT"), ("vector_name", "TEXT"), ("vector_f32", "BLOB"))),
)


def create_manifest(db: sqlite_utils.Database) -> None:
    """Make a new manifest's tables, inside the caller's transaction."""
    for change in MANIFEST_TABLES:
        _apply(db, change, [], set())


def _apply(db: sqlite_utils.Database, change: Change, todo: list[Change], made: set[str]) -> None:
    if isinstance(change, Table):
        db.execute(_create_table(change, [c for c in todo if isinstance(c, Column) and c.table == change.name]))
    elif isinstance(change, Index):
        db.execute(f"CREATE {'UNIQUE ' if change.unique else ''}INDEX {_quoted([change.name])}\n"
                   f"    ON {_quoted([change.table])} ({_quoted(change.columns)})")
    elif change.table not in made:
        db.execute(f"ALTER TABLE [{change.table}] ADD COLUMN [{change.name}] {change.sql_type}")


def upgrade(db: sqlite_utils.Database, version: int, target: int = SCHEMA_VERSION) -> None:
    """Bring a store of schema ``version`` (0: a new, empty store) to ``target``, inside the caller's
    transaction: apply what it lacks of the history's first ``target`` steps, then record ``target``."""
    todo = lacking(db, target)
    made = {change.name for change in todo if isinstance(change, Table)}
    for change in todo:
        _apply(db, change, todo, made)
    if version == 0:
        db.execute("INSERT INTO visloc_schema (version, created_at) VALUES (?, ?)", [target, now_iso()])
    elif version < target:
        db.execute("UPDATE visloc_schema SET version = ?", [target])


def _create_table(table: Table, added: list[Column]) -> str:
    """``CREATE TABLE`` for ``table`` with the columns ``added`` in their places, laid out as sqlite-utils does."""
    columns = list(table.columns)
    for column in added:
        names = [name for name, _ in columns]
        at = len(columns) if column.after is None else names.index(column.after) + 1
        columns.insert(at, (column.name, column.sql_type))
    lines = [f"   {_quoted([name])} {declaration}" for name, declaration in columns]
    if table.key:
        lines.append(f"   PRIMARY KEY ({_quoted(table.key)})")
    return f"CREATE TABLE {_quoted([table.name])} (\n" + ",\n".join(lines) + "\n)"


def _quoted(names: tuple[str, ...] | list[str]) -> str:
    return ", ".join(f'"{name}"' for name in names)
