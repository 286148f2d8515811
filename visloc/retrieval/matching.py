"""Keypoint correspondences between two images: the paper's equations (1) and (2).

For every query descriptor g we find its nearest and second-nearest descriptors
f1, f2 in one database image (exact, brute force). g and f1 correspond when

    (1)  d^2(g, f1) / d^2(g, f2) < tau1^2      (Lowe's ratio test)
    (2)  cos(g, f1) = f1.g / (|f1| |g|) > tau2  (cosine similarity)

The number of correspondences is the database image's score.

Exactness: SIFT descriptors are whole numbers 0..255 with L2 norm about 512, so
every dot product is an integer below 2^24 and float32 arithmetic is exact here:
the same descriptors always give the same neighbours and distances.

Three exact backends give the same neighbours and counts, side by side:

* ``nearest_two``: numpy float32 GEMMs per database image, a block of query rows each (the paper's path);
* ``nearest_two_faiss``: faiss's brute-force k-NN (BLAS inside);
* ``count_many``: the candidates of one query stacked into one GEMM (the fast path).

A *counter* scores candidates for one query: ``counter(query_u8, key)`` returns a
``CountFn``, candidate database indices -> correspondence counts. ``brute_force_counter``
and ``backend_counter`` compute every count; ``PairCountCache`` remembers them per
(query key, database key) and how long each took when first computed.
"""

from __future__ import annotations

import functools
import os
import time
from collections.abc import Callable, Hashable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
from threadpoolctl import ThreadpoolController

from visloc.errors import ParameterError
from visloc.params import MatchParams


@dataclass(frozen=True)
class NearestTwo:
    """Nearest and second-nearest database descriptors of each query descriptor.

    index1:    (N,) int64, row of the nearest database descriptor.
    dist1_sq:  (N,) float32, squared L2 distance to it.
    dist2_sq:  (N,) float32, squared L2 distance to the second nearest
               (inf when the database image has a single descriptor).
    cosine1:   (N,) float32, cosine similarity with the nearest; NaN when either
               vector is zero (undefined, so it never passes equation (2)).
    """

    index1: np.ndarray
    dist1_sq: np.ndarray
    dist2_sq: np.ndarray
    cosine1: np.ndarray


def best_two(score: np.ndarray, q_sq: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The one nearest-two kernel every matcher uses. ``score`` (..., n): g.f - |f|^2 / 2 of each query
    descriptor g (its |g|^2 in ``q_sq``, over the leading axes) against n database descriptors f, so
    that the largest score is the nearest f; -inf where there is no descriptor. Returns (index1, best,
    dist1_sq, dist2_sq) along the last axis: the nearest's index and score and the squared distances
    to the nearest two, |g - f|^2 = |g|^2 - 2 score (exact in float32 for SIFT's integer values, see
    the module docstring). ``score``'s best entries are overwritten with -inf."""
    index1 = np.argmax(score, axis=-1)  # two passes of argmax: much faster than a partial sort
    best = np.take_along_axis(score, index1[..., None], axis=-1)[..., 0]
    np.put_along_axis(score, index1[..., None], -np.inf, axis=-1)
    second = score.max(axis=-1)  # -inf with one database descriptor
    dist1_sq, dist2_sq = _squared_distances(q_sq.reshape(q_sq.shape + (1,) * (best.ndim - q_sq.ndim)), best, second)
    return index1, best, dist1_sq, dist2_sq


_SCORE_BLOCK_BYTES = 2 << 20  # scores of a block of query rows: about one core's L2 cache
_threads: dict[int, ThreadPoolExecutor] = {}  # per process id (a forked worker makes its own)


@functools.cache
def _blas() -> ThreadpoolController:
    return ThreadpoolController()


def _blas_threads() -> int:
    """How many threads BLAS runs now (one inside ``threadpool_limits(1)``)."""
    return max([c.num_threads for c in _blas().lib_controllers if c.user_api == "blas"] or [1])


def _row_threads(n: int) -> ThreadPoolExecutor:
    key = os.getpid()
    pool = _threads.get(key)
    if pool is None or pool._max_workers < n:
        pool = _threads[key] = ThreadPoolExecutor(max_workers=n, thread_name_prefix="visloc-match")
    return pool


def nearest_two(query_u8: np.ndarray, database_u8: np.ndarray) -> NearestTwo:
    """Exact two nearest neighbours of every query row among the database rows."""
    return _nearest_two(query_u8, database_u8, both_ways=False)[0]


def nearest_two_both_ways(a_u8: np.ndarray, b_u8: np.ndarray) -> tuple[NearestTwo, NearestTwo]:
    """(``nearest_two(a, b)``, ``nearest_two(b, a)``), the same numbers, from one product of the two images'
    descriptors instead of two: the products are exact (module docstring), so b's scores against a are the
    transposed products less a's halved squared norms, and the nearest two of each b row are gathered over a's row
    blocks as they pass, the earliest row winning a tie as ``argmax`` has it."""
    return _nearest_two(a_u8, b_u8, both_ways=True)


def _no_neighbours(n_query: int) -> NearestTwo:
    return NearestTwo(np.full(n_query, -1, np.int64), np.full(n_query, np.inf, np.float32),
                      np.full(n_query, np.inf, np.float32), np.zeros(n_query, np.float32))


class _ColumnsBestTwo:
    """The nearest two query rows of every database row (a column of the scores), gathered block by block of
    query rows in their order: index of the best, its score, the second score (-inf until seen)."""

    def __init__(self, n_columns: int):
        self.index1 = np.full(n_columns, -1, np.intp)
        self.best = np.full(n_columns, -np.inf, np.float32)
        self.second = np.full(n_columns, -np.inf, np.float32)

    def merge(self, index1: np.ndarray, best: np.ndarray, second: np.ndarray) -> None:
        """Take the best two of rows that come after every row seen so far: a later row wins only when better."""
        later = best > self.best
        self.second = np.where(later, np.maximum(self.best, second), np.maximum(self.second, best))
        self.index1 = np.where(later, index1, self.index1)
        self.best = np.where(later, best, self.best)

    def add_block(self, column_score: np.ndarray, first_row: int) -> None:
        """``column_score`` (rows, columns), the block's scores from the columns' side, is overwritten."""
        index1 = np.argmax(column_score, axis=0)
        columns = np.arange(column_score.shape[1])
        best = column_score[index1, columns]
        column_score[index1, columns] = -np.inf
        self.merge(index1 + first_row, best, column_score.max(axis=0))


def _squared_distances(q_sq: np.ndarray, best: np.ndarray, second: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """|g - f|^2 = |g|^2 - 2 score to the nearest two, from their scores (``best_two``)."""
    with np.errstate(over="ignore", invalid="ignore"):
        return (np.maximum(q_sq - 2.0 * best, 0.0).astype(np.float32),
                np.maximum(q_sq - 2.0 * second, 0.0).astype(np.float32))


def _with_cosine(index1: np.ndarray, best: np.ndarray, dist1_sq: np.ndarray, dist2_sq: np.ndarray, q_sq: np.ndarray,
                 d_sq: np.ndarray) -> NearestTwo:
    """A ``NearestTwo`` from each query row's nearest (index, score) and squared distances to the nearest two."""
    dot1 = best + 0.5 * d_sq[index1]
    norms = np.sqrt(q_sq) * np.sqrt(d_sq[index1])
    with np.errstate(invalid="ignore", divide="ignore"):
        cosine1 = np.where(norms > 0, dot1 / norms, np.nan).astype(np.float32)
    return NearestTwo(index1.astype(np.int64), dist1_sq, dist2_sq, cosine1)


def _nearest_two(query_u8: np.ndarray, database_u8: np.ndarray, *, both_ways: bool
                 ) -> tuple[NearestTwo, NearestTwo | None]:
    q = np.asarray(query_u8, dtype=np.float32)
    d = np.asarray(database_u8, dtype=np.float32)
    n_query, n_db = q.shape[0], d.shape[0]
    if n_query == 0 or n_db == 0:
        return _no_neighbours(n_query), _no_neighbours(n_db) if both_ways else None
    q_sq = np.einsum("ij,ij->i", q, q)
    d_sq = np.einsum("ij,ij->i", d, d)
    half_d_sq = 0.5 * d_sq
    half_q_sq = 0.5 * q_sq
    d_t = np.ascontiguousarray(d.T)
    # |g - f|^2 = |g|^2 + |f|^2 - 2 g.f; per row |g|^2 is constant, so the nearest f
    # maximises score = g.f - |f|^2 / 2 (exact in float32, see the module docstring). The query rows
    # go a block at a time, each block's scores small enough to stay in the core's cache for the passes
    # that find the nearest two: every row's numbers are the same as in one product of all rows.
    rows = max(1, _SCORE_BLOCK_BYTES // (4 * n_db))
    index1 = np.empty(n_query, np.intp)
    best = np.empty(n_query, np.float32)
    dist1_sq = np.empty(n_query, np.float32)
    dist2_sq = np.empty(n_query, np.float32)

    def blocks(first: int, last: int) -> _ColumnsBestTwo | None:  # query rows first..last-1, a block at a time
        score_block = np.empty((min(rows, last - first), n_db), np.float32)
        columns = _ColumnsBestTwo(n_db) if both_ways else None
        column_block = np.empty_like(score_block) if both_ways else None
        for start in range(first, last, rows):
            stop = min(start + rows, last)
            score = score_block[: stop - start]
            np.matmul(q[start:stop], d_t, out=score)
            if columns is not None:  # the database rows' scores against these query rows: f.g - |g|^2 / 2
                column_score = column_block[: stop - start]
                np.subtract(score, half_q_sq[start:stop, None], out=column_score)
                columns.add_block(column_score, start)
            score -= half_d_sq
            index1[start:stop], best[start:stop], dist1_sq[start:stop], dist2_sq[start:stop] = \
                best_two(score, q_sq[start:stop])
        return columns

    # The blocks' products are small: with BLAS's own threads, a second thread mostly waits for the first (about
    # twice the CPU time for the same pair, and far more on a busy machine, where it waits to be scheduled). So
    # BLAS runs one thread, and the rows are shared among as many threads of ours as BLAS had (one in ingest's
    # workers, one per core elsewhere), each through its own blocks: nothing to wait for until all are done.
    n_threads = min(_blas_threads(), -(-n_query // rows))
    with _blas().limit(limits=1, user_api="blas"):
        if n_threads <= 1:
            parts = [blocks(0, n_query)]
        else:
            cuts = [round(n_query * k / n_threads) for k in range(n_threads + 1)]
            parts = list(_row_threads(n_threads).map(blocks, cuts[:-1], cuts[1:]))
    forward = _with_cosine(index1, best, dist1_sq, dist2_sq, q_sq, d_sq)
    if not both_ways:
        return forward, None
    columns = parts[0]
    for part in parts[1:]:  # the threads' row ranges in their order
        columns.merge(part.index1, part.best, part.second)
    return forward, _with_cosine(columns.index1, columns.best, *_squared_distances(d_sq, columns.best, columns.second),
                                 d_sq, q_sq)


def correspondence_mask(nn: NearestTwo, params: MatchParams) -> np.ndarray:
    """(N,) bool: which query descriptors pass equations (1) and (2)."""
    ratio_ok = nn.dist1_sq < (params.tau1 ** 2) * nn.dist2_sq  # (1), no division: d2 = 0 fails
    cosine_ok = nn.cosine1 > params.tau2  # (2); NaN (zero vector) compares False
    return ratio_ok & cosine_ok & (nn.index1 >= 0)


def correspondences(query_u8: np.ndarray, database_u8: np.ndarray, params: MatchParams) -> np.ndarray:
    """(M, 2) int64 pairs (query row, database row) that correspond."""
    return _pairs(nearest_two(query_u8, database_u8), params)


def correspondences_both_ways(a_u8: np.ndarray, b_u8: np.ndarray, params: MatchParams) -> tuple[np.ndarray, np.ndarray]:
    """(``correspondences(a, b)``, ``correspondences(b, a)``) from one product (``nearest_two_both_ways``)."""
    forward, backward = nearest_two_both_ways(a_u8, b_u8)
    return _pairs(forward, params), _pairs(backward, params)


def _pairs(nn: NearestTwo, params: MatchParams) -> np.ndarray:
    mask = correspondence_mask(nn, params)
    return np.stack([np.flatnonzero(mask), nn.index1[mask]], axis=1)


def count_correspondences(query_u8: np.ndarray, database_u8: np.ndarray, params: MatchParams) -> int:
    """The paper's score of one database image for one query."""
    return int(correspondence_mask(nearest_two(query_u8, database_u8), params).sum())


# -- faiss and batched backends -------------------------------------------------------------

def nearest_two_faiss(query_u8: np.ndarray, database_u8: np.ndarray) -> NearestTwo:
    """``nearest_two`` computed by faiss's exact brute-force k-NN; same neighbours and distances."""
    q = np.ascontiguousarray(query_u8, dtype=np.float32)
    d = np.ascontiguousarray(database_u8, dtype=np.float32)
    n_query, n_db = q.shape[0], d.shape[0]
    if n_query == 0 or n_db < 2:
        return nearest_two(query_u8, database_u8)  # edge cases: the reference handles them
    import faiss  # here: only this backend needs it, and it costs every command's start-up

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
    found per candidate. The arithmetic is ``nearest_two``'s, in the same float32 order, so
    the counts are the same numbers.
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
        # score = g.f - |f|^2 / 2, maximal at the nearest f (see nearest_two)
        score = (q @ d.reshape(c * width, -1).T).reshape(q.shape[0], c, width)
        score -= 0.5 * d_sq[None, :, :]
        index1, best, dist1_sq, dist2_sq = best_two(score, q_sq)  # (Nq, c) each
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            d_sq1 = d_sq[np.arange(c)[None, :], index1]
            dot1 = best + 0.5 * d_sq1
            norms = q_norm[:, None] * np.sqrt(d_sq1)
            cosine1 = np.where(norms > 0, dot1 / norms, np.nan).astype(np.float32)
            ok = (dist1_sq < tau1_sq * dist2_sq) & (cosine1 > params.tau2) & np.isfinite(best)
        out[start : start + c] = ok.sum(axis=0)
    return out


# -- counters: how a retrieval scores its candidates -------------------------------------------

CountFn = Callable[[np.ndarray], np.ndarray]  # candidate database indices (M,) -> counts (M,)
Counter = Callable[[np.ndarray, Hashable], CountFn]  # (query descriptors, query key) -> CountFn


def brute_force_counts(query_u8: np.ndarray, db_descriptors: Sequence[np.ndarray], params: MatchParams) -> CountFn:
    """Matches the query against each candidate in turn, exactly as the paper does."""

    def counts(candidates: np.ndarray) -> np.ndarray:
        return np.array([count_correspondences(query_u8, db_descriptors[i], params) for i in candidates], np.int64)

    return counts


def backend_counts(backend: str, query_u8: np.ndarray, db_descriptors: Sequence[np.ndarray],
                   params: MatchParams) -> CountFn:
    """"batched" stacks the candidates into one GEMM (``count_many``); "gemm" and "faiss" match them
    one at a time."""

    def counts(candidates: np.ndarray) -> np.ndarray:
        if backend == "batched":
            return count_many(query_u8, db_descriptors, candidates, params)
        return np.array([count_correspondences_with(backend, query_u8, db_descriptors[int(i)], params)
                         for i in candidates], np.int64)

    return counts


def brute_force_counter(db_descriptors: Sequence[np.ndarray], params: MatchParams) -> Counter:
    """A counter that computes every count, one image at a time (the paper's path)."""
    return lambda query_u8, key=None: brute_force_counts(query_u8, db_descriptors, params)


def backend_counter(backend: str, db_descriptors: Sequence[np.ndarray], params: MatchParams) -> Counter:
    """A counter that computes every count with ``backend`` ("batched", "faiss" or "gemm")."""
    return lambda query_u8, key=None: backend_counts(backend, query_u8, db_descriptors, params)


class PairCountCache:
    """A counter that remembers correspondence counts per (query key, database key), for
    evaluations where the same query image appears in many series. Remembers how long each pair
    took the first time, so latency can still be reported as if computed afresh.

    ``db_keys`` names the database images (default: their indices); ``known`` seeds the cache,
    e.g. with counts persisted by an earlier run; ``take_new_entries()`` hands over what was
    computed since it was last called, to persist; ``selected_contrast``: the counts are of features selected
    at this SIFT contrast threshold (None: as stored); ``persistent`` False: counts not to be kept beyond this run.
    """

    def __init__(self, db_descriptors: Sequence[np.ndarray], match_params: MatchParams, *,
                 db_keys: Sequence[Hashable] | None = None,
                 known: dict[tuple[Hashable, Hashable], tuple[int, float]] | None = None,
                 selected_contrast: float | None = None, persistent: bool = True):
        self.db_descriptors = db_descriptors
        self.match_params = match_params
        self.selected_contrast, self.persistent = selected_contrast, persistent
        self.db_keys = list(range(len(db_descriptors))) if db_keys is None else list(db_keys)
        self._entries: dict[tuple[Hashable, Hashable], tuple[int, float]] = dict(known or {})
        self._new: dict[tuple[Hashable, Hashable], tuple[int, float]] = {}
        self.fresh_ms = 0.0  # matching time spent in the latest query's counts

    def check_thresholds(self, match_params: MatchParams) -> None:
        """Refuse to count for other thresholds than the cache holds counts for."""
        if self.match_params != match_params:
            raise ParameterError(f"cache holds counts for {self.match_params}, not {match_params}")

    def __call__(self, query_u8: np.ndarray, key: Hashable) -> CountFn:
        if key is None:
            raise ValueError("PairCountCache needs queries with a key")
        self.fresh_ms = 0.0

        def counts(candidates: np.ndarray) -> np.ndarray:
            out = np.empty(len(candidates), np.int64)
            for j, i in enumerate(candidates):
                pair = (key, self.db_keys[int(i)])
                if pair not in self._entries:
                    t0 = time.perf_counter()
                    n = count_correspondences(query_u8, self.db_descriptors[int(i)], self.match_params)
                    ms = (time.perf_counter() - t0) * 1000.0
                    self._entries[pair] = self._new[pair] = (n, ms)
                    self.fresh_ms += ms
                out[j] = self._entries[pair][0]
            return out

        return counts

    def cost_ms(self, key: Hashable, candidates: np.ndarray) -> float:
        """Time the first computation of these pairs took, ms."""
        return float(sum(self._entries[(key, self.db_keys[int(i)])][1] for i in candidates))

    def take_new_entries(self) -> dict[tuple[Hashable, Hashable], tuple[int, float]]:
        new, self._new = self._new, {}
        return new


class MatchCancelled(Exception):
    """Work stopped because its ``cancelled()`` callback said so."""


def cancellable(counter: Counter, cancelled: Callable[[], bool] | None, chunk: int = 4) -> Counter:
    """``counter``, but polling ``cancelled()`` before every ``chunk`` candidates and raising
    ``MatchCancelled`` when it is true."""
    if cancelled is None:
        return counter

    def for_query(query_u8: np.ndarray, key: Hashable = None) -> CountFn:
        counts = counter(query_u8, key)

        def checked(candidates: np.ndarray) -> np.ndarray:
            parts = []
            for lo in range(0, len(candidates), chunk):
                if cancelled():
                    raise MatchCancelled()
                parts.append(counts(candidates[lo:lo + chunk]))
            return np.concatenate(parts) if parts else np.zeros(0, np.int64)

        if hasattr(counts, "pairs"):  # the matches behind the counts go on to the retrieval (StructureMatcher)
            checked.pairs = counts.pairs  # type: ignore[attr-defined]
        return checked

    return for_query
