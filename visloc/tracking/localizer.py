"""The localizer: a retriever, a measurer and the constant-velocity filter, one query at a time.

``Localizer`` is composed of parts, each replaceable:

* a retriever (``visloc.retrieval.retrievers``): the paper's ``WindowRetriever`` or the fast path's
  ``ShortlistRetriever``, which the filter's prediction gates;
* a measurer (``visloc.pose.measurement``): the paper's ``GeotagMeasurer`` or the refined
  method's ``visloc.pose.refined.PoseMeasurer``;
* the filter (``visloc.tracking.kalman.ConstantVelocityKalman``), with an optional Mahalanobis gate.

``visloc.tracking.methods`` composes them into the named methods (the paper's, the refined one).
Each ``step`` returns everything about that query, its timings included.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from visloc.features.sift import Query
from visloc.pose.measurement import Measurement, Measurer
from visloc.params import FilterParams
from visloc.retrieval.retrievers import Prediction, Retrieval
from visloc.tracking.kalman import ConstantVelocityKalman, FilterStep


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
                 gate_chi2: float = 0.0, reinit_after_gated: int = 0):
        self.retriever = retriever
        self.measurer = measurer
        self.filter_params = filter_params
        self.gate_chi2 = float(gate_chi2)  # 0: every measurement is applied
        self.reinit_after_gated = int(reinit_after_gated)  # 0: never restart the track
        self.reset()

    def reset(self) -> None:
        """Forget the track: the next query scans the whole database again."""
        self.retriever.reset()
        self._kalman = ConstantVelocityKalman(self.filter_params, gate_chi2=self.gate_chi2,
                                              reinit_after_gated=self.reinit_after_gated)

    def step(self, query: Query) -> StepResult:
        t0 = time.perf_counter()
        retrieval = self.retriever.retrieve(query, self._kalman.prediction())
        t1 = time.perf_counter()
        measurement = self.measurer.measure(query, retrieval)
        t2 = time.perf_counter()
        filtered = self._kalman.step(measurement.east_north_m, measurement.cov_m2)
        t3 = time.perf_counter()
        timings = StepTimings((t1 - t0) * 1000.0, (t2 - t1) * 1000.0, (t3 - t2) * 1000.0)
        return StepResult(query, retrieval, measurement, filtered, timings)
