"""A localization run over a whole drive: what the dashboard scrubs through, usable headless.

The run is split in two so that live tuning stays cheap:

- ``match_drive``: retrieval and measurement for every query (slow; depends on tau1, tau2,
  the query schedule, the exclusion window and the method). Counts go through a
  ``PairCountCache``, so a rerun only computes new pairs.
- ``track_drive``: the Kalman filter over those measurements (milliseconds; depends on R,
  Q, P0 and the gate only).

Unlike ``evaluate`` (six-query series), the filter here runs once over the whole drive,
from the start time to the end, one query per ``interval_s``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from visloc.store.database import GeoDatabase, QuerySet
from visloc.errors import ParameterError
from visloc.tracking.localizer import StepResult, StepTimings
from visloc.retrieval.matching import PairCountCache, cancellable
from visloc.pose.measurement import GEOMETRY, Measurement
from visloc.params.methods import PAPER_METHOD, Method
from visloc.tracking.methods import build_localizer
from visloc.params import FilterParams, MatchParams, RetrievalParams
from visloc.pose.refined import StructureCache
from visloc.protocols.records import QueryTruth, StepRecord, records_of
from visloc.retrieval.retrievers import Retrieval
from visloc.tracking.runs import run_queries
from visloc.tracking.kalman import FilterStep, run_filter
from visloc.features.vlad import GlobalIndex


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
    """Retrievals and measurements of a drive run, one per query."""

    query_indices: np.ndarray  # (K,) indices into the QuerySet
    retrievals: tuple[Retrieval, ...]
    measurements: tuple[Measurement, ...]
    match_params: MatchParams
    retrieval_params: RetrievalParams
    method: Method
    latency_ms: np.ndarray  # (K,) see visloc.tracking.runs.latency_ms
    # how each step was measured when the run followed points (visloc.protocols.following): "tracked",
    # "relocalized" or "predicted" (visloc.tracking.follower); empty: every query measured in full
    kinds: tuple[str, ...] = ()

    @property
    def follows_points(self) -> bool:
        return bool(self.kinds)

    def __len__(self) -> int:
        return len(self.retrievals)


def match_drive(queries: QuerySet, db: GeoDatabase, match_params: MatchParams, retrieval_params: RetrievalParams,
                query_indices: Sequence[int], *, method: Method = PAPER_METHOD,
                cache: PairCountCache | None = None, progress: Callable[[int, int], None] | None = None,
                cancelled: Callable[[], bool] | None = None, structures: StructureCache | None = None,
                filter_params: FilterParams = FilterParams(), stored: dict | None = None,
                shortlist_index: GlobalIndex | None = None,
                on_step: Callable[[DriveMatches], None] | None = None) -> DriveMatches:
    """Retrieve and measure every query in ``query_indices``, in order, with ``method``.

    ``progress(done, total)`` is called after each query; ``cancelled()`` is polled between
    small groups of candidate pairs and raises ``MatchCancelled`` when true. Counts computed so
    far stay in ``cache`` either way; database structure built by the refined method stays in
    ``structures``. ``filter_params`` only matter to a retrieval the filter gates (the fast ones).
    ``stored`` and ``shortlist_index``: the database's stored structure and global vectors, which the
    camera-rate method uses (``Workspace.load_structure``, ``Workspace.load_database_index``).
    ``on_step(partial)`` is handed the run so far (the queries matched up to now, in order) after
    each query, so a caller can show a run as it is matched.
    """
    cache = cache if cache is not None else PairCountCache(db.retrieval_descriptors_u8, match_params)
    cache.check_thresholds(match_params)
    localizer = build_localizer(method, db, match_params, retrieval_params, filter_params,
                                query_camera=queries.camera_model,
                                query_what=queries.name,
                                counter=cancellable(cache, cancelled), structures=structures, stored=stored,
                                shortlist_index=shortlist_index)
    indices = np.asarray(query_indices, np.int64)

    def matches_of(steps: Sequence) -> DriveMatches:
        return DriveMatches(indices[:len(steps)], tuple(s.result.retrieval for s in steps),
                            tuple(s.result.measurement for s in steps), match_params, retrieval_params, method,
                            np.array([s.latency_ms for s in steps], float))

    done: list = []

    def step_done(step) -> None:
        done.append(step)
        on_step(matches_of(done))

    steps = run_queries(localizer, (queries.query(int(q)) for q in indices),
                        cache=None if method.camera_rate else cache, cancelled=cancelled,
                        progress=(lambda n: progress(n, len(indices))) if progress else None,
                        on_step=step_done if on_step else None)
    return matches_of(steps)


def filter_measurements(measurements: Sequence[Measurement], filter_params: FilterParams, *,
                        gate_chi2: float = 0.0, reinit_after_gated: int = 0, corr_fraction: float = 0.0,
                        corr_time_s: float = 1.0) -> list[FilterStep]:
    """Re-run only the filter over measurements already made (no image work).

    Each measurement's own covariance is used where it has one, the filter's R
    (``filter_params.meas_var_m2``) otherwise; ``gate_chi2`` 0 = no gate; ``reinit_after_gated``
    gated measurements in a row restart the track (0 = never); ``corr_fraction`` of a pose measurement's
    covariance is shared with its neighbours' over ``corr_time_s`` (``visloc.tracking.kalman``; 0 = none).
    """
    return run_filter([m.east_north_m for m in measurements], filter_params,
                      covariances_m2=[m.cov_m2 for m in measurements], gate_chi2=gate_chi2,
                      reinit_after_gated=reinit_after_gated, correlated=[m.source == GEOMETRY for m in measurements],
                      corr_fraction=corr_fraction, corr_time_s=corr_time_s)


def track_drive(matches: DriveMatches, queries: QuerySet, db: GeoDatabase, filter_params: FilterParams, *,
                gate_chi2: float | None = None) -> list[StepRecord]:
    """Run the Kalman filter over a drive's measurements and describe every step against its
    ground truth. A refined measurement brings its own covariance; geotags use
    ``filter_params``' R. ``gate_chi2`` defaults to the method's gate (0 = off)."""
    options = dict(matches.method.filter_options)
    options["gate_chi2"] = options["gate_chi2"] if gate_chi2 is None else gate_chi2
    options["reinit_after_gated"] = options["reinit_after_gated"] if options["gate_chi2"] > 0 else 0
    filtered = filter_measurements(matches.measurements, filter_params, **options)
    no_time = StepTimings(0.0, 0.0, 0.0)
    results = [StepResult(queries.query(int(q)), retrieval, m, f, no_time) for q, retrieval, m, f in
               zip(matches.query_indices, matches.retrievals, matches.measurements, filtered)]
    return records_of(results, matches.latency_ms, [int(q) for q in matches.query_indices],
                      QueryTruth.of_queries(queries, db, matches.method.geotag_sigma_m), db, keep_counts=True)


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
        "geometry_fraction": (sum(1 for r in records if r.measurement_source == GEOMETRY) / len(records)
                              if records else None),
        "gated_steps": sum(1 for r in records if r.gated),
    }
