"""The localizer: a retriever, a measurer and the constant-velocity filter, one query at a time.

``Localizer`` is composed of parts, each replaceable:

* a retriever (``visloc.retrieval.retrievers``): the paper's ``WindowRetriever`` or the fast path's
  ``ShortlistRetriever``, which the filter's prediction gates;
* a measurer (``visloc.pose.measurement``): the paper's ``GeotagMeasurer`` or the refined
  method's ``visloc.pose.refined.PoseMeasurer``;
* the filter (``visloc.tracking.kalman.ConstantVelocityKalman``), with an optional Mahalanobis gate.

``visloc.tracking.methods`` composes them into the named methods (the paper's, the refined one).
Each ``step`` returns everything about that query, its timings included. ``first_fix`` makes a track's first
measurement (``step(first=...)``).
"""

from __future__ import annotations

import copy
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Protocol

import numpy as np

from visloc.features.sift import Query
from visloc.pose.measurement import GEOMETRY, GEOTAG, Measurement, Measurer
from visloc.params import FilterParams
from visloc.retrieval.retrievers import Prediction, Retrieval
from visloc.tracking.kalman import ConstantVelocityKalman, FilterStep


FirstMeasurement = Callable[[Measurement, Retrieval], Measurement]
FIRST_FIX_CANDIDATES = 5
FIRST_FIX_AGREEMENT_M = 10.0


class Retriever(Protocol):
    def reset(self) -> None: ...

    def retrieve(self, query: Query, prediction: Prediction = None) -> Retrieval: ...


@dataclass(frozen=True)
class StepTimings:
    """Wall time of one step's stages in this process, ms. Work a cache answered costs nothing here
    (``visloc.tracking.runs.latency_ms`` replays what it cost when first done)."""

    retrieval_ms: float
    measurement_ms: float
    filter_ms: float

    @property
    def total_ms(self) -> float:
        return self.retrieval_ms + self.measurement_ms + self.filter_ms


@dataclass(frozen=True)
class StepResult:
    query: Query
    retrieval: Retrieval
    measurement: Measurement  # source None: the query gave no measurement
    filter: FilterStep
    timings: StepTimings

    @property
    def best_index(self) -> int | None:
        return self.retrieval.best_index

    @property
    def measurement_m(self) -> np.ndarray | None:
        """(east_m, north_m) measured (geotag or pose), None without a measurement."""
        return self.measurement.east_north_m


class Localizer:
    """Retrieval against a geotagged database, a measurement, and the constant-velocity filter."""

    def __init__(self, retriever: Retriever, measurer: Measurer, filter_params: FilterParams, *,
                 gate_chi2: float = 0.0, reinit_after_gated: int = 0, corr_fraction: float = 0.0,
                 corr_time_s: float = 1.0):
        self.retriever = retriever
        self.measurer = measurer
        self.filter_params = filter_params
        self.gate_chi2 = float(gate_chi2)  # 0: every measurement is applied
        self.reinit_after_gated = int(reinit_after_gated)  # 0: never restart the track
        self.corr_fraction, self.corr_time_s = float(corr_fraction), float(corr_time_s)  # 0: independent measurements
        self.reset()

    def reset(self) -> None:
        """Forget the track: the next query scans the whole database again."""
        self.retriever.reset()
        self._kalman = ConstantVelocityKalman(self.filter_params, gate_chi2=self.gate_chi2,
                                              reinit_after_gated=self.reinit_after_gated,
                                              corr_fraction=self.corr_fraction, corr_time_s=self.corr_time_s)

    def prediction(self) -> Prediction:
        """The filter's predicted position and covariance for the next step (None before the first)."""
        return self._kalman.prediction()

    @property
    def velocity_m_s(self) -> np.ndarray | None:
        """The filter's velocity estimate (east, north), m/s; None before the first measurement."""
        x = self._kalman.x
        return None if x is None else np.asarray(x[2:4], float).copy()

    @property
    def started(self) -> bool:
        """The filter holds a track (it has been given a measurement)."""
        return self._kalman.x is not None

    def measure(self, query: Query, prediction: Prediction = None) -> tuple[Retrieval, Measurement, float, float]:
        """Retrieval and measurement of ``query`` without touching the filter (safe from another thread):
        (retrieval, measurement, retrieval ms, measurement ms)."""
        t0 = time.perf_counter()
        retrieval = self.retriever.retrieve(query, prediction)
        t1 = time.perf_counter()
        measurement = self.measurer.measure(query, retrieval)
        t2 = time.perf_counter()
        return retrieval, measurement, (t1 - t0) * 1000.0, (t2 - t1) * 1000.0

    def fuse(self, query: Query, retrieval: Retrieval, measurement: Measurement, retrieval_ms: float = 0.0,
             measurement_ms: float = 0.0) -> StepResult:
        """The filter's step with ``measurement`` (one query's, made by ``measure`` or otherwise)."""
        t0 = time.perf_counter()
        filtered = self._kalman.step(measurement.east_north_m, measurement.cov_m2,
                                     correlated=measurement.source == GEOMETRY)
        filter_ms = (time.perf_counter() - t0) * 1000.0
        return StepResult(query, retrieval, measurement, filtered, StepTimings(retrieval_ms, measurement_ms, filter_ms))

    def snapshot(self) -> object:
        """The filter's state as it is now, for ``restore`` (a measurement that arrives late is fused in its
        place and the later ones again)."""
        return copy.deepcopy(self._kalman)

    def restore(self, snapshot: object) -> None:
        """The filter as ``snapshot`` holds it."""
        self._kalman = copy.deepcopy(snapshot)

    def step(self, query: Query, first: FirstMeasurement | None = None) -> StepResult:
        """Retrieval, measurement and the filter's step for ``query``; ``first(measurement, retrieval)``, if given,
        chooses the measurement that starts the track while the filter holds none."""
        retrieval, measurement, retrieval_ms, measurement_ms = self.measure(query, self._kalman.prediction())
        if first is not None and not self.started:
            measurement = first(measurement, retrieval)
        return self.fuse(query, retrieval, measurement, retrieval_ms, measurement_ms)


def first_fix(measurement: Measurement, retrieval: Retrieval, db_east_north_m: np.ndarray,
              k: int = FIRST_FIX_CANDIDATES, agreement_m: float = FIRST_FIX_AGREEMENT_M) -> Measurement:
    """A track's first measurement: a refined measurement's geotag fallback whose candidate lies more than ``agreement_m`` from the median
    geotag of the ``k`` best candidates is replaced by that median (a lone far candidate is more often a
    look-alike place than the vehicle's); anything else is kept."""
    if measurement.source != GEOTAG or measurement.fallback_reason is None or retrieval.counts.size < 3:
        return measurement  # a pose, or the paper's own measurement (the geotag by design, not a fallback)
    best = np.argsort(-retrieval.counts, kind="stable")[:k]
    best = best[retrieval.counts[best] > 0]
    if best.size < 3:
        return measurement
    positions = np.asarray(db_east_north_m, float)[retrieval.candidates[best]]
    centre = np.median(positions, axis=0)
    if np.linalg.norm(np.asarray(measurement.east_north_m, float) - centre) <= agreement_m:
        return measurement
    reason = (f"{measurement.fallback_reason}; first fix: the best candidate's geotag lies far from the other "
              f"candidates', their median geotag is used")
    return replace(measurement, east_north_m=centre, fallback_reason=reason)
