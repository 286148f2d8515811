"""A localization run over a whole drive: what the dashboard scrubs through, usable headless.

The run is split in two so that live tuning stays cheap:

- ``match_drive``: retrieval for every query (SIFT correspondences against the
  candidates). Slow; depends on tau1, tau2, the query schedule and the exclusion
  window. Counts go through a ``PairCountCache``, so a rerun only computes new pairs.
- ``track_drive``: the Kalman filter over the resulting measurements. Milliseconds;
  depends on R, Q and P0 (and, in the refined mode, the gate) only.

Both modes work the same way: ``mode="paper"`` measures the best match's geotag,
``mode="refined"`` a metric pose from the database's geometry (``visloc.refined``),
falling back to the geotag with a reason.

Unlike ``evaluate`` (six-query series), the filter here runs once over the whole
drive, from the start time to the end, one query per ``interval_s``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from visloc.database import GeoDatabase, QuerySet
from visloc.errors import ParameterError
from visloc.evaluation import StepRecord, localization_inputs, step_record
from visloc.localizer import Localizer, PairCountCache, Query, StepResult
from visloc.params import REFINED, FilterParams, MatchParams, RefinedParams, RetrievalParams
from visloc.refined import Measurement, StructureCache
from visloc.retrieval import CountFn, Retrieval
from visloc.tracking import run_filter


class MatchCancelled(Exception):
    """``match_drive`` stopped because its ``cancelled()`` callback said so."""


def drive_query_indices(timestamps_s: np.ndarray, start_s: float, interval_s: float) -> np.ndarray:
    """Indices of the queries of a drive run: from ``start_s`` after the first frame to
    the end, every m-th frame with m = round(interval_s / median frame interval)
    (the evaluation's "stride" sampling; every 10th frame for 1 s on KITTI)."""
    t = np.asarray(timestamps_s, float)
    if not interval_s > 0:
        raise ParameterError(f"interval_s={interval_s}: must be > 0")
    if not start_s >= 0:
        raise ParameterError(f"start_s={start_s}: must be >= 0")
    if t.size == 0:
        return np.zeros(0, np.int64)
    duration_s = float(t[-1] - t[0])
    if start_s > duration_s:
        raise ParameterError(f"start_s={start_s:g}: after the end of the drive ({duration_s:.1f} s long)")
    frame_interval_s = float(np.median(np.diff(t))) if t.size > 1 else interval_s
    stride = max(1, int(round(interval_s / frame_interval_s)))
    first = int(np.searchsorted(t, t[0] + start_s - 1e-6))
    return np.arange(first, t.size, stride, dtype=np.int64)


@dataclass(frozen=True)
class DriveMatches:
    """Retrieval results of a drive run, one per query."""

    query_indices: np.ndarray  # (K,) indices into the QuerySet
    retrievals: tuple[Retrieval, ...]
    match_params: MatchParams
    retrieval_params: RetrievalParams
    latency_ms: np.ndarray  # (K,) query SIFT time + its candidate pairs' time when first computed + measurement
    measurements: tuple[Measurement, ...] = ()  # (K,) what each query measured
    mode: str = "paper"
    refined_params: RefinedParams = REFINED

    def __len__(self) -> int:
        return len(self.retrievals)


def _cancellable(counts: CountFn, cancelled: Callable[[], bool] | None, chunk: int = 4) -> CountFn:
    if cancelled is None:
        return counts

    def checked(candidates: np.ndarray) -> np.ndarray:
        parts = []
        for lo in range(0, len(candidates), chunk):
            if cancelled():
                raise MatchCancelled()
            parts.append(counts(candidates[lo:lo + chunk]))
        return np.concatenate(parts) if parts else np.zeros(0, np.int64)

    return checked


def match_drive(queries: QuerySet, db: GeoDatabase, match_params: MatchParams, retrieval_params: RetrievalParams,
                query_indices: Sequence[int], *, cache: PairCountCache | None = None,
                progress: Callable[[int, int], None] | None = None,
                cancelled: Callable[[], bool] | None = None, mode: str = "paper",
                refined_params: RefinedParams = REFINED, structure_cache: StructureCache | None = None
                ) -> DriveMatches:
    """Retrieve the best database match of every query in ``query_indices``, in order,
    with the paper's search window around the previous best match, and measure it
    (``mode``: "paper" or "refined").

    ``progress(done, total)`` is called after each query; ``cancelled()`` is polled
    between small groups of candidate pairs and raises ``MatchCancelled`` when true.
    Counts computed so far stay in ``cache`` either way; database structure built by
    the refined mode stays in ``structure_cache``.
    """
    cache, geometry, query_camera = localization_inputs(queries, db, match_params, mode, cache)
    indices = np.asarray(query_indices, np.int64)
    localizer = Localizer(db.timestamps_s, db.east_north_m, db.descriptors_u8, match_params, retrieval_params,
                          FilterParams(), counter=lambda q: _cancellable(cache(q), cancelled), mode=mode,
                          refined_params=refined_params, geometry=geometry, query_camera=query_camera,
                          structure_cache=structure_cache)
    retrievals, measurements, latency = [], [], []
    for k, q in enumerate(indices):
        key = queries.key(int(q))
        keypoints = queries.keypoints_f32[q] if queries.keypoints_f32 else None
        result = localizer.step(Query(queries.descriptors_u8[q], float(queries.timestamps_s[q]), key=key,
                                      keypoints_f32=keypoints))
        if cancelled is not None and cancelled():
            raise MatchCancelled()
        sift_ms = float(queries.sift_ms[q]) if np.isfinite(queries.sift_ms[q]) else 0.0
        m = result.measurement
        measure_ms = (m.compute_ms - m.structure_ms) if m is not None else 0.0  # query side only, as evaluate
        retrievals.append(result.retrieval)
        measurements.append(m)
        latency.append(sift_ms + cache.cost_ms(key, result.retrieval.candidates) + measure_ms)
        if progress:
            progress(k + 1, len(indices))
    return DriveMatches(indices, tuple(retrievals), match_params, retrieval_params, np.array(latency, float),
                        tuple(measurements), mode, refined_params)


def track_drive(matches: DriveMatches, queries: QuerySet, db: GeoDatabase, filter_params: FilterParams, *,
                gate_chi2: float | None = None) -> list[StepRecord]:
    """Run the Kalman filter over a drive's measurements and describe every step against
    its ground truth. Cheap: no matching. A refined measurement brings its own covariance;
    geotags use ``filter_params``' R. ``gate_chi2`` (default: the refined mode's, 0 = off in
    the paper mode) rejects measurements too far from the prediction."""
    if gate_chi2 is None:
        gate_chi2 = matches.refined_params.gate_chi2 if matches.mode == "refined" else 0.0
    measurements = list(matches.measurements)
    filtered = run_filter([m.east_north_m for m in measurements], filter_params,
                          covariances_m2=[m.cov_m2 for m in measurements], gate_chi2=gate_chi2)
    records = []
    for k, (q, retrieval, m, f) in enumerate(zip(matches.query_indices, matches.retrievals, measurements, filtered)):
        result = StepResult(float(queries.timestamps_s[q]), retrieval, m.east_north_m, f, 0.0, m)
        records.append(step_record(k, result, db, query_frame=int(queries.frames[q]),
                                   truth_lat_deg=queries.lat_deg[q], truth_lon_deg=queries.lon_deg[q],
                                   latency_ms=float(matches.latency_ms[k]), keep_counts=True))
    return records


def drive_summary(records: Sequence[StepRecord]) -> dict:
    """Mean measurement and estimate errors over a drive run, and the final estimate error, m."""
    def mean(attr: str) -> float | None:
        vals = [getattr(r, attr) for r in records if getattr(r, attr) is not None]
        return float(np.mean(vals)) if vals else None

    return {
        "n_steps": len(records),
        "mean_measurement_error_m": mean("measurement_error_m"),
        "mean_estimate_error_m": mean("estimate_error_m"),
        "final_estimate_error_m": records[-1].estimate_error_m if records else None,
        "steps_without_measurement": sum(1 for r in records if r.measurement_source is None),
        "geometry_fraction": (sum(1 for r in records if r.measurement_source == "geometry") / len(records)
                              if records else None),
        "gated_steps": sum(1 for r in records if r.gated),
    }
