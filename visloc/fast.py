"""The opt-in fast path (issue 5): the same correspondence tests, fewer and cheaper comparisons.

Three levers, each a pure function over numpy arrays:

* **Exact nearest two by faiss** (``nearest_two_faiss``): faiss's brute-force k-NN
  (``faiss.knn``, BLAS inside) instead of our float32 GEMM. Both are exact for SIFT's
  integer descriptors (every dot product is an integer below 2^24), so the
  correspondence counts are the same; ``count_correspondences_with`` picks the backend.
* **Filter gate** (``gate_mask``): while the filter tracks, only database images within
  ``gate_sigmas`` standard deviations (largest axis of the predicted position
  covariance, at least ``gate_min_radius_m``) of the predicted position are candidates.
  A first query, a lost track (no prediction) or a gate in which no candidate has a
  correspondence widens to every allowed image.
* **Global shortlist** (``GlobalEncoder``, ``shortlist``): one small vector per image
  (VLAD over SIFT with a k-means codebook trained on the database, power- and
  L2-normalised, optionally PCA-projected) ranks the candidates; only the
  ``shortlist_size`` most similar are matched exactly by the paper's two tests.

``fast_retrieve`` combines them into the same ``Retrieval`` the paper's path returns
(``candidates`` are the images matched exactly; ``allowed`` every image the gate let
through, which the refined mode may use as triangulation neighbours).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from visloc.errors import ParameterError
from visloc.matching import NearestTwo, correspondence_mask, nearest_two
from visloc.params import MatchParams, RetrievalParams, _check, _Params
from visloc.retrieval import Retrieval, candidate_mask

NN_BACKENDS = ("gemm", "faiss", "batched")


@dataclass(frozen=True)
class FastParams(_Params):
    """Parameters of the fast path.

    gate_sigmas:        gate radius in standard deviations of the predicted position (largest axis)
    gate_min_radius_m:  the gate is never narrower than this, metres
    shortlist_size:     candidates matched exactly, the most similar by global vector (0 = all in the gate)
    nn_backend:         exact nearest-two search: "batched" (every shortlisted image in one GEMM),
                        "faiss" or "gemm" (numpy float32 GEMM per image, the paper path's)
    max_keypoints:      keypoint cap: query and database images keep their this many strongest keypoints
                        (by SIFT response) for retrieval; 0 = all. Geometry always uses every keypoint.
    n_words:            k-means words of the VLAD codebook
    pca_dim:            dimension of the global vectors after PCA (0 = no PCA, n_words * 128)
    train_descriptors:  descriptors sampled from the database to train the codebook
    seed:               seed of sampling, k-means and PCA
    """

    gate_sigmas: float = 3.0
    gate_min_radius_m: float = 20.0
    shortlist_size: int = 8
    nn_backend: str = "batched"
    max_keypoints: int = 0
    n_words: int = 32
    pca_dim: int = 0
    train_descriptors: int = 100_000
    seed: int = 0

    def __post_init__(self) -> None:
        _check("gate_sigmas", self.gate_sigmas, self.gate_sigmas > 0, "> 0")
        _check("gate_min_radius_m", self.gate_min_radius_m, self.gate_min_radius_m >= 0, ">= 0")
        for name, low in (("shortlist_size", 0), ("max_keypoints", 0), ("n_words", 1), ("pca_dim", 0), ("train_descriptors", 1),
                          ("seed", 0)):
            v = getattr(self, name)
            _check(name, v, isinstance(v, int) and not isinstance(v, bool) and v >= low, f"an integer >= {low}")
        if self.nn_backend not in NN_BACKENDS:
            raise ParameterError(f"nn_backend={self.nn_backend!r}: must be one of {', '.join(NN_BACKENDS)}")


FAST = FastParams()


# -- exact nearest two by faiss -------------------------------------------------------------

def nearest_two_faiss(query_u8: np.ndarray, database_u8: np.ndarray) -> NearestTwo:
    """``matching.nearest_two`` computed by faiss's exact brute-force k-NN; same neighbours and distances."""
    import faiss

    q = np.ascontiguousarray(query_u8, dtype=np.float32)
    d = np.ascontiguousarray(database_u8, dtype=np.float32)
    n_query, n_db = q.shape[0], d.shape[0]
    if n_query == 0 or n_db < 2:
        return nearest_two(query_u8, database_u8)  # edge cases: the reference handles them
    dist_sq, index = faiss.knn(q, d, 2)
    # faiss computes |q|^2 + |d|^2 - 2 q.d in float32 too: exact for integer descriptors
    q_sq = np.einsum("ij,ij->i", q, q)
    d_sq = np.einsum("ij,ij->i", d, d)
    index1 = index[:, 0].astype(np.int64)
    dist1_sq = np.maximum(dist_sq[:, 0], 0.0).astype(np.float32)
    dist2_sq = np.maximum(dist_sq[:, 1], 0.0).astype(np.float32)
    dot1 = 0.5 * (q_sq + d_sq[index1] - dist1_sq)
    norms = np.sqrt(q_sq) * np.sqrt(d_sq[index1])
    with np.errstate(invalid="ignore", divide="ignore"):
        cosine1 = np.where(norms > 0, dot1 / norms, np.nan).astype(np.float32)
    return NearestTwo(index1, dist1_sq, dist2_sq, cosine1)


def count_correspondences_with(backend: str, query_u8: np.ndarray, database_u8: np.ndarray,
                               params: MatchParams) -> int:
    """The paper's score of one database image, nearest two found by ``backend`` ("gemm" or "faiss")."""
    if backend not in ("gemm", "faiss"):
        raise ParameterError(f"nn_backend={backend!r}: must be gemm or faiss for one image")
    nn = nearest_two_faiss(query_u8, database_u8) if backend == "faiss" else nearest_two(query_u8, database_u8)
    return int(correspondence_mask(nn, params).sum())


def count_many(query_u8: np.ndarray, db_descriptors: Sequence[np.ndarray], candidates: np.ndarray,
               params: MatchParams, *, block_bytes: int = 64 << 20) -> np.ndarray:
    """(M,) correspondence counts of the query against each candidate image, in one GEMM per block.

    The candidates' descriptors are stacked (padded to the longest with columns whose score is
    -inf) so that one large matrix product replaces M small ones; the nearest two are then
    found per candidate. The arithmetic is ``matching.nearest_two``'s, in the same float32
    order, so the counts are the same numbers (``tests/test_fast.py`` checks it).
    """
    candidates = np.asarray(candidates, np.int64)
    out = np.zeros(candidates.size, np.int64)
    q = np.asarray(query_u8, np.float32)
    if candidates.size == 0 or q.shape[0] == 0:
        return out
    q_sq = np.einsum("ij,ij->i", q, q)
    q_norm = np.sqrt(q_sq)
    sizes = np.array([len(db_descriptors[int(i)]) for i in candidates])
    width = max(int(sizes.max()), 1)
    per_block = max(1, block_bytes // (4 * width * max(q.shape[0], 1)))
    tau1_sq = params.tau1 ** 2
    for start in range(0, candidates.size, per_block):
        chunk = candidates[start : start + per_block]
        c = chunk.size
        d = np.zeros((c, width, q.shape[1]), np.float32)
        d_sq = np.full((c, width), np.inf, np.float32)
        for j, i in enumerate(chunk):
            rows = np.asarray(db_descriptors[int(i)], np.float32)
            d[j, : len(rows)] = rows
            d_sq[j, : len(rows)] = np.einsum("ij,ij->i", rows, rows)
        # score = g.f - |f|^2 / 2, maximal at the nearest f (see matching.nearest_two)
        score = (q @ d.reshape(c * width, -1).T).reshape(q.shape[0], c, width)
        score -= 0.5 * d_sq[None, :, :]
        index1 = score.argmax(axis=2)  # (Nq, c)
        best = np.take_along_axis(score, index1[:, :, None], axis=2)[:, :, 0]
        np.put_along_axis(score, index1[:, :, None], -np.inf, axis=2)
        second = score.max(axis=2)
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            dist1_sq = np.maximum(q_sq[:, None] - 2.0 * best, 0.0).astype(np.float32)
            dist2_sq = np.maximum(q_sq[:, None] - 2.0 * second, 0.0).astype(np.float32)
            d_sq1 = d_sq[np.arange(c)[None, :], index1]
            dot1 = best + 0.5 * d_sq1
            norms = q_norm[:, None] * np.sqrt(d_sq1)
            cosine1 = np.where(norms > 0, dot1 / norms, np.nan).astype(np.float32)
            ok = (dist1_sq < tau1_sq * dist2_sq) & (cosine1 > params.tau2) & np.isfinite(best)
        out[start : start + c] = ok.sum(axis=0)
    return out


def counts_with(backend: str, query_u8: np.ndarray, db_descriptors: Sequence[np.ndarray], params: MatchParams):
    """A ``retrieval.CountFn`` for this query: "batched" stacks the candidates into one GEMM
    (``count_many``), "gemm" and "faiss" match them one at a time."""

    def counts(candidates: np.ndarray) -> np.ndarray:
        if backend == "batched":
            return count_many(query_u8, db_descriptors, candidates, params)
        return np.array([count_correspondences_with(backend, query_u8, db_descriptors[int(i)], params)
                         for i in candidates], np.int64)

    return counts


# -- the filter's gate ----------------------------------------------------------------------

def gate_radius_m(position_cov_m2: np.ndarray, params: FastParams) -> float:
    """Gate radius around a predicted position with covariance ``position_cov_m2`` (2x2, m^2), metres."""
    sigma_m = float(np.sqrt(max(np.linalg.eigvalsh(np.asarray(position_cov_m2, float)).max(), 0.0)))
    return max(params.gate_sigmas * sigma_m, params.gate_min_radius_m)


def gate_mask(db_east_north_m: np.ndarray, predicted_m: np.ndarray, position_cov_m2: np.ndarray,
              params: FastParams) -> np.ndarray:
    """(N,) bool: database images within the gate radius of the predicted position."""
    offset = np.asarray(db_east_north_m, float) - np.asarray(predicted_m, float).reshape(1, 2)
    return np.einsum("ij,ij->i", offset, offset) <= gate_radius_m(position_cov_m2, params) ** 2


# -- global vectors: VLAD over SIFT -----------------------------------------------------------

@dataclass(frozen=True)
class GlobalEncoder:
    """Turns an image's SIFT descriptors into one unit-length global vector.

    codebook_f32:    (K, 128) k-means centres
    pca_mean_f32:    (K*128,) or None; pca_basis_f32: (D, K*128) or None (rows orthonormal)
    """

    codebook_f32: np.ndarray
    pca_mean_f32: np.ndarray | None = None
    pca_basis_f32: np.ndarray | None = None

    @property
    def dim(self) -> int:
        return int(self.pca_basis_f32.shape[0]) if self.pca_basis_f32 is not None else self.codebook_f32.size

    def vlad(self, descriptors_u8: np.ndarray) -> np.ndarray:
        """(K*128,) float32 VLAD: residuals to the nearest word summed per word, signed square root,
        per-word then global L2 normalisation."""
        c = self.codebook_f32
        x = np.asarray(descriptors_u8, np.float32)
        out = np.zeros(c.shape, np.float32)
        if x.shape[0]:
            # nearest word by |x - c|^2 = |c|^2 - 2 x.c + const
            words = np.argmin((c * c).sum(1)[None, :] - 2.0 * (x @ c.T), axis=1)
            onehot = np.zeros((x.shape[0], c.shape[0]), np.float32)
            onehot[np.arange(x.shape[0]), words] = 1.0
            out = onehot.T @ x - onehot.sum(axis=0)[:, None] * c
        out = np.sign(out) * np.sqrt(np.abs(out))
        norms = np.linalg.norm(out, axis=1, keepdims=True)
        out = np.divide(out, norms, out=np.zeros_like(out), where=norms > 0).ravel()
        n = np.linalg.norm(out)
        return out / n if n > 0 else out

    def encode(self, descriptors_u8: np.ndarray) -> np.ndarray:
        """(dim,) float32 unit vector (zero for an image without descriptors)."""
        v = self.vlad(descriptors_u8)
        if self.pca_basis_f32 is not None:
            v = self.pca_basis_f32 @ (v - self.pca_mean_f32)
            n = np.linalg.norm(v)
            v = v / n if n > 0 else v
        return v.astype(np.float32)

    def encode_many(self, descriptors: Sequence[np.ndarray]) -> np.ndarray:
        """(N, dim) float32, one row per image."""
        out = np.zeros((len(descriptors), self.dim), np.float32)
        for i, d in enumerate(descriptors):
            out[i] = self.encode(d)
        return out


def train_codebook(sample_u8: np.ndarray, n_words: int, seed: int) -> np.ndarray:
    """(n_words, 128) float32 k-means centres of ``sample_u8`` (faiss k-means, seeded)."""
    import faiss

    x = np.ascontiguousarray(sample_u8, np.float32)
    if x.shape[0] < n_words:
        raise ParameterError(f"n_words={n_words}: the training sample has only {x.shape[0]} descriptors")
    km = faiss.Kmeans(x.shape[1], n_words, niter=20, seed=seed, verbose=False)
    km.train(x)
    return np.ascontiguousarray(km.centroids, np.float32)


def sample_descriptors(descriptors: Sequence[np.ndarray], n: int, seed: int) -> np.ndarray:
    """Up to ``n`` descriptor rows drawn uniformly from the images, without replacement (seeded)."""
    sizes = np.array([len(d) for d in descriptors])
    total = int(sizes.sum())
    rng = np.random.default_rng(seed)
    pick = np.sort(rng.choice(total, size=min(n, total), replace=False))
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    image = np.searchsorted(starts, pick, side="right") - 1
    return np.stack([descriptors[i][r] for i, r in zip(image, pick - starts[image])]) if total else \
        np.zeros((0, 128), np.uint8)


def fit_pca(vectors_f32: np.ndarray, dim: int) -> tuple[np.ndarray, np.ndarray]:
    """Mean (D0,) and the ``dim`` leading principal directions (dim, D0) of the rows of ``vectors_f32``."""
    x = np.asarray(vectors_f32, np.float64)
    if dim > min(x.shape):
        raise ParameterError(f"pca_dim={dim}: at most {min(x.shape)} with {x.shape[0]} training images")
    mean = x.mean(axis=0)
    _, _, vt = np.linalg.svd(x - mean, full_matrices=False)
    return mean.astype(np.float32), np.ascontiguousarray(vt[:dim], np.float32)


def train_encoder(descriptors: Sequence[np.ndarray], params: FastParams) -> GlobalEncoder:
    """Codebook (and PCA when ``params.pca_dim``) trained on the database images ``descriptors``."""
    codebook = train_codebook(sample_descriptors(descriptors, params.train_descriptors, params.seed),
                              params.n_words, params.seed)
    encoder = GlobalEncoder(codebook)
    if params.pca_dim:
        mean, basis = fit_pca(np.stack([encoder.vlad(d) for d in descriptors]), params.pca_dim)
        encoder = GlobalEncoder(codebook, mean, basis)
    return encoder


def shortlist(db_vectors_f32: np.ndarray, query_vector_f32: np.ndarray, size: int,
              among: np.ndarray | None = None) -> np.ndarray:
    """Indices of the ``size`` database rows most similar (inner product) to the query, best first.

    ``among`` restricts the search to those row indices. Ties keep the lower index.
    """
    rows = np.arange(db_vectors_f32.shape[0]) if among is None else np.asarray(among, np.int64)
    if rows.size == 0:
        return rows
    scores = np.asarray(db_vectors_f32[rows] if among is not None else db_vectors_f32) @ query_vector_f32
    if size <= 0 or size >= rows.size:
        order = np.argsort(-scores, kind="stable")
    else:
        top = np.argpartition(-scores, size - 1)[:size]
        order = top[np.lexsort((rows[top], -scores[top]))]
    return rows[order]


def strongest(keypoints_f32: np.ndarray, n: int) -> np.ndarray:
    """Rows of the ``n`` keypoints with the largest SIFT response (column 4), in their original order;
    every row when ``n`` is 0 or not smaller than the number of keypoints. Ties keep the earlier row."""
    k = np.asarray(keypoints_f32)
    if n <= 0 or n >= k.shape[0]:
        return np.arange(k.shape[0])
    order = np.argsort(-k[:, 4], kind="stable")[:n]
    return np.sort(order)


# -- the fast retrieval -----------------------------------------------------------------------

@dataclass(frozen=True)
class FastRetrieval:
    """A fast retrieval and how it was made."""

    retrieval: Retrieval
    gated: bool  # the filter's gate chose the candidates (False: first or lost query, or widened)
    widened: bool  # the gate held no image with a correspondence and the search widened to every allowed image
    n_gate: int  # allowed images in the search area before the shortlist
    encode_ms: float  # global vector of the query
    count_ms: float  # exact matching of the shortlist


@dataclass(frozen=True)
class FastDatabase:
    """What the fast path keeps per database image: its global vector."""

    encoder: GlobalEncoder
    vectors_f32: np.ndarray  # (N, dim)
    params: FastParams
    descriptors_u8: tuple[np.ndarray, ...]  # what retrieval matches: every image's, capped if params say so

    @classmethod
    def build(cls, descriptors: Sequence[np.ndarray], params: FastParams = FAST,
              keypoints: Sequence[np.ndarray] | None = None) -> "FastDatabase":
        """Train the encoder on ``descriptors`` and encode every image. A keypoint cap needs ``keypoints``."""
        if params.max_keypoints:
            if keypoints is None or len(keypoints) != len(descriptors):
                raise ParameterError("max_keypoints: capping the database needs its keypoints")
            descriptors = tuple(np.ascontiguousarray(d[strongest(k, params.max_keypoints)])
                                for d, k in zip(descriptors, keypoints))
        descriptors = tuple(descriptors)
        encoder = train_encoder(descriptors, params)
        return cls(encoder, encoder.encode_many(descriptors), params, descriptors)

    def cap_query(self, descriptors_u8: np.ndarray, keypoints_f32: np.ndarray | None) -> np.ndarray:
        """The query's descriptors retrieval uses (its strongest ``max_keypoints`` when capped)."""
        if not self.params.max_keypoints:
            return descriptors_u8
        if keypoints_f32 is None:
            raise ParameterError("max_keypoints: capping a query needs its keypoints")
        return np.ascontiguousarray(descriptors_u8[strongest(keypoints_f32, self.params.max_keypoints)])


def fast_retrieve(query_u8: np.ndarray, counts_of, db_timestamps_s: np.ndarray, db_east_north_m: np.ndarray,
                  fast_db: FastDatabase, query_timestamp_s: float, retrieval_params: RetrievalParams,
                  predicted_m: np.ndarray | None = None, predicted_cov_m2: np.ndarray | None = None) -> FastRetrieval:
    """Gate, shortlist, then the paper's exact counts on the shortlist.

    ``counts_of`` is a ``retrieval.CountFn`` for this query. Without a prediction (first or
    lost query) every image the exclusion window allows is searched (no +-window_s: there is
    no previous match to centre it on).
    """
    params = fast_db.params
    allowed = candidate_mask(db_timestamps_s, query_timestamp_s, None, retrieval_params)
    t0 = time.perf_counter()
    q_vec = fast_db.encoder.encode(query_u8)
    encode_ms = (time.perf_counter() - t0) * 1000.0
    count_ms = 0.0

    def search(area: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        nonlocal count_ms
        rows = np.flatnonzero(area)
        chosen = shortlist(fast_db.vectors_f32, q_vec, params.shortlist_size, among=rows)
        t = time.perf_counter()
        counts = np.asarray(counts_of(chosen), np.int64) if chosen.size else np.zeros(0, np.int64)
        count_ms += (time.perf_counter() - t) * 1000.0
        return chosen, counts

    gated = predicted_m is not None and predicted_cov_m2 is not None and np.all(np.isfinite(predicted_m))
    area = allowed & gate_mask(db_east_north_m, predicted_m, predicted_cov_m2, params) if gated else allowed
    chosen, counts = search(area)
    widened = False
    if gated and (counts.size == 0 or counts.max() == 0):
        widened, area = True, allowed
        chosen, counts = search(area)
    best = int(chosen[int(np.argmax(counts))]) if counts.size and counts.max() > 0 else None
    # best by count; ties go to the earliest candidate in time, as in the paper's path
    if best is not None:
        ties = chosen[counts == counts.max()]
        best = int(ties.min())
    retrieval = Retrieval(candidates=chosen, counts=counts, best_index=best, allowed=np.flatnonzero(area))
    return FastRetrieval(retrieval, gated=bool(gated and not widened), widened=widened, n_gate=int(area.sum()),
                         encode_ms=encode_ms, count_ms=count_ms)
