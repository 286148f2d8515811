"""A sharded store: a folder holding one store file per geographic tile and a manifest.

Layout of the folder::

    manifest.sqlite        the grid, the tiles (file, bounds, counts, checksum) and the global index
    tiles/<tile>.sqlite    one store each, today's schema: the images of the tile and of its halo
    work/staging.sqlite    the ingest's working store (features of every image, then what is made
                           from them); tiles are cut from it

Tables of the manifest
----------------------
``grid``          one row: schema version of the tiles, the CRS (EPSG code) of the metric grid, the
                  tile size and halo in metres, when the store was created.
``tiles``         per tile: its key, grid column and row, bounds (metres in the grid's CRS), its
                  file, the images it holds (with its halo) and owns, the SHA-256 of its file, the
                  digest of the rows it was cut from (``rows_digest``), when it was published.
``tile_datasets`` per (tile, source, camera): images owned and the time they span.
``global_index``  per image: its id, source, camera, frame, time, grid position, the tile that
                  owns it and its global vector (float32 BLOB) under the encoder's name.

A tile is written whole into a temporary file, renamed into place, and only then recorded in
the manifest in one transaction: a reader never sees half a tile, and a tile whose file does not
match the checksum the manifest states is not trusted.
"""

from __future__ import annotations

import hashlib
import json
import os
import sqlite3
import uuid
from collections.abc import Collection
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import sqlite_utils

from visloc.db.connection import BUSY_TIMEOUT_S, Database, connect
from visloc.db.records import NotAStoreError, StoreError
from visloc.db.schema import SCHEMA_VERSION, create_manifest, now_iso
from visloc.db.store import FeatureStore
from visloc.db.structures import StructureTable

MANIFEST_NAME = "manifest.sqlite"
TILES_FOLDER = "tiles"
STAGING_NAME = "work/staging.sqlite"

# the tables a tile carries, and how their rows are tied to images (None: every row)
_IMAGE_KEYED = {"images": "id", "structures": "image_id", "global_vectors": "image_id", "self_checks": "image_id"}
_WHOLE = ("settings", "cameras", "arrays", "skipped_frames")
_FEATURE_BLOBS = {"keypoints_f32", "descriptors_u8"}
# left out of a catalogue (NULL; their counts and checksums stay): read from the tile that owns the image
_CATALOGUE_LEAVES_OUT = {"images": _FEATURE_BLOBS, "structures": {"points_f64", "cov_f64"}}
# when a row was written, and how long making it took, are not what it says
_DIGEST_SKIPS = {"created_at", "checked_at", "skipped_at", "sift_ms", "build_ms"}


def is_sharded(path: str | Path) -> bool:
    """True when ``path`` is a folder holding a sharded store's manifest."""
    return Path(path).is_dir() and (Path(path) / MANIFEST_NAME).is_file()


@dataclass(frozen=True)
class TileRecord:
    key: str
    ix: int
    iy: int
    bounds_m: tuple[float, float, float, float]  # east_min, north_min, east_max, north_max in the grid's CRS
    file: str  # relative to the store folder
    n_images: int  # with the halo
    n_owned: int
    sha256: str
    rows_digest: str
    datasets: tuple[tuple[str, str, int, float, float], ...] = ()  # (source, camera, n_owned, first_s, last_s)


@dataclass(frozen=True)
class Grid:
    epsg: int
    tile_m: float
    halo_m: float


class Manifest:
    """The manifest of the sharded store in ``folder``."""

    def __init__(self, folder: str | Path, *, create: bool = False, read_only: bool = False):
        self.folder = Path(folder)
        self.path = self.folder / MANIFEST_NAME
        self.label = str(self.folder)
        if not self.path.exists():
            if not create or read_only:
                raise StoreError(f"{self.label}: no sharded store here (no {MANIFEST_NAME}; build it with "
                                 "'visloc ingest --tile-m')")
            self.folder.mkdir(parents=True, exist_ok=True)
        self.db = Database(connect(self.path, str(self.path), read_only=read_only))
        if create and not read_only and "grid" not in self.db.table_names():
            with self.db.atomic():
                self._create()
        if "grid" not in self.db.table_names():
            raise NotAStoreError(f"{self.path}: not a visloc sharded store manifest")

    def _create(self) -> None:
        create_manifest(self.db)

    def close(self) -> None:
        self.db.close()

    def __enter__(self) -> "Manifest":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- the grid -----------------------------------------------------------------------------

    def grid(self) -> Grid | None:
        row = next(self.db.query("SELECT epsg, tile_m, halo_m FROM grid LIMIT 1"), None)
        return None if row is None else Grid(int(row["epsg"]), float(row["tile_m"]), float(row["halo_m"]))

    def require_grid(self, grid: Grid) -> None:
        """Record the grid of a new store; refuse another grid for one that has tiles already."""
        with self.db.atomic():
            have = self.grid()
            if have is None:
                self.db.execute("INSERT INTO grid VALUES (?, ?, ?, ?, ?)",
                                [SCHEMA_VERSION, grid.epsg, grid.tile_m, grid.halo_m, now_iso()])
                return
        if have != grid:
            raise StoreError(f"{self.label}: a sharded store of {have.tile_m:g} m tiles with a {have.halo_m:g} m "
                             f"halo in EPSG:{have.epsg}; asked {grid.tile_m:g} m, {grid.halo_m:g} m, "
                             f"EPSG:{grid.epsg}")

    # -- tiles --------------------------------------------------------------------------------

    def tiles(self) -> list[TileRecord]:
        datasets: dict[str, list] = {}
        for r in self.db.query("SELECT * FROM tile_datasets ORDER BY tile, source, camera"):
            datasets.setdefault(r["tile"], []).append((r["source"], r["camera"], r["n_owned"],
                                                       r["first_timestamp_s"], r["last_timestamp_s"]))
        return [TileRecord(r["key"], r["ix"], r["iy"], (r["east_min_m"], r["north_min_m"], r["east_max_m"],
                                                          r["north_max_m"]), r["file"], r["n_images"], r["n_owned"],
                           r["sha256"], r["rows_digest"], tuple(datasets.get(r["key"], ())))
                for r in self.db.query("SELECT * FROM tiles ORDER BY key")]

    def publish(self, tile: TileRecord) -> None:
        """Record a tile whose file is in place, with its datasets, in one transaction."""
        with self.db.atomic():
            self.db.execute("DELETE FROM tile_datasets WHERE tile = ?", [tile.key])
            self.db.execute("INSERT OR REPLACE INTO tiles VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                            [tile.key, tile.ix, tile.iy, *tile.bounds_m, tile.file, tile.n_images, tile.n_owned,
                             tile.sha256, tile.rows_digest, now_iso()])
            self.db.conn.executemany("INSERT INTO tile_datasets VALUES (?, ?, ?, ?, ?, ?)",
                                     [(tile.key, *d) for d in tile.datasets])

    # -- the global index -------------------------------------------------------------------------

    def put_global_index(self, rows: list[tuple], vector_name: str, vectors_f32: np.ndarray | None) -> None:
        """Replace the global index: ``rows`` of (image_id, source, camera, frame, timestamp_s, east_m,
        north_m, tile), with each image's global vector (None: no vectors), in one transaction."""
        with self.db.atomic():
            self.db.execute("DELETE FROM global_index")
            self.add_global_index(rows, vector_name, vectors_f32)

    def add_global_index(self, rows: list[tuple], vector_name: str, vectors_f32: np.ndarray | None) -> None:
        """Add ``rows`` (as ``put_global_index`` takes them) to the global index, in one transaction."""
        vectors = ([None] * len(rows) if vectors_f32 is None
                   else [np.ascontiguousarray(v, np.float32).tobytes() for v in vectors_f32])
        with self.db.atomic():
            self.db.conn.executemany("INSERT INTO global_index VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                                     [(*r, vector_name, v) for r, v in zip(rows, vectors)])

    def owner_tiles(self, source: str, camera: str) -> dict[int, str]:
        """image id -> the key of the tile that owns it, for the images of (``source``, ``camera``)."""
        return {int(i): t for i, t in self.db.execute(
            "SELECT image_id, tile FROM global_index WHERE source = ? AND camera = ?", [source, camera])}

    def global_index(self) -> tuple[dict[str, np.ndarray], np.ndarray | None]:
        """(columns of the global index as arrays, the (N, D) vectors or None), read in parts so that a
        city's million rows never sit in memory as Python objects."""
        parts: list[tuple] = []
        cursor = self.db.execute("SELECT image_id, timestamp_s, east_m, north_m, tile, vector_f32 FROM global_index "
                                 "ORDER BY image_id")
        while rows := cursor.fetchmany(50_000):
            ids, t, e, n, tiles, blobs = zip(*rows)
            vectors = None if blobs[0] is None else np.frombuffer(b"".join(blobs), np.float32).reshape(len(rows), -1)
            parts.append((np.array(ids, np.int64), np.array(t, float), np.array(e, float), np.array(n, float),
                          np.array(tiles, object), vectors))
        names = ("image_id", "timestamp_s", "east_m", "north_m", "tile")
        if not parts:
            return {k: np.zeros(0) for k in names}, None
        columns = {k: np.concatenate([p[i] for p in parts]) for i, k in enumerate(names)}
        if parts[0][5] is None:
            return columns, None
        return columns, np.concatenate([p[5] for p in parts])


def file_sha256(path: str | Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()


def _columns(conn: sqlite3.Connection, schema: str, table: str) -> list[str]:
    return [r[1] for r in conn.execute(f"PRAGMA [{schema}].table_info([{table}])")]


def rows_digest(path: str | Path, image_ids: list[int]) -> str:
    """A digest of the rows a tile of ``image_ids`` holds, read from the store at ``path``: every column
    but BLOBs (their CRC-32 stands for them), the times rows were written and how long they took. Equal digests: the same
    rows, whichever store they are read from."""
    ids = sorted(int(i) for i in image_ids)
    conn = connect(Path(path), str(path), read_only=True)
    try:
        digest = hashlib.sha256()
        _want(conn, ids, "main")
        for table in (*_WHOLE, *_IMAGE_KEYED):
            declared = conn.execute(f"PRAGMA main.table_info([{table}])").fetchall()
            names = [r[1] for r in declared if r[2].upper() != "BLOB" and r[1] not in _DIGEST_SKIPS]
            where = _tile_rows(table)
            listed = ", ".join(f"[{n}]" for n in names)
            for row in conn.execute(f"SELECT {listed} FROM [{table}]{where} ORDER BY {listed}"):
                digest.update(json.dumps([table, *row]).encode())
        return digest.hexdigest()
    finally:
        conn.close()


def _want(conn: sqlite3.Connection, image_ids: list[int], schema: str) -> None:
    """Temporary tables of the images a tile holds and of their (source, camera)s, from ``schema``'s images."""
    conn.execute("CREATE TEMP TABLE wanted (id INTEGER PRIMARY KEY)")
    conn.executemany("INSERT INTO wanted VALUES (?)", [(int(i),) for i in image_ids])
    conn.execute("CREATE TEMP TABLE wanted_datasets (source TEXT, camera TEXT, prefix TEXT)")
    conn.execute(f"INSERT INTO wanted_datasets SELECT DISTINCT source, camera, 'vlad:' || source || '/' || camera "
                 f"|| ':' FROM [{schema}].images WHERE id IN (SELECT id FROM wanted)")


def _tile_rows(table: str) -> str:
    """The WHERE clause picking a tile's rows of ``table`` (after ``_want``): the rows of its images, and of
    the store-wide tables only what its drives need. A drive added to the store changes only the tiles
    it passes through: its camera and its global vectors' encoder (named 'vlad:SOURCE/CAMERA:...', as
    ``visloc.store.workspace.global_vectors_name`` names them) go only into the tiles holding its images."""
    if table in _IMAGE_KEYED:
        return f" WHERE [{_IMAGE_KEYED[table]}] IN (SELECT id FROM wanted)"
    if table in ("cameras", "skipped_frames"):
        return " WHERE (source, camera) IN (SELECT source, camera FROM wanted_datasets)"
    if table == "arrays":
        return (" WHERE substr([key], 1, 5) != 'vlad:' OR EXISTS (SELECT 1 FROM wanted_datasets w "
                "WHERE substr([key], 1, length(w.prefix)) = w.prefix)")
    return ""


def write_tile(staging: str | Path, folder: str | Path, key: str, image_ids: list[int]) -> tuple[str, str, str]:
    """Cut the tile ``key`` holding ``image_ids`` from the store ``staging`` into ``folder``/tiles: written
    whole into a temporary file and renamed into place. Returns (its file relative to ``folder``, its
    SHA-256, the digest of its rows). Deterministic: the same rows whichever process writes it."""
    folder = Path(folder)
    (folder / TILES_FOLDER).mkdir(parents=True, exist_ok=True)
    relative = f"{TILES_FOLDER}/{key}.sqlite"
    final = folder / relative
    temporary = final.with_name(f".{key}.{uuid.uuid4().hex}.tmp")
    try:
        FeatureStore(temporary, create=True).close()
        conn = sqlite3.connect(str(temporary), timeout=BUSY_TIMEOUT_S)
        try:
            conn.execute("PRAGMA journal_mode=DELETE")  # one self-contained file, no side files to rename
            conn.execute("ATTACH DATABASE ? AS staging", [Path(staging).absolute().as_uri() + "?mode=ro"])
            _want(conn, sorted(int(i) for i in image_ids), "staging")
            with conn:
                for table in (*_WHOLE, *_IMAGE_KEYED):
                    names = ", ".join(f"[{c}]" for c in _columns(conn, "main", table))
                    where = _tile_rows(table)
                    conn.execute(f"INSERT OR REPLACE INTO main.[{table}] ({names}) SELECT {names} "
                                 f"FROM staging.[{table}]{where} ORDER BY rowid")
            conn.execute("DETACH DATABASE staging")
        finally:
            conn.close()
        digest = rows_digest(temporary, image_ids)
        sha = file_sha256(temporary)
        os.replace(temporary, final)
    except BaseException:
        temporary.unlink(missing_ok=True)
        raise
    return relative, sha, digest


def merge_tiles(folder: str | Path, files: list[str], target: str | Path, *, features: bool = True,
                datasets: Collection[tuple[str, str]] | None = None) -> None:
    """One store at ``target`` holding every row of the tiles ``files`` (relative to ``folder``), each
    image once: written into a temporary file and renamed into place. ``features=False`` leaves the
    images' keypoint and descriptor BLOBs and the structure's points and covariances out (NULL; their
    counts and checksums stay): a catalogue of the store, whose features and points are read from the
    tiles when a query needs them. ``datasets``: only the rows of these (source, camera)s (their images
    and what is tied to them, their cameras, skipped frames and global-vector encoders) and the settings."""
    target = Path(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    temporary = target.with_name(f".{target.name}.{uuid.uuid4().hex}.tmp")
    try:
        FeatureStore(temporary, create=True).close()
        conn = sqlite3.connect(str(temporary), timeout=BUSY_TIMEOUT_S)
        try:
            conn.execute("PRAGMA journal_mode=DELETE")
            for file in files:
                conn.execute("ATTACH DATABASE ? AS tile", [(Path(folder) / file).absolute().as_uri() + "?mode=ro"])
                if datasets is not None:
                    _want_datasets(conn, datasets, "tile")
                with conn:
                    for table in (*_WHOLE, *_IMAGE_KEYED):
                        columns = _columns(conn, "main", table)
                        names = ", ".join(f"[{c}]" for c in columns)
                        picked = ", ".join("NULL" if not features and c in _CATALOGUE_LEAVES_OUT.get(table, ())
                                           else f"[{c}]" for c in columns)
                        where = "" if datasets is None else _tile_rows(table)
                        conn.execute(f"INSERT OR IGNORE INTO main.[{table}] ({names}) SELECT {picked} "
                                     f"FROM tile.[{table}]{where} ORDER BY rowid")
                conn.execute("DETACH DATABASE tile")
        finally:
            conn.close()
        os.replace(temporary, target)
    except BaseException:
        temporary.unlink(missing_ok=True)
        raise


def _want_datasets(conn: sqlite3.Connection, datasets: Collection[tuple[str, str]], schema: str) -> None:
    """``_want``'s temporary tables for the images of ``datasets`` in ``schema`` (emptied first: one tile
    after another is attached as ``schema``)."""
    conn.execute("CREATE TEMP TABLE IF NOT EXISTS wanted (id INTEGER PRIMARY KEY)")
    conn.execute("CREATE TEMP TABLE IF NOT EXISTS wanted_datasets (source TEXT, camera TEXT, prefix TEXT)")
    conn.execute("DELETE FROM temp.wanted")
    conn.execute("DELETE FROM temp.wanted_datasets")
    conn.executemany("INSERT INTO wanted_datasets VALUES (?, ?, 'vlad:' || ? || '/' || ? || ':')",
                     [(s, c, s, c) for s, c in sorted(datasets)])
    conn.execute(f"INSERT INTO wanted SELECT id FROM [{schema}].images WHERE (source, camera) IN "
                 "(SELECT source, camera FROM wanted_datasets)")


def tile_features(path: str | Path, image_ids: list[int]) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """image id -> (keypoints_f32, descriptors_u8) of ``image_ids`` from the tile at ``path`` (each checked
    against its CRC-32); ``StoreError`` naming the file when it cannot be read."""
    with FeatureStore(path, read_only=True) as store:
        return store.features(image_ids)


def tile_structure_points(path: str | Path, image_ids: list[int], params_json: str
                          ) -> dict[int, dict[str, tuple[np.ndarray, np.ndarray]]]:
    """image id -> variant -> (points_f64 (M, 3), cov_f64 (M, 3, 3)) of the structure of ``image_ids`` made
    with ``params_json``, from the tile at ``path`` (each checked against its CRC-32)."""
    with FeatureStore(path, read_only=True) as store:
        records = StructureTable(store).get(image_ids, params_json)
    out: dict[int, dict[str, tuple[np.ndarray, np.ndarray]]] = {}
    for (image_id, variant), r in records.items():
        out.setdefault(image_id, {})[variant] = (r.points_f64, r.cov_f64)
    return out


def table_bytes(path: str | Path) -> dict[str, int]:
    """Table -> the bytes its pages (indexes included) take in the store at ``path`` (SQLite's dbstat)."""
    conn = connect(Path(path), str(path), read_only=True)
    try:
        out: dict[str, int] = {}
        for name, table, size in conn.execute("SELECT d.name, m.tbl_name, sum(d.pgsize) FROM dbstat d "
                                              "JOIN sqlite_master m ON m.name = d.name GROUP BY d.name"):
            out[table] = out.get(table, 0) + int(size)
        return out
    finally:
        conn.close()


def staging_images(path: str | Path) -> list[tuple[int, str, str, int, float, float, float]]:
    """(id, source, camera, frame, timestamp_s, lat_deg, lon_deg) of every image of the store at ``path``."""
    db = sqlite_utils.Database(connect(Path(path), str(path), read_only=True))
    try:
        return [tuple(r) for r in db.execute("SELECT id, source, camera, frame, timestamp_s, lat_deg, lon_deg "
                                             "FROM images ORDER BY id").fetchall()]
    finally:
        db.close()
