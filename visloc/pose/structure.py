"""Database structure made once, at ingest: each image's triangulated points, ready for any query.

The refined method poses a query against a database image (a *view*) whose keypoints carry 3D
points, triangulated from the view and its database neighbours with their geotags and attitudes
(``visloc.pose.refined``). Nothing in that depends on the query, except which neighbours the query
allows: with an exclusion window (queries from the database's own camera), a neighbour inside
the window must not be used, or the query's own geotag would build the structure it is posed
against. So every image keeps three *variants*:

* ``both``:   neighbours before and after it (what the exact path builds when every image is allowed);
* ``before``: neighbours before it only, for a view before a query whose window holds later images;
* ``after``:  neighbours after it only, the mirror case.

``choose_variant`` picks, for a view and the images a query allows, the first variant whose
neighbours are all allowed. Pure functions over numpy arrays; the store keeps the results.
"""

from __future__ import annotations

import json
import time
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from visloc.params import RefinedParams
from visloc.pose.refined import StructureCache, build_view_structure, neighbours_of
from visloc.pose.viewpose import DatabaseGeometry

VARIANTS = {"both": (-1, 1), "before": (-1,), "after": (1,)}
# the settings structure depends on: structure made with other values is rebuilt
STRUCTURE_SETTINGS = ("ratio", "neighbour_baselines_m", "max_neighbour_gap", "min_baseline_m", "triangulation_px",
                      "min_parallax_deg", "max_depth_m", "refine_poses", "max_adjusted_points", "relative_geotag_sigma_m",
                      "attitude_prior_per_heading_spread", "min_attitude_prior_deg")


# settings that came later, at the value that makes the structure made before them: left out of the JSON there,
# so that a store built before keeps its structure
_SINCE = {"max_adjusted_points": 0}


def structure_settings_json(params: RefinedParams) -> str:
    """The settings of ``params`` that structure depends on, as canonical JSON."""
    d = params.as_dict()
    return json.dumps({k: list(d[k]) if isinstance(d[k], tuple) else d[k] for k in STRUCTURE_SETTINGS
                       if not (k in _SINCE and d[k] == _SINCE[k])}, sort_keys=True)


@dataclass(frozen=True)
class ViewStructure:
    """One view's triangulated points.

    view, neighbours: database indices; rows: (M,) the view's keypoint rows that carry a point;
    points_world: (M, 3) metres; cov_world: (M, 3, 3) m^2; reason: why there are none (else None).
    """

    view: int
    variant: str
    neighbours: tuple[int, ...]
    rows: np.ndarray
    points_world: np.ndarray
    cov_world: np.ndarray
    reason: str | None = None
    build_ms: float = 0.0

    def __len__(self) -> int:
        return int(len(self.rows))

    def lookup(self) -> dict[int, tuple[np.ndarray, np.ndarray]]:
        """keypoint row -> (world point, covariance): the form the pose solver reads."""
        return {int(k): (X, S) for k, X, S in zip(self.rows.tolist(), self.points_world, self.cov_world)}

    @classmethod
    def empty(cls, view: int, variant: str, reason: str, neighbours: tuple[int, ...] = ()) -> "ViewStructure":
        return cls(view, variant, neighbours, np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3, 3)), reason)


def view_structures(geometry: DatabaseGeometry, view: int, params: RefinedParams,
                    cache: StructureCache | None = None) -> list[ViewStructure]:
    """Every variant of ``view``'s structure, with every posed database image allowed as a neighbour.

    The ``both`` variant is exactly what ``visloc.pose.refined`` builds for this view when the retrieval
    allows every image."""
    cache = cache if cache is not None else StructureCache()
    n = len(geometry.T_world_camera)
    out = []
    for variant, directions in VARIANTS.items():
        if not np.all(np.isfinite(geometry.T_world_camera[view])):
            out.append(ViewStructure.empty(view, variant, "the image has no attitude"))
            continue
        neighbours = neighbours_of(view, np.arange(n), geometry.T_world_camera, params, directions)
        if not neighbours:
            out.append(ViewStructure.empty(view, variant, f"no neighbour at least {params.min_baseline_m:g} m away "
                                                          f"within {params.max_neighbour_gap} frames"))
            continue
        t0 = time.perf_counter()
        found = build_view_structure(geometry, view, neighbours, params, cache)
        rows = np.array(sorted(found), np.int64)
        points = np.array([found[k][0] for k in rows.tolist()], float).reshape(-1, 3)
        covs = np.array([found[k][1] for k in rows.tolist()], float).reshape(-1, 3, 3)
        out.append(ViewStructure(view, variant, tuple(neighbours), rows, points, covs,
                                 None if len(rows) else "no point triangulated",
                                 (time.perf_counter() - t0) * 1000.0))
    return out


def choose_variant(structures: dict[str, ViewStructure], allowed: np.ndarray | None,
                   query_after_view: bool) -> ViewStructure | None:
    """The structure of a view to pose against: ``both`` when the query allows all its neighbours,
    else the side away from the query (``before`` when the query comes after the view) when it
    allows those; None when no stored variant fits. ``allowed``: (N,) bool over database images,
    None: every image."""
    order = ("both", "before", "after") if query_after_view else ("both", "after", "before")
    for variant in order:
        s = structures.get(variant)
        if s is None or not len(s):
            continue
        if allowed is None or all(bool(allowed[j]) for j in s.neighbours):
            return s
    return None


def seeded_structure_cache(structures: Mapping[int, dict[str, ViewStructure]],
                           pairs: StructureCache | None = None) -> StructureCache:
    """A ``StructureCache`` holding stored structure under the keys the exact path looks up (view and
    its neighbours): where the exact path would triangulate the same view with the same neighbours,
    it reads the stored points instead (the same numbers). A view's stored structure is taken when
    the exact path first looks it up (a sharded store's is read from its tile then). ``pairs``: a cache whose
    database pairs' matches this one shares."""
    cache = _SeededStructureCache(structures)
    if pairs is not None:
        cache.share_pairs(pairs)
    return cache


class _SeededStructureCache(StructureCache):
    def __init__(self, structures: Mapping[int, dict[str, ViewStructure]]):
        super().__init__()
        self._stored = structures
        self._seeded: set[int] = set()

    def get(self, key: tuple[int, tuple[int, ...]]) -> dict[int, np.ndarray] | None:
        view = key[0]
        if view not in self._seeded:
            self._seeded.add(view)
            for s in self._stored.get(view, {}).values():
                if len(s) and (s.view, s.neighbours) not in self._views:
                    self.put((s.view, s.neighbours), s.lookup(), 0.0)
        return super().get(key)
