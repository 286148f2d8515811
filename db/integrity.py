"""Finding damage in a store, and clearing what was made from damaged or replaced rows.

``scan`` reads every BLOB of a store once (a chunk at a time) and yields a ``Damage`` for each row that
fails: a BLOB that is NULL, of another size than its row states, or whose bytes fail the CRC-32 stored
beside them; a count that is not a count; a row that names an image the store lacks. ``sqlite_problems``
is SQLite's own integrity check, ``missing_schema`` the tables and columns the schema needs but the
store lacks. ``forget_derived`` deletes what was made from images that ingest replaced (their
structure and that of images triangulated with them, the global vectors and encoders of their
drive, self-checks, cached counts), so the build steps make it again from the new features;
``move_geotags`` what was made from the geotags of a drive whose geotags its source now states otherwise.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass

import numpy as np

from visloc.db.arrays import GLOBAL_VECTOR, NAMED_ARRAY, arrays_of, chunks
from visloc.db.blobs import blob_problem
from visloc.db.schema import lacking, missing_names
from visloc.db.store import FeatureStore, where_drive

CHUNK_ROWS = 64  # rows whose BLOBs are in memory at a time
PAIR_COUNT_TABLES = ("pair_counts", "selected_pair_counts")  # cached counts: of the features as stored, selected


@dataclass(frozen=True)
class Damage:
    """One damaged row. ``table`` and ``key`` find it (``key``: images: (id,); structures: (image_id,
    variant); global_vectors: (name, image_id); arrays: (key,); the store as a whole: ()), ``image``
    names the image it belongs to ("drive/camera frame N"; an array: "array KEY"), ``problem`` says
    what is wrong."""

    table: str
    key: tuple
    image: str
    problem: str
    source: str | None = None
    camera: str | None = None
    frame: int | None = None


def sqlite_problems(store: FeatureStore) -> list[str]:
    """What SQLite's own integrity check finds (empty when it finds nothing)."""
    rows = [r[0] for r in store.db.execute("PRAGMA integrity_check")]
    return [] if rows == ["ok"] else rows


def missing_schema(store: FeatureStore) -> list[str]:
    """The tables, columns and indexes the schema needs that the store lacks, named."""
    return missing_names(lacking(store.db))


def row_counts(store: FeatureStore) -> dict[str, int]:
    tables = set(store.db.table_names())
    return {t: store.db.execute(f"SELECT count(*) FROM [{t}]").fetchone()[0] if t in tables else 0
            for t in ("images", "structures", "global_vectors", "arrays")}


def _name(row: dict) -> str:
    return f"{row['source']}/{row['camera']} frame {row['frame']}"


def _count_problem(n: object, what: str) -> str | None:
    return None if isinstance(n, int) and n >= 0 else f"{what} {n!r} is not a count"


def _chunks(store: FeatureStore, sql_ids: str, args: list, sql_rows: str) -> Iterator[dict]:
    """Rows of ``sql_rows`` (a query with ``{marks}`` for rowids) for the rowids ``sql_ids`` selects,
    ``CHUNK_ROWS`` at a time."""
    rowids = [r[0] for r in store.db.execute(sql_ids, args)]
    for chunk, marks in chunks(rowids, CHUNK_ROWS):
        yield from store.db.query(sql_rows.format(marks=marks), chunk)


def scan(store: FeatureStore, *, source: str | None = None, camera: str | None = None,
         progress: Callable[[int, int], None] | None = None) -> Iterator[Damage]:
    """Every damaged row of the store (of one drive and camera, when given), image by image: the
    image's own BLOBs, then its structure and global vectors; then the named arrays (the whole
    store only). ``progress(done, total)`` counts images."""
    tables = set(store.db.table_names())
    where, args = where_drive(source, camera)
    total = store.db.execute(f"SELECT count(*) FROM images {where}", args).fetchone()[0]
    if progress:
        progress(0, total)
    done = 0
    ids_sql = f"SELECT rowid FROM images {where} ORDER BY source, camera, frame"
    image_ids: set[int] = set()
    for r in _chunks(store, ids_sql, args, "SELECT * FROM images WHERE rowid IN ({marks}) ORDER BY source, camera, "
                                          "frame"):
        image_ids.add(r["id"])
        yield from _image_damage(r)
        done += 1
        if progress and (done % CHUNK_ROWS == 0 or done == total):
            progress(done, total)
    known = image_ids if source is not None or camera is not None else None
    if "structures" in tables:
        yield from _structure_damage(store, source, camera, known)
    if "global_vectors" in tables:
        yield from _vector_damage(store, source, camera)
    if "arrays" in tables and source is None and camera is None:
        yield from _array_damage(store)


def _array_problems(r: dict, table: str, count_what: str) -> tuple[bool, list[str]]:
    """(whether the row's count is a count, what is wrong with it or with each array of ``table`` it counts)."""
    arrays = arrays_of(table)
    n = r[arrays[0].count]
    problem = _count_problem(n, count_what)
    if problem:
        return False, [problem]
    return True, [p for a in arrays if (p := a.problem(r, n))]


def _image_damage(r: dict) -> Iterator[Damage]:
    _, problems = _array_problems(r, "images", "keypoint count")
    for problem in problems:
        yield Damage("images", (r["id"],), _name(r), problem, r["source"], r["camera"], r["frame"])


def _structure_damage(store: FeatureStore, source: str | None, camera: str | None,
                      known: set[int] | None) -> Iterator[Damage]:
    where, args = where_drive(source, camera, "i.")
    all_ids = known if known is not None else {r[0] for r in store.db.execute("SELECT id FROM images")}
    ids_sql = (f"SELECT s.rowid FROM structures s LEFT JOIN images i ON i.id = s.image_id {where} "
               "ORDER BY i.source, i.camera, i.frame, s.variant")
    rows_sql = ("SELECT s.*, i.source, i.camera, i.frame FROM structures s LEFT JOIN images i ON i.id = s.image_id "
                "WHERE s.rowid IN ({marks}) ORDER BY i.source, i.camera, i.frame, s.variant")
    for r in _chunks(store, ids_sql, args, rows_sql):
        def damage(problem: str, r=r) -> Damage:
            image = _name(r) if r["source"] is not None else f"image id {r['image_id']}"
            return Damage("structures", (r["image_id"], r["variant"]), image, f"structure ({r['variant']}) {problem}",
                          r["source"], r["camera"], r["frame"])

        if r["source"] is None:
            yield damage("belongs to no stored image")
            continue
        counted, problems = _array_problems(r, "structures", "point count")
        yield from map(damage, problems)
        if not counted:
            continue
        try:
            neighbours = [int(i) for i in json.loads(r["neighbour_ids_json"])]
        except (TypeError, ValueError):
            yield damage("neighbour list is not a list of image ids")
            continue
        if known is None and not set(neighbours) <= all_ids:
            yield damage(f"names neighbours the store lacks ({sorted(set(neighbours) - all_ids)[:3]})")


def _vector_damage(store: FeatureStore, source: str | None, camera: str | None) -> Iterator[Damage]:
    where, args = where_drive(source, camera, "i.")
    sizes = dict(store.db.execute("SELECT name, length(vector_f32) AS n FROM global_vectors GROUP BY name, n "
                                  "ORDER BY count(*)").fetchall())  # each name's most common size
    ids_sql = (f"SELECT v.rowid FROM global_vectors v LEFT JOIN images i ON i.id = v.image_id {where} "
               "ORDER BY v.name, i.source, i.camera, i.frame")
    rows_sql = ("SELECT v.*, i.source, i.camera, i.frame FROM global_vectors v LEFT JOIN images i "
                "ON i.id = v.image_id WHERE v.rowid IN ({marks}) ORDER BY v.name, i.source, i.camera, i.frame")
    for r in _chunks(store, ids_sql, args, rows_sql):
        image = _name(r) if r["source"] is not None else f"image id {r['image_id']}"
        size = sizes.get(r["name"]) or 0
        problem = ("belongs to no stored image" if r["source"] is None
                   else blob_problem(r[GLOBAL_VECTOR.blob], size, r[GLOBAL_VECTOR.crc]))
        if problem:
            yield Damage("global_vectors", (r["name"], r["image_id"]), image, f"global vector ({r['name']}) {problem}",
                         r["source"], r["camera"], r["frame"])


def _array_damage(store: FeatureStore) -> Iterator[Damage]:
    for (key,) in store.db.execute("SELECT key FROM arrays ORDER BY key").fetchall():
        r = next(store.db.query("SELECT * FROM arrays WHERE key = ?", [key]))
        try:
            shape = json.loads(r["shape_json"])
            size = int(np.prod(shape)) * np.dtype(r["dtype"]).itemsize
        except (TypeError, ValueError):
            yield Damage("arrays", (key,), f"array {key}", "shape or type cannot be read")
            continue
        problem = blob_problem(r[NAMED_ARRAY.blob], size, r[NAMED_ARRAY.crc])
        if problem:
            yield Damage("arrays", (key,), f"array {key}", problem)


def forget_damage(store: FeatureStore, damage: Iterable[Damage]) -> None:
    """Delete the damaged rows of structure, global vectors and arrays (ingest builds them again); a
    damaged array takes every global vector of the encoder it belongs to with it. Image rows are
    not deleted here: ingest replaces them in place (``FeatureStore.replace_images``)."""
    damage = list(damage)
    with store.db.atomic():
        for d in damage:
            if d.table == "structures":
                store.db.execute("DELETE FROM structures WHERE image_id = ? AND variant = ?", list(d.key))
            elif d.table == "global_vectors":
                store.db.execute("DELETE FROM global_vectors WHERE name = ? AND image_id = ?", list(d.key))
            elif d.table == "arrays":
                names = [r[0] for r in store.db.execute("SELECT DISTINCT name FROM global_vectors")]
                for name in [n for n in names if d.key[0].startswith(n + "_")]:
                    _forget_encoder(store, name)
                store.db.execute("DELETE FROM arrays WHERE key = ?", list(d.key))


def _forget_encoder(store: FeatureStore, name: str) -> None:
    store.db.execute("DELETE FROM global_vectors WHERE name = ?", [name])
    store.db.execute("DELETE FROM arrays WHERE substr(key, 1, ?) = ?", [len(name) + 1, name + "_"])


def forget_derived(store: FeatureStore, source: str, camera: str, image_ids: Iterable[int]) -> None:
    """Delete what was made from the features of ``image_ids`` (images of ``source``/``camera`` that ingest
    replaced), in one transaction: their structure and the structure of every image triangulated with
    one of them, the global vectors of the drive's camera and the encoders that made them (trained on
    its descriptors), its self-checks, and the cached counts of pairs with one of them."""
    ids = {int(i) for i in image_ids}
    if not ids:
        return
    in_drive = "IN (SELECT id FROM images WHERE source = ? AND camera = ?)"
    with store.db.atomic():
        for image_id, variant, neighbours in store.db.execute(
                f"SELECT image_id, variant, neighbour_ids_json FROM structures WHERE image_id {in_drive}",
                [source, camera]).fetchall():
            try:
                used = {int(i) for i in json.loads(neighbours)}
            except (TypeError, ValueError):
                used = ids
            if image_id in ids or used & ids:
                store.db.execute("DELETE FROM structures WHERE image_id = ? AND variant = ?", [image_id, variant])
        names = [r[0] for r in store.db.execute(f"SELECT DISTINCT name FROM global_vectors WHERE image_id {in_drive}",
                                                [source, camera])]
        for name in names:
            _forget_encoder(store, name)
        store.db.execute(f"DELETE FROM self_checks WHERE image_id {in_drive}", [source, camera])
        for chunk, marks in chunks(sorted(ids), 400):
            for table in PAIR_COUNT_TABLES:
                store.db.execute(f"DELETE FROM {table} WHERE query_image_id IN ({marks}) OR db_image_id IN ({marks})",
                                 [*chunk, *chunk])


def move_geotags(store: FeatureStore, source: str, camera: str, geotags_deg: dict[int, tuple[float, float]]) -> int:
    """Set the geotag (lat, lon) of stored frames of ``source``/``camera`` and delete what was made from the
    drive's geotags (the structure of each of its images, triangulated at the geotags' poses, and its
    self-checks), in one transaction: the build steps make them again. Features, global vectors and cached
    counts are the images' own and stay. Returns rows changed."""
    if not geotags_deg:
        return 0
    changed = 0
    in_drive = "IN (SELECT id FROM images WHERE source = ? AND camera = ?)"
    with store.db.atomic():
        for frame, (lat, lon) in geotags_deg.items():
            changed += store.db.execute("UPDATE images SET lat_deg = ?, lon_deg = ? WHERE source = ? AND camera = ? "
                                        "AND frame = ?", [float(lat), float(lon), source, camera, int(frame)]).rowcount
        store.db.execute(f"DELETE FROM structures WHERE image_id {in_drive}", [source, camera])
        store.db.execute(f"DELETE FROM self_checks WHERE image_id {in_drive}", [source, camera])
    return changed


def clear_pair_counts(store: FeatureStore) -> int:
    """Forget every cached image-pair count (a store as ingest leaves it); returns how many there were."""
    n = 0
    with store.db.atomic():
        for table in PAIR_COUNT_TABLES:
            n += store.db.execute(f"SELECT COUNT(*) FROM {table}").fetchone()[0]
            store.db.execute(f"DELETE FROM {table}")
    return int(n)


def drive_blobs(store: FeatureStore, source: str, camera: str) -> list[bytes]:
    """Every BLOB a run loads for (source, camera): its images' keypoints and descriptors, their
    structure and global vectors (to time what checking them costs)."""
    blobs = [b for row in store.db.execute(
        "SELECT keypoints_f32, descriptors_u8 FROM images WHERE source = ? AND camera = ?", [source, camera])
        for b in row]
    blobs += [b for row in store.db.execute(
        "SELECT s.rows_i32, s.points_f64, s.cov_f64 FROM structures s JOIN images i ON i.id = s.image_id "
        "WHERE i.source = ? AND i.camera = ?", [source, camera]) for b in row]
    blobs += [r[0] for r in store.db.execute(
        "SELECT v.vector_f32 FROM global_vectors v JOIN images i ON i.id = v.image_id "
        "WHERE i.source = ? AND i.camera = ?", [source, camera])]
    return [b for b in blobs if b is not None]
