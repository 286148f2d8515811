"""The paper's evaluation protocol (section 4) and its statistics.

A series is ``n_steps`` queries about ``dt_s`` apart (t-5 ... t for six steps),
sampled as ``series_schedule`` describes. Every start frame whose series fits in
the drive is evaluated. Errors are distances between a geotag (the measurement, i.e. the best
match's geotag, or the filter's estimate) and the query's own ground-truth geotag.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from visloc.database import GeoDatabase, QuerySet
from visloc.geo import geodesic_distance_m, haversine_distance_m
from visloc.localizer import Localizer, PairCountCache, Query, StepResult
from visloc.errors import ParameterError
from visloc.params import FilterParams, MatchParams, RetrievalParams


SAMPLINGS = ("stride", "time")


def step_labels(n_steps: int) -> list[str]:
    """The paper's step names: t-5, ..., t-1, t for six steps."""
    return [f"t-{n_steps - 1 - k}" if k < n_steps - 1 else "t" for k in range(n_steps)]


def series_schedule(timestamps_s: np.ndarray, dt_s: float, n_steps: int, sampling: str = "stride") -> list[list[int]]:
    """Indices of the queries of every series that fits in the sequence, one list per start index.

    sampling="stride" (the paper's protocol): every m-th frame, m = round(dt_s / median
        frame interval); on KITTI (9.7 Hz) every 10th frame, so queries are 1.03 s apart,
        as in the paper's Table 2 (frames 0, 10, ..., 50).
    sampling="time": the frame nearest to t0 + k*dt_s, which must lie within half a
        frame interval of it; queries are dt_s apart to within +-0.05 s on KITTI.
    """
    if sampling not in SAMPLINGS:
        raise ParameterError(f"sampling={sampling!r}: must be one of {', '.join(SAMPLINGS)}")
    t = np.asarray(timestamps_s, float)
    if t.size < 2:
        return []
    frame_interval_s = float(np.median(np.diff(t)))
    if sampling == "stride":
        stride = max(1, int(round(dt_s / frame_interval_s)))
        span = stride * (n_steps - 1)
        return [list(range(start, start + span + 1, stride)) for start in range(t.size - span)]
    tolerance_s = 0.5 * frame_interval_s
    out = []
    for start in range(t.size):
        targets = t[start] + dt_s * np.arange(n_steps)
        if targets[-1] > t[-1] + tolerance_s:
            break
        idx = np.abs(t[None, :] - targets[:, None]).argmin(axis=1)
        if np.all(np.abs(t[idx] - targets) <= tolerance_s) and np.all(np.diff(idx) > 0):
            out.append([int(i) for i in idx])
    return out


@dataclass
class StepRecord:
    """One query of one series, everything a report or a dashboard shows."""

    step: int
    query_frame: int
    query_timestamp_s: float
    truth_lat_deg: float
    truth_lon_deg: float
    n_candidates: int
    best_db_frame: int | None
    best_count: int
    best_offset_s: float | None  # best match's timestamp minus the query's
    measurement_lat_deg: float | None
    measurement_lon_deg: float | None
    estimate_lat_deg: float | None
    estimate_lon_deg: float | None
    estimate_sigma_m: float | None  # sqrt of the largest eigenvalue of the position covariance
    measurement_error_m: float | None  # geodesic (WGS84)
    estimate_error_m: float | None
    measurement_error_haversine_m: float | None
    estimate_error_haversine_m: float | None
    latency_ms: float
    nearest_candidate_error_m: float | None = None  # floor: the candidate geotag closest to the truth
    estimate_cov_m2: list[list[float]] | None = None  # 2x2 east/north position covariance of the estimate
    counts: list[int] = field(default_factory=list, repr=False)
    candidate_frames: list[int] = field(default_factory=list, repr=False)


def step_record(step: int, result: StepResult, db: GeoDatabase, *, query_frame: int, truth_lat_deg: float,
                truth_lon_deg: float, latency_ms: float, keep_counts: bool = False) -> StepRecord:
    """Everything about one localized query, in geotags and metres, against its ground truth."""
    truth = (float(truth_lat_deg), float(truth_lon_deg))
    best = result.best_index
    m_lat = m_lon = e_lat = e_lon = sigma = None
    m_err = e_err = m_hav = e_hav = cov = None
    if best is not None:
        m_lat, m_lon = float(db.lat_deg[best]), float(db.lon_deg[best])
        m_err = float(geodesic_distance_m(m_lat, m_lon, *truth))
        m_hav = float(haversine_distance_m(m_lat, m_lon, *truth))
    candidates = result.retrieval.candidates
    floor = None
    if candidates.size:
        floor = float(geodesic_distance_m(db.lat_deg[candidates], db.lon_deg[candidates], *truth).min())
    if np.all(np.isfinite(result.filter.x)):
        lat, lon = db.frame.to_geo(result.filter.x[:2])
        e_lat, e_lon = float(lat), float(lon)
        e_err = float(geodesic_distance_m(e_lat, e_lon, *truth))
        e_hav = float(haversine_distance_m(e_lat, e_lon, *truth))
        sigma = float(np.sqrt(np.linalg.eigvalsh(result.filter.position_cov_m2).max()))
        cov = result.filter.position_cov_m2.tolist()
    return StepRecord(
        step=step, query_frame=int(query_frame), query_timestamp_s=float(result.query_timestamp_s),
        truth_lat_deg=truth[0], truth_lon_deg=truth[1], n_candidates=int(result.retrieval.candidates.size),
        best_db_frame=None if best is None else int(db.images[best].frame), best_count=result.retrieval.best_count,
        best_offset_s=None if best is None else float(db.timestamps_s[best] - result.query_timestamp_s),
        measurement_lat_deg=m_lat, measurement_lon_deg=m_lon, estimate_lat_deg=e_lat, estimate_lon_deg=e_lon,
        estimate_sigma_m=sigma, measurement_error_m=m_err, estimate_error_m=e_err,
        measurement_error_haversine_m=m_hav, estimate_error_haversine_m=e_hav, latency_ms=latency_ms,
        nearest_candidate_error_m=floor, estimate_cov_m2=cov,
        counts=[int(c) for c in result.retrieval.counts] if keep_counts else [],
        candidate_frames=[int(db.images[i].frame) for i in result.retrieval.candidates] if keep_counts else [],
    )


@dataclass
class Evaluation:
    series: list[list[StepRecord]]
    params: dict

    @property
    def n_steps(self) -> int:
        return len(self.series[0]) if self.series else 0

    def _per_step(self, attr: str) -> list[float | None]:
        out = []
        for k in range(self.n_steps):
            vals = [getattr(s[k], attr) for s in self.series if getattr(s[k], attr) is not None]
            out.append(float(np.mean(vals)) if vals else None)
        return out

    def _final_by_steps_ahead(self) -> dict[str, dict]:
        groups: dict[int, list[float]] = {}
        for s in self.series:
            if s[-1].estimate_error_m is not None:
                ahead = sum(1 for r in s if r.best_offset_s is not None and r.best_offset_s > 0)
                groups.setdefault(ahead, []).append(s[-1].estimate_error_m)
        return {str(k): {"n_series": len(v), "mean": float(np.mean(v))} for k, v in sorted(groups.items())}

    def summary(self) -> dict:
        finals = np.array([s[-1].estimate_error_m for s in self.series if s[-1].estimate_error_m is not None])
        latency = np.array([r.latency_ms for s in self.series for r in s])
        offsets = np.array([r.best_offset_s for s in self.series for r in s if r.best_offset_s is not None])
        n_queries = sum(len(s) for s in self.series)

        def stats(values: np.ndarray, *names: str) -> dict:
            if values.size == 0:
                return {n: None for n in names}
            table = {"mean": np.mean, "median": np.median, "min": np.min, "max": np.max,
                     "p50": lambda v: np.percentile(v, 50), "p90": lambda v: np.percentile(v, 90),
                     "p95": lambda v: np.percentile(v, 95)}
            return {n: float(table[n](values)) for n in names}

        return {
            "n_series": len(self.series),
            "n_steps": self.n_steps,
            "steps": step_labels(self.n_steps),
            "measurement_error_m": self._per_step("measurement_error_m"),
            "estimate_error_m": self._per_step("estimate_error_m"),
            "measurement_error_haversine_m": self._per_step("measurement_error_haversine_m"),
            "estimate_error_haversine_m": self._per_step("estimate_error_haversine_m"),
            # the best a retrieval could do: the candidate image nearest to the truth
            "nearest_candidate_error_m": self._per_step("nearest_candidate_error_m"),
            "final_error_m": stats(finals, "mean", "median", "p90", "min", "max"),
            # series grouped by how many of their best matches lie ahead of the query in time
            "final_error_m_by_steps_ahead": self._final_by_steps_ahead(),
            "latency_ms": stats(latency, "p50", "p95"),
            "best_match_offset_s": {
                **stats(offsets, "median"),
                "fraction_ahead": float(np.mean(offsets > 0)) if offsets.size else None,
                "fraction_behind": float(np.mean(offsets < 0)) if offsets.size else None,
            },
            "steps_without_measurement": n_queries - int(offsets.size),
            "params": self.params,
        }


def evaluate(
    queries: QuerySet,
    db: GeoDatabase,
    match_params: MatchParams,
    retrieval_params: RetrievalParams,
    filter_params: FilterParams,
    *,
    n_steps: int = 6,
    sampling: str = "stride",
    start_indices: Sequence[int] | None = None,
    cache: PairCountCache | None = None,
    progress=None,
) -> Evaluation:
    """Run every series (or those starting at ``start_indices``, indices into ``queries``).

    Latency of a query = its SIFT time (measured at ingest) + the time its
    candidate comparisons took when first computed + the filter step. Pairs are
    computed once and reused across series that share a query image; pass a
    ``cache`` keyed by query and database image ids to reuse them across runs.
    """
    schedule = series_schedule(queries.timestamps_s, filter_params.dt_s, n_steps, sampling)
    if start_indices is not None:
        wanted = set(int(i) for i in start_indices)
        schedule = [s for s in schedule if s[0] in wanted]
    if cache is None:
        cache = PairCountCache(db.descriptors_u8, match_params)
    elif cache.match_params != match_params:
        raise ParameterError(f"cache holds counts for {cache.match_params}, not {match_params}")
    localizer = Localizer(db.timestamps_s, db.east_north_m, db.descriptors_u8, match_params, retrieval_params,
                          filter_params, counter=cache)
    series = []
    for indices in schedule:
        localizer.reset()
        records = []
        for k, q in enumerate(indices):
            key = queries.key(q)
            result = localizer.step(Query(queries.descriptors_u8[q], float(queries.timestamps_s[q]), key=key))
            match_ms = cache.cost_ms(key, result.retrieval.candidates)
            sift_ms = float(queries.sift_ms[q]) if np.isfinite(queries.sift_ms[q]) else 0.0
            # compute_ms covers retrieval + filter, including any pair computed afresh in this step;
            # take that fresh work out and add the recorded cost of every candidate pair instead
            latency = sift_ms + match_ms + max(result.compute_ms - cache.fresh_ms, 0.0)
            records.append(step_record(k, result, db, query_frame=int(queries.frames[q]),
                                       truth_lat_deg=queries.lat_deg[q], truth_lon_deg=queries.lon_deg[q],
                                       latency_ms=latency))
        series.append(records)
        if progress:
            progress(1)
    params = {
        "match": match_params.as_dict(), "retrieval": retrieval_params.as_dict(), "filter": filter_params.as_dict(),
        "n_steps": n_steps, "sampling": sampling, "database": f"{db.source}/{db.camera}",
        "queries": f"{queries.source}/{queries.camera}",
    }
    return Evaluation(series=series, params=params)
