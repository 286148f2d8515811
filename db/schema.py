"""The store's tables: creating them, and migrating a store of an older schema version in place.

Schema versions: 1 had no attitudes and no camera extrinsics. Version 2 adds them as NULL
columns (``ALTER TABLE ... ADD COLUMN``), every existing row and cached count kept. Version 3
adds each image's stated geotag accuracy (``position_accuracy_m``) the same way. Version 4 adds
the tables of database structure (``structures``) and of global vectors (``global_vectors``,
``arrays``), which ``visloc ingest`` fills; every image and cached count is kept.

Two tables are made when first needed, in any version: ``skipped_frames`` (frames ingest left
out) and ``self_checks`` (how well the database poses its own images).
"""

from __future__ import annotations

import datetime as _dt

import sqlite_utils

SCHEMA_VERSION = 4
# columns added by each version after the first: table -> (column, SQL type)
MIGRATIONS = {
    2: [("images", "roll_rad", "REAL"), ("images", "pitch_rad", "REAL"), ("images", "yaw_rad", "REAL"),
        ("cameras", "t_camera_imu_json", "TEXT")],
    3: [("images", "position_accuracy_m", "REAL")],
    4: [],
}
REQUIRED_TABLES = {"visloc_schema", "settings", "cameras", "images"}  # pair_counts, a cache, is added when missing


def now_iso() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def migrate(db: sqlite_utils.Database, version: int) -> None:
    """Bring a store of an older schema version to ``SCHEMA_VERSION`` in one transaction."""
    with db.atomic():
        for target in range(version + 1, SCHEMA_VERSION + 1):
            for table, column, sql_type in MIGRATIONS[target]:
                if column not in db[table].columns_dict:
                    db.execute(f"ALTER TABLE [{table}] ADD COLUMN [{column}] {sql_type}")
        if version < 4:
            _create_v4_tables(db)
        db.execute("UPDATE visloc_schema SET version = ?", [SCHEMA_VERSION])


def create_schema(db: sqlite_utils.Database) -> None:
    """Every table of a new store, in one transaction."""
    with db.atomic():
        db["visloc_schema"].create({"version": int, "created_at": str})
        db["visloc_schema"].insert({"version": SCHEMA_VERSION, "created_at": now_iso()})
        db["settings"].create({"key": str, "value_json": str}, pk="key")
        db["cameras"].create(
            {"source": str, "camera": str, "p_rect_json": str, "width_px": int, "height_px": int,
             "t_camera_imu_json": str},
            pk=("source", "camera"),
        )
        db["images"].create(
            {
                "id": int,
                "source": str,
                "camera": str,
                "frame": int,
                "path": str,
                "timestamp_s": float,
                "lat_deg": float,
                "lon_deg": float,
                "alt_m": float,
                "heading_deg": float,
                "width_px": int,
                "height_px": int,
                "sift_ms": float,
                "roll_rad": float,
                "pitch_rad": float,
                "yaw_rad": float,
                "position_accuracy_m": float,
                "n_keypoints": int,
                "keypoints_f32": bytes,
                "descriptors_u8": bytes,
                "created_at": str,
            },
            pk="id",
            not_null={"source", "camera", "frame", "timestamp_s", "lat_deg", "lon_deg", "n_keypoints"},
        )
        create_pair_counts(db)
        _create_v4_tables(db)
        db["images"].create_index(["source", "camera", "frame"], unique=True)
        db["images"].create_index(["source", "camera", "timestamp_s"])


def create_pair_counts(db: sqlite_utils.Database) -> None:
    db["pair_counts"].create(
        {"query_image_id": int, "db_image_id": int, "tau1": float, "tau2": float,
         "n_correspondences": int, "match_ms": float},
        pk=("query_image_id", "db_image_id", "tau1", "tau2"),
    )


def _create_v4_tables(db: sqlite_utils.Database) -> None:
    """Structure and global vectors (inside the caller's transaction)."""
    if "structures" not in db.table_names():
        db["structures"].create(
            {"image_id": int, "variant": str, "params_json": str, "neighbour_ids_json": str, "n_points": int,
             "rows_i32": bytes, "points_f64": bytes, "cov_f64": bytes, "reason": str, "build_ms": float,
             "created_at": str},
            pk=("image_id", "variant"),
        )
    if "global_vectors" not in db.table_names():
        db["global_vectors"].create({"name": str, "image_id": int, "vector_f32": bytes}, pk=("name", "image_id"))
    if "arrays" not in db.table_names():
        db["arrays"].create({"key": str, "dtype": str, "shape_json": str, "data": bytes}, pk="key")


def ensure_vector_tables(db: sqlite_utils.Database) -> None:
    """The optional tables of global vectors and named arrays (large databases)."""
    if "global_vectors" not in db.table_names():
        with db.atomic():
            db["global_vectors"].create({"name": str, "image_id": int, "vector_f32": bytes}, pk=("name", "image_id"))
            db["arrays"].create({"key": str, "dtype": str, "shape_json": str, "data": bytes}, pk="key")


def ensure_skipped_frames(db: sqlite_utils.Database) -> None:
    """The table of frames ingest skipped as bad (inside the caller's transaction); made when first needed."""
    if "skipped_frames" not in db.table_names():
        db["skipped_frames"].create({"source": str, "camera": str, "frame": int, "path": str, "reason": str,
                                     "skipped_at": str}, pk=("source", "camera", "frame"))


def ensure_self_checks(db: sqlite_utils.Database) -> None:
    """The table of self-checks (inside the caller's transaction); made when first needed."""
    if "self_checks" not in db.table_names():
        db["self_checks"].create({"image_id": int, "params_json": str, "error_east_m": float, "error_north_m": float,
                                  "cov_ee_m2": float, "cov_en_m2": float, "cov_nn_m2": float, "lever_m": float,
                                  "side": str, "reason": str, "checked_at": str}, pk=("image_id", "params_json"))
