"""Building a store: SIFT of every frame, then what the refined and camera-rate methods read from it
(global vectors, triangulated structure, the self-check). The workspace only keeps and hands out
what these make; every step is resumable and skips what the store already holds.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from visloc.db import StructureRecord
from visloc.features.vlad import train_encoder
from visloc.params import FAST, REFINED, FastParams, RefinedParams, SiftParams
from visloc.pose.refined import StructureCache
from visloc.pose.selfcheck import pose_record, self_check, self_check_settings_json
from visloc.pose.structure import VARIANTS, seeded_structure_cache, structure_settings_json, view_structures
from visloc.sources.drives import Sequence
from visloc.sources.imagesize import DEFAULT_MAX_IMAGE_MP
from visloc.store.ingest import IngestReport
from visloc.store.workspace import Workspace, global_vectors_name

Progress = Callable[[int, int], None] | None


def ingest_sequence(ws: Workspace, sequence: Sequence, sift: SiftParams, *, workers: int | None = None,
                    limit: int | None = None, progress: Progress = None, structure_progress: Progress = None,
                    structure: bool = True, skip_bad_frames: bool = False, max_image_mp: float = DEFAULT_MAX_IMAGE_MP,
                    vectors_progress: Progress = None, self_check_progress: Progress = None,
                    repair: bool = False) -> IngestReport:
    """SIFT every frame of ``sequence`` the store lacks (``Workspace.add_features``; ``repair``: and those
    whose features are damaged), then its global vectors, its structure and its self-check
    (``structure=False``: SIFT only); resumable."""
    report = ws.add_features(sequence, sift, workers=workers, limit=limit, progress=progress,
                             skip_bad_frames=skip_bad_frames, max_image_mp=max_image_mp, repair=repair)
    if structure and ws.stored_frame_count(sequence.source, sequence.camera):
        build_global_vectors(ws, sequence.source, sequence.camera, progress=vectors_progress)
        build_structure(ws, sequence.source, sequence.camera, progress=structure_progress)
        build_self_check(ws, sequence.source, sequence.camera, progress=self_check_progress)
    return report


def build_global_vectors(ws: Workspace, source: str, camera: str, params: FastParams = FAST,
                         progress: Progress = None) -> int:
    """Train the global-vector encoder of (source, camera) if the store has none, and encode every image
    that lacks a vector; returns how many were encoded. Images added later are encoded with the
    encoder trained first."""
    name = global_vectors_name(source, camera, params)
    ids = ws.image_ids(source, camera)
    have = ws.stored_vector_ids(name)
    todo = [int(i) for i in ids if int(i) not in have]
    if not todo:
        return 0
    if progress:  # training the encoder comes first: the count moves once encoding starts
        progress(0, len(todo))
    if ws.has_global_index(name):
        encoder = ws.load_global_encoder(name)
    else:
        descriptors = [d for _, d in ws.iter_descriptors(ids.tolist())]
        encoder = train_encoder(descriptors, params.n_words, params.pca_dim, params.train_descriptors, params.seed)
        ws.save_global_encoder(name, encoder)
    for start in range(0, len(todo), 256):
        chunk = todo[start : start + 256]
        ws.add_global_vectors(name, chunk, np.stack([encoder.encode(d) for _, d in ws.iter_descriptors(chunk)]))
        if progress:
            progress(start + len(chunk), len(todo))
    return len(todo)


def build_structure(ws: Workspace, source: str, camera: str, params: RefinedParams = REFINED,
                    progress: Progress = None) -> int:
    """Triangulate every image of (source, camera) the store holds no structure for (made with
    ``params``' structure settings), each variant of ``visloc.pose.structure``, committing image by
    image: an interrupted build resumes. Nothing to do without calibration and attitudes.
    Returns the images built."""
    settings = structure_settings_json(params)
    ids = ws.image_ids(source, camera)
    done = ws.structure_complete_ids(ids.tolist(), settings, len(VARIANTS))
    if len(done) == len(ids):
        return 0
    db = ws.load_database(source, camera)
    geometry = db.geometry()
    if geometry.camera is None:
        return 0
    ids_of = [im.image_id for im in db.images]
    todo = [k for k, image_id in enumerate(ids_of) if image_id not in done]
    if progress:
        progress(0, len(todo))
    for n, k in enumerate(todo, 1):
        ws.save_structure([StructureRecord(ids_of[k], s.variant, settings, tuple(ids_of[j] for j in s.neighbours),
                                           s.rows, s.points_world, s.cov_world, s.reason, s.build_ms)
                           for s in view_structures(geometry, k, params, StructureCache())])
        if progress:
            progress(n, len(todo))
    return len(todo)


def build_self_check(ws: Workspace, source: str, camera: str, params: RefinedParams = REFINED,
                     progress: Progress = None) -> int:
    """Pose every image of (source, camera) that has no self-check with ``params``' settings as a query
    of its own drive (``visloc.pose.selfcheck``), committing every few images: an interrupted check
    resumes. Nothing to do without calibration, attitudes or global vectors. Returns the images checked."""
    settings = self_check_settings_json(params)
    ids = ws.image_ids(source, camera)
    done = ws.self_checked_ids(ids.tolist(), settings)
    if len(done) == len(ids):
        return 0
    db = ws.load_database(source, camera)
    geometry = db.geometry()
    index = ws.load_database_index(db)
    if geometry.camera is None or index is None:
        return 0
    ids_of = [im.image_id for im in db.images]
    todo = [k for k, image_id in enumerate(ids_of) if image_id not in done]
    if progress:
        progress(0, len(todo))
    cache = seeded_structure_cache(ws.load_structure(db, params))  # the views' stored structure, read
    for start in range(0, len(todo), 16):
        chunk = todo[start : start + 16]
        poses = self_check(geometry, db.east_north_m, db.timestamps_s, db.keypoints_f32, db.descriptors_u8,
                           index.vectors_f32, params, indices=chunk, cache=cache)
        ws.add_self_checks([pose_record(p, ids_of[p.index], settings) for p in poses])
        if progress:
            progress(start + len(chunk), len(todo))
    return len(todo)
