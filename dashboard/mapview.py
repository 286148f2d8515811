"""The top-down map, as a picture: pure drawing (numpy, OpenCV) from a run's records in metres.

North is up, east is right, one scale for both axes. Two views stacked: the whole run, and a
close-up around the current step. Each has a scale bar in metres and a north arrow. Colours
are the 3D view's (``visloc.dashboard.scene``).
"""

from __future__ import annotations

import cv2
import numpy as np

import visloc
from visloc.dashboard.scene import (CURRENT_RGB, DATABASE_RGB, ELLIPSE_RGB, ESTIMATE_RGB, MEASUREMENT_ELLIPSE_RGB,
                                    MEASUREMENT_RGB, TRUTH_RGB, positions)

MAP_WIDTH_PX = 620
VIEW_HEIGHT_PX = 300
ZOOM_HALF_M = 25.0  # the close-up shows at most this many metres above and below the current step
MARGIN_PX = 16
HEADER_PX, FOOTER_PX = 30, 28
FONT = cv2.FONT_HERSHEY_SIMPLEX
INK = (60, 60, 60)


class View:
    """Local metres to pixels: a centre (m), a scale (px per m), a picture size."""

    def __init__(self, center_m: np.ndarray, px_per_m: float, width_px: int, height_px: int):
        self.center_m, self.px_per_m = np.asarray(center_m, float), float(px_per_m)
        self.width_px, self.height_px = width_px, height_px

    @classmethod
    def fitting(cls, points_m: np.ndarray, width_px: int, height_px: int, min_span_m: float = 10.0) -> "View":
        p = np.asarray(points_m, float).reshape(-1, 2)
        p = p[np.all(np.isfinite(p), axis=1)]
        lo, hi = (p.min(axis=0), p.max(axis=0)) if len(p) else (np.zeros(2), np.zeros(2))
        span = np.maximum(hi - lo, min_span_m)
        scale = min((width_px - 2 * MARGIN_PX) / span[0], (height_px - 2 * MARGIN_PX) / span[1])
        return cls(0.5 * (lo + hi), scale, width_px, height_px)

    def px(self, points_m) -> np.ndarray:
        """(N, 2) int32 pixel coordinates (x right, y down) of (N, 2) east/north metres."""
        p = np.asarray(points_m, float).reshape(-1, 2)
        x = (p[:, 0] - self.center_m[0]) * self.px_per_m + self.width_px / 2
        y = self.height_px / 2 - (p[:, 1] - self.center_m[1]) * self.px_per_m
        return np.clip(np.round(np.c_[x, y]), -10_000, 10_000).astype(np.int32)


def closeup_half_m(whole: View) -> float:
    """Half the close-up's height in metres: ``ZOOM_HALF_M``, or a quarter of what the whole-run view shows when
    that is less (a short drive's close-up is then still closer than its overview), at least 2 m."""
    whole_half_m = (whole.height_px - 2 * MARGIN_PX) / (2 * whole.px_per_m)
    return float(max(min(ZOOM_HALF_M, whole_half_m / 4), 2.0))


def nice_length_m(max_m: float) -> float:
    """The largest of 1, 2, 5 x 10^n metres not above ``max_m``."""
    if not max_m > 0:
        return 1.0
    base = 10.0 ** np.floor(np.log10(max_m))
    return float(max(f * base for f in (1.0, 2.0, 5.0) if f * base <= max_m * (1 + 1e-9)))  # 2 × 0.1 may exceed 0.2 by a rounding


def _label(img: np.ndarray, text: str, xy: tuple[int, int], scale: float = 0.55, color=INK, thick: int = 1) -> None:
    cv2.putText(img, text, xy, FONT, scale, (255, 255, 255), thick + 3, cv2.LINE_AA)  # a halo, readable on lines
    cv2.putText(img, text, xy, FONT, scale, color, thick, cv2.LINE_AA)


def _footer(view: View) -> np.ndarray:
    """The strip under a view: its scale bar (metres) and what the axes are."""
    img = np.full((FOOTER_PX, view.width_px, 3), 255, np.uint8)
    length_m = nice_length_m(0.25 * view.width_px / view.px_per_m)
    length_px = int(round(length_m * view.px_per_m))
    x0, y0 = 12, FOOTER_PX // 2 + 2
    cv2.line(img, (x0, y0), (x0 + length_px, y0), INK, 2)
    for x in (x0, x0 + length_px):
        cv2.line(img, (x, y0 - 5), (x, y0 + 4), INK, 2)
    _label(img, f"{length_m:g} m", (x0 + length_px + 8, y0 + 6), thick=2)
    _label(img, "east to the right, north up", (view.width_px - 250, y0 + 6), scale=0.5, color=(110, 110, 110))
    return img


def _header(view: View, title: str) -> np.ndarray:
    """The strip above a view: its title and a north arrow."""
    img = np.full((HEADER_PX, view.width_px, 3), 255, np.uint8)
    _label(img, title, (8, HEADER_PX - 8), scale=0.6, thick=2)
    x = view.width_px - 18
    cv2.arrowedLine(img, (x, HEADER_PX - 3), (x, 3), INK, 2, cv2.LINE_AA, tipLength=0.4)
    _label(img, "N", (x - 22, HEADER_PX - 7), scale=0.6, thick=2)
    return img


def _ellipse(img: np.ndarray, view: View, center_m, cov_m2, color, thick: int) -> None:
    ring = visloc.covariance_ellipse_m(np.asarray(center_m, float), np.asarray(cov_m2, float), n_sigma=2.0)
    cv2.polylines(img, [view.px(ring)], True, color, thick, cv2.LINE_AA)


def _polyline(img: np.ndarray, view: View, points_m: np.ndarray, color, thick: int) -> None:
    ok = np.all(np.isfinite(points_m), axis=1)
    if ok.sum() >= 2:
        cv2.polylines(img, [view.px(points_m[ok])], False, color, thick, cv2.LINE_AA)


def draw_view(view: View, title: str, truth_track_m: np.ndarray, db_m: np.ndarray,
              records: list[visloc.StepRecord], k: int | None, tiles=None) -> np.ndarray:
    """One map view: database images, the truth track, measurements (refined ones with their own 2σ
    ellipses, light orange), estimates with theirs (the filter's covariance, blue),
    step ``k`` highlighted; ``title`` and a north arrow above, a scale bar below; on ``tiles``'s web map
    (``visloc.dashboard.tiles.TileLayer``) when given, with its attribution or why it has none."""
    under = None if tiles is None else tiles.under(view.center_m, view.px_per_m, view.width_px, view.height_px)
    img = np.full((view.height_px, view.width_px, 3), 255, np.uint8) if under is None else under
    for p in view.px(db_m):
        cv2.circle(img, tuple(int(v) for v in p), 2, DATABASE_RGB, -1, cv2.LINE_AA)
    _polyline(img, view, truth_track_m, TRUTH_RGB, 2)
    truth, meas, est = (positions([getattr(r, a) for r in records]) for a in ("truth_m", "measurement_m", "estimate_m"))
    for r, e, m in zip(records, est, meas):
        if np.all(np.isfinite(e)) and r.estimate_cov_m2 is not None:
            _ellipse(img, view, e, r.estimate_cov_m2, ELLIPSE_RGB, 1)
        if r.measurement_source == visloc.GEOMETRY and r.measurement_cov_m2 is not None and np.all(np.isfinite(m)):
            _ellipse(img, view, m, r.measurement_cov_m2, MEASUREMENT_ELLIPSE_RGB, 1)
    for t, m in zip(view.px(truth), view.px(meas)):
        if np.all(np.abs(m) < 10_000):
            cv2.line(img, tuple(int(v) for v in t), tuple(int(v) for v in m), MEASUREMENT_RGB, 1, cv2.LINE_AA)
    _polyline(img, view, est, ESTIMATE_RGB, 2)
    for p in view.px(truth):
        cv2.circle(img, tuple(int(v) for v in p), 3, TRUTH_RGB, -1, cv2.LINE_AA)
    ok = np.all(np.isfinite(meas), axis=1)
    for x, y in view.px(meas[ok]):
        cv2.fillConvexPoly(img, np.array([[x, y - 5], [x + 5, y], [x, y + 5], [x - 5, y]], np.int32),
                           MEASUREMENT_RGB, cv2.LINE_AA)
    ok = np.all(np.isfinite(est), axis=1)
    for p in view.px(est[ok]):
        cv2.circle(img, tuple(int(v) for v in p), 3, ESTIMATE_RGB, -1, cv2.LINE_AA)
    if k is not None and 0 <= k < len(records):
        rec = records[k]
        if rec.estimate_m is not None and rec.estimate_cov_m2 is not None:
            _ellipse(img, view, rec.estimate_m, rec.estimate_cov_m2, CURRENT_RGB, 2)
            cv2.circle(img, tuple(int(v) for v in view.px(rec.estimate_m)[0]), 5, ESTIMATE_RGB, -1, cv2.LINE_AA)
        cv2.circle(img, tuple(int(v) for v in view.px(rec.truth_m)[0]), 9, CURRENT_RGB, 2, cv2.LINE_AA)
    if tiles is not None:
        _label(img, tiles.caption[:90], (6, view.height_px - 8), scale=0.42, color=(90, 90, 90))
    cv2.rectangle(img, (0, 0), (view.width_px - 1, view.height_px - 1), (200, 200, 200), 1)
    return np.concatenate([_header(view, title), img, _footer(view)], axis=0)


def map_image(truth_track_m: np.ndarray, db_m: np.ndarray, records: list[visloc.StepRecord], k: int | None,
              *, note: str | None = None, width_px: int = MAP_WIDTH_PX, tiles=None) -> np.ndarray:
    """The Map tab's picture (RGB): the whole run above a close-up around step ``k``, on ``tiles`` when
    given; ``note`` (e.g. "previous run, re-matching") greys the picture and says so on it."""
    truth_track_m = np.asarray(truth_track_m, float).reshape(-1, 2)
    db_m = np.asarray(db_m, float).reshape(-1, 2)
    everything = np.concatenate([truth_track_m, db_m] + [positions([r.estimate_m for r in records])])
    overview = View.fitting(everything, width_px, VIEW_HEIGHT_PX)
    whole = draw_view(overview, "Whole run", truth_track_m, db_m, records, k, tiles)
    views = [whole]
    if k is not None and 0 <= k < len(records):
        center = np.asarray(records[k].truth_m, float)
        half_m = closeup_half_m(overview)
        scale = (VIEW_HEIGHT_PX - 2 * MARGIN_PX) / (2 * half_m)
        wide_m, tall_m = width_px / scale, VIEW_HEIGHT_PX / scale  # what the picture shows, edge to edge
        views.append(draw_view(View(center, scale, width_px, VIEW_HEIGHT_PX),
                               f"Around step {k + 1} ({wide_m:.3g} m by {tall_m:.3g} m)", truth_track_m, db_m,
                               records, k, tiles))
    img = np.concatenate(views, axis=0)
    if note:
        img = (0.55 * img + 0.45 * 235).astype(np.uint8)  # dimmed: not the run the controls ask for
        cv2.rectangle(img, (1, HEADER_PX + 2), (width_px - 2, HEADER_PX + 30), (225, 225, 225), -1)
        cv2.putText(img, note, (8, HEADER_PX + 22), FONT, 0.55, (80, 80, 80), 1, cv2.LINE_AA)
    return img
