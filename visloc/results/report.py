"""The edge where results leave the engine: the paper's Tables 2 and 3 as text, Figure 4 as a
PNG, and JSON. Positions turn from the local frame into latitude and longitude here."""

from __future__ import annotations

import dataclasses
import json
import textwrap
import math
from pathlib import Path

from visloc.protocols.evaluation import Evaluation, step_labels
from visloc.geo import LocalFrame
from visloc.protocols.records import StepRecord, record_geotags

PAPER_FINAL_ERROR_M = 1.85  # section 4, Figure 4
PAPER_TABLE3_MEASUREMENT_ERROR_M = [18.99, 18.99, 17.57, 16.52, 17.57, 16.19]
# what the paper evaluated: KITTI drive 0001, left gray queries against the right gray camera's database
PAPER_DATABASE, PAPER_QUERIES = "2011_09_26_drive_0001/image_01", "2011_09_26_drive_0001/image_00"


def _cell(value: float | None, fmt: str) -> str:
    return "-" if value is None or (isinstance(value, float) and math.isnan(value)) else format(value, fmt)


def series_tables(records: list[StepRecord], frame: LocalFrame) -> str:
    """Tables 2 and 3 of the paper for one series (their inaccuracies by the Haversine formula, as
    there, and labelled so); every other distance is geodesic (WGS84). ``frame``: the database's local frame."""
    labels = step_labels(len(records))
    geotags = [record_geotags(r, frame) for r in records]

    def coordinate(which: str, axis: int) -> list[float | None]:
        return [None if getattr(g, which) is None else getattr(g, which)[axis] for g in geotags]

    head = f"{'':38}" + "".join(f"{lab:>11}" for lab in labels)

    def row(name: str, values: list, fmt: str) -> str:
        return f"{name:38}" + "".join(f"{_cell(v, fmt):>11}" for v in values)

    lines = [
        "Table 2: output of the image retrieval step",
        head,
        row("Geotag of the best match  lon", coordinate("measurement", 1), ".5f"),
        row("                          lat", coordinate("measurement", 0), ".5f"),
        row("Actual GPS coordinates    lon", coordinate("truth", 1), ".5f"),
        row("                          lat", coordinate("truth", 0), ".5f"),
        row("Best match: database frame", [r.best_db_frame for r in records], "d"),
        row("            correspondences", [r.best_count for r in records], "d"),
        row("            time offset (s)", [r.best_offset_s for r in records], "+.2f"),
        "",
        "Table 3: Kalman filter estimation of the vehicle location (inaccuracies by Haversine, as the paper's Table 3)",
        head,
        row("Kalman filter estimates   lon", coordinate("estimate", 1), ".5f"),
        row("                          lat", coordinate("estimate", 0), ".5f"),
        row("Measurement inaccuracy (Haversine, m)", [r.measurement_error_haversine_m for r in records], ".2f"),
        row("Estimation inaccuracy (Haversine, m)", [r.estimate_error_haversine_m for r in records], ".2f"),
        row("Estimate 1-sigma, largest axis (m)", [r.estimate_sigma_m for r in records], ".2f"),
        row("Latency (ms)", [r.latency_ms for r in records], ".0f"),
        "",
        "Measurements as the filter took them (errors: WGS84 geodesic, as elsewhere in visloc)",
        head,
        row("Source", [r.measurement_source for r in records], "s"),
        row("Measurement 1-sigma (m)", [r.measurement_sigma_m for r in records], ".2f"),
        row("Measurement error (m)", [r.measurement_error_m for r in records], ".2f"),
        row("Estimate error (m)", [r.estimate_error_m for r in records], ".2f"),
        row("Gated (not applied)", ["yes" if r.gated else "no" for r in records], "s"),
    ]
    reasons = [f"  {lab}: {r.fallback_reason}" for lab, r in zip(labels, records) if r.fallback_reason]
    if reasons:
        lines += ["Fallbacks to the geotag:", *reasons]
    return "\n".join(lines)


def _measures_pose(summary: dict) -> bool:
    """Whether the evaluation's method measured poses: only then does its summary hold pose statistics."""
    return summary.get("measurement_nees") is not None


def is_paper_protocol(summary: dict) -> bool:
    """Whether an evaluation ran the paper's setup (drive 0001, left queries, right database), so that
    its numbers compare with the paper's."""
    names = (summary["params"].get("database") or "", summary["params"].get("queries") or "")
    return tuple(n.replace("_sync/", "/") for n in names) == (PAPER_DATABASE, PAPER_QUERIES)


def _paper_measurement_m() -> float:
    """The paper's mean measurement error over its Table 3's steps (m, Haversine)."""
    return sum(PAPER_TABLE3_MEASUREMENT_ERROR_M) / len(PAPER_TABLE3_MEASUREMENT_ERROR_M)


def summary_text(summary: dict) -> str:
    """An evaluation's summary for the terminal; errors are WGS84 geodesic distances to the geotags."""
    labels = summary["steps"]
    lines = [
        f"series evaluated: {summary['n_series']}   database: {summary['params']['database']}   "
        f"queries: {summary['params']['queries']}   exclusion: {summary['params']['retrieval']['exclusion_s']} s   "
        "(errors: WGS84 geodesic, m)",
        f"{'step':28}" + "".join(f"{lab:>9}" for lab in labels),
        f"{'mean measurement error (m)':28}" + "".join(f"{_cell(v, '.2f'):>9}" for v in summary["measurement_error_m"]),
        f"{'mean estimate error (m)':28}" + "".join(f"{_cell(v, '.2f'):>9}" for v in summary["estimate_error_m"]),
        f"{'nearest candidate (m)':28}" + "".join(f"{_cell(v, '.2f'):>9}" for v in summary["nearest_candidate_error_m"]),
        "final estimate error (m): mean {mean}  median {median}  p90 {p90}  min {min}  max {max}".format(
            **{k: _cell(v, ".2f") for k, v in summary["final_error_m"].items()}),
        "latency per query (ms): p50 {p50}  p95 {p95}".format(
            **{k: _cell(v, ".0f") for k, v in summary["latency_ms"].items()}),
        "best match vs query time: median offset {m} s, ahead {a}, behind {b}".format(
            m=_cell(summary["best_match_offset_s"]["median"], "+.2f"),
            a=_cell(summary["best_match_offset_s"]["fraction_ahead"], ".0%"),
            b=_cell(summary["best_match_offset_s"]["fraction_behind"], ".0%")),
        "final estimate error (m) by best matches ahead of the query: " + "  ".join(
            f"{k}/{summary['n_steps']} ahead: {v['mean']:.2f} ({v['n_series']} series)"
            for k, v in summary["final_error_m_by_steps_ahead"].items()),
    ]
    if is_paper_protocol(summary):
        lines.append(f"the paper on this drive and protocol (its Table 3 and Figure 4): measurement about "
                     f"{_paper_measurement_m():.0f} m (Haversine), final estimate {PAPER_FINAL_ERROR_M} m")
    if _measures_pose(summary):
        src = summary["measurement_source_fraction"]
        nees = summary["measurement_nees"] or {}
        lines += [
            f"mode {summary['mode']}: geometry {_cell(src['geometry'], '.0%')} of steps, geotag fallback "
            f"{_cell(summary['geometry_fallback_fraction'], '.1%')} of measurements, posed on thin support "
            f"{_cell(summary.get('thin_support_fraction'), '.1%')}, gated {_cell(summary['gated_fraction'], '.1%')}",
            f"{'mean measurement 1-sigma (m)':28}" + "".join(f"{_cell(v, '.2f'):>9}" for v in summary["measurement_sigma_m"]),
            f"geometry NEES mean {_cell(nees.get('mean'), '.2f')} (2 if honest), within 95 %: "
            f"{_cell(nees.get('fraction_within_95'), '.0%')}",
            "of the latency, the measurement (ms): p50 {p50}  p95 {p95}".format(
                **{k: _cell(v, ".0f") for k, v in summary["measurement_latency_ms"].items()}),
        ]
        if summary["fallback_reasons"]:
            lines.append("fallback reasons: " + "; ".join(f"{k}: {v}" for k, v in summary["fallback_reasons"].items()))
    if summary.get("smoothed_error_m"):
        lines.append(f"{'mean RTS-smoothed error (m)':28}" + "".join(f"{_cell(v, '.2f'):>9}"
                                                                    for v in summary["smoothed_error_m"]))
    return "\n".join(lines)


def record_json(record: StepRecord, frame: LocalFrame) -> dict:
    """A record as JSON: positions as latitude and longitude (``*_lat_deg``, ``*_lon_deg``) in place of
    local metres."""
    geotags = record_geotags(record, frame)
    as_geotag = {"truth_geotag_deg": "truth", "measurement_m": "measurement", "estimate_m": "estimate",
                 "smoothed_m": "smoothed"}
    out: dict = {}
    for f in dataclasses.fields(record):
        if f.name in as_geotag:
            name = as_geotag[f.name]
            value = getattr(geotags, name)
            out[f"{name}_lat_deg"], out[f"{name}_lon_deg"] = (None, None) if value is None else value
        elif f.name not in ("truth_m", "measurement_geotag_deg", "best_db_index"):
            out[f.name] = getattr(record, f.name)
    return out


def evaluation_json(evaluation: Evaluation, summary: dict | None = None) -> dict:
    """An evaluation's summary and every step of every series."""
    return {**(summary or evaluation.summary()),
            "series": [[record_json(r, evaluation.frame) for r in s] for s in evaluation.series]}


def write_json(path: Path, payload: dict) -> None:
    def default(obj):
        if dataclasses.is_dataclass(obj):
            return dataclasses.asdict(obj)
        if hasattr(obj, "tolist"):
            return obj.tolist()
        raise TypeError(type(obj).__name__)

    Path(path).write_text(json.dumps(payload, indent=1, default=default))


def save_error_plot(summary: dict, path: Path, title: str, *, paper: bool = False) -> None:
    """Figure 4: mean measurement and estimate error per step; ``paper``: with the paper's final error
    (only for its drive and protocol, ``is_paper_protocol``)."""
    import matplotlib  # on demand: it takes a second to import, and only this function draws

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels = summary["steps"]
    x = list(range(len(labels)))
    nan = float("nan")
    meas = [nan if v is None else v for v in summary["measurement_error_m"]]
    est = [nan if v is None else v for v in summary["estimate_error_m"]]
    fig, ax = plt.subplots(figsize=(7, 4), dpi=120)
    source = "metric pose" if _measures_pose(summary) else "best-match geotag"
    ax.plot(x, meas, "o-", color="tab:orange", label=f"measurement ({source})")
    ax.plot(x, est, "s-", color="tab:blue", label="Kalman estimate")
    if paper:
        ax.plot([x[-1]], [PAPER_FINAL_ERROR_M], "k*", markersize=11,
                label=f"paper's final estimate ({PAPER_FINAL_ERROR_M} m)")
    for xi, v in zip(x, est):
        if not math.isnan(v):
            ax.annotate(f"{v:.1f}", (xi, v), textcoords="offset points", xytext=(0, -14), ha="center", fontsize=8,
                        color="tab:blue")
    ax.set_xticks(x, labels)
    ax.set_xlabel("query step")
    ax.set_ylabel("mean error over series (m, geodesic)")
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3)
    ax.set_title(textwrap.fill(title, 80), fontsize=9)  # a long drive name wraps instead of leaving the figure
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def track_text(s: dict) -> str:
    """The summary of a track run, for the terminal (errors: WGS84 geodesic)."""
    lat, st, e, m, g = s["latency_ms"], s["stages_ms"], s["error_m"], s["measurement_error_m"], \
        s["geometry_measurement_error_m"]
    geometry = f"{100 * s['geometry_fraction']:.0f}% of frames measured by geometry"
    return "\n".join([
        f"{s['queries']} against {s['database']}: {s['frames']} frames, refined {s['path']} path, exclusion "
        f"{s['params']['track']['exclusion_s']:g} s",
        f"latency per frame (ms): p50 {lat['p50']:.0f}, p95 {lat['p95']:.0f}, max {lat['max']:.0f}   (median SIFT "
        f"{st['sift_ms']:.0f}, retrieval {st['retrieval_ms']:.0f}, geometry {st['geometry_ms']:.0f}, filter "
        f"{st['filter_ms']:.1f})",
        f"sustained {s['sustained_hz']:.1f} frames/s over {s['wall_s']:.1f} s of wall time"
        + (f" (frames read at {s['pace_hz']:g} Hz, as a camera delivers them)" if s.get("pace_hz") else
           " (frames read as fast as the relocalizations keep up)" if "tracked" in (s.get("kinds") or {})
           and s["params"]["track"].get("pace_hz", 0) is None else "")
        + (f", processor {s['cpu_share_of_one_core']:.2f} of one core" if s.get("cpu_share_of_one_core") else ""),
        *([following_line(s["kinds"])] if "tracked" in (s.get("kinds") or {}) else []),
        *([relocalizations_line(s["relocalizations"])] if s.get("relocalizations") else []),
        f"estimate error (m): mean {e['mean']:.3f}, median {e['median']:.3f}, p90 {e['p90']:.3f}, max {e['max']:.3f}",
        f"measurement error (m): mean {m['mean']:.3f}, median {m['median']:.3f}, p90 {m['p90']:.3f}, "
        f"max {m['max']:.3f}; {geometry}" + (f" (their mean {g['mean']:.3f})" if g["n"] else ""),
        *([calibration_line(s["calibration"]["all"], s["estimate_calibration"])] if s.get("calibration") else []),
    ])


def following_line(kinds: dict) -> str:
    """How a run that follows map points spent its frames: tracked and relocalized, their share and latency."""
    parts = [f"{kind} {100 * k['share']:.0f}% (p50 {k['latency_ms']['p50']:.0f} ms, p95 {k['latency_ms']['p95']:.0f} ms)"
             for kind, k in sorted(kinds.items(), reverse=True)]
    return "following points: frames " + ", ".join(parts)


def relocalizations_line(r: dict) -> str:
    """What a run that follows map points spent on new points: how many relocalizations, how made, their cost."""
    how = f", {r['guided']} guided by the tracked pose" if r.get("guided") else ""
    return (f"relocalizations: {r['n']}{how}, {r['per_s'] or 0:.1f} per second, median {r['total_ms']:.0f} ms each "
            f"(SIFT {r['stages_ms']['sift_ms']:.0f} ms)")


def calibration_line(measurements: dict, estimates: dict) -> str:
    """How honest the covariances were: NEES (2 if honest) and the share inside the 95 % ellipse."""
    def one(k: dict) -> str:
        return "-" if not k["n"] else f"NEES {k['nees_mean']:.2f}, {100 * k['inside_95']:.0f}% inside the 95% ellipse"
    return f"uncertainty: geometry measurements {one(measurements)}; estimates {one(estimates)}"
