"""A sharded store: building it on a distributed engine, and reading it.

Ingest runs in three stages. Feature extraction is spread over the cluster's workers image by image
into the store's working file (``work/staging.sqlite``, today's format: resumable, checksummed);
the global vectors, structure and self-check of each drive are made there as for a single file;
then every tile is cut from it by one task, written whole into a temporary file, renamed into
place and only then recorded in the manifest. A tile the manifest records with the same rows
(``rows_digest``) and a file that still has its checksum is skipped: a killed ingest run again
redoes only what it had not finished.

Reading: ``TileIndex`` picks the tiles a gate touches from the manifest, and the global index
answers a query without a prediction; ``merged_store`` gives the commands the store's catalogue (every
row but the features, cached by the tiles' checksums), and ``visloc.store.tilecache`` reads the features
of the tiles a query touches.
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
from collections.abc import Callable, Collection
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from visloc.db.records import StoreError
from visloc.db.shards import (STAGING_NAME, Grid, Manifest, TileRecord, file_sha256, merge_tiles, rows_digest,
                              staging_images, write_tile)
from visloc.errors import InputError
from visloc.store.cluster import Cluster
from visloc.store.tiles import (cell_bounds_m, cells_within, owner_cells, tile_key, tiles_of_images, to_grid_m,
                                utm_epsg)

DEFAULT_HALO_M = 50.0  # wider than the refined method's widest neighbour baseline, so a view's neighbours are in its tile


@dataclass(frozen=True)
class TilesReport:
    n_tiles: int
    n_written: int
    n_skipped: int  # complete already: same rows, file intact
    n_images: int
    n_copies: int  # images stored, halo copies included


def staging_path(folder: str | Path) -> Path:
    return Path(folder) / STAGING_NAME


def prepare_store(folder: str | Path, tile_m: float, halo_m: float, lat_deg: float, lon_deg: float) -> Grid:
    """Make the sharded store ``folder`` (its manifest and working store) with a grid of ``tile_m`` tiles
    in the UTM zone of (``lat_deg``, ``lon_deg``), or check that the one there has that grid."""
    staging_path(folder).parent.mkdir(parents=True, exist_ok=True)
    try:
        with Manifest(folder, create=True) as manifest:
            grid = manifest.grid() or Grid(utm_epsg(lat_deg, lon_deg), float(tile_m), float(halo_m))
            manifest.require_grid(Grid(grid.epsg, float(tile_m), float(halo_m)))
            return grid
    except StoreError as exc:
        raise InputError(str(exc)) from None


def publish_tiles(folder: str | Path, cluster: Cluster, vectors: tuple[str, dict[int, np.ndarray]] | None = None,
                  progress: Callable[[int, int], None] | None = None) -> TilesReport:
    """Cut every tile from the working store into ``folder``/tiles, one task per tile on ``cluster``,
    and record each in the manifest as it is published; then write the global index, with the global
    vectors ``vectors`` (their name, image id -> vector; ``Workspace.global_vectors_by_image``)."""
    folder = Path(folder)
    staging = staging_path(folder)
    rows = staging_images(staging)
    if not rows:
        raise InputError(f"{folder}: no images to cut into tiles")
    ids = np.array([r[0] for r in rows], np.int64)
    lat, lon = np.array([r[5] for r in rows]), np.array([r[6] for r in rows])
    with Manifest(folder) as manifest:
        grid = manifest.grid()
        known = {t.key: t for t in manifest.tiles()}
    east_north = to_grid_m(grid.epsg, lat, lon)
    owners = owner_cells(east_north, grid.tile_m)
    todo, records, n_copies = [], {}, 0
    for cell, members in tiles_of_images(east_north, grid.tile_m, grid.halo_m).items():
        owned = members[(owners[members] == np.array(cell)).all(axis=1)]
        if not len(owned):
            continue  # only halo here: a gate looks each image up in its owner tile
        key = tile_key(*cell)
        member_ids = ids[members].tolist()
        n_copies += len(member_ids)
        digest = rows_digest(staging, member_ids)
        have = known.get(key)
        if (have is not None and have.rows_digest == digest and (folder / have.file).is_file()
                and file_sha256(folder / have.file) == have.sha256):
            continue
        datasets: dict[tuple[str, str], list[float]] = {}
        for k in owned:
            datasets.setdefault((rows[k][1], rows[k][2]), []).append(rows[k][4])
        records[key] = TileRecord(key, int(cell[0]), int(cell[1]), cell_bounds_m(*cell, grid.tile_m), "",
                                  len(member_ids), len(owned), "", digest,
                                  tuple((s, c, len(t), min(t), max(t)) for (s, c), t in sorted(datasets.items())))
        todo.append((str(staging), str(folder), key, member_ids))
    n_tiles = sum(1 for cell in set(map(tuple, owners.tolist())))
    if progress:
        progress(0, len(todo))
    with Manifest(folder) as manifest:
        for done, (args, (file, sha, digest)) in enumerate(cluster.run_all(write_tile, todo), 1):
            record = records[args[2]]
            if digest != record.rows_digest:
                raise InputError(f"{folder}: tile {record.key} was written with other rows than asked; run the "
                                 "same command again")
            manifest.publish(TileRecord(record.key, record.ix, record.iy, record.bounds_m, file, record.n_images,
                                        record.n_owned, sha, digest, record.datasets))
            if progress:
                progress(done, len(todo))
        _write_global_index(manifest, vectors, rows, east_north, owners)
    return TilesReport(n_tiles, len(todo), n_tiles - len(todo), len(rows), n_copies)


def _write_global_index(manifest: Manifest, vectors: tuple[str, dict[int, np.ndarray]] | None, rows: list,
                        east_north: np.ndarray, owners: np.ndarray) -> None:
    """Every image's place, owner tile and global vector (when ``vectors`` holds one for each) in the manifest."""
    name, by_id = vectors if vectors is not None else ("", {})
    entries = [(r[0], r[1], r[2], r[3], r[4], float(e), float(n), tile_key(*cell))
               for r, (e, n), cell in zip(rows, east_north, owners.tolist())]
    have_all = bool(by_id) and all(r[0] in by_id for r in rows)
    manifest.put_global_index(entries, name, np.stack([by_id[r[0]] for r in rows]) if have_all else None)


def sharded_grid(folder: str | Path) -> Grid:
    """The grid of the sharded store ``folder``; ``InputError`` when it is none or has no grid yet."""
    try:
        with Manifest(folder, read_only=True) as manifest:
            grid = manifest.grid()
    except StoreError as exc:
        raise InputError(f"{exc}; give --tile-m to make one") from None
    if grid is None:
        raise InputError(f"{folder}: a sharded store without tiles yet: give --tile-m")
    return grid


# -- reading ---------------------------------------------------------------------------------------


def check_tiles(folder: str | Path) -> list[str]:
    """One line per tile whose file is missing or no longer has the checksum the manifest states."""
    with Manifest(folder, read_only=True) as manifest:
        tiles = manifest.tiles()
    return [problem for t in tiles if (problem := _tile_problem(Path(folder), t)) is not None]


def _tile_problem(folder: Path, tile: TileRecord) -> str | None:
    path = folder / tile.file
    if not path.is_file():
        return f"{path}: tile {tile.key} is missing"
    if file_sha256(path) != tile.sha256:
        return (f"{path}: tile {tile.key} does not match its checksum in the manifest (damaged or changed); "
                "'visloc ingest' of its drives into the store writes it again")
    return None


def sharded_summary(folder: str | Path) -> str:
    """One line on the sharded store ``folder``: its grid and tiles."""
    with Manifest(folder, read_only=True) as manifest:
        grid, tiles = manifest.grid(), manifest.tiles()
    owned, held = sum(t.n_owned for t in tiles), sum(t.n_images for t in tiles)
    return (f"sharded store: {len(tiles)} tiles of {grid.tile_m:g} m in EPSG:{grid.epsg} with a {grid.halo_m:g} m "
            f"halo, {owned} images owned, {held / max(owned, 1):.1f} copies each")


def _cache_folder() -> Path:
    return Path(tempfile.gettempdir()) / f"visloc-{os.getuid() if hasattr(os, 'getuid') else 0}"


def verify_tiles(folder: str | Path, tiles: list[TileRecord]) -> None:
    """Refuse, naming the file, a tile that is missing or fails the checksum the manifest states. A
    tile is hashed again only when its size or modification time changed since it last matched (as
    git checks its working tree), so opening a large store reads no tile it does not need."""
    folder = Path(folder)
    stamps_path = _cache_folder() / "tile-stamps" / (
        hashlib.sha256(str(folder.resolve()).encode()).hexdigest()[:24] + ".json")
    try:
        known = json.loads(stamps_path.read_text())
    except (OSError, ValueError):
        known = {}
    fresh = {}
    for t in tiles:
        try:
            st = (folder / t.file).stat()
        except OSError:
            raise InputError(_tile_problem(folder, t)) from None
        stamp = [t.sha256, st.st_size, st.st_mtime_ns]
        if known.get(t.file) != stamp and (problem := _tile_problem(folder, t)) is not None:
            raise InputError(problem)
        fresh[t.file] = stamp
    if fresh != known:
        stamps_path.parent.mkdir(parents=True, exist_ok=True)
        temporary = stamps_path.with_name(f".{stamps_path.name}.{os.getpid()}.tmp")
        temporary.write_text(json.dumps(fresh))
        os.replace(temporary, stamps_path)


def merged_store(folder: str | Path, *, features: bool = True,
                 datasets: Collection[tuple[str, str]] | None = None) -> Path:
    """One store file holding every tile of the sharded store ``folder`` (each image once), made at the
    first read and kept in the temporary folder under the digest of the tiles' checksums: a store that
    changes gets a new one, which replaces the one made before for the same folder. ``features=False``:
    its catalogue, every row but the images' keypoints and descriptors, which ``visloc.store.tilecache``
    reads from the tiles a query needs. ``datasets``: of these (source, camera)s only, merged from the
    tiles that own their images (none: the store's settings, from one tile). Refuses a store with a tile
    that is missing or fails its checksum (``verify_tiles``)."""
    folder = Path(folder)
    with Manifest(folder, read_only=True) as manifest:
        tiles = manifest.tiles()
    if not tiles:
        raise InputError(f"{folder}: a sharded store without tiles yet (build it with 'visloc ingest --tile-m')")
    verify_tiles(folder, tiles)
    kind = "store" if features else "catalogue without points"  # a catalogue once held the structure's points
    if datasets is not None:
        wanted = sorted(set(datasets))
        kind += " of " + "".join(f"{s}/{c};" for s, c in wanted)  # "of " alone: the settings only
        tiles = [t for t in tiles if any((d[0], d[1]) in set(wanted) for d in t.datasets)] or tiles[:1]
    digest = hashlib.sha256((kind + "".join(f"{t.key}:{t.sha256};" for t in tiles)).encode()).hexdigest()[:24]
    place = hashlib.sha256(f"{kind}:{folder.resolve()}".encode()).hexdigest()[:12]
    target = _cache_folder() / f"{place}-{digest}.sqlite"
    if not target.is_file():
        merge_tiles(folder, [t.file for t in tiles], target, features=features, datasets=datasets)
        for older in target.parent.glob(f"{place}-*.sqlite"):  # what this folder held before it changed
            if older != target:
                older.unlink(missing_ok=True)  # a reader that has it open reads on; the next one merges anew
    return target


def held_datasets(folder: str | Path) -> list[tuple[str, str]]:
    """The (source, camera)s the sharded store ``folder`` holds images of, from its manifest."""
    with Manifest(folder, read_only=True) as manifest:
        return sorted({(d[0], d[1]) for t in manifest.tiles() for d in t.datasets})


class Catalogue:
    """The catalogue a ``Workspace`` reads a sharded store's rows from (``merged_store`` without features):
    of the datasets it was asked for so far, merged again when a command asks for another one. A
    command reads the tiles of the drives it uses, however many the city holds."""

    def __init__(self, folder: str | Path):
        self.folder = Path(folder)
        self.covered: frozenset[tuple[str, str]] = frozenset()
        self._path = merged_store(self.folder, features=False, datasets=self.covered)

    @property
    def path(self) -> Path:
        """Its file; merged again if it is gone (another process extended the store, and replaced it)."""
        if not self._path.is_file():
            self._path = merged_store(self.folder, features=False, datasets=self.covered)
        return self._path

    def cover(self, datasets: Collection[tuple[str, str]]) -> Path:
        """The catalogue holding ``datasets`` too; returns its file."""
        wanted = self.covered | {(str(s), str(c)) for s, c in datasets}
        if wanted != self.covered:
            self._path = merged_store(self.folder, features=False, datasets=wanted)
            self.covered = frozenset(wanted)
        return self.path

    def cover_all(self) -> Path:
        return self.cover(held_datasets(self.folder))

    def image_count(self) -> int:
        with Manifest(self.folder, read_only=True) as manifest:
            return sum(t.n_owned for t in manifest.tiles())


def owner_tiles(folder: str | Path, source: str, camera: str) -> dict[int, str]:
    """image id -> the tile that owns it, for (``source``, ``camera``) of the sharded store ``folder``."""
    with Manifest(folder, read_only=True) as manifest:
        return manifest.owner_tiles(source, camera)


@dataclass(frozen=True)
class TileIndex:
    """The tiles of a sharded store as arrays, to pick those a query must open."""

    tile_m: float
    cells: np.ndarray  # (T, 2) grid cell of each tile
    files: tuple[str, ...]
    _row_of: dict

    @classmethod
    def of(cls, tile_m: float, cells: np.ndarray, files: tuple[str, ...]) -> "TileIndex":
        cells = np.asarray(cells, np.int64).reshape(-1, 2)
        return cls(float(tile_m), cells, tuple(files), {(int(a), int(b)): k for k, (a, b) in enumerate(cells)})

    @classmethod
    def from_manifest(cls, folder: str | Path) -> "TileIndex":
        with Manifest(folder, read_only=True) as manifest:
            grid, tiles = manifest.grid(), manifest.tiles()
        return cls.of(grid.tile_m, np.array([(t.ix, t.iy) for t in tiles]), tuple(t.file for t in tiles))

    def for_gate(self, center_m: np.ndarray, radius_m: float) -> list[int]:
        """Rows of the tiles that hold an image within ``radius_m`` of ``center_m`` (grid metres)."""
        rows = (self._row_of.get((int(a), int(b))) for a, b in cells_within(center_m, radius_m, self.tile_m))
        return [r for r in rows if r is not None]


class GlobalSearch:
    """Exact inner-product search over every image's global vector (the manifest's global index), for
    a query without a prediction: its nearest images and the tiles that own them."""

    def __init__(self, vectors_f32: np.ndarray, tiles: np.ndarray):
        import faiss

        self.index = faiss.IndexFlatIP(vectors_f32.shape[1])
        self.index.add(np.ascontiguousarray(vectors_f32, np.float32))
        self.tiles = np.asarray(tiles, object)

    def tiles_for(self, query_f32: np.ndarray, k: int = 10) -> tuple[np.ndarray, list]:
        """(rows of the ``k`` nearest images, the distinct tiles owning them, best first)."""
        _, rows = self.index.search(np.ascontiguousarray(query_f32, np.float32).reshape(1, -1), k)
        rows = rows[0][rows[0] >= 0]
        return rows, list(dict.fromkeys(self.tiles[rows].tolist()))
