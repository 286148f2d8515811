"""The paper's evaluation protocol (section 4) and its statistics.

A series is ``n_steps`` queries about ``dt_s`` apart (t-5 ... t for six steps),
sampled as ``series_schedule`` describes. Every start frame whose series fits in
the drive is evaluated. Errors are distances between a geotag (the measurement, i.e. the best
match's geotag or, in the refined mode, the metric pose, or the filter's estimate) and the
query's own ground-truth geotag.

Both modes report the same keys; mode-specific ones are None where they do not apply.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from visloc.database import GeoDatabase, QuerySet, camera_model
from visloc.geo import geodesic_distance_m, haversine_distance_m
from visloc.localizer import Localizer, PairCountCache, Query, StepResult
from visloc.errors import ParameterError
from visloc.params import REFINED, FilterParams, MatchParams, RefinedParams, RetrievalParams, check_mode
from visloc.refined import GEOMETRY, GEOTAG, StructureCache
from visloc.tracking import SmoothedStep, rts_smooth


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
    # what the measurement was and how the filter took it (both modes)
    measurement_source: str | None = None  # "geometry", "geotag" or None (no measurement)
    fallback_reason: str | None = None  # refined mode: why this step's measurement is a geotag
    measurement_cov_m2: list[list[float]] | None = None  # the R the filter used, m^2 (east, north)
    measurement_sigma_m: float | None = None  # sqrt of its largest eigenvalue
    measurement_nees: float | None = None  # e' R^-1 e of the measurement error e (about 2 on average if R is honest)
    mahalanobis: float | None = None  # innovation's Mahalanobis distance to the prediction
    gated: bool = False  # rejected by the filter's gate: this step only predicted
    view_db_frames: list[int] = field(default_factory=list)  # refined: database frames the pose was solved against
    neighbour_db_frames: list[int] = field(default_factory=list)  # refined: frames triangulated with those views
    n_pnp_inliers: int = 0
    measurement_ms: float = 0.0  # time the measurement took on the query side (refined: matching, RANSAC, PnP)
    measurement_heading_deg: float | None = None  # refined: compass heading of the pose
    smoothed_lat_deg: float | None = None  # RTS smoother (evaluate --smooth)
    smoothed_lon_deg: float | None = None
    smoothed_error_m: float | None = None


def step_record(step: int, result: StepResult, db: GeoDatabase, *, query_frame: int, truth_lat_deg: float,
                truth_lon_deg: float, latency_ms: float, keep_counts: bool = False,
                smoothed: SmoothedStep | None = None) -> StepRecord:
    """Everything about one localized query, in geotags and metres, against its ground truth."""
    truth = (float(truth_lat_deg), float(truth_lon_deg))
    best = result.best_index
    m = result.measurement
    m_lat = m_lon = e_lat = e_lon = sigma = None
    m_err = e_err = m_hav = e_hav = cov = None
    source = m.source if m is not None else (GEOTAG if best is not None else None)
    if source == GEOTAG:
        index = m.db_index if m is not None else best
        m_lat, m_lon = float(db.lat_deg[index]), float(db.lon_deg[index])
    elif source == GEOMETRY:
        lat, lon = db.frame.to_geo(m.east_north_m)
        m_lat, m_lon = float(lat), float(lon)
    if m_lat is not None:
        m_err = float(geodesic_distance_m(m_lat, m_lon, *truth))
        m_hav = float(haversine_distance_m(m_lat, m_lon, *truth))
    R = result.filter.R
    nees = m_sigma = None
    if R is not None and result.measurement_m is not None:
        m_sigma = float(np.sqrt(np.linalg.eigvalsh(R).max()))
        e = np.asarray(result.measurement_m, float) - db.frame.to_local(*truth)
        nees = float(e @ np.linalg.solve(R, e))
    s_lat = s_lon = s_err = None
    if smoothed is not None and np.all(np.isfinite(smoothed.x)):
        lat, lon = db.frame.to_geo(smoothed.x[:2])
        s_lat, s_lon = float(lat), float(lon)
        s_err = float(geodesic_distance_m(s_lat, s_lon, *truth))
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
        measurement_source=source, fallback_reason=None if m is None else m.fallback_reason,
        measurement_cov_m2=None if R is None else np.asarray(R, float).tolist(), measurement_sigma_m=m_sigma,
        measurement_nees=nees,
        mahalanobis=None if result.filter.innovation is None else float(result.filter.innovation.mahalanobis),
        gated=bool(result.filter.gated),
        view_db_frames=[] if m is None else [int(db.images[i].frame) for i in m.view_indices],
        neighbour_db_frames=[] if m is None else [int(db.images[i].frame) for i in m.neighbour_indices],
        n_pnp_inliers=0 if m is None else int(m.n_pnp_inliers),
        measurement_ms=0.0 if m is None else float(m.compute_ms - m.structure_ms),
        measurement_heading_deg=None if m is None else m.heading_deg,
        smoothed_lat_deg=s_lat, smoothed_lon_deg=s_lon, smoothed_error_m=s_err,
    )


def _reason_kind(reason: str) -> str:
    """A fallback reason without its numbers, to count reasons of one kind together."""
    return re.split(r"[:(\[\d]", reason, maxsplit=1)[0].strip() or reason


@dataclass
class Evaluation:
    series: list[list[StepRecord]]
    params: dict
    mode: str = "paper"
    smoothed: bool = False
    structure_build_ms: float = 0.0  # refined: database-side triangulation time, not part of any query's latency

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
        records = [r for s in self.series for r in s]
        measured = [r for r in records if r.measurement_source is not None]
        refined = self.mode == "refined"
        fallbacks = [r for r in measured if r.fallback_reason is not None]
        reasons: dict[str, int] = {}
        for r in fallbacks:
            reasons[_reason_kind(r.fallback_reason)] = reasons.get(_reason_kind(r.fallback_reason), 0) + 1
        geometry_nees = np.array([r.measurement_nees for r in measured
                                  if r.measurement_source == GEOMETRY and r.measurement_nees is not None])

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
            # the part of the latency the measurement takes (0 for the paper's geotag)
            "measurement_latency_ms": stats(np.array([r.measurement_ms for r in records]), "p50", "p95"),
            "best_match_offset_s": {
                **stats(offsets, "median"),
                "fraction_ahead": float(np.mean(offsets > 0)) if offsets.size else None,
                "fraction_behind": float(np.mean(offsets < 0)) if offsets.size else None,
            },
            "steps_without_measurement": n_queries - int(offsets.size),
            "mode": self.mode,
            "measurement_source_fraction": {
                src: (sum(1 for r in records if r.measurement_source == src) / n_queries if n_queries else None)
                for src in (GEOMETRY, GEOTAG)
            },
            # refined mode: of the steps with a measurement, the fraction where geometry fell back to the geotag
            "geometry_fallback_fraction": (len(fallbacks) / len(measured) if measured else None) if refined else None,
            "fallback_reasons": dict(sorted(reasons.items(), key=lambda kv: -kv[1])) if refined else None,
            "gated_fraction": (sum(r.gated for r in records) / n_queries if n_queries else None),
            "measurement_sigma_m": self._per_step("measurement_sigma_m"),
            # mean of e' R^-1 e over geometry measurements: 2 if their covariances are honest (chi-square, 2 dof)
            "measurement_nees": {
                "mean": float(geometry_nees.mean()) if geometry_nees.size else None,
                "fraction_within_95": float(np.mean(geometry_nees <= 5.991)) if geometry_nees.size else None,
                "n": int(geometry_nees.size),
            } if refined else None,
            "smoothed_error_m": self._per_step("smoothed_error_m") if self.smoothed else None,
            "structure_build_ms": self.structure_build_ms if refined else None,
            "params": self.params,
        }


def localization_inputs(queries: QuerySet, db: GeoDatabase, match_params: MatchParams, mode: str,
                        cache: PairCountCache | None, fast=None):
    """What a Localizer over ``queries`` and ``db`` needs besides parameters: a count cache for
    these thresholds (a new one if None) and, in the refined mode, the database's geometry and
    the query camera. Refuses a cache built for other thresholds."""
    check_mode(mode)
    if cache is None:  # the fast path may match capped descriptors: count what it matches
        cache = PairCountCache(fast.descriptors_u8 if fast is not None else db.descriptors_u8, match_params)
    elif cache.match_params != match_params:
        raise ParameterError(f"cache holds counts for {cache.match_params}, not {match_params}")
    geometry = query_camera = None
    if mode == "refined":
        geometry = db.geometry()
        query_camera, _ = camera_model(queries.calibration, f"queries {queries.source}/{queries.camera}")
        if not queries.keypoints_f32:
            raise ParameterError("mode='refined': the query set has no keypoints")
    return cache, geometry, query_camera


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
    mode: str = "paper",
    refined_params: RefinedParams = REFINED,
    smooth: bool = False,
    fast=None,
) -> Evaluation:
    """Run every series (or those starting at ``start_indices``, indices into ``queries``).

    Latency of a query = its SIFT time (measured at ingest) + the time its
    candidate comparisons took when first computed + the filter step. Pairs are
    computed once and reused across series that share a query image; pass a
    ``cache`` keyed by query and database image ids to reuse them across runs.

    ``mode="refined"`` measures metric poses (``visloc.refined``); the database and
    query cameras' calibration and the database's attitudes come from ``db`` and
    ``queries``; without them every step falls back to the geotag, with the reason.
    A refined query's latency adds its measurement time (matching the top candidates
    again, RANSAC, PnP) but not the triangulation of database structure, which is
    database-side work done once per database pair (``structure_build_ms``).
    ``smooth`` adds the RTS smoother's estimates of every step of each series.
    ``fast`` (a ``visloc.fast.FastDatabase`` of ``db``) selects the opt-in fast retrieval: the
    filter gates the candidates and global vectors shortlist them before the exact counts.
    """
    check_mode(mode)
    schedule = series_schedule(queries.timestamps_s, filter_params.dt_s, n_steps, sampling)
    if start_indices is not None:
        wanted = set(int(i) for i in start_indices)
        schedule = [s for s in schedule if s[0] in wanted]
    if fast is not None and fast.params.max_keypoints and cache is not None:
        raise ParameterError("fast.params.max_keypoints: counts of capped descriptors cannot come from a cache of "
                             "full ones; pass cache=None")
    cache, geometry, query_camera = localization_inputs(queries, db, match_params, mode, cache, fast)
    structures = StructureCache()
    localizer = Localizer(db.timestamps_s, db.east_north_m, db.descriptors_u8, match_params, retrieval_params,
                          filter_params, counter=cache, mode=mode, refined_params=refined_params, geometry=geometry,
                          query_camera=query_camera, structure_cache=structures, measurement_cache={},
                          fast=fast)
    series = []
    for indices in schedule:
        localizer.reset()
        results, latencies = [], []
        for k, q in enumerate(indices):
            key = queries.key(q)
            keypoints = queries.keypoints_f32[q] if queries.keypoints_f32 else None
            result = localizer.step(Query(queries.descriptors_u8[q], float(queries.timestamps_s[q]), key=key,
                                          keypoints_f32=keypoints))
            match_ms = cache.cost_ms(key, result.retrieval.candidates)
            sift_ms = float(queries.sift_ms[q]) if np.isfinite(queries.sift_ms[q]) else 0.0
            # compute_ms covers retrieval + measurement + filter, including any pair or measurement
            # computed afresh in this step; take that fresh work out and add the recorded cost of
            # every candidate pair and of the measurement (without database-side structure) instead
            m = result.measurement
            measure_ms = (m.compute_ms - m.structure_ms) if m is not None else 0.0
            overhead = max(result.compute_ms - cache.fresh_ms - localizer.last_measure_ms, 0.0)
            latencies.append(sift_ms + match_ms + measure_ms + overhead)
            results.append(result)
        smoothed = rts_smooth([r.filter for r in results], filter_params.dt_s) if smooth else [None] * len(results)
        records = [step_record(k, result, db, query_frame=int(queries.frames[q]), truth_lat_deg=queries.lat_deg[q],
                               truth_lon_deg=queries.lon_deg[q], latency_ms=latency, smoothed=sm)
                   for k, (q, result, latency, sm) in enumerate(zip(indices, results, latencies, smoothed))]
        series.append(records)
        if progress:
            progress(1)
    params = {
        "match": match_params.as_dict(), "retrieval": retrieval_params.as_dict(), "filter": filter_params.as_dict(),
        "n_steps": n_steps, "sampling": sampling, "database": f"{db.source}/{db.camera}",
        "queries": f"{queries.source}/{queries.camera}", "mode": mode,
        "refined": refined_params.as_dict() if mode == "refined" else None, "smooth": smooth,
        "fast": fast.params.as_dict() if fast is not None else None,
    }
    return Evaluation(series=series, params=params, mode=mode, smoothed=smooth,
                      structure_build_ms=structures.build_ms)
