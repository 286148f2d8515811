"""What the control panel shows, as pure functions: status lines, the step table, the run summary,
the store's description, the two plots' data, and the step's pictures.

Text that comes from a store or a file (names, paths, cameras, reasons, error messages) goes
through ``text`` here, so it reaches the page as text, never as markup. viser renders HTML
inside markdown, and Markdown's own syntax (``*``, ``_``, ``[..](..)``, ``![..](..)``) would
turn a name into formatting, a link or an image; ``text`` writes every such character as a
character reference, which neither HTML nor Markdown reads as syntax. Markdown still turns
a bare ``www.``, ``http://`` or e-mail address in plain text into a link (GitHub's autolinks,
whatever the escaping), so the panels that show store text (status, store, step table) are
HTML, not markdown.
"""

from __future__ import annotations

import cv2
import numpy as np

import visloc
from visloc.dashboard.explain import TERMS
from visloc.dashboard.scene import (CURRENT_RGB, ELLIPSE_RGB, ESTIMATE_RGB, MEASUREMENT_ELLIPSE_RGB, MEASUREMENT_RGB,
                                    TRUTH_RGB, css)

FIGURE_WIDTH_PX = 620
FRUSTUM_IMAGE_WIDTH_PX = 320

LEGEND = (
    (TRUTH_RGB, "ground truth"), (MEASUREMENT_RGB, "measurement"), (ESTIMATE_RGB, "Kalman estimate"),
    (ELLIPSE_RGB, "estimate 2σ (filter's P)"), (MEASUREMENT_ELLIPSE_RGB, "measurement 2σ (its R)"),
    ((150, 150, 150), "database images"), (CURRENT_RGB, "current step"),
)


def text(value: object) -> str:
    """``value`` as literal text for viser's HTML and markdown alike: every character but letters,
    digits and spaces becomes a numeric character reference (``<`` is ``&#60;``, ``*`` is ``&#42;``),
    which HTML and Markdown both show as the character itself and neither reads as syntax. Line
    breaks and control characters too, so a name cannot start a new Markdown block."""
    return "".join(c if c == " " or (c.isalnum() and c.isprintable()) else f"&#{ord(c)};" for c in str(value))


def _swatch(rgb: tuple[int, int, int], label: str) -> str:
    return (f'<span style="display:inline-block;width:11px;height:11px;border-radius:2px;margin:0 5px 0 2px;'
            f'background:{css(rgb)};vertical-align:-1px"></span>{text(label)}')


def legend_html() -> str:
    items = "".join(f"<div>{_swatch(rgb, label)}</div>" for rgb, label in LEGEND)
    return f'<div style="font-size:12px;line-height:1.7;display:grid;grid-template-columns:1fr 1fr">{items}</div>'


def map_legend_html() -> str:
    items = "".join(f"<div>{_swatch(rgb, label)}</div>" for rgb, label in LEGEND)
    return (f'<div style="font-size:12px;line-height:1.7;display:grid;grid-template-columns:1fr 1fr 1fr;'
            f'padding:0 12px">{items}</div><div style="font-size:12px;color:#555;padding:2px 12px 12px">'
            f'Lines from each truth point to its measurement. Blue ellipses: the estimates&#39; 2σ (the '
            f'filter&#39;s covariance); light orange: a refined measurement&#39;s own 2σ (its covariance R). Both '
            f'are relative to the map; the map&#39;s own GPS error is stated in the step table. The lower view '
            f'is centred on the current step (magenta ring: its truth, magenta ellipse: its estimate).</div>')


def series_names(queries, db) -> tuple[str, str]:
    """What to call the queries and the database in a line: their cameras, or, when the cameras share a name (two
    CSV drives are both "camera"), their drives and cameras."""
    if queries.camera != db.camera:
        return queries.camera, db.camera
    return f"{queries.source}/{queries.camera}", f"{db.source}/{db.camera}"


def status_html(message: str, *, error: bool = False) -> str:
    """A status line: wraps anywhere (long paths included), never clipped or scrolled sideways."""
    color, weight = ("#b00020", "600") if error else ("#333", "400")
    return (f'<div style="font-size:13px;color:{color};font-weight:{weight};padding:2px 0;white-space:normal;'
            f'overflow-wrap:anywhere;word-break:break-word;max-width:100%">'
            f'{text(("⚠ " if error else "") + message)}</div>')


def session_html(line: str, tab: int | None = None) -> str:
    """The shared-session line (tab count, the last change and the tab it came from)."""
    own = f" (this is tab {tab})" if tab is not None else ""
    return (f'<div style="font-size:12px;color:#555;padding:0 0 4px;overflow-wrap:anywhere">'
            f'{text(line + own)}</div>')


def tiles_html(caption: str, *, problem: bool) -> str:
    """The line under the map about its web-map tiles: their attribution, or (``problem``) why there are none."""
    color = "#b35c00" if problem else "#666"
    return f'<div style="font-size:12px;color:{color};padding:2px 12px;overflow-wrap:anywhere">{text(caption)}</div>'


def stale_badge_html(note: str | None) -> str:
    """A grey badge saying the numbers below belong to the previous run ("" when they are current)."""
    if not note:
        return ""
    return (f'<div style="margin:6px 12px 2px;padding:4px 8px;border-radius:4px;background:#e9ecef;color:#555;'
            f'font-size:12.5px;font-weight:600;overflow-wrap:anywhere">{text(note)}</div>')


def stale_note(shown_key: tuple, asked_key: tuple) -> str:
    """What the shown run was made with where it differs from the run being matched, e.g.
    "previous run (τ1 0.8) — re-matching for τ1 0.85…". Keys: ``Controls.match_key``, (what, value) pairs."""
    differ = [(old, new) for old, new in zip(shown_key, asked_key) if old != new and old[0] not in ("data", "rerun")]
    if not differ:
        return "previous run — re-matching…"
    say = lambda pairs: ", ".join(f"{n} {v:g}" if isinstance(v, float) else f"{n} {v}" for n, v in pairs)
    return f"previous run ({say(o for o, _ in differ)}) — re-matching for {say(n for _, n in differ)}…"


def step_note(view, k: int, matching_key: tuple | None) -> str | None:
    """The badge over step ``k`` of ``view`` (``Run.shown``): whose numbers these are when they are not
    the run being matched (None: they are)."""
    if view.from_previous(k):
        return stale_note(view.previous.match_key, view.match_key)
    if matching_key is not None and matching_key != view.match_key and not view.partial:
        return stale_note(view.match_key, matching_key)
    return None


def ready_text(number: int, matches, queries, db, n_new_pairs: int, elapsed_s: float,
               not_following: str | None = None) -> str:
    """The status line once a run is matched; ``not_following``: why a camera-rate run could not follow points."""
    names, match = series_names(queries, db), matches.match_params
    if matches.follows_points:
        return (f"Ready (run {number}, {matches.method.name}, following points): {len(matches)} queries of "
                f"{names[0]} against {len(db)} images of {names[1]}, read from the drive's images in {elapsed_s:.1f} s")
    work = f"{n_new_pairs} new image pairs matched in {elapsed_s:.1f} s" if n_new_pairs else "all image pairs cached"
    why = f"; not following points: {not_following}" if not_following else ""
    return (f"Ready (run {number}, {matches.method.name}, τ1 {match.tau1:g}, τ2 {match.tau2:g}): {len(matches)} "
            f"queries of {names[0]} against {len(db)} images of {names[1]}; {work}{why}")


def _fmt(value: float | None, fmt: str = ".2f", unit: str = " m") -> str:
    return "–" if value is None else f"{value:{fmt}}{unit}"


def _position(xy: tuple[float, float] | None, geotag: tuple[float, float] | None, latlon: bool) -> str:
    """East and north in metres from the database's origin; latitude and longitude too when asked."""
    if xy is None:
        return "–"
    local = f"E {xy[0]:.2f} m, N {xy[1]:.2f} m"
    return local + (f" ({geotag[0]:.7f}°, {geotag[1]:.7f}°)" if latlon and geotag is not None else "")


FOLLOWED_KINDS = {  # how a step of a run that followed points was measured (visloc.DriveMatches.kinds)
    "tracked": "followed points (no retrieval, no SIFT: the map points of the last relocalization, followed "
               "into this frame by optical flow), ",
    "relocalized": "a relocalization that fetched new map points to follow (in full: SIFT, retrieval and PnP; or "
                   "guided by the frame's tracked pose: SIFT near where the map's points project, and PnP), ",
    "predicted": "nothing of its own (its points lost, a relocalization under way): ",
}


def source_text(rec: visloc.StepRecord, kind: str | None = None) -> str:
    """What measured the step, in words; ``kind``: how, in a run that followed points."""
    return FOLLOWED_KINDS.get(kind or "", "") + _measured_by(rec)


def _measured_by(rec: visloc.StepRecord) -> str:
    if rec.measurement_source == visloc.GEOMETRY:
        return (f"geometry: PnP against frames {', '.join(map(str, rec.view_db_frames))} (database views whose "
                f"3D points were triangulated with frames {', '.join(map(str, rec.neighbour_db_frames))}); "
                f"{rec.n_pnp_inliers} inliers (correspondences that agree with the pose)"
                + ("; thin support: too few inliers at the strict PnP threshold, posed again at the looser one"
                   if rec.thin_support else ""))
    if rec.measurement_source == visloc.GEOTAG:
        return "geotag of the best match" + (f" (fallback: {rec.fallback_reason})" if rec.fallback_reason else "")
    return "nothing" + (f" ({rec.fallback_reason})" if rec.fallback_reason else "")


def filter_note(rec: visloc.StepRecord) -> str:
    """How the filter took the step's measurement, when not as usual."""
    if rec.gated:
        return "  (measurement gated: prediction only)"
    if rec.retracted_previous:
        return "  (the previous measurement contradicted this one and the track: taken out)"
    if rec.maneuver:
        return "  (applied with the maneuver prediction: the car turned or braked)"
    return ""


def measurement_sigma_note(rec: visloc.StepRecord) -> str:
    """What a measurement's σ is made of, in words."""
    if rec.measurement_source == visloc.GEOTAG:
        return " (the filter's R)"
    if rec.measurement_source != visloc.GEOMETRY:
        return ""
    # a term that is zero wherever the drive's geotags are all fixes is named only where it counts
    parts = ", ".join(f"{name} {sigma:.2f}" for name, sigma in rec.measurement_term_sigma_m.items()
                      if name != "geotags" or sigma > 0)
    side = {"both": "views on both sides", "one": "views on one side"}.get(rec.measurement_side or "", "")
    lever = "" if rec.measurement_lever_m is None else f", {rec.measurement_lever_m:.1f} m from the nearest"
    return f" (relative to the map; {parts}; {side}{lever})" if parts else ""


_CELL = "padding:3px 12px 3px 0;border-bottom:1px solid #e9ecef;vertical-align:top"


def step_html(rec: visloc.StepRecord, n_steps: int, geotags: visloc.RecordGeotags, query_camera: str,
              db_camera: str, t0_s: float, *, latlon: bool = False, matched: tuple[int, int] | None = None,
              stale: bool = False, kind: str | None = None) -> str:
    """The current step's table: query, best match, measurement and estimate with their errors.
    Positions in local metres (lat/lon too with ``latlon``); every row explains itself on hover.
    ``matched``: (queries matched so far, queries in the run) while the run is still being matched.
    ``stale``: the step shown is the previous run's (a new one is being matched): the numbers are dimmed.
    ``kind``: how the step was measured in a run that followed points (``visloc.DriveMatches.kinds``)."""
    best = (("none: no retrieval at this step" if kind in ("tracked", "predicted") else "none")
            if rec.best_db_frame is None else
            f"{db_camera} frame {rec.best_db_frame} ({rec.best_offset_s:+.2f} s), {rec.best_count} correspondences, "
            f"{rec.n_candidates} candidates")
    rows = [
        ("query", f"{query_camera} frame {rec.query_frame}, t = {rec.query_timestamp_s - t0_s:.2f} s"),
        ("best match", best),
        ("measurement", _position(rec.measurement_m, geotags.measurement, latlon)),
        ("measured by", source_text(rec, kind)),
        ("measurement error", _fmt(rec.measurement_error_m)),
        ("measurement σ", _fmt(rec.measurement_sigma_m) + measurement_sigma_note(rec)),
        ("map's own error", _fmt(rec.absolute_sigma_m) + (" per axis (the database geotags' stated accuracy)"
                                                         if rec.absolute_sigma_m is not None else "")),
        ("estimate", _position(rec.estimate_m, geotags.estimate, latlon)),
        ("estimate error", _fmt(rec.estimate_error_m) + filter_note(rec)),
        ("estimate 2σ", _fmt(None if rec.estimate_sigma_m is None else 2.0 * rec.estimate_sigma_m)),
        ("nearest allowed image", _fmt(rec.nearest_candidate_error_m)),
        ("truth", _position(rec.truth_m, geotags.truth, latlon)),
    ]
    hint = "border-bottom:1px dotted #999;cursor:help"
    body = "".join(f'<tr><td style="{_CELL};white-space:nowrap;font-weight:500">'
                   f'<span title="{text(TERMS.get(a, ""))}" style="{hint}">{text(a)}</span></td>'
                   f'<td style="{_CELL};overflow-wrap:anywhere">{text(b)}</td></tr>' for a, b in rows)
    title = f"Step {rec.step + 1} of {n_steps}"
    partial = ("" if matched is None or matched[0] >= matched[1] else
               f'<div style="color:#555;font-size:12px">{text(f"{matched[0]} of {matched[1]} queries matched so far")}'
               f"</div>")
    frame = "positions: east, north in metres from the database&#39;s origin" + (", then lat, lon" if latlon else "")
    if stale:
        partial += '<div style="color:#666;font-size:12px">numbers of the previous run, shown until the new run reaches this step</div>'
    dim = "opacity:0.5;" if stale else ""
    return (f'<div style="font-size:13px;line-height:1.45;padding:4px 12px 10px">'
            f'<div style="font-weight:700;margin-bottom:4px">{text(title)}</div>{partial}'
            f'<table style="border-collapse:collapse;width:100%;{dim}">{body}</table>'
            f'<div style="color:#666;font-size:11.5px;margin-top:3px">{frame}; hover a name for its meaning</div>'
            f'</div>')


def run_summary_markdown(records: list[visloc.StepRecord], matches: visloc.DriveMatches) -> str:
    summary = visloc.drive_summary(records)
    refined = (f"geometry on {100 * summary['geometry_fraction']:.0f}% of steps, {summary['gated_steps']} gated; "
               if matches.method.measures_pose else "")
    exclusion = matches.retrieval_params.exclusion_s
    same = any(r.truth_shares_map for r in records)  # the queries' own drive (a few of its geotags may be no fix)
    warning = ("**Warning: exclusion 0 s with a database of the queries' own drive**: a query may be posed from its own "
               "image or its stereo twin, and its error then says nothing of how well visloc localizes. " if same and
               exclusion == 0 else "")
    why = " (the database holds this drive's own images)" if same and exclusion > 0 else ""
    return (f"{warning}**This run** ({text(matches.method.name)} mode, {summary['n_steps']} queries, "
            f"{exclusion:g} s exclusion{why}): {refined}"
            f"mean measurement error {_fmt(summary['mean_measurement_error_m'])}, "
            f"mean estimate error {_fmt(summary['mean_estimate_error_m'])}, "
            f"final estimate error {_fmt(summary['final_estimate_error_m'])}; "
            f"query latency median {np.median(matches.latency_ms):.0f} ms, p95 "
            f"{np.percentile(matches.latency_ms, 95):.0f} ms (SIFT + retrieval + geometry + filter, when first "
            "computed)." + camera_rate_note(matches))


def camera_rate_note(matches: visloc.DriveMatches) -> str:
    """How a camera-rate run was made: following points on the drive's images, or on the stored features."""
    if not matches.method.camera_rate:
        return ""
    if matches.follows_points:
        tracked = sum(1 for k in matches.kinds if k == "tracked")
        return (f" Camera-rate path as `visloc track` runs it: each frame read from the drive's images and described "
                f"at three quarters of its size; {tracked} of {len(matches)} frames posed on followed map points "
                "between relocalizations, each frame read once the relocalization asked for before it had "
                "come (so the run is the same every time). R, Q and P0 re-run the filter over these measurements.")
    return (" Camera-rate path on the stored query features, every query localized in full, not following points "
            "as `visloc track` does (the status line says why).")


def store_html(path: str, datasets: list[visloc.StoredDrive], sift: visloc.SiftParams | None) -> str:
    """The store panel: the file, its datasets (``source/camera``) and its SIFT settings."""
    items = "".join(f"<li>{text(d.name)}: {d.n_images} images over {d.duration_s:.1f} s, "
                    f"{d.mean_keypoints:.0f} keypoints/image{'' if d.has_calibration else ', no calibration'}</li>"
                    for d in datasets)
    settings = ", ".join(f"{k}={v}" for k, v in sift.as_dict().items()) if sift else "none yet"
    return (f'<div style="font-size:13px;line-height:1.5;overflow-wrap:anywhere;padding:2px 12px 10px">'
            f'<div style="font-weight:700">{text(path)}</div>'
            f'<ul style="margin:4px 0;padding-left:18px">{items}</ul>'
            f'<div>SIFT settings: {text(settings)}</div></div>')


def counts_plot(retrieval: visloc.Retrieval, db_timestamps_s: np.ndarray, query_timestamp_s: float,
                t0_s: float) -> tuple[tuple, dict, str]:
    """(data, scales, title) of the correspondences against database time: every database image, gaps
    where an image was no candidate (outside the search window, or inside the exclusion window)."""
    times = db_timestamps_s - t0_s
    counts = np.full(len(db_timestamps_s), np.nan)
    counts[retrieval.candidates] = retrieval.counts
    best = np.full(len(db_timestamps_s), np.nan)
    if retrieval.best_index is not None:
        best[retrieval.best_index] = counts[retrieval.best_index]
    top = float(np.nanmax(counts)) if np.isfinite(counts).any() else 1.0
    # uPlot joins a line across NaN, so the images before and after the query are two series; the
    # exclusion window between them stays a gap
    earlier = np.where(db_timestamps_s < query_timestamp_s, counts, np.nan)
    later = np.where(db_timestamps_s >= query_timestamp_s, counts, np.nan)
    # an explicit y range: uPlot's automatic range breaks on NaN
    scales = {"x": {"time": False}, "y": {"auto": False, "range": (0.0, 1.1 * top + 1.0)}}
    title = f"Correspondences per database image (query at {query_timestamp_s - t0_s:.1f} s)"
    return (times, earlier, later, best), scales, title


def error_plot(records: list[visloc.StepRecord], k: int, t0_s: float) -> tuple[tuple, dict]:
    """(data, scales) of the error per step (the paper's Figure 4 over the run), step ``k`` marked."""
    def values(attr: str, factor: float = 1.0) -> np.ndarray:
        return np.array([np.nan if getattr(r, attr) is None else factor * getattr(r, attr) for r in records])

    times = np.array([r.query_timestamp_s - t0_s for r in records])
    m_err, e_err, two_sigma = values("measurement_error_m"), values("estimate_error_m"), values("estimate_sigma_m", 2.0)
    current = np.full(len(times), np.nan)
    current[k] = e_err[k] if np.isfinite(e_err[k]) else m_err[k]
    both = np.concatenate([m_err, e_err, two_sigma])
    top = float(np.nanmax(both)) if np.isfinite(both).any() else 1.0
    return (times, m_err, e_err, two_sigma, current), {"x": {"time": False},
                                                       "y": {"auto": False, "range": (0.0, 1.1 * top + 0.1)}}


def placeholder(text: str, width_px: int = FIGURE_WIDTH_PX, height_px: int = 120) -> np.ndarray:
    """A gray picture with a message, where an image cannot be shown."""
    img = np.full((height_px, width_px, 3), 235, np.uint8)
    for row, line in enumerate(text.split("\n")):
        cv2.putText(img, line[:90], (10, 30 + 24 * row), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (90, 90, 90), 1, cv2.LINE_AA)
    return img


def frustum_image(gray: np.ndarray | None) -> np.ndarray | None:
    """A small RGB copy of an image, for a camera frustum in the scene."""
    if gray is None:
        return None
    h, w = gray.shape
    small = cv2.resize(gray, (FRUSTUM_IMAGE_WIDTH_PX, max(1, round(h * FRUSTUM_IMAGE_WIDTH_PX / w))),
                       interpolation=cv2.INTER_AREA)
    return np.repeat(small[:, :, None], 3, axis=2)


def read_gray(path: str | None) -> np.ndarray | None:
    """The image at ``path``, or None when it is not reachable (the store keeps features, not images)."""
    try:
        return visloc.load_gray(path) if path else None
    except visloc.VislocError:
        return None


def step_figure(queries: visloc.QuerySet, db: visloc.GeoDatabase, q_index: int, best: int | None,
                match: visloc.MatchParams, q_gray: np.ndarray | None, d_gray: np.ndarray | None,
                kind: str | None = None) -> np.ndarray:
    """The paper's Figure 3 for one step: the query above its best match, correspondences joined. ``kind``: how
    the step was measured in a run that followed points (a followed or predicted step made no retrieval)."""
    if kind in ("tracked", "predicted"):
        return placeholder(f"Query frame {queries.frames[q_index]}: no retrieval at this step, "
                           + ("posed on the map points followed into it" if kind == "tracked" else
                              "predicted by the filter"))
    if best is None:
        return placeholder(f"Query frame {queries.frames[q_index]}: no database image has a correspondence")
    if q_gray is None or d_gray is None:
        missing = queries.paths[q_index] if q_gray is None else db.images[best].path
        return placeholder(f"Image file not reachable:\n{missing}\n(the store keeps features, not images)")
    # the features retrieval counted (the paper's, on a store described at a lower contrast): its count
    (q_xy, q_desc), (d_xy, d_desc) = (db.as_retrieved(queries.keypoints_f32[q_index], queries.descriptors_u8[q_index]),
                                      db.as_retrieved(db.keypoints_f32[best], db.descriptors_u8[best]))
    pairs = visloc.correspondences(q_desc, d_desc, match)
    names = series_names(queries, db)
    return visloc.correspondence_figure(
        q_gray, d_gray, q_xy[pairs[:, 0], :2], d_xy[pairs[:, 1], :2],
        width_px=FIGURE_WIDTH_PX,
        labels=(f"query {names[0]} frame {queries.frames[q_index]}",
                f"best match {names[1]} frame {db.images[best].frame}: {len(pairs)} correspondences"))
