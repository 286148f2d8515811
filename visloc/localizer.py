"""The paper's two steps for a stream of queries: retrieval, then the Kalman filter.

``Localizer`` works on arrays only: database timestamps, positions in the local
metric frame, and descriptors. Feed it one query at a time with ``step``.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Hashable, Sequence
from dataclasses import dataclass

import numpy as np

from visloc.params import FilterParams, MatchParams, RetrievalParams
from visloc.matching import count_correspondences
from visloc.retrieval import CountFn, Retrieval, brute_force_counts, retrieve
from visloc.tracking import ConstantVelocityKalman, FilterStep


@dataclass(frozen=True)
class Query:
    descriptors_u8: np.ndarray  # (N, 128)
    timestamp_s: float
    key: Hashable = None  # identifies the query image for caches (e.g. its frame index)


@dataclass(frozen=True)
class StepResult:
    query_timestamp_s: float
    retrieval: Retrieval
    measurement_m: np.ndarray | None  # (east_m, north_m) of the best match's geotag, None without a match
    filter: FilterStep
    compute_ms: float  # wall time of retrieval + filter in this step

    @property
    def best_index(self) -> int | None:
        return self.retrieval.best_index


CounterFactory = Callable[[Query], CountFn]


class Localizer:
    """Retrieval against a geotagged database followed by the constant-velocity filter."""

    def __init__(
        self,
        db_timestamps_s: np.ndarray,
        db_east_north_m: np.ndarray,
        db_descriptors: Sequence[np.ndarray],
        match_params: MatchParams,
        retrieval_params: RetrievalParams,
        filter_params: FilterParams,
        *,
        counter: CounterFactory | None = None,
    ):
        self.db_timestamps_s = np.asarray(db_timestamps_s, float)
        self.db_east_north_m = np.asarray(db_east_north_m, float)
        self.db_descriptors = db_descriptors
        n = self.db_timestamps_s.shape[0]
        if self.db_east_north_m.shape != (n, 2) or len(db_descriptors) != n:
            raise ValueError("database timestamps, positions and descriptors must have the same length")
        self.match_params = match_params
        self.retrieval_params = retrieval_params
        self.filter_params = filter_params
        self._counter = counter or (lambda q: brute_force_counts(q.descriptors_u8, self.db_descriptors, match_params))
        self.reset()

    def reset(self) -> None:
        """Forget the track: the next query scans the whole database again."""
        self._kalman = ConstantVelocityKalman(self.filter_params)
        self._center_timestamp_s: float | None = None

    def step(self, query: Query) -> StepResult:
        start = time.perf_counter()
        retrieval = retrieve(self._counter(query), self.db_timestamps_s, query.timestamp_s,
                             self._center_timestamp_s, self.retrieval_params)
        measurement = None
        if retrieval.best_index is not None:
            measurement = self.db_east_north_m[retrieval.best_index]
            self._center_timestamp_s = float(self.db_timestamps_s[retrieval.best_index])
        else:
            self._center_timestamp_s = None  # lost: scan everything next time
        filtered = self._kalman.step(measurement)
        return StepResult(query.timestamp_s, retrieval, measurement, filtered,
                          (time.perf_counter() - start) * 1000.0)


class PairCountCache:
    """Memoised correspondence counts per (query key, database key), for evaluations
    where the same query image appears in many series. Remembers how long each pair
    took the first time, so latency can still be reported as if computed afresh.

    ``db_keys`` names the database images (default: their indices); ``known`` seeds
    the cache, e.g. with counts persisted by an earlier run; ``take_new_entries()``
    hands over what was computed since it was last called, to persist.
    """

    def __init__(self, db_descriptors: Sequence[np.ndarray], match_params: MatchParams, *,
                 db_keys: Sequence[Hashable] | None = None,
                 known: dict[tuple[Hashable, Hashable], tuple[int, float]] | None = None):
        self.db_descriptors = db_descriptors
        self.match_params = match_params
        self.db_keys = list(range(len(db_descriptors))) if db_keys is None else list(db_keys)
        self._entries: dict[tuple[Hashable, Hashable], tuple[int, float]] = dict(known or {})
        self._new: dict[tuple[Hashable, Hashable], tuple[int, float]] = {}
        self.fresh_ms = 0.0  # matching time spent in the latest query's counter

    def __call__(self, query: Query) -> CountFn:
        if query.key is None:
            raise ValueError("PairCountCache needs queries with a key")
        self.fresh_ms = 0.0

        def counts(candidates: np.ndarray) -> np.ndarray:
            out = np.empty(len(candidates), np.int64)
            for j, i in enumerate(candidates):
                pair = (query.key, self.db_keys[int(i)])
                if pair not in self._entries:
                    t0 = time.perf_counter()
                    n = count_correspondences(query.descriptors_u8, self.db_descriptors[int(i)], self.match_params)
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
