"""Runs saved as JSON, read back: what ``evaluate``, ``evaluate-drives`` and ``track`` wrote, as one shape.

``run_files(path)`` lists the runs a file holds (``evaluate-drives`` writes ``drives.json``,
which names one JSON per drive, protocol and mode beside it; the others write one run).
``load_run(path)`` reads one run into ``SavedRun``: its series of ``SavedStep`` (an
evaluation has one series per start frame, a ``track`` run one series of every frame), in
east/north metres of one local frame, with the parameters it was made with and every
per-step field as written. ``run_figures`` and ``params_that_differ`` compare two runs.
Everything here is plain data: the dashboard draws it, nothing here reads a store.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from visloc.errors import InputError
from visloc.geo import LocalFrame
from visloc.params import dashboard_controls

Position = tuple[float, float]

EVALUATION, TRACK = "evaluation", "track"


@dataclass
class SavedStep:
    """One step of a saved run (the attribute names of ``StepRecord`` where they mean the same)."""

    step: int  # 0-based, within its series
    frame: int  # the query's frame number in its drive
    time_s: float  # since the run's first query
    truth_m: Position
    estimate_m: Position | None
    estimate_cov_m2: list[list[float]] | None
    estimate_sigma_m: float | None
    estimate_error_m: float | None
    measurement_m: Position | None
    measurement_cov_m2: list[list[float]] | None
    measurement_sigma_m: float | None
    measurement_error_m: float | None
    measurement_source: str | None
    fallback_reason: str | None
    gated: bool
    n_pnp_inliers: int | None
    latency_ms: float | None
    measurement_nees: float | None
    estimate_nees: float | None
    fields: dict = field(default_factory=dict, repr=False)  # every field as the file has it


@dataclass
class SavedRun:
    path: Path
    kind: str  # EVALUATION or TRACK
    name: str  # what it is, in a few words: "refined, 2011_09_26_drive_0001_sync/image_00 queries"
    params: dict  # as written
    summary: dict  # the file's own summary figures (every top-level number), as written
    series: list[list[SavedStep]]
    frame: LocalFrame | None  # the local frame of the positions; None: not recorded (an older track file)
    series_labels: list[str] = field(default_factory=list)

    @property
    def n_steps(self) -> int:
        return sum(len(s) for s in self.series)


def _read_json(path: Path) -> dict:
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise InputError(f"{path}: no such file") from None
    except IsADirectoryError:
        raise InputError(f"{path}: a folder, not a run file (give the JSON that evaluate or track wrote)") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: cannot be read ({exc.__class__.__name__})") from None
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise InputError(f"{path}: not JSON (line {exc.lineno}: {exc.msg})") from None
    if not isinstance(data, dict):
        raise InputError(f"{path}: not a run file written by visloc (a JSON object was expected)")
    return data


def run_files(path: Path | str) -> list[tuple[str, Path]]:
    """(label, file) of every run ``path`` holds: itself, or for ``evaluate-drives``' JSON each drive's
    run files beside it (those present)."""
    path = Path(path)
    data = _read_json(path)
    if "drives" not in data or "series" in data or "per_frame" in data:
        kind_of(data, path)  # a file that is no run is refused here, in one line
        return [(path.stem, path)]
    out = []
    for drive, entries in (data.get("drives") or {}).items():
        for e in entries if isinstance(entries, list) else []:
            if isinstance(e, dict) and e.get("file") and (path.parent / e["file"]).is_file():
                out.append((f"{drive}, {e.get('protocol_label', e.get('protocol', ''))}, {e.get('mode', '')}",
                            path.parent / e["file"]))
    if not out:
        raise InputError(f"{path}: names no run file that is beside it (evaluate-drives writes them together)")
    return out


def kind_of(data: dict, path: Path) -> str:
    if isinstance(data.get("series"), list):
        return EVALUATION
    if isinstance(data.get("per_frame"), list):
        return TRACK
    raise InputError(f"{path}: not a run written by 'visloc evaluate', 'evaluate-drives' or 'track' "
                     "(it has neither 'series' nor 'per_frame')")


def _num(v) -> float | None:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return None
    return float(v) if math.isfinite(v) else None


def _pair(v) -> Position | None:
    if isinstance(v, (list, tuple)) and len(v) == 2 and all(_num(x) is not None for x in v):
        return float(v[0]), float(v[1])
    return None


def _cov(v) -> list[list[float]] | None:
    try:
        a = np.asarray(v, float)
    except (TypeError, ValueError):
        return None
    return a.tolist() if a.shape == (2, 2) and np.all(np.isfinite(a)) else None


def _sigma(cov) -> float | None:
    return None if cov is None else float(np.sqrt(max(np.linalg.eigvalsh(np.asarray(cov, float)).max(), 0.0)))


def _at(frame: LocalFrame, lat, lon) -> Position | None:
    if _num(lat) is None or _num(lon) is None:
        return None
    en = frame.to_local(float(lat), float(lon))
    return float(en[0]), float(en[1])


def _summary(data: dict) -> dict:
    return {k: v for k, v in data.items() if k not in ("series", "per_frame", "params")}


def _evaluation(data: dict, path: Path, frame: LocalFrame | None) -> SavedRun:
    series_in = [s for s in data["series"] if isinstance(s, list) and s]
    first = next((r for s in series_in for r in s if isinstance(r, dict)), None)
    if first is None:
        raise InputError(f"{path}: holds no steps")
    if frame is None:
        if _num(first.get("truth_lat_deg")) is None:
            raise InputError(f"{path}: its steps have no truth_lat_deg")
        frame = LocalFrame(float(first["truth_lat_deg"]), float(first["truth_lon_deg"]))
    t0 = min(_num(r.get("query_timestamp_s")) or 0.0 for s in series_in for r in s)
    series, labels = [], []
    for s in series_in:
        steps = []
        for i, r in enumerate(s):
            truth = _at(frame, r.get("truth_lat_deg"), r.get("truth_lon_deg"))
            if truth is None:
                raise InputError(f"{path}: a step of series {len(series) + 1} has no truth_lat_deg/truth_lon_deg")
            est_cov, meas_cov = _cov(r.get("estimate_cov_m2")), _cov(r.get("measurement_cov_m2"))
            steps.append(SavedStep(
                step=int(r.get("step", i)), frame=int(r.get("query_frame", i)),
                time_s=(_num(r.get("query_timestamp_s")) or 0.0) - t0, truth_m=truth,
                estimate_m=_at(frame, r.get("estimate_lat_deg"), r.get("estimate_lon_deg")), estimate_cov_m2=est_cov,
                estimate_sigma_m=_num(r.get("estimate_sigma_m")), estimate_error_m=_num(r.get("estimate_error_m")),
                measurement_m=_at(frame, r.get("measurement_lat_deg"), r.get("measurement_lon_deg")),
                measurement_cov_m2=meas_cov, measurement_sigma_m=_num(r.get("measurement_sigma_m")),
                measurement_error_m=_num(r.get("measurement_error_m")),
                measurement_source=r.get("measurement_source"), fallback_reason=r.get("fallback_reason"),
                gated=bool(r.get("gated")), n_pnp_inliers=r.get("n_pnp_inliers"), latency_ms=_num(r.get("latency_ms")),
                measurement_nees=_num(r.get("measurement_nees")), estimate_nees=_num(r.get("estimate_nees")),
                fields=dict(r)))
        series.append(steps)
        labels.append(f"series {len(series)}: frames {steps[0].frame}-{steps[-1].frame} ({len(steps)} steps)")
    p = data.get("params") or {}
    queries = (p.get("queries") or {}).get("name") if isinstance(p.get("queries"), dict) else p.get("queries")
    name = f"evaluate, {data.get('mode', p.get('mode', '?'))}" + (f", {queries} queries" if queries else "")
    return SavedRun(path, EVALUATION, name, p, _summary(data), series, frame, labels)


def _track(data: dict, path: Path, frame: LocalFrame | None) -> SavedRun:
    rows = [r for r in data["per_frame"] if isinstance(r, dict)]
    if not rows:
        raise InputError(f"{path}: holds no frames")
    origin = data.get("frame_origin_deg")
    own = LocalFrame(float(origin[0]), float(origin[1])) if _pair(origin) else None

    def moved(v) -> Position | None:  # into ``frame`` when both are known
        p = _pair(v)
        if p is None or own is None or frame is None or own == frame:
            return p
        lat, lon = own.to_geo(np.asarray(p))
        return _at(frame, float(lat), float(lon))

    t0 = _num(rows[0].get("timestamp_s")) or 0.0
    steps = []
    for i, r in enumerate(rows):
        truth = moved(r.get("truth_m"))
        if truth is None:
            raise InputError(f"{path}: frame {i} has no truth_m")
        est_cov, meas_cov = _cov(r.get("estimate_cov_m2")), _cov(r.get("measurement_cov_m2"))
        steps.append(SavedStep(
            step=i, frame=int(r.get("frame", i)), time_s=(_num(r.get("timestamp_s")) or 0.0) - t0, truth_m=truth,
            estimate_m=moved(r.get("estimate_m")), estimate_cov_m2=est_cov,
            estimate_sigma_m=_num(r.get("estimate_sigma_m")), estimate_error_m=_num(r.get("error_m")),
            measurement_m=moved(r.get("measurement_m")), measurement_cov_m2=meas_cov,
            measurement_sigma_m=_num(r.get("measurement_sigma_m")),
            measurement_error_m=_num(r.get("measurement_error_m")), measurement_source=r.get("measurement_source"),
            fallback_reason=r.get("fallback_reason"), gated=bool(r.get("gated")),
            n_pnp_inliers=r.get("n_pnp_inliers"), latency_ms=_num(r.get("latency_ms")),
            measurement_nees=_num(r.get("measurement_nees")), estimate_nees=_num(r.get("estimate_nees")),
            fields=dict(r)))
    name = f"track, {data.get('path', '?')} path, {data.get('queries', '?')} against {data.get('database', '?')}"
    return SavedRun(path, TRACK, name, data.get("params") or {}, _summary(data), [steps],
                    frame if (frame is not None and own is not None) else own,
                    [f"every frame: {steps[0].frame}-{steps[-1].frame} ({len(steps)} frames)"])


def load_run(path: Path | str, frame: LocalFrame | None = None) -> SavedRun:
    """One saved run (an ``evaluate`` or ``track`` JSON), positions in ``frame`` (default: the run's own:
    an evaluation's first truth, a track run's database frame). Bad files: ``InputError`` naming them."""
    path = Path(path)
    data = _read_json(path)
    kind = kind_of(data, path)
    try:
        return (_evaluation if kind == EVALUATION else _track)(data, path, frame)
    except (TypeError, ValueError, KeyError, IndexError) as exc:
        raise InputError(f"{path}: a run file with a field visloc cannot read ({exc.__class__.__name__}: "
                         f"{str(exc)[:80]})") from None


def _flat(d: dict, prefix: str = "") -> dict[str, object]:
    out: dict[str, object] = {}
    for k, v in (d or {}).items():
        if isinstance(v, dict):
            out |= _flat(v, f"{prefix}{k}.")
        else:
            out[f"{prefix}{k}"] = v
    return out


def flat_params(run: SavedRun) -> dict[str, object]:
    """The run's parameters as "group.name": value."""
    return _flat(run.params)


def params_that_differ(a: SavedRun, b: SavedRun) -> list[tuple[str, object, object]]:
    """(name, a's value, b's value) of every parameter the two runs do not share (None: the run has none)."""
    fa, fb = flat_params(a), flat_params(b)
    return [(k, fa.get(k), fb.get(k)) for k in sorted(set(fa) | set(fb)) if fa.get(k) != fb.get(k)]


# where a run file keeps each parameter class's values: ``evaluate`` writes match/retrieval/filter/refined,
# ``track`` writes track (its exclusion) and filter
_GROUPS = {"MatchParams": ("match",), "RetrievalParams": ("retrieval", "track"), "FilterParams": ("filter",),
           "RefinedParams": ("refined",)}


@dataclass(frozen=True)
class LiveSettings:
    """What the live dashboard starts from to tune a saved run again: its mode, query rate, the value of
    every parameter with a control that the run records, and the database and queries it ran on."""

    method: str | None  # a ``visloc.METHODS`` name
    rate_hz: float | None
    params: dict[str, float]  # by parameter name, in the parameter's own units
    database: str | None  # dataset names as the store lists them ("<drive>/<camera>")
    queries: str | None


def live_settings(run: SavedRun) -> LiveSettings:
    """The settings ``run`` was made with, as the live dashboard's controls take them."""
    p = run.params
    params: dict[str, float] = {}
    for cls, name, _, _ in dashboard_controls():
        for group in _GROUPS.get(cls.__name__, ()):
            value = _num((p.get(group) or {}).get(name)) if isinstance(p.get(group), dict) else None
            if value is not None:
                params[name] = value
                break
    if run.kind == TRACK:
        fast = bool((p.get("track") or {}).get("fast", True))
        method = "refined-fast" if fast else "refined"
        database, queries = run.summary.get("database"), run.summary.get("queries")
    else:
        mode = p.get("mode")
        method = f"{mode}-fast" if mode == "refined" and p.get("fast") else mode
        database, queries = p.get("database"), p.get("queries")
    dt_s = _num((p.get("filter") or {}).get("dt_s")) if isinstance(p.get("filter"), dict) else None
    return LiveSettings(method if isinstance(method, str) else None, 1.0 / dt_s if dt_s else None, params,
                        database if isinstance(database, str) else None, queries if isinstance(queries, str) else None)


def _stat(values, fn) -> float | None:
    v = [x for x in values if x is not None]
    return float(fn(np.asarray(v, float))) if v else None


def run_figures(run: SavedRun) -> dict[str, float | int | None]:
    """The same summary figures for any run, computed from its steps (so two runs compare like for like)."""
    steps = [s for series in run.series for s in series]
    est = [s.estimate_error_m for s in steps]
    sources = [s.measurement_source for s in steps]
    return {
        "steps": len(steps),
        "series": len(run.series),
        "estimate error mean (m)": _stat(est, np.mean),
        "estimate error p90 (m)": _stat(est, lambda v: np.percentile(v, 90)),
        "estimate error max (m)": _stat(est, np.max),
        "final estimate error mean (m)": _stat([s[-1].estimate_error_m for s in run.series], np.mean),
        "measurement error mean (m)": _stat([s.measurement_error_m for s in steps], np.mean),
        "estimate 1σ median (m)": _stat([s.estimate_sigma_m for s in steps], np.median),
        "estimate NEES mean (2 if honest)": _stat([s.estimate_nees for s in steps], np.mean),
        "geometry share": (sum(x == "geometry" for x in sources) / len(steps)) if steps else None,
        "tracked share (following points)": (sum(s.fields.get("kind") == "tracked" for s in steps) / len(steps))
        if any("kind" in s.fields and s.fields["kind"] != "full" for s in steps) else None,
        "fallbacks": sum(bool(s.fallback_reason) for s in steps),
        "gated": sum(s.gated for s in steps),
        "latency p50 (ms)": _stat([s.latency_ms for s in steps], np.median),
        "latency p95 (ms)": _stat([s.latency_ms for s in steps], lambda v: np.percentile(v, 95)),
    }


def worst_steps(series: list[SavedStep], n: int = 10) -> list[int]:
    """Indices of the ``n`` steps with the largest estimate error, worst first."""
    scored = [(s.estimate_error_m, i) for i, s in enumerate(series) if s.estimate_error_m is not None]
    return [i for _, i in sorted(scored, reverse=True)[:n]]


def steps_of_records(records, t0_s: float | None = None) -> list[SavedStep]:
    """A run's ``StepRecord`` list as ``SavedStep`` (the shape the timelines draw), times since ``t0_s``
    (default: the first record's)."""
    if not records:
        return []
    t0 = records[0].query_timestamp_s if t0_s is None else t0_s
    return [SavedStep(step=i, frame=r.query_frame, time_s=r.query_timestamp_s - t0, truth_m=r.truth_m,
                      estimate_m=r.estimate_m, estimate_cov_m2=r.estimate_cov_m2, estimate_sigma_m=r.estimate_sigma_m,
                      estimate_error_m=r.estimate_error_m, measurement_m=r.measurement_m,
                      measurement_cov_m2=r.measurement_cov_m2, measurement_sigma_m=r.measurement_sigma_m,
                      measurement_error_m=r.measurement_error_m, measurement_source=r.measurement_source,
                      fallback_reason=r.fallback_reason, gated=r.gated, n_pnp_inliers=r.n_pnp_inliers,
                      latency_ms=r.latency_ms, measurement_nees=r.measurement_nees, estimate_nees=r.estimate_nees)
            for i, r in enumerate(records)]
