"""The feature store: one SQLite file per database, written through sqlite-utils.

Tables
------
``visloc_schema``  one row: the schema version and when the file was created.
``settings``       key -> JSON value; ``sift`` holds the SIFT settings the
                   features were extracted with (every image in a store shares them).
``cameras``        per (source, camera): the rectified projection matrix ``P_rect``
                   (3x4, pixels) when known, the image size in pixels and (since
                   version 2) ``T_camera_imu`` (4x4, metres: X_camera = T_camera_imu
                   X_imu, the rectified camera's extrinsics relative to the geotag's
                   reference point, the IMU) when known.
``images``         per (source, camera, frame): geotag, timestamp, original path,
                   attitude of the geotag's reference frame (since version 2:
                   roll_rad, pitch_rad, yaw_rad as KITTI's OXTS gives them, NULL when
                   unknown), the geotag's stated accuracy (since version 3:
                   position_accuracy_m, standard deviation per horizontal axis in
                   metres, NULL when unknown), SIFT keypoints (float32, N x 6: x_px,
                   y_px, size_px, angle_deg, response, octave) and descriptors
                   (uint8, N x 128) as BLOBs.
``pair_counts``    a cache: correspondences between a query image and a database
                   image for given (tau1, tau2), and how long computing it took.
``selected_pair_counts`` (since version 6) the same, of features selected at a higher contrast.
``structures``     (since version 4) each database image's triangulated points: the
                   keypoint rows that carry one, the points and their covariances, the
                   neighbours and settings that made them (``visloc.db.structures``).
``global_vectors`` (since version 4) one small float32 vector per image under a name
                   (the VLAD encoder that made it), for a shortlist search that never
                   loads the descriptors.
``arrays``         named numpy arrays (e.g. that encoder's codebook).
``skipped_frames`` (since version 4) the frames ingest skipped as bad, and why.
``self_checks``    (since version 4) how well the database poses its own images
                   (``visloc.db.selfchecks``).

Every table, column and index is defined once, in the schema's history (``visloc.db.schema``).

Writes happen in transactions (``FeatureStore.add_images`` commits a batch at
once), the journal is in WAL mode, and an interrupted write rolls back: a store
never holds half an image.

Opening a store of an older schema version for writing migrates it in place (``visloc.db.schema``);
``visloc ingest`` then fills what the new columns lack from the source without
re-extracting any feature.
"""

from __future__ import annotations

import json
import sqlite3
import time
from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np
import sqlite_utils

from visloc.db.arrays import DESCRIPTORS, KEYPOINTS, chunks
from visloc.db.blobs import repair_hint
from visloc.db.connection import BUSY_TIMEOUT_S, Database, connect
from visloc.db.records import (DESCRIPTOR_DIM, KEYPOINT_COLUMNS, CameraRecord, DamagedStoreError, EmptyStoreError,
                               ImageRecord, NotAStoreError, SettingsMismatchError, SkippedFrame, StoredImage, StoreError)
from visloc.db.checksums import fill_checksums
from visloc.db.schema import REQUIRED_TABLES, SCHEMA_VERSION, lacking, missing_names, now_iso, upgrade


def _enable_wal(db: sqlite_utils.Database) -> None:
    """Switch the file to WAL. The switch needs the file to itself, and where other writers are opening
    it at the same moment SQLite can answer "database is locked" at once instead of waiting: look again
    and retry until it is WAL, for up to the busy timeout."""
    deadline = time.monotonic() + BUSY_TIMEOUT_S
    while db.journal_mode != "wal":
        try:
            db.enable_wal()
        except sqlite3.OperationalError as exc:
            if "locked" not in str(exc) or time.monotonic() > deadline:
                raise
            time.sleep(0.05)


class FeatureStore:
    """A visloc store in one SQLite file.

    ``FeatureStore(path)`` opens an existing store for reading and writing;
    ``FeatureStore(path, create=True)`` also creates a new store when the file
    does not exist or is an empty file. A file that is not SQLite, or is a SQLite
    database of something else, is refused with ``NotAStoreError`` and left
    untouched. ``FeatureStore.memory()`` gives an in-memory store for tests.
    """

    def __init__(self, path: str | Path, *, create: bool = False, read_only: bool = False,
                 lacking_ok: bool = False):
        self.path = Path(path)
        self.read_only = read_only
        self._lacking_ok = lacking_ok  # read-only: open a store that lacks tables too (to report what it lacks)
        label = str(self.path)
        if not self.path.exists():
            if not create or read_only:
                raise StoreError(f"{label}: database file does not exist (build it with 'visloc ingest')")
            if not self.path.parent.exists():
                raise StoreError(f"{label}: folder {self.path.parent} does not exist")
        elif self.path.is_dir():
            raise StoreError(f"{label}: is a folder, not a database file")
        conn = connect(self.path, label, read_only=read_only)
        self._open(Database(conn), label, create=create and not read_only, on_disk=True)

    @classmethod
    def memory(cls) -> "FeatureStore":
        store = cls.__new__(cls)
        store.path = Path(":memory:")
        store.read_only = False
        store._lacking_ok = False
        store._open(Database(memory=True), ":memory:", create=True, on_disk=False)
        return store

    def _open(self, db: sqlite_utils.Database, label: str, *, create: bool, on_disk: bool) -> None:
        self.db = db
        self.label = label
        self.migrated_from: int | None = None  # the schema version this opening migrated from, if it did
        tables = set(db.table_names())
        if not tables and create:
            # another process may be creating this store right now: take the write lock (waiting for
            # it), then look again
            with db.atomic():
                if not db.table_names():
                    upgrade(db, 0)  # a new store: the whole schema history
            tables = set(db.table_names())
        if not tables:
            raise EmptyStoreError(f"{label}: empty database file (build it with 'visloc ingest')")
        if "visloc_schema" not in tables:
            shown = ", ".join(sorted(tables)[:5])
            raise NotAStoreError(f"{label}: SQLite database but not a visloc store (its tables: {shown})")
        row = next(db.query("SELECT version FROM visloc_schema LIMIT 1"), None)
        version = None if row is None else row["version"]
        older = isinstance(version, int) and 1 <= version < SCHEMA_VERSION and not (REQUIRED_TABLES - tables)
        if older and self.read_only:
            raise NotAStoreError(f"{label}: visloc store schema version {version}; reading it needs version "
                                 f"{SCHEMA_VERSION}: upgrade it first with 'visloc upgrade --db {label}'")
        if not older and version != SCHEMA_VERSION:
            raise NotAStoreError(
                f"{label}: visloc store schema version {version}, this visloc reads version {SCHEMA_VERSION}"
            )
        missing = REQUIRED_TABLES - tables
        if missing:
            raise NotAStoreError(f"{label}: damaged visloc store, missing tables {sorted(missing)}; it cannot be "
                                 "repaired: ingest its drives into a new store")
        self.checksums_filled = 0  # BLOBs whose checksums this opening computed (upgrading from version < 5)
        if self.read_only:
            absent = [] if self._lacking_ok else lacking(db)
            if absent:
                shown = ", ".join(missing_names(absent)[:4])
                raise DamagedStoreError(f"{label}: damaged visloc store: missing {shown}; 'visloc ingest' of its "
                                        "drives rebuilds what is missing (or ingest them into a new store)")
            return
        if older or lacking(db):  # an older version, or a table lost or once made when first needed
            with db.atomic():
                upgrade(db, version)
                if older and version < 5:
                    self.checksums_filled = fill_checksums(db)
            if older:
                self.migrated_from = version
        if on_disk:
            _enable_wal(db)

    def close(self) -> None:
        self.db.close()

    def __enter__(self) -> "FeatureStore":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- settings ---------------------------------------------------------------

    def get_setting(self, key: str) -> object | None:
        row = next(self.db.query("SELECT value_json FROM settings WHERE key = ?", [key]), None)
        return None if row is None else json.loads(row["value_json"])

    def require_setting(self, key: str, value: object, *, what: str = "settings") -> None:
        """Record ``value`` under ``key`` if the store has none; refuse a different one.

        Values are compared as JSON, so ``{"a": 1}`` equals ``{"a": 1.0}`` only if
        the caller normalised them the same way (it should pass plain dicts).
        """
        stored = self.get_setting(key)
        if stored is None:
            with self.db.atomic():  # the write lock first, then look again: another writer may have recorded it
                stored = self.get_setting(key)
                if stored is None:
                    if self.image_count() and key == "sift":
                        raise StoreError(f"{self.label}: holds images but no SIFT settings; rebuild it")
                    self.db["settings"].upsert({"key": key, "value_json": json.dumps(value, sort_keys=True)},
                                               pk="key")
                    return
        if json.loads(json.dumps(value, sort_keys=True)) != stored:
            diffs = _dict_diff(stored, value)
            raise SettingsMismatchError(f"{self.label}: built with other {what} ({diffs})")

    # -- cameras ----------------------------------------------------------------

    def set_camera(self, camera: CameraRecord) -> None:
        p_json = None if camera.P_rect is None else json.dumps(np.asarray(camera.P_rect, float).tolist())
        t_json = None if camera.T_camera_imu is None else json.dumps(np.asarray(camera.T_camera_imu, float).tolist())
        with self.db.atomic():
            self.db["cameras"].upsert(
                {
                    "source": camera.source,
                    "camera": camera.camera,
                    "p_rect_json": p_json,
                    "width_px": int(camera.width_px),
                    "height_px": int(camera.height_px),
                    "t_camera_imu_json": t_json,
                },
                pk=("source", "camera"),
            )

    def get_camera(self, source: str, camera: str) -> CameraRecord | None:
        row = next(
            self.db.query("SELECT * FROM cameras WHERE source = ? AND camera = ?", [source, camera]), None
        )
        return None if row is None else _camera_from_row(row)

    def cameras(self) -> list[CameraRecord]:
        return [_camera_from_row(r) for r in self.db.query("SELECT * FROM cameras ORDER BY source, camera")]

    # -- images -----------------------------------------------------------------

    def image_count(self, source: str | None = None, camera: str | None = None) -> int:
        where, args = where_drive(source, camera)
        return next(self.db.query(f"SELECT count(*) AS n FROM images {where}", args))["n"]

    def stored_frames(self, source: str, camera: str) -> set[int]:
        rows = self.db.query("SELECT frame FROM images WHERE source = ? AND camera = ?", [source, camera])
        return {r["frame"] for r in rows}

    def add_images(self, batch: Sequence[tuple[ImageRecord, np.ndarray, np.ndarray]],
                   skipped: Sequence[SkippedFrame] = ()) -> int:
        """Insert (record, keypoints_f32 (N, 6), descriptors_u8 (N, 128)) triples in one transaction,
        together with the frames ``skipped`` as bad (replacing what was recorded for them).

        Images already stored (same source, camera, frame) are skipped; a stored image is no longer
        recorded as skipped. Returns the number inserted. Either all of it is committed or none.
        """
        rows = [image_row(record, keypoints, descriptors) for record, keypoints, descriptors in batch]
        if not rows and not skipped:
            return 0
        before = self.image_count()
        with self.db.atomic():
            self.db["images"].insert_all(rows, ignore=True)
            if skipped:
                self.db["skipped_frames"].insert_all(
                    [{**vars(f), "skipped_at": now_iso()} for f in skipped], replace=True)
            for r in rows:
                self.db.execute("DELETE FROM skipped_frames WHERE source = ? AND camera = ? AND frame = ?",
                                [r["source"], r["camera"], r["frame"]])
        return self.image_count() - before

    def skipped_frames(self, source: str | None = None, camera: str | None = None) -> list[SkippedFrame]:
        """The frames ingest skipped as bad, of (source, camera) (None: of all), in order."""
        if "skipped_frames" not in self.db.table_names():
            return []
        where, args = where_drive(source, camera)
        return [SkippedFrame(**r) for r in self.db.query(
            f"SELECT source, camera, frame, path, reason FROM skipped_frames {where} ORDER BY source, camera, frame",
            args)]

    def frames_without_attitude(self, source: str, camera: str) -> set[int]:
        rows = self.db.query("SELECT frame FROM images WHERE source = ? AND camera = ? AND "
                             "(roll_rad IS NULL OR pitch_rad IS NULL OR yaw_rad IS NULL)", [source, camera])
        return {r["frame"] for r in rows}

    def set_attitudes(self, source: str, camera: str, attitudes_rad: dict[int, tuple[float, float, float]]) -> int:
        """Fill (roll_rad, pitch_rad, yaw_rad) of stored frames, in one transaction. Returns rows changed."""
        changed = 0
        with self.db.atomic():
            for frame, (roll, pitch, yaw) in attitudes_rad.items():
                cur = self.db.execute(
                    "UPDATE images SET roll_rad = ?, pitch_rad = ?, yaw_rad = ? "
                    "WHERE source = ? AND camera = ? AND frame = ?",
                    [float(roll), float(pitch), float(yaw), source, camera, int(frame)])
                changed += cur.rowcount
        return changed

    def frames_without_accuracy(self, source: str, camera: str) -> set[int]:
        rows = self.db.query("SELECT frame FROM images WHERE source = ? AND camera = ? AND "
                             "position_accuracy_m IS NULL", [source, camera])
        return {r["frame"] for r in rows}

    def set_position_accuracies(self, source: str, camera: str, accuracies_m: dict[int, float | None]) -> int:
        """Set the stated geotag accuracy (metres; None: unknown) of stored frames, in one transaction. Returns
        rows changed."""
        changed = 0
        with self.db.atomic():
            for frame, sigma_m in accuracies_m.items():
                cur = self.db.execute("UPDATE images SET position_accuracy_m = ? "
                                      "WHERE source = ? AND camera = ? AND frame = ?",
                                      [None if sigma_m is None else float(sigma_m), source, camera, int(frame)])
                changed += cur.rowcount
        return changed

    def images(self, source: str | None = None, camera: str | None = None) -> list[StoredImage]:
        """Metadata of the stored images, ordered by (source, camera, timestamp)."""
        where, args = where_drive(source, camera)
        columns = ", ".join(["id", "n_keypoints", *ImageRecord.__dataclass_fields__])
        rows = self.db.query(
            f"SELECT {columns} FROM images {where} ORDER BY source, camera, timestamp_s, frame", args
        )
        return [StoredImage(image_id=r.pop("id"), **r) for r in rows]

    def features(self, image_ids: Iterable[int]) -> dict[int, tuple[np.ndarray, np.ndarray]]:
        """image_id -> (keypoints_f32 (N, 6), descriptors_u8 (N, 128)), as writable arrays."""
        ids = [int(i) for i in image_ids]
        out: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        for chunk, marks in chunks(ids):
            for r in self.db.query(
                f"SELECT id, source, camera, frame, n_keypoints, keypoints_crc32, descriptors_crc32, keypoints_f32, "
                f"descriptors_u8 FROM images WHERE id IN ({marks})", chunk
            ):
                n, what = _count(r, self.label), _row_name(r, self.label)
                out[r["id"]] = (KEYPOINTS.read(r, n, what, self.label), DESCRIPTORS.read(r, n, what, self.label))
        missing = set(ids) - set(out)
        if missing:
            raise StoreError(f"{self.label}: no image with id {sorted(missing)[:5]}")
        return out

    # -- cached correspondence counts ----------------------------------------------

    def pair_counts(self, query_image_ids: Iterable[int], tau1: float, tau2: float,
                    contrast_threshold: float | None = None) -> dict[tuple[int, int], tuple[int, float]]:
        """(query_image_id, db_image_id) -> (n_correspondences, match_ms) cached for (tau1, tau2), of the features
        as stored, or (``contrast_threshold``) of those selected at that SIFT contrast threshold."""
        table, where, args = _pair_table(contrast_threshold)
        out = {}
        ids = [int(i) for i in query_image_ids]
        for chunk, marks in chunks(ids):
            for r in self.db.query(
                f"SELECT query_image_id, db_image_id, n_correspondences, match_ms FROM {table} "
                f"WHERE tau1 = ? AND tau2 = ?{where} AND query_image_id IN ({marks})", [tau1, tau2, *args, *chunk]
            ):
                out[(r["query_image_id"], r["db_image_id"])] = (r["n_correspondences"], r["match_ms"])
        return out

    def add_pair_counts(self, counts: dict[tuple[int, int], tuple[int, float]], tau1: float, tau2: float,
                        contrast_threshold: float | None = None) -> None:
        table = _pair_table(contrast_threshold)[0]
        selected = {} if contrast_threshold is None else {"contrast_threshold": float(contrast_threshold)}
        rows = [{"query_image_id": q, "db_image_id": d, "tau1": tau1, "tau2": tau2, **selected,
                 "n_correspondences": int(n), "match_ms": float(ms)} for (q, d), (n, ms) in counts.items()]
        if rows:
            with self.db.atomic():
                self.db[table].insert_all(rows, replace=True)

    # -- streaming (the fast path) ----------------------------------------------------------

    def iter_descriptors(self, image_ids: Iterable[int], chunk_size: int = 256):
        """Yield (image_id, descriptors_u8 (N, 128)) for ``image_ids`` in order, ``chunk_size`` rows per
        query: memory stays bounded by one chunk however large the store."""
        ids = [int(i) for i in image_ids]
        for chunk, marks in chunks(ids, chunk_size):
            rows = {r["id"]: r for r in self.db.query(
                "SELECT id, source, camera, frame, n_keypoints, descriptors_crc32, descriptors_u8 FROM images "
                f"WHERE id IN ({marks})", chunk)}
            for i in chunk:
                if i not in rows:
                    raise StoreError(f"{self.label}: no image with id {i}")
                r = rows[i]
                yield i, DESCRIPTORS.read(r, _count(r, self.label), _row_name(r, self.label), self.label)

    def image_ids(self, source: str | None = None, camera: str | None = None) -> np.ndarray:
        """(N,) int64 image ids in (source, camera, timestamp) order, without loading any metadata."""
        where, args = where_drive(source, camera)
        rows = self.db.execute(f"SELECT id FROM images {where} ORDER BY source, camera, timestamp_s, frame", args)
        return np.array([r[0] for r in rows], np.int64)

    def sources(self) -> list[dict]:
        """One dict per (source, camera): image count, time span, keypoint statistics."""
        return list(
            self.db.query(
                "SELECT source, camera, count(*) AS n_images, min(timestamp_s) AS first_timestamp_s, "
                "max(timestamp_s) AS last_timestamp_s, avg(n_keypoints) AS mean_keypoints "
                "FROM images GROUP BY source, camera ORDER BY source, camera"
            )
        )


def image_row(record: ImageRecord, keypoints: np.ndarray, descriptors: np.ndarray) -> dict:
    """The ``images`` row of ``record`` with keypoints_f32 (N, 6) and descriptors_u8 (N, 128) as BLOBs, each
    with its CRC-32; ``StoreError`` naming the image's file when the arrays have other shapes or types."""
    descriptors = np.asarray(descriptors)
    if descriptors.dtype != DESCRIPTORS.dtype or descriptors.shape[1:] != DESCRIPTORS.item_shape:
        raise StoreError(f"{record.path}: descriptors must be uint8 (N, {DESCRIPTOR_DIM}), got "
                         f"{descriptors.dtype} {descriptors.shape}")
    if np.shape(keypoints) != KEYPOINTS.shape(descriptors.shape[0]):
        raise StoreError(f"{record.path}: keypoints must be ({descriptors.shape[0]}, {KEYPOINT_COLUMNS}), got "
                         f"{np.shape(keypoints)}")
    row = {k: getattr(record, k) for k in ImageRecord.__dataclass_fields__}
    row.update(n_keypoints=int(descriptors.shape[0]), **KEYPOINTS.fields(keypoints), **DESCRIPTORS.fields(descriptors),
               created_at=now_iso())
    return row


def _row_name(row: dict, label: str) -> str:
    return f"{label}: {row['source']}/{row['camera']} frame {row['frame']}"


def _count(row: dict, label: str) -> int:
    n = row["n_keypoints"]
    if not isinstance(n, int) or n < 0:
        raise DamagedStoreError(f"{_row_name(row, label)}: keypoint count {n!r} is not a count; {repair_hint(label)}")
    return n


def where_drive(source: str | None, camera: str | None, prefix: str = "") -> tuple[str, list]:
    """(``WHERE`` clause, its arguments) selecting images of ``source`` and ``camera`` (None: any);
    ``prefix``: the images table's alias and a dot, e.g. ``"i."``."""
    clauses, args = [], []
    for column, value in (("source", source), ("camera", camera)):
        if value is not None:
            clauses.append(f"{prefix}{column} = ?")
            args.append(value)
    return ("WHERE " + " AND ".join(clauses)) if clauses else "", args


def _camera_from_row(row: dict) -> CameraRecord:
    p = row["p_rect_json"]
    t = row.get("t_camera_imu_json")
    return CameraRecord(
        source=row["source"],
        camera=row["camera"],
        P_rect=None if p is None else np.array(json.loads(p), dtype=np.float64),
        width_px=row["width_px"],
        height_px=row["height_px"],
        T_camera_imu=None if t is None else np.array(json.loads(t), dtype=np.float64),
    )


def _dict_diff(stored: object, wanted: object) -> str:
    if isinstance(stored, dict) and isinstance(wanted, dict):
        keys = sorted(set(stored) | set(wanted))
        parts = [f"{k}: store {stored.get(k)!r}, asked {wanted.get(k)!r}" for k in keys if stored.get(k) != wanted.get(k)]
        return "; ".join(parts)
    return f"store {stored!r}, asked {wanted!r}"


def _pair_table(contrast_threshold: float | None) -> tuple[str, str, list]:
    """The table of counts of the features as stored (None) or selected at ``contrast_threshold``, and its rows'."""
    if contrast_threshold is None:
        return "pair_counts", "", []
    return "selected_pair_counts", " AND contrast_threshold = ?", [float(contrast_threshold)]
