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
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from visloc.store.database import GeoDatabase, QuerySet
from visloc.errors import ParameterError
from visloc.geo import LocalFrame
from visloc.retrieval.matching import PairCountCache
from visloc.pose.measurement import GEOMETRY, GEOTAG
from visloc.params.methods import PAPER_METHOD, Method
from visloc.tracking.methods import build_localizer
from visloc.params import FilterParams, MatchParams, RetrievalParams
from visloc.pose.refined import StructureCache
from visloc.pose.structure import seeded_structure_cache
from visloc.protocols.records import QueryTruth, StepRecord, records_of
from visloc.tracking.runs import run_queries
from visloc.tracking.kalman import rts_smooth
from visloc.pose.uncertainty import SIDES, calibration
from visloc.stats import CHI2_2DOF_95, summary_of
from visloc.features.vlad import GlobalIndex


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


def measurement_calibration(records: Sequence[StepRecord]) -> dict:
    """Calibration figures of the geometry measurements' covariances: over all of them ("all") and per
    side of their views ("both", "one"); see ``visloc.pose.uncertainty.calibration``."""
    geometry = [r for r in records if r.measurement_source == GEOMETRY and r.measurement_nees is not None]
    out = {"all": calibration([r.measurement_nees for r in geometry]).as_dict()}
    for side in SIDES:
        out[side] = calibration([r.measurement_nees for r in geometry if r.measurement_side == side]).as_dict()
    return out


def _reason_kind(reason: str) -> str:
    """A fallback reason with its numbers as N (its lists as [...]), to count reasons of one kind together:
    "PnP RANSAC: 7 inliers (need 12)" is "PnP RANSAC: N inliers (need N)"."""
    kind = re.sub(r"\[[^\]]*\]", "[...]", reason)
    kind = re.sub(r"(?<![\w.-])-?\d+(\.\d+)?(?![\w-])", "N", kind)
    return re.sub(r"\s+", " ", kind).strip()


@dataclass
class Evaluation:
    """Every series of an evaluation; ``summary()`` gives its statistics, ``frame`` is the database's
    local frame (records are in metres)."""

    series: list[list[StepRecord]]
    params: dict
    method: Method
    frame: LocalFrame
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
        refined = self.method.measures_pose
        fallbacks = [r for r in measured if r.fallback_reason is not None]
        reasons: dict[str, int] = {}
        for r in fallbacks:
            reasons[_reason_kind(r.fallback_reason)] = reasons.get(_reason_kind(r.fallback_reason), 0) + 1
        geometry_nees = np.array([r.measurement_nees for r in measured
                                  if r.measurement_source == GEOMETRY and r.measurement_nees is not None])

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
            "final_error_m": summary_of(finals.tolist(), ("mean", "median", "p90", "min", "max")),
            # series grouped by how many of their best matches lie ahead of the query in time
            "final_error_m_by_steps_ahead": self._final_by_steps_ahead(),
            "latency_ms": summary_of(latency.tolist(), ("p50", "p95")),
            # the part of the latency the measurement takes (0 for the paper's geotag)
            "measurement_latency_ms": summary_of([r.measurement_ms for r in records], ("p50", "p95")),
            "best_match_offset_s": {
                **summary_of(offsets.tolist(), ("median",)),
                "fraction_ahead": float(np.mean(offsets > 0)) if offsets.size else None,
                "fraction_behind": float(np.mean(offsets < 0)) if offsets.size else None,
            },
            "steps_without_measurement": n_queries - int(offsets.size),
            "mode": self.method.name,
            "measurement_source_fraction": {
                src: (sum(1 for r in records if r.measurement_source == src) / n_queries if n_queries else None)
                for src in (GEOMETRY, GEOTAG)
            },
            # refined mode: of the steps with a measurement, the fraction where geometry fell back to the geotag
            "geometry_fallback_fraction": (len(fallbacks) / len(measured) if measured else None) if refined else None,
            "fallback_reasons": dict(sorted(reasons.items(), key=lambda kv: -kv[1])) if refined else None,
            # refined mode: of the steps with a measurement, the fraction posed at the looser thin-support threshold
            "thin_support_fraction": (sum(r.thin_support for r in measured) / len(measured) if measured else None)
            if refined else None,
            "gated_fraction": (sum(r.gated for r in records) / n_queries if n_queries else None),
            "measurement_sigma_m": self._per_step("measurement_sigma_m"),
            # mean of e' R^-1 e over geometry measurements: 2 if their covariances are honest (chi-square, 2 dof)
            "measurement_nees": {
                "mean": float(geometry_nees.mean()) if geometry_nees.size else None,
                "fraction_within_95": float(np.mean(geometry_nees <= CHI2_2DOF_95)) if geometry_nees.size else None,
                "n": int(geometry_nees.size),
            } if refined else None,
            # how honest the covariances are (visloc.pose.uncertainty.calibration): the geometry measurements', over
            # every one and split by the side their views lie on, and the estimates' (the filter's P)
            "calibration": measurement_calibration(records) if refined else None,
            "estimate_calibration": calibration([r.estimate_nees for r in records]).as_dict() if refined else None,
            "truth_shares_map": any(r.truth_shares_map for r in records) if records else None,
            "smoothed_error_m": self._per_step("smoothed_error_m") if self.smoothed else None,
            "structure_build_ms": self.structure_build_ms if refined else None,
            "params": self.params,
        }


def evaluate(
    queries: QuerySet,
    db: GeoDatabase,
    match_params: MatchParams,
    retrieval_params: RetrievalParams,
    filter_params: FilterParams,
    *,
    method: Method = PAPER_METHOD,
    n_steps: int = 6,
    sampling: str = "stride",
    start_indices: Sequence[int] | None = None,
    cache: PairCountCache | None = None,
    progress: Callable[[int, int], None] | None = None,
    smooth: bool = False,
    shortlist_index: GlobalIndex | None = None,
    stored: dict | None = None,
) -> Evaluation:
    """Run every series (or those starting at ``start_indices``, indices into ``queries``) with ``method``.

    Latency of a query = its SIFT time (measured at ingest) + its retrieval, with each candidate
    pair costing what it took when first computed + the query side of its measurement + the filter
    step (``visloc.tracking.runs.latency_ms``). Pairs are computed once and reused across series that share
    a query image; pass a ``cache`` keyed by store image ids to reuse them across runs.

    The refined method needs the database's and the queries' calibration and the database's
    attitudes; the triangulation of database structure is database-side work, done once per
    database pair and not part of any query's latency (``structure_build_ms``). ``smooth`` adds
    the RTS smoother's estimates of every step of each series. ``progress(done, total)`` is told
    of each series done. ``stored``: the database's stored structure, which the camera-rate method needs
    and the exact refined one reads where it can
    (``Workspace.load_structure``).
    """
    schedule = series_schedule(queries.timestamps_s, filter_params.dt_s, n_steps, sampling)
    if start_indices is not None:
        wanted = set(int(i) for i in start_indices)
        schedule = [s for s in schedule if s[0] in wanted]
    cache = cache if cache is not None else PairCountCache(db.retrieval_descriptors_u8, match_params)
    # the exact path reads the store's structure where it would triangulate the same view with the same
    # neighbours (the same numbers, built at ingest) and triangulates the rest
    structures = seeded_structure_cache(stored) if stored and not method.camera_rate else StructureCache()
    localizer = build_localizer(method, db, match_params, retrieval_params, filter_params,
                                query_camera=queries.camera_model, query_what=queries.name,
                                counter=cache, shortlist_index=shortlist_index, structures=structures, memoise=True,
                                stored=stored)
    latency_cache = None if method.camera_rate else cache  # the camera-rate path counts without the cache
    truth = QueryTruth.of_queries(queries, db, method.geotag_sigma_m)
    series = []
    for done, indices in enumerate(schedule, 1):
        localizer.reset()
        steps = run_queries(localizer, [queries.query(q) for q in indices], cache=latency_cache)
        smoothed = (rts_smooth([s.result.filter for s in steps], filter_params.dt_s) if smooth
                    else [None] * len(steps))
        series.append(records_of([s.result for s in steps], [s.latency_ms for s in steps], indices, truth, db,
                                  smoothed=smoothed))
        if progress:
            progress(done, len(schedule))
    params = {
        "match": match_params.as_dict(), "retrieval": retrieval_params.as_dict(), "filter": filter_params.as_dict(),
        "n_steps": n_steps, "sampling": sampling, "database": f"{db.source}/{db.camera}",
        "queries": f"{queries.source}/{queries.camera}", "mode": method.name,
        "refined": method.pose.as_dict() if method.pose is not None else None, "smooth": smooth,
        "fast": method.shortlist.as_dict() if method.shortlist is not None else None,
    }
    return Evaluation(series=series, params=params, method=method, frame=db.frame, smoothed=smooth,
                      structure_build_ms=structures.build_ms)
