"""Building a store: SIFT of every frame, then what the refined and camera-rate methods read from it
(global vectors, triangulated structure, the self-check). The workspace only keeps and hands out
what these make; every step is resumable and skips what the store already holds.
"""

from __future__ import annotations

import math
import os
import uuid
from collections.abc import Callable
from contextlib import contextmanager

import numpy as np

from visloc.db import StructureRecord
from visloc.features.vlad import train_encoder
from visloc.features.sift import Query
from visloc.params import FAST, REFINED, TRACK, FastParams, RefinedParams, SiftParams
from visloc.pose.refined import StructureCache, one_blas_thread
from visloc.pose.selfcheck import (CAMERA_RATE_PARAMS, pose_record, self_check, self_check_settings_json,
                                   self_checked_indices)
from visloc.pose.structure import VARIANTS, seeded_structure_cache, structure_settings_json, view_structures
from visloc.sources.drives import Drive
from visloc.sources.imagesize import DEFAULT_MAX_IMAGE_MP
from visloc.sources.queries import extract_queries
from visloc.store.ingest import IngestReport
from visloc.store.processes import local_processes
from visloc.store.workspace import Workspace, global_vectors_name

Progress = Callable[[int, int], None] | None


def ingest_sequence(ws: Workspace, sequence: Drive, sift: SiftParams, *, workers: int | None = None,
                    limit: int | None = None, progress: Progress = None, structure_progress: Progress = None,
                    structure: bool = True, skip_bad_frames: bool = False, max_image_mp: float = DEFAULT_MAX_IMAGE_MP,
                    vectors_progress: Progress = None, self_check_progress: Progress = None,
                    camera_rate_check_progress: Progress = None,
                    repair: bool = False, cluster=None) -> IngestReport:
    """SIFT every frame of ``sequence`` the store lacks (``Workspace.add_features``; ``repair``: and those
    whose features are damaged), then its global vectors, its structure and its self-checks (the refined
    path's, then the camera-rate path's; ``structure=False``: SIFT only); resumable. ``workers``: processes of
    this machine for SIFT, structure and the refined path's self-check (default: one per core; 1: all in this
    process). ``cluster``: run those steps on a distributed engine's workers instead (``visloc.store.cluster``)."""
    report = ws.add_features(sequence, sift, workers=workers, limit=limit, progress=progress,
                             skip_bad_frames=skip_bad_frames, max_image_mp=max_image_mp, repair=repair,
                             cluster=cluster)
    if structure and ws.stored_frame_count(sequence.source, sequence.camera):
        build_global_vectors(ws, sequence.source, sequence.camera, progress=vectors_progress)
        # the self-check matches the pairs the structure did (a worker process keeps them from one to the other)
        pairs, run = StructureCache(), uuid.uuid4().hex
        with _build_processes(ws, workers, cluster) as engine:
            build_structure(ws, sequence.source, sequence.camera, progress=structure_progress, cluster=engine,
                            pairs=pairs, run=run)
            build_self_check(ws, sequence.source, sequence.camera, progress=self_check_progress, cluster=engine,
                             pairs=pairs, run=run)
        build_self_check(ws, sequence.source, sequence.camera, CAMERA_RATE_PARAMS,
                         progress=camera_rate_check_progress, camera_rate=sequence)
    return report


@contextmanager
def _build_processes(ws: Workspace, workers: int | None, cluster):
    """What structure and the self-check run on: ``cluster`` when given; else, with more than one worker
    (default: one per core), worker processes of this machine (``visloc.store.processes``: the same
    tasks, the same rows), started only if a step has enough images to spread."""
    n = workers or min(os.cpu_count() or 1, 8)
    if cluster is not None or n <= 1:
        yield cluster
        return
    with local_processes(n, str(ws.path)) as processes:
        yield processes


def build_global_vectors(ws: Workspace, source: str, camera: str, params: FastParams = FAST,
                         progress: Progress = None) -> int:
    """Train the global-vector encoder of (source, camera) if the store has none, and encode every image
    that lacks a vector; returns how many were encoded. Images added later are encoded with the
    encoder trained first."""
    name = global_vectors_name(source, camera, params)
    ids = ws.image_ids(source, camera)
    have = ws.global_vectors.stored_vector_ids(name)
    todo = [int(i) for i in ids if int(i) not in have]
    if not todo:
        return 0
    if progress:  # training the encoder comes first: the count moves once encoding starts
        progress(0, len(todo))
    if ws.global_vectors.has_global_index(name):
        encoder = ws.global_vectors.load_global_encoder(name)
    else:
        descriptors = [d for _, d in ws.iter_descriptors(ids.tolist())]
        encoder = train_encoder(descriptors, params.n_words, params.pca_dim, params.train_descriptors, params.seed)
        ws.global_vectors.save_global_encoder(name, encoder)
    for start in range(0, len(todo), 256):
        chunk = todo[start : start + 256]
        ws.global_vectors.add_global_vectors(name, chunk, np.stack([encoder.encode(d) for _, d in ws.iter_descriptors(chunk)]))
        if progress:
            progress(start + len(chunk), len(todo))
    return len(todo)


def _pending(db, done: set[int], progress) -> tuple[list[int], list[int]]:
    """(the image ids of ``db`` in its order, the rows of those not in ``done``); ``progress`` is told how many."""
    ids_of = [im.image_id for im in db.images]
    todo = [k for k, image_id in enumerate(ids_of) if image_id not in done]
    if progress:
        progress(0, len(todo))
    return ids_of, todo


def build_structure(ws: Workspace, source: str, camera: str, params: RefinedParams = REFINED,
                    progress: Progress = None, cluster=None, pairs: StructureCache | None = None,
                    run: str | None = None) -> int:
    """Triangulate every image of (source, camera) the store holds no structure for (made with
    ``params``' structure settings), each variant of ``visloc.pose.structure``, committing image by
    image: an interrupted build resumes. Nothing to do without calibration and attitudes.
    ``cluster``: triangulate on a distributed engine's workers or this machine's processes
    (``visloc.store.processes``), a few images per task, each committed as it comes back (the same rows as
    in this process). Returns the images built. ``pairs``: the database pairs matched so far, kept for the
    self-check; ``run``: the build's name on the engine's workers (``_on_cluster``)."""
    settings = structure_settings_json(params)
    ids = ws.image_ids(source, camera)
    done = ws.structure_complete_ids(ids.tolist(), settings, len(VARIANTS))
    if len(done) == len(ids):
        return 0
    db = ws.load_database(source, camera)
    geometry = db.geometry()
    if geometry.camera is None:
        return 0
    ids_of, todo = _pending(db, done, progress)
    if cluster is not None and cluster.worth_spreading(len(todo)):
        return _on_cluster(cluster, structure_records, ws.save_structure, ws, source, camera, params, todo, 4, progress,
                           run)
    pairs = pairs if pairs is not None else StructureCache()  # a view's neighbour is mostly a neighbour's view too
    for n, k in enumerate(todo, 1):
        ws.save_structure(_view_records(geometry, ids_of, k, params, settings, pairs))
        if progress:
            progress(n, len(todo))
    return len(todo)


def _view_records(geometry, ids_of: list[int], k: int, params: RefinedParams, settings: str,
                  pairs: StructureCache) -> list[StructureRecord]:
    """The structure records of database index ``k``; ``pairs``: the matches of database pairs found so far."""
    return [StructureRecord(ids_of[k], s.variant, settings, tuple(ids_of[j] for j in s.neighbours),
                            s.rows, s.points_world, s.cov_world, s.reason, s.build_ms)
            for s in view_structures(geometry, k, params, pairs)]  # with one BLAS thread


def _on_cluster(cluster, task, keep, ws: Workspace, source: str, camera: str, params: RefinedParams,
                todo: list[int], per_task: int, progress: Progress, run: str | None = None) -> int:
    """Run ``task`` on chunks of the database indices ``todo`` on the distributed engine (at most
    ``per_task`` each, ``task_sizes``), keeping each chunk's records (``keep``) as it comes back: an
    interrupted step resumes. Returns len(todo). ``run``: the build's name (default a new one), under which a worker
    keeps what it loaded from one task to the next, and from a build's structure to its self-check."""
    run = run or uuid.uuid4().hex  # workers of a cluster outlive a run: what they loaded for another is not used
    chunks, start = [], 0
    for size in task_sizes(len(todo), cluster.n_workers, per_task):
        chunks.append((str(ws.path), source, camera, params, run, todo[start : start + size]))
        start += size
    n = 0
    for args, records in cluster.run_all(task, chunks):
        keep(records)
        n += len(args[-1])
        if progress:
            progress(n, len(todo))
    return len(todo)


def task_sizes(n_items: int, n_workers: int, most: int) -> list[int]:
    """How many items each task takes, in the order the tasks are handed out: a third of what is left per
    worker, at most ``most``, shrinking to one item at the end (guided scheduling). The step after this
    one waits for the last task, so the last tasks are short: no worker is left with a long one while
    the others idle, and the first tasks are long enough that the engine's cost per task stays small."""
    sizes, left = [], n_items
    while left > 0:
        size = max(1, min(most, math.ceil(left / (3 * max(n_workers, 1)))))
        sizes.append(size)
        left -= size
    return sizes


_loaded: dict[tuple, tuple] = {}  # in a worker: the last database a task loaded, for the next task of its stage


def _database_for(path: str, source: str, camera: str, run: str):
    """(database, its geometry, a cache of its pairs' matches) of (source, camera) in the store at ``path``, loaded
    once per build step (``run``) in a worker process of the distributed engine."""
    key = (path, source, camera, run)
    if key not in _loaded:
        _loaded.clear()
        db = Workspace(path, read_only=True).load_database(source, camera)
        _loaded[key] = (db, db.geometry(), StructureCache())
    return _loaded[key]


def structure_records(path: str, source: str, camera: str, params: RefinedParams, run: str, views: list[int]
                      ) -> list[StructureRecord]:
    """A task of the distributed engine: the structure records of the database indices ``views``."""
    db, geometry, pairs = _database_for(path, source, camera, run)
    ids_of = [im.image_id for im in db.images]
    settings = structure_settings_json(params)
    return [r for k in views for r in _view_records(geometry, ids_of, k, params, settings, pairs)]


def build_self_check(ws: Workspace, source: str, camera: str, params: RefinedParams = REFINED,
                     progress: Progress = None, cluster=None, camera_rate: Drive | None = None,
                     pairs: StructureCache | None = None, run: str | None = None) -> int:
    """Pose the images of (source, camera) the self-check poses (``self_checked_indices``: every other one) that
    have no self-check with ``params``' settings as queries of their own drive (``visloc.pose.selfcheck``),
    committing every few images: an interrupted check resumes. Nothing to do without calibration, attitudes or
    global vectors. Returns the images checked. ``camera_rate``: the drive itself, for the camera-rate path's
    self-check (``params``: that path's, ``CAMERA_RATE_PARAMS``): its images described as that path
    describes a frame (``TRACK``'s scale and keypoints), posed on the stored structure (nothing to do without
    it); it triangulates nothing, so it runs in this process. ``pairs`` and ``run``: as ``build_structure``'s."""
    settings = self_check_settings_json(params, camera_rate=camera_rate is not None)
    ids = ws.image_ids(source, camera).tolist()
    wanted = {ids[k] for k in self_checked_indices(len(ids))}
    checked = ws.self_checked_ids(ids, settings)
    if wanted <= checked:
        return 0
    done = checked | (set(ids) - wanted)  # the images between are not checked
    db = ws.load_database(source, camera)
    geometry = db.geometry()
    index = ws.global_vectors.load_database_index(db)
    if geometry.camera is None or index is None:
        return 0
    stored = None
    if camera_rate is not None:
        stored = ws.load_structure(db, params)  # what that path poses on
        if not stored:
            return 0
    ids_of, todo = _pending(db, done, progress)
    if camera_rate is None and cluster is not None and cluster.worth_spreading(len(todo)):
        return _on_cluster(cluster, self_check_records, ws.add_self_checks, ws, source, camera, params, todo, 16,
                           progress, run)
    # the refined path reads the views' stored structure where it would triangulate the same
    cache = seeded_structure_cache(ws.load_structure(db, params), pairs) if camera_rate is None else None
    for start in range(0, len(todo), 16):
        chunk = todo[start : start + 16]
        queries = None if camera_rate is None else _frames_as_queries(camera_rate, db, chunk, ws.sift_params)
        with one_blas_thread():
            poses = self_check(geometry, db.east_north_m, db.timestamps_s, db.keypoints_f32, db.descriptors_u8,
                               index.vectors_f32, params, indices=chunk, cache=cache,
                               stored=stored, queries=queries)
        ws.add_self_checks([pose_record(p, ids_of[p.index], settings) for p in poses])
        if progress:
            progress(start + len(chunk), len(todo))
    return len(todo)


def _frames_as_queries(drive: Drive, db, indices: list[int], store_sift: SiftParams) -> dict[int, Query]:
    """Database index -> its frame of ``drive`` described as the camera-rate path describes a frame (the store's
    SIFT settings at ``TRACK``'s scale and keypoints), for the database indices ``indices`` the drive holds."""
    position_of = {f.frame: i for i, f in enumerate(drive.frames)}
    wanted = [(k, position_of[db.images[k].frame]) for k in indices if db.images[k].frame in position_of]
    sift = store_sift.replace(image_scale=TRACK.query_image_scale, n_features=TRACK.query_max_keypoints)
    return {k: q for (k, _), q in zip(wanted, extract_queries(drive, [i for _, i in wanted], sift))}


def self_check_records(path: str, source: str, camera: str, params: RefinedParams, run: str, indices: list[int]
                       ) -> list:
    """A task of the distributed engine: the self-check records of the database indices ``indices``."""
    db, geometry, pairs = _database_for(path, source, camera, run)
    if ("cache", run) not in _loaded:
        ws = Workspace(path, read_only=True)
        _loaded[("cache", run)] = (seeded_structure_cache(ws.load_structure(db, params), pairs),
                                   ws.global_vectors.load_database_index(db))
    cache, index = _loaded[("cache", run)]
    settings = self_check_settings_json(params)
    ids_of = [im.image_id for im in db.images]
    with one_blas_thread():
        poses = self_check(geometry, db.east_north_m, db.timestamps_s, db.keypoints_f32, db.descriptors_u8,
                           index.vectors_f32, params, indices=indices, cache=cache)
    return [pose_record(p, ids_of[p.index], settings) for p in poses]
