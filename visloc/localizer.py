"""The paper's two steps for a stream of queries: retrieval, then the Kalman filter.

``Localizer`` works on arrays only: database timestamps, positions in the local
metric frame, and descriptors. Feed it one query at a time with ``step``.

``mode="paper"`` (default) is the paper's method. ``mode="refined"`` turns each
retrieval into a metric pose measurement with its own covariance
(``visloc.refined``) and gates outliers in the filter; it needs the database's
``DatabaseGeometry``, the query camera's ``CameraModel`` and queries with keypoints.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Hashable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from visloc.geometry import CameraModel
from visloc.params import REFINED, FilterParams, MatchParams, RefinedParams, RetrievalParams, check_mode
from visloc.matching import count_correspondences
from visloc.refined import DatabaseGeometry, Measurement, StructureCache, measurement_from_retrieval
from visloc.retrieval import CountFn, Retrieval, brute_force_counts, retrieve
if TYPE_CHECKING:
    from visloc.fast import FastDatabase
from visloc.tracking import ConstantVelocityKalman, FilterStep, predict


@dataclass(frozen=True)
class Query:
    descriptors_u8: np.ndarray  # (N, 128)
    timestamp_s: float
    key: Hashable = None  # identifies the query image for caches (e.g. its frame index)
    keypoints_f32: np.ndarray | None = None  # (N, 6) or (N, 2), pixel x, y first; the refined mode needs them


@dataclass(frozen=True)
class StepResult:
    query_timestamp_s: float
    retrieval: Retrieval
    measurement_m: np.ndarray | None  # (east_m, north_m) measured (geotag or pose), None without a measurement
    filter: FilterStep
    compute_ms: float  # wall time of retrieval + measurement + filter in this step
    measurement: Measurement | None = None  # the full measurement: source, covariance, fallback reason

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
        mode: str = "paper",
        refined_params: RefinedParams = REFINED,
        geometry: DatabaseGeometry | None = None,
        query_camera: CameraModel | None = None,
        structure_cache: StructureCache | None = None,
        measurement_cache: dict | None = None,
        fast: "FastDatabase | None" = None,
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
        self.mode = check_mode(mode)
        self.refined_params = refined_params
        self.geometry = geometry
        self.query_camera = query_camera
        self.structure_cache = structure_cache if structure_cache is not None else StructureCache()
        # (query key, candidates) -> Measurement: the same query with the same candidates measures the same
        self.measurement_cache = measurement_cache
        self.last_measure_ms = 0.0  # wall time of the latest step's measurement (about 0 when memoised)
        self.last_retrieval_ms = 0.0  # wall time of the latest step's retrieval
        # opt-in fast path (visloc.fast): the filter gates retrieval, global vectors shortlist, exact counts
        self.fast = fast
        self.last_fast = None  # the latest step's FastRetrieval (fast path only)
        if counter is None and fast is not None:
            from visloc.fast import counts_with

            counter = lambda q: counts_with(fast.params.nn_backend, q.descriptors_u8, fast.descriptors_u8,  # noqa: E731
                                            match_params)
        self._counter = counter or (lambda q: brute_force_counts(q.descriptors_u8, self.db_descriptors, match_params))
        self.reset()

    def reset(self) -> None:
        """Forget the track: the next query scans the whole database again."""
        gate = self.refined_params.gate_chi2 if self.mode == "refined" else 0.0
        self._kalman = ConstantVelocityKalman(self.filter_params, gate_chi2=gate)
        self._center_timestamp_s: float | None = None

    def step(self, query: Query) -> StepResult:
        start = time.perf_counter()
        if self.fast is None:
            retrieval = retrieve(self._counter(query), self.db_timestamps_s, query.timestamp_s,
                                 self._center_timestamp_s, self.retrieval_params)
        else:
            retrieval = self._fast_retrieve(query)
        self.last_retrieval_ms = (time.perf_counter() - start) * 1000.0
        if retrieval.best_index is not None:
            self._center_timestamp_s = float(self.db_timestamps_s[retrieval.best_index])
        else:
            self._center_timestamp_s = None  # lost: scan everything next time
        t_measure = time.perf_counter()
        measurement = self.measure(query, retrieval)
        self.last_measure_ms = (time.perf_counter() - t_measure) * 1000.0
        filtered = self._kalman.step(measurement.east_north_m, measurement.cov_m2)
        return StepResult(query.timestamp_s, retrieval, measurement.east_north_m, filtered,
                          (time.perf_counter() - start) * 1000.0, measurement)

    def _fast_retrieve(self, query: Query) -> Retrieval:
        from visloc.fast import fast_retrieve

        predicted = predicted_cov = None
        k = self._kalman
        if k.initialised:
            x, P = predict(k.x, k.P, k.F, k.Q)
            predicted, predicted_cov = x[:2], P[:2, :2]
        if self.fast.params.max_keypoints:  # retrieval sees the strongest keypoints only; geometry sees all
            capped = self.fast.cap_query(query.descriptors_u8, query.keypoints_f32)
            query = Query(capped, query.timestamp_s, key=query.key, keypoints_f32=None)
        self.last_fast = fast_retrieve(query.descriptors_u8, self._counter(query), self.db_timestamps_s,
                                       self.db_east_north_m, self.fast, query.timestamp_s, self.retrieval_params,
                                       predicted, predicted_cov)
        return self.last_fast.retrieval

    def measure(self, query: Query, retrieval: Retrieval) -> Measurement:
        """The measurement of one retrieved query in this localizer's mode (memoised if asked)."""
        memo_key = None
        if self.measurement_cache is not None and query.key is not None and self.mode == "refined":
            memo_key = (query.key, retrieval.candidates.tobytes(), retrieval.counts.tobytes())
            if memo_key in self.measurement_cache:
                return self.measurement_cache[memo_key]
        m = measurement_from_retrieval(query.keypoints_f32, query.descriptors_u8, retrieval, self.db_east_north_m,
                                       mode=self.mode, geometry=self.geometry, query_camera=self.query_camera,
                                       params=self.refined_params, cache=self.structure_cache)
        if memo_key is not None:
            self.measurement_cache[memo_key] = m
        return m


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
