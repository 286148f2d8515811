"""The database views a track at camera rate may use as it goes: the exclusion window over time, and the views
nearest a pose.

A run that localizes a drive against a database of the same drive (same camera or its stereo partner) uses no
database image closer in time to the frame than ``exclusion_s`` (else a frame is posed on its own image). A
frame's followed map points must obey it too: a point whose view, or any image its view's structure was
triangulated with, lies inside the window of the frame is not used (``ViewWindow.allowed``), and the views whose
points a frame takes on are those it may use now and a little later (``ViewWindow.nearest_views``).

Pure functions over numpy arrays.
"""

from __future__ import annotations

import numpy as np

from visloc.pose.flowtrack import TrackedPoints
from visloc.pose.structure import ViewStructure, choose_variant


class ViewWindow:
    """The views of a database (``db_east_north_m`` (N, 2) m, ``db_timestamps_s`` (N,)) a track may use, with the
    exclusion window ``exclusion_s`` (0: off) and the stored structure ``stored`` (view -> variant -> structure);
    ``direction``: +1 for a drive run forward in time, -1 backward."""

    def __init__(self, db_east_north_m: np.ndarray, db_timestamps_s: np.ndarray, exclusion_s: float,
                 stored: dict | None, direction: float = 1.0):
        self.db_east_north_m = np.asarray(db_east_north_m, float)
        self.db_timestamps_s = np.asarray(db_timestamps_s, float)
        self.exclusion_s = float(exclusion_s)
        self.stored = stored or {}
        self.direction = 1.0 if direction >= 0 else -1.0

    def usable(self, timestamp_s: float) -> np.ndarray:
        """(N,) bool: the database views the exclusion window lets a frame at ``timestamp_s`` use."""
        return np.abs(self.db_timestamps_s - timestamp_s) >= self.exclusion_s

    def nearest_view_m(self, east_north_m: np.ndarray, timestamp_s: float) -> float:
        """How far from ``east_north_m`` the nearest database view a frame at ``timestamp_s`` may use is, m."""
        d = np.linalg.norm(self.db_east_north_m - np.asarray(east_north_m, float), axis=1)[self.usable(timestamp_s)]
        return float(d.min()) if d.size else np.inf

    def allowed(self, points: TrackedPoints, timestamp_s: float) -> TrackedPoints:
        """The points the exclusion window lets a frame at ``timestamp_s`` use: their view and every image its
        structure was triangulated with outside the window."""
        if self.exclusion_s <= 0 or not len(points):
            return points
        far = self.usable(timestamp_s)
        ok_view = {v: bool(far[v]) and all(far[j] for j in points.neighbours.get(v, ()))
                   for v in np.unique(points.view_of).tolist()}
        return points.subset(np.array([ok_view[v] for v in points.view_of.tolist()], bool))

    def nearest_views(self, east_north_m: np.ndarray, timestamp_s: float, lookahead_s: float, n_views: int,
                      radius_m: float) -> dict[int, ViewStructure]:
        """The stored structure of up to ``n_views`` database views nearest ``east_north_m`` (within ``radius_m``),
        as many before the frame as after it, that a frame at ``timestamp_s`` may use and the frames of the next
        ``lookahead_s`` too, each in the variant whose neighbours they may use (with the exclusion window on, the
        views behind the vehicle, with their neighbours on the side away from it, keep serving longest)."""
        if not self.stored:
            return {}
        allowed = None
        if self.exclusion_s > 0:
            allowed = self.usable(timestamp_s) & self.usable(timestamp_s + lookahead_s * self.direction)
        distance = np.linalg.norm(self.db_east_north_m - np.asarray(east_north_m, float), axis=1)
        out: dict[int, ViewStructure] = {}
        taken = {True: 0, False: 0}  # as many views before the frame as after it, nearest first
        for v in np.argsort(distance, kind="stable").tolist():
            if distance[v] > radius_m or len(out) >= n_views:
                break
            before = bool(self.db_timestamps_s[v] < timestamp_s)
            if (allowed is not None and not allowed[v]) or taken[before] >= n_views // 2:
                continue
            s = choose_variant(self.stored.get(v, {}), allowed, before)  # the frame comes after a view before it
            if s is not None:
                out[v] = s
                taken[before] += 1
        return out

    def nearest_views_only(self, points: TrackedPoints, east_north_m: np.ndarray, timestamp_s: float, per_side: int,
                           min_points: int) -> TrackedPoints:
        """``points`` without the views farther from ``east_north_m`` than the ``per_side`` nearest on their side
        of a frame at ``timestamp_s`` (before or after it) that hold ``min_points`` points or more (every view of a
        side with fewer such views stays)."""
        views, counts = np.unique(points.view_of, return_counts=True)
        distance = np.linalg.norm(self.db_east_north_m[views] - np.asarray(east_north_m, float), axis=1)
        keep = np.zeros(len(views), bool)
        for before in (True, False):
            side = np.flatnonzero((self.db_timestamps_s[views] < timestamp_s) == before)
            side = side[np.argsort(distance[side], kind="stable")]
            held = side[counts[side] >= min_points]
            reach_m = distance[held[per_side - 1]] if len(held) >= per_side else np.inf
            keep[side[distance[side] <= reach_m]] = True
        return points if keep.all() else points.subset(np.isin(points.view_of, views[keep]))

