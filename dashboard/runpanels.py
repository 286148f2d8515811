"""What the saved-run viewer shows, as pure functions: the scale of the 3D view, the timelines'
data, the step table and the runs' tables. Text from a file goes through ``panels.text``.
"""

from __future__ import annotations

import math

import numpy as np

from visloc import SavedRun, SavedStep, flat_params, params_that_differ, run_figures, worst_steps
from visloc.dashboard.mapview import nice_length_m as map_length_m
from visloc.dashboard.panels import text
from visloc.dashboard.scene import CURRENT_RGB, ELLIPSE_RGB, ESTIMATE_RGB, MEASUREMENT_RGB, css

MAGNIFICATIONS = {"true size": 1.0, "×10": 10.0, "×100": 100.0}
TIMELINES = ("error", "sigma", "nees", "inliers", "latency")
NO_COMPARISON = "none"
COMPARE_RGB = (150, 60, 200)  # a comparison run's estimate track, ellipses and timeline
COLOURS = {"estimate": css(ESTIMATE_RGB), "measurement": css(MEASUREMENT_RGB), "ellipse": css(ELLIPSE_RGB),
           "compare": css(COMPARE_RGB), "current": css(CURRENT_RGB)}


def nice_length_m(target_m: float) -> float:
    """A scale bar's length: the map's 1-2-5 × 10^k length not above ``target_m``, at least 1 cm."""
    return map_length_m(max(float(target_m), 0.01))


def length_text(length_m: float) -> str:
    return f"{length_m * 100:g} cm" if length_m < 1.0 else f"{length_m:g} m"


def scale_marks(look_at_m: np.ndarray, view_distance_m: float) -> dict:
    """A scale bar and a north arrow for a view at ``view_distance_m`` from ``look_at_m`` (east, north): a bar
    about a quarter of the distance long, east of the point looked at, and an arrow of the same length pointing
    north beside it. Returns the bar's two ends, the arrow's two ends (3D, metres) and the bar's label."""
    length = nice_length_m(view_distance_m / 4.0)
    x, y = float(look_at_m[0]), float(look_at_m[1])
    z = 0.1
    start = np.array([x + 0.5 * length, y - 0.5 * length, z])
    bar = np.stack([start, start + [length, 0.0, 0.0]])
    arrow = np.stack([start + [0.0, 0.2 * length, 0.0], start + [0.0, 1.2 * length, 0.0]])
    return {"bar": bar, "arrow": arrow, "label": length_text(length), "length_m": length}


def grid_step_m(extent_m: float) -> float:
    """Grid cell size for a drive ``extent_m`` across: about 20 cells, a 1-2-5 length."""
    return nice_length_m(max(extent_m, 1.0) / 20.0)


def axis_ticks(lo_m: float, hi_m: float, step_m: float) -> list[float]:
    """Tick positions (metres) every ``step_m`` from ``lo_m`` to ``hi_m``."""
    first = math.ceil(lo_m / step_m) * step_m
    return [round(first + i * step_m, 9) for i in range(int((hi_m - first) // step_m) + 1)]


def drawn_factor(cov_m2, magnification: float, largest_m: float) -> float:
    """How many times larger an ellipse is drawn: ``magnification``, but never so much that its 2σ major axis
    exceeds ``largest_m`` (a quarter of the drive), and never smaller than true size. A paper run's ellipses
    (tens of metres) stay true; a refined run's (centimetres) grow until they can be seen."""
    if cov_m2 is None:
        return 1.0
    major_m = 4.0 * math.sqrt(max(np.linalg.eigvalsh(np.asarray(cov_m2, float)).max(), 1e-12))
    return float(max(1.0, min(magnification, largest_m / major_m)))


def magnified(cov: list[list[float]] | None, factor: float) -> np.ndarray | None:
    """A covariance drawn ``factor`` times larger (its ellipse's axes scale by that factor)."""
    return None if cov is None else np.asarray(cov, float) * factor**2


def follow_distance_m(step: SavedStep, factor: float, farthest_m: float) -> float:
    """How far the camera stands from the current estimate so that its 2σ ellipse (drawn ``factor`` times larger)
    spans about a third of the view; at most ``farthest_m`` (the scene must stay in view), at least 1 m."""
    sigma = step.estimate_sigma_m or step.measurement_sigma_m or 1.0
    return float(min(max(6.0 * 2.0 * sigma * factor, 1.0), max(farthest_m, 1.0)))


def marker_m(sigma_m: float | None, factor: float) -> float:
    """A position marker's size: a quarter of the (drawn) 1σ, so it sits inside the ellipse (1 cm to 1 m)."""
    return float(np.clip(0.25 * (sigma_m or 1.0) * factor, 0.01, 1.0))


def ellipse_px(cov_m2, view_distance_m: float, view_px: float = 800.0, fov_rad: float = math.radians(50)) -> float:
    """About how many pixels the 2σ ellipse's major axis spans at that distance (a pinhole estimate)."""
    if cov_m2 is None:
        return 0.0
    major_m = 4.0 * math.sqrt(max(np.linalg.eigvalsh(np.asarray(cov_m2, float)).max(), 0.0))
    return major_m * view_px / (2.0 * max(view_distance_m, 1e-6) * math.tan(fov_rad / 2))


def _values(series: list[SavedStep], attr: str, factor: float = 1.0) -> np.ndarray:
    return np.array([np.nan if getattr(s, attr) is None else factor * float(getattr(s, attr)) for s in series])


def _on(times: np.ndarray, other: list[SavedStep] | None, attr: str, factor: float = 1.0) -> np.ndarray:
    """The comparison's values at the main run's times (nearest step within half a step; NaN elsewhere)."""
    out = np.full(len(times), np.nan)
    if not other:
        return out
    t = np.array([s.time_s for s in other])
    v = _values(other, attr, factor)
    gap = np.median(np.diff(times)) / 2 if len(times) > 1 else 0.5
    for i, ti in enumerate(times):
        j = int(np.argmin(np.abs(t - ti)))
        if abs(t[j] - ti) <= gap + 1e-9:
            out[i] = v[j]
    return out


def timeline(kind: str, series: list[SavedStep], k: int, other: list[SavedStep] | None = None) -> tuple:
    """(data, y range) of one timeline over a series, step ``k`` marked; ``other``: the comparison run's series
    on the same times. Data columns: time, then the kind's lines (see ``timeline_series``), then the marks of
    fallback and gated steps, then the current step."""
    times = np.array([s.time_s for s in series])
    if kind == "error":
        lines = [_values(series, "estimate_error_m"), _values(series, "measurement_error_m"),
                 _values(series, "estimate_sigma_m", 2.0), _on(times, other, "estimate_error_m")]
    elif kind == "sigma":
        lines = [_values(series, "estimate_sigma_m"), _values(series, "measurement_sigma_m"),
                 _on(times, other, "estimate_sigma_m")]
    elif kind == "nees":
        lines = [_values(series, "estimate_nees"), _values(series, "measurement_nees"), np.full(len(times), 2.0)]
    elif kind == "inliers":
        lines = [_values(series, "n_pnp_inliers"), _on(times, other, "n_pnp_inliers")]
    elif kind == "latency":
        lines = [_values(series, "latency_ms"), _on(times, other, "latency_ms")]
    else:
        raise ValueError(kind)
    first = lines[0]
    fell_back = np.where([bool(s.fallback_reason) for s in series], first, np.nan)
    gated = np.where([s.gated for s in series], first, np.nan)
    current = np.full(len(times), np.nan)
    current[k] = first[k]
    stacked = np.concatenate([v for v in lines if np.isfinite(v).any()] or [np.ones(1)])
    top = float(np.nanmax(stacked)) if np.isfinite(stacked).any() else 1.0
    return (times, *lines, fell_back, gated, current), (0.0, 1.1 * top + 1e-3)


def timeline_series(kind: str, colours: dict[str, str] = COLOURS) -> tuple[dict, ...]:
    """uPlot series options matching ``timeline``'s columns."""
    def line(label, colour, width=2.0, dash=None, points=True):
        s = {"label": label, "stroke": colour, "width": width}
        if dash:
            s["dash"] = dash
        if points:
            s["points"] = {"show": True, "size": 4}
        return s

    c = colours
    lines = {
        "error": (line("estimate error (m)", c["estimate"]), line("measurement error (m)", c["measurement"]),
                  line("estimate 2σ (m)", c["ellipse"], 1.5, (5.0, 4.0), False),
                  line("comparison estimate error (m)", c["compare"])),
        "sigma": (line("estimate 1σ (m)", c["estimate"]), line("measurement 1σ (m)", c["measurement"]),
                  line("comparison estimate 1σ (m)", c["compare"])),
        "nees": (line("estimate NEES", c["estimate"]), line("measurement NEES", c["measurement"]),
                 line("2 (honest on average)", "rgb(120,120,120)", 1.0, (3.0, 3.0), False)),
        "inliers": (line("PnP inliers", c["estimate"]), line("comparison PnP inliers", c["compare"])),
        "latency": (line("latency (ms)", c["estimate"]), line("comparison latency (ms)", c["compare"])),
    }[kind]
    marks = ({"label": "fell back to a geotag", "stroke": "rgb(200,0,0)", "width": 0,
              "points": {"show": True, "size": 9, "fill": "rgb(255,255,255)"}},
             {"label": "gated", "stroke": "rgb(0,0,0)", "width": 0,
              "points": {"show": True, "size": 9, "fill": "rgb(0,0,0)"}},
             {"label": "current step", "stroke": c["current"], "width": 0,
              "points": {"show": True, "size": 11, "fill": c["current"]}})
    return ({"label": "time (s)"}, *lines, *marks)


TIMELINE_TITLES = {"error": "Error per step (m) and the estimate's 2σ", "sigma": "1σ per step (m)",
                   "nees": "NEES per step (2 if the covariance is honest)", "inliers": "PnP inliers per step",
                   "latency": "Latency per step (ms)"}

_CELL = "padding:2px 10px 2px 0;border-bottom:1px solid #e9ecef;vertical-align:top"


def _cell(value, digits: str = ".4g") -> str:
    if value is None:
        return "–"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        return f"{value:{digits}}"
    if isinstance(value, (list, tuple)):
        return ", ".join(_cell(v, digits) for v in value) if len(value) <= 12 else f"{len(value)} values"
    if isinstance(value, dict):
        return "; ".join(f"{k} {_cell(v)}" for k, v in value.items())
    return str(value)


def table_html(rows: list[tuple], header: tuple | None = None, digits_of=None) -> str:
    """Rows as an HTML table, every cell escaped; ``digits_of(first cell)``: the float format of a row's values."""
    head = "" if header is None else "<tr>" + "".join(f'<th style="{_CELL};text-align:left">{text(h)}</th>'
                                                      for h in header) + "</tr>"

    def cells(row: tuple) -> str:
        digits = digits_of(str(row[0])) if digits_of else ".4g"
        return "".join(f'<td style="{_CELL}">{text(_cell(v, digits))}</td>' for v in row)

    body = "".join(f"<tr>{cells(row)}</tr>" for row in rows)
    return f'<table style="font-size:0.85em;border-collapse:collapse;width:100%">{head}{body}</table>'


def step_html(step: SavedStep, n_steps: int, other: SavedStep | None, magnification: float) -> str:
    """Every field of the step as the file has it (the comparison's beside it when there is one)."""
    title = (f"<b>Step {step.step + 1} of {n_steps}</b>, frame {step.frame}, {step.time_s:.1f} s"
             + ("" if magnification == 1.0 else f"; ellipses drawn up to ×{magnification:g}"))
    names = list(step.fields) + [k for k in (other.fields if other else {}) if k not in step.fields]
    rows = [(k, step.fields.get(k), other.fields.get(k)) if other else (k, step.fields.get(k)) for k in names]
    return f"<div>{title}</div>" + table_html(rows, ("field", "this run", "comparison") if other else ("field", "value"),
                                              digits_of=_digits_of)


def _digits_of(field_name: str) -> str:
    """How a step field's numbers are written: latitudes and longitudes to 1e-7 degrees (about a centimetre),
    everything else to four significant digits."""
    return ".7f" if field_name.endswith(("geotag_deg", "lat_deg", "lon_deg")) else ".4g"


def runs_html(main: SavedRun, other: SavedRun | None) -> str:
    """Summary figures (computed alike for both runs), the parameters that differ, and every parameter."""
    fa = run_figures(main)
    parts = [f"<b>{text(main.name)}</b><br>{text(main.path)}"]
    if other is None:
        parts.append(table_html([(k, v) for k, v in fa.items()], ("figure", "this run")))
    else:
        fb = run_figures(other)
        parts.append(f"compared with <b>{text(other.name)}</b><br>{text(other.path)}")
        parts.append(table_html([(k, fa[k], fb[k]) for k in fa], ("figure", "this run", "comparison")))
        differ = params_that_differ(main, other)
        parts.append("<b>Parameters that differ</b>" + (table_html(differ, ("parameter", "this run", "comparison"))
                                                      if differ else "<br>none"))
        if other.frame is None and main.frame is not None:
            parts.append("the comparison file does not record its local frame: drawn in its own")
    parts.append("<b>Parameters of this run</b>" + table_html(list(flat_params(main).items()),
                                                              ("parameter", "value")))
    parts.append("To tune this run live, start the dashboard on the store it ran on from its parameters: "
                 f"<code>{text(f'visloc dashboard --db STORE --tune-from {main.path}')}</code>")
    return "<br>".join(parts)


def jump_choices(series: list[SavedStep], n_worst: int = 10) -> list[str]:
    """The "Jump to" list: the worst steps by estimate error, then every step that fell back, was gated or was
    posed on thin support."""
    out = [f"step {i + 1}: error {series[i].estimate_error_m:.3g} m" for i in worst_steps(series, n_worst)]
    out += [f"step {i + 1}: fell back ({s.fallback_reason})" for i, s in enumerate(series) if s.fallback_reason]
    out += [f"step {i + 1}: gated" for i, s in enumerate(series) if s.gated]
    out += [f"step {i + 1}: posed on thin support" for i, s in enumerate(series) if s.fields.get("thin_support")]
    return out


def step_of_choice(choice: str) -> int | None:
    """The 1-based step a "Jump to" entry names."""
    if not choice.startswith("step "):
        return None
    try:
        return int(choice.split(":")[0].split()[1])
    except (IndexError, ValueError):
        return None


def nearest_step(series: list[SavedStep], east_north_m: np.ndarray) -> int:
    """The 0-based step whose estimate (or truth) is nearest a point on the ground: a click in 3D."""
    pts = np.array([s.estimate_m if s.estimate_m is not None else s.truth_m for s in series], float)
    return int(np.argmin(np.linalg.norm(pts - np.asarray(east_north_m, float)[:2], axis=1)))


def ground_point(ray_origin, ray_direction) -> np.ndarray | None:
    """Where a click's ray meets the ground (z = 0), or None when it points away."""
    o, d = np.asarray(ray_origin, float), np.asarray(ray_direction, float)
    if abs(d[2]) < 1e-9 or -o[2] / d[2] < 0:
        return None
    return o + (-o[2] / d[2]) * d

