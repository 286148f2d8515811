"""What a frame posed on followed points states about its error beyond its own pose: the map's error, which
every frame posed on the same points of the same views repeats (``shared_map_error``, ``ViewRuns``), and how far
one view's pose strays, pooled over a run's own poses on several views posed apart (``ViewScatter``). Pure
functions over numpy arrays.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field, replace

import numpy as np

from visloc.pose.measurement import GEOMETRY, Measurement


def shared_map_error(m: Measurement, frames: float) -> Measurement:
    """A tracked measurement whose map part of the covariance (the views' spread, the lever and the geotags that are
    no fix: errors of the map points, which every frame posed on the same points of the same views repeats) counts
    ``frames`` times (``ViewRuns.frames``): the filter then learns from ``frames`` frames on the same map what it
    would learn from one about the map's error, and keeps the pixel noise (PnP's term), new in each frame. (The
    filter's own measurement bias, fitted on poses that change views from one frame to the next, does not know
    that followed frames repeat one map.)"""
    terms = m.cov_terms_m2
    if m.cov_m2 is None or frames <= 1 or not {"pnp", "views", "lever"} <= set(terms):
        return m
    map_terms = [k for k in ("views", "views_round", "lever", "geotags") if k in terms]
    cov = np.asarray(terms["pnp"], float) + frames * sum(np.asarray(terms[k], float) for k in map_terms)
    counted = {k: frames * np.asarray(terms[k], float) for k in map_terms}
    return replace(m, cov_m2=cov, cov_terms_m2={**terms, **counted})


@dataclass
class ViewRuns:
    """How many tracked frames in a row each database view has been posed on.

    Frames posed on the same followed points repeat their map's error only while they rest on the same views: the
    followed points are linked into the structure of the views the vehicle nears (``visloc.pose.flowtrack.linked``),
    and a frame posed on another view's structure carries that view's error, as the next frame localized in full
    does. So the map part counts once per frame in a row on the same views, not once per frame since the points
    came: ``frames`` is the mean, over a frame's views, of how many frames in a row have been posed on each, at
    most the frames posed on these points."""

    runs: dict[int, int] = field(default_factory=dict)  # view -> tracked frames in a row posed on it

    def frames(self, views, frames_on_points: int) -> float:
        """Count a tracked frame posed on the database ``views``; how many times its map error counts: the mean
        run of its views, at most ``frames_on_points`` (``frames_on_points`` when it names no view)."""
        views = {int(v) for v in views}
        self.runs = {v: self.runs.get(v, 0) + 1 for v in views}
        if not views:
            return float(frames_on_points)
        return float(min(np.mean([self.runs[v] for v in views]), frames_on_points))


VIEW_SCATTER_MEASUREMENTS = 50  # the view scatter is pooled over the run's last this many poses on views posed apart


@dataclass
class ViewScatter:
    """How far one view's pose strays, per square metre of lever: pooled over a run's last
    ``VIEW_SCATTER_MEASUREMENTS`` poses on two or more views posed apart.

    A pose on n views posed apart states the covariance of their mean from their spread (its "views" term: the
    views' sample covariance over n). Two views' spread is one degree of freedom: where they happen to agree, the
    term is near zero however far one view's pose may stray, and the ellipse claims far too much; and a followed
    frame often rests on one view only (at speed, with the exclusion window on, the views that hold its points lie
    behind it), with no spread at all. ``stated`` counts the scatter the run's own poses on several views show, at
    the frame's lever (the farther the view, the farther its pose strays), as one more view's worth of spread:
    the views' sample covariance S (n - 1 degrees of freedom) and the pooled one P (one) make
    ((n - 1) S + P) / n, one view's; one view alone states P.

    Their mean is no better than one view on each side of the frame: views on one side share their error (their
    structure is triangulated from the same neighbours and seen from the same side; frames posed on two views
    ahead and two behind stray together, for a second at a time, by two or three times what four independent
    views would claim). So one view's covariance is divided by the sides the views lie on (2 for "both", else
    1), never by more than n."""

    samples: deque = field(default_factory=lambda: deque(maxlen=VIEW_SCATTER_MEASUREMENTS))

    def add(self, m: Measurement) -> None:
        """Learn from ``m`` when it is a pose on views posed apart (the terms as posed, before any counting)."""
        n, lever_m = m.views_posed_apart, m.lever_m
        if m.source != GEOMETRY or n < 2 or not lever_m or "views" not in m.cov_terms_m2:
            return
        self.samples.append((n - 1, n * np.asarray(m.cov_terms_m2["views"], float) / lever_m ** 2))

    def per_m2(self) -> np.ndarray | None:
        """One view's scatter per square metre of lever, m^2/m^2 (None: no pose on several views yet)."""
        if not self.samples:
            return None
        dof = sum(d for d, _ in self.samples)
        return sum(d * c for d, c in self.samples) / dof

    def stated(self, m: Measurement) -> Measurement:
        """``m`` with its "views" term made from its own spread and the pooled scatter at its lever (the class
        docstring); as it is when nothing is pooled yet, or it is no pose."""
        per_m2 = self.per_m2()
        if (per_m2 is None or m.source != GEOMETRY or m.cov_m2 is None or not m.lever_m
                or "views" not in m.cov_terms_m2):
            return m
        n = max(m.views_posed_apart, 1)
        sides = min(n, 2 if m.side == "both" else 1)
        own = np.asarray(m.cov_terms_m2["views"], float)  # the views' sample covariance over n
        views = ((n - 1) * n * own + per_m2 * m.lever_m ** 2) / n / sides
        rounded = np.asarray(m.cov_terms_m2.get("views_round", np.zeros((2, 2))), float)  # the pooled scatter says
        cov = np.asarray(m.cov_m2, float) - own - rounded + views  # what a few views' spread could not
        terms = {k: v for k, v in m.cov_terms_m2.items() if k != "views_round"}
        return replace(m, cov_m2=cov, cov_terms_m2={**terms, "views": views})
