"""A synthetic database of many images (100 000 by default) for the lost-query scale test.

Places lie 1 m apart along a straight east-west road. Each place anchors
``LANDMARKS_PER_PLACE`` random SIFT-like descriptors (non-negative, L2 norm about
512, whole numbers 0..255); an image sees a random subset of the landmarks
anchored within +-``VISIBLE_PLACES`` places of it, each with fresh noise, so
neighbouring images share most landmarks and far ones share none. A query of
place j is another noisy view of place j. Everything is seeded.

``build_store`` writes the images in batches (features, geotags, one VLAD+PCA
vector per image from an encoder trained on the first batch, and a few stored 3D
points per image, as ingest stores structure), never holding more than one batch.
``lost_query`` then localizes a query from the store the way a first or lost query
would: global vectors only in memory, a shortlist, the shortlist's descriptors
streamed from SQLite for the paper's exact counts and its structure read for posing.
"""

from __future__ import annotations

import resource
import time
from functools import lru_cache
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from visloc.db import ImageRecord, StructureRecord
from visloc.retrieval.matching import count_correspondences_with
from visloc.params import PAPER_MATCH
from visloc.features.vlad import GlobalEncoder, fit_pca, shortlist, train_codebook
from visloc.store.workspace import Workspace

LANDMARKS_PER_PLACE = 16
VISIBLE_PLACES = 2
SOURCE, CAMERA = "synthetic", "cam0"
VECTORS_NAME = "vlad"
STRUCTURE_SETTINGS = '{"synthetic": true}'
LAT0_DEG, LON0_DEG = 49.0, 8.4
METRES_PER_DEG_LON = 111_195.0 * np.cos(np.radians(LAT0_DEG))


def peak_rss_mb() -> float:
    """This process's peak resident memory, MB: VmHWM of its own address space (Linux), which a
    spawned child does not inherit from its parent the way ``getrusage``'s ru_maxrss does."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


@dataclass(frozen=True)
class SyntheticSpec:
    n_images: int = 100_000
    descriptors_per_image: int = 64
    n_words: int = 32
    pca_dim: int = 128
    structure_points: int = 16  # triangulated points stored per image (the camera-rate path's structure)
    seed: int = 0

    def key(self) -> dict:
        return {"n_images": self.n_images, "descriptors_per_image": self.descriptors_per_image,
                "n_words": self.n_words, "pca_dim": self.pca_dim, "structure_points": self.structure_points,
                "seed": self.seed}


@lru_cache(maxsize=4096)  # consecutive images share landmarks: generate each place's once
def _landmarks(place: int, seed: int) -> np.ndarray:
    """(LANDMARKS_PER_PLACE, 128) float32 SIFT-like descriptors anchored at ``place``."""
    rng = np.random.default_rng([seed, 1, place])
    x = rng.gamma(0.6, 1.0, size=(LANDMARKS_PER_PLACE, 128)).astype(np.float32)
    x *= 512.0 / np.linalg.norm(x, axis=1, keepdims=True)
    return np.minimum(x, 255.0)


def _view(place: int, n_places: int, n_desc: int, seed: int, stream: int, noise: float) -> np.ndarray:
    """(n_desc, 128) uint8: a noisy view of ``place`` (stream 2: database image, 3: query)."""
    lo, hi = max(0, place - VISIBLE_PLACES), min(n_places - 1, place + VISIBLE_PLACES)
    pool = np.concatenate([_landmarks(p, seed) for p in range(lo, hi + 1)])
    rng = np.random.default_rng([seed, stream, place])
    pick = rng.choice(pool.shape[0], size=min(n_desc, pool.shape[0]), replace=False)
    x = pool[pick] + rng.normal(0.0, noise, size=(pick.size, 128)).astype(np.float32)
    return np.clip(np.rint(x), 0, 255).astype(np.uint8)


def database_image(place: int, spec: SyntheticSpec) -> np.ndarray:
    return _view(place, spec.n_images, spec.descriptors_per_image, spec.seed, 2, 6.0)


def query_image(place: int, spec: SyntheticSpec) -> np.ndarray:
    return _view(place, spec.n_images, spec.descriptors_per_image, spec.seed, 3, 8.0)


def _record(place: int) -> ImageRecord:
    return ImageRecord(source=SOURCE, camera=CAMERA, frame=place, path=f"synthetic/{place}", timestamp_s=float(place),
                       lat_deg=LAT0_DEG, lon_deg=LON0_DEG + place / METRES_PER_DEG_LON)


def _structure(image_id: int, place: int, spec: SyntheticSpec) -> StructureRecord:
    """Points seen from ``place``: a few metres ahead of it, with a 10 cm standard deviation each."""
    rng = np.random.default_rng([spec.seed, 4, place])
    n = spec.structure_points
    points = np.c_[place + rng.uniform(2, 30, n), rng.uniform(-10, 10, n), rng.uniform(-1, 4, n)]
    return StructureRecord(image_id, "both", STRUCTURE_SETTINGS, (image_id - 1, image_id + 1),
                           np.arange(n, dtype=np.int32), points, np.tile(0.01 * np.eye(3), (n, 1, 1)))


def build_store(path: Path, spec: SyntheticSpec, *, batch_size: int = 2000, progress=None) -> float:
    """Write the synthetic database to ``path`` (reused when it already holds this spec). Returns seconds."""
    start = time.perf_counter()
    if path.exists():
        ws = Workspace(path)
        if ws.setting("synthetic") == spec.key() and ws.global_vectors.has_global_index(VECTORS_NAME):
            return 0.0
    path.unlink(missing_ok=True)
    for suffix in ("-wal", "-shm"):
        Path(str(path) + suffix).unlink(missing_ok=True)
    ws = Workspace(path, create=True)
    encoder = None
    for first in range(0, spec.n_images, batch_size):
        places = range(first, min(first + batch_size, spec.n_images))
        descs = [database_image(p, spec) for p in places]
        if encoder is None:  # train on the first batch: codebook, then PCA of its VLADs
            sample = np.concatenate(descs)
            codebook = train_codebook(sample, spec.n_words, spec.seed)
            vlads = np.stack([GlobalEncoder(codebook).vlad(d) for d in descs])
            mean, basis = fit_pca(vlads, min(spec.pca_dim, len(descs)))
            encoder = GlobalEncoder(codebook, mean, basis)
        keypoints = np.zeros((spec.descriptors_per_image, 6), np.float32)
        ws.add_images([(_record(p), keypoints[: len(d)], d) for p, d in zip(places, descs)])
        if progress:
            progress(len(descs))
    # vectors and structure in a second pass over the stored images, streamed in chunks
    image_ids = ws.image_ids(SOURCE, CAMERA)
    for first in range(0, image_ids.size, batch_size):
        chunk = image_ids[first : first + batch_size]
        vecs = np.stack([encoder.encode(d) for _, d in ws.iter_descriptors(chunk)])
        ws.global_vectors.add_global_vectors(VECTORS_NAME, chunk.tolist(), vecs)
        ws.save_structure([_structure(int(i), first + k, spec) for k, i in enumerate(chunk)])
    ws.global_vectors.save_global_encoder(VECTORS_NAME, encoder)  # last: its presence marks a finished store
    ws.record_setting("synthetic", spec.key())
    return time.perf_counter() - start


def lost_query(path: Path, spec: SyntheticSpec, places: list[int], shortlist_size: int) -> dict:
    """Localize queries of ``places`` with no prior: global vectors, shortlist, exact counts on the shortlist.

    Runs in its own process (see ``bench.run``), so peak memory is this test's alone.
    """
    t0 = time.perf_counter()
    ws = Workspace(path)
    ids, index = ws.global_vectors.load_global_index(VECTORS_NAME)
    vectors, encoder = index.vectors_f32, index.encoder
    load_s = time.perf_counter() - t0
    rss_after_load_mb = peak_rss_mb()
    frame_of = {int(i): p for i, p in zip(ws.image_ids(SOURCE, CAMERA), range(spec.n_images))}
    rows = []
    for place in places:
        q = query_image(place, spec)
        t = time.perf_counter()
        short_ids = ids[shortlist(vectors, encoder.encode(q), shortlist_size)]
        t_short = time.perf_counter()
        counts = {int(i): count_correspondences_with("faiss", q, d, PAPER_MATCH)
                  for i, d in ws.iter_descriptors(short_ids.tolist())}
        best_id = max(counts, key=lambda i: (counts[i], -i))
        structure = ws.stored_structure(short_ids.tolist(), STRUCTURE_SETTINGS)  # what posing the query reads next
        t_best = time.perf_counter()
        n_points = sum(len(r.rows_i32) for r in structure.values())
        rows.append({"place": place, "shortlist_ms": (t_short - t) * 1000.0,
                     "candidates_ms": (t_best - t) * 1000.0, "structure_points_read": n_points,
                     "shortlist_has_place": bool(any(abs(frame_of[int(i)] - place) <= 1 for i in short_ids)),
                     "best_error_m": float(abs(frame_of[best_id] - place))})
    ms = np.array([r["candidates_ms"] for r in rows])
    return {
        "n_images": spec.n_images, "descriptors_per_image": spec.descriptors_per_image,
        "vector_dim": int(vectors.shape[1]), "shortlist_size": shortlist_size, "n_queries": len(rows),
        "store_mb": path.stat().st_size / 1e6, "global_vectors_mb": vectors.nbytes / 1e6,
        "index_load_s": load_s,
        "candidates_ms": {"p50": float(np.percentile(ms, 50)), "p95": float(np.percentile(ms, 95)),
                          "max": float(ms.max())},
        "shortlist_ms_p50": float(np.median([r["shortlist_ms"] for r in rows])),
        "structure_points_read_p50": float(np.median([r["structure_points_read"] for r in rows])),
        "recall_shortlist": float(np.mean([r["shortlist_has_place"] for r in rows])),
        "best_within_1m": float(np.mean([r["best_error_m"] <= 1 for r in rows])),
        "peak_rss_after_load_mb": rss_after_load_mb,
        "peak_rss_mb": peak_rss_mb(),
    }
