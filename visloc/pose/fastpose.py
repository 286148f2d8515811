"""The refined measurement at camera rate: stored structure, a gated shortlist, matching against 3D only.

The exact refined path (``visloc.pose.refined``) verifies eight candidates with two-view geometry and
triangulates its views' structure when it needs it. The fast path does what a vehicle can do in
a frame interval:

1. **Candidates.** The fast retrieval (``visloc.retrieval.retrievers.ShortlistRetriever``): the database
   images inside the filter's gate (every allowed image for a first or lost query), the
   ``shortlist_size`` most similar by stored global vector.
2. **Matching against structure only.** ``StructureMatcher`` matches the query's descriptors
   against the descriptors of each candidate's keypoints that carry a stored 3D point (Lowe's
   ratio), one matrix product per candidate; the number of matches ranks the candidates, and
   the matches themselves are the 2D-3D correspondences. No essential-matrix verification:
   PnP RANSAC rejects the outliers.
3. **Pose** exactly as the exact path poses (``visloc.pose.viewpose.pose_from_views``: views on
   both sides, per-view check, covariance), against the stored structure of each view
   (``visloc.pose.structure``: the variant whose neighbours the query allows).

Given the same views, correspondences and structure, both paths give the same measurement;
they differ in which candidates they look at and in the matches.
"""

from __future__ import annotations

from collections.abc import Hashable, Mapping, Sequence

import numpy as np

from visloc.errors import InputError, ParameterError
from visloc.features.sift import Query
from visloc.geometry.projective import CameraModel
from visloc.retrieval.matching import CountFn, best_two, correspondences
from visloc.pose.measurement import Measurement, MeasurementEnd, query_pixels
from visloc.params import MatchParams, RefinedParams
from visloc.retrieval.retrievers import Retrieval
from visloc.pose.structure import ViewStructure, choose_variant
from visloc.pose.viewpose import DatabaseGeometry, pose_from_views, require_calibrated

# database index -> variant -> structure (a sharded store's reads a view's points when it is asked for)
StoredStructures = Mapping[int, dict[str, ViewStructure]]


def structure_rows(structures: dict[str, ViewStructure]) -> np.ndarray:
    """Keypoint rows of a view that carry a point in any of its variants, sorted."""
    parts = [s.rows for s in structures.values() if len(s)]
    return np.unique(np.concatenate(parts)) if parts else np.zeros(0, np.int64)


def _matches(q: np.ndarray, q_sq: np.ndarray, d: np.ndarray, half_d_sq: np.ndarray, ratio: float,
             mutual: bool) -> np.ndarray:
    """(M, 2) (query row, database row): Lowe's ratio against the rows of ``d``, and, with ``mutual``,
    the database row's nearest query descriptor is that query row too (a cross-check: matching
    against a subset of an image's keypoints lets more ambiguous matches pass the ratio alone).
    ``q``, ``d``: float32 descriptors; ``q_sq`` = |q|^2 per row, ``half_d_sq`` = |d|^2 / 2 per row."""
    if len(q) == 0 or len(d) < 2:
        return np.zeros((0, 2), np.int64)
    score = q @ d.T  # |g - f|^2 = |g|^2 + |f|^2 - 2 g.f
    score -= half_d_sq[None, :]  # g.f - |f|^2 / 2: the largest along a row is that query's nearest
    column_best = None
    if mutual:  # each database row's nearest query: the largest g.f - |g|^2 / 2 down its column (a maximum over
        # rows, which numpy takes row by row, where an argmax down columns walks the matrix across)
        column_best = (score - 0.5 * q_sq[:, None]).max(axis=0) + half_d_sq
    index1, best, d1, d2 = best_two(score, q_sq)
    ok = d1 < ratio**2 * d2
    if mutual:  # the query is its nearest database row's nearest query: g.f - |g|^2 / 2 is that column's largest
        ok &= best + half_d_sq[index1] - 0.5 * q_sq >= column_best[index1]
    return np.stack([np.flatnonzero(ok), index1[ok]], axis=1).astype(np.int64)


NO_PAIRS = np.zeros((0, 2), np.int64)  # a candidate the retrieval did not match


class StructureMatcher:
    """A retrieval counter over stored structure: a candidate's count is the number of query
    descriptors matched to the candidate's 3D-carrying keypoints. The count function it makes for a
    query keeps those matches (``pairs``: candidate -> (M, 2) query row, keypoint row of the view);
    the retrieval hands them to the measurer (``Retrieval.pairs``).

    against="structure" (the camera-rate path): nearest neighbour among those keypoints only, Lowe's ratio
    and a mutual check. against="image": Lowe's ratio against every keypoint of the
    candidate, the exact path's matches (slower; for comparing the paths)."""

    def __init__(self, db_descriptors: Sequence[np.ndarray], structures: StoredStructures, ratio: float,
                 against: str = "structure"):
        if against not in ("structure", "image"):
            raise ParameterError(f"against={against!r}: must be structure or image")
        self.match = MatchParams(tau1=ratio, tau2=-1.0)
        self.against = against
        self._structures = structures
        self._rows: dict[int, np.ndarray | None] = {}  # a view's structured keypoint rows, when first counted
        self._db_descriptors = db_descriptors
        # a view's structured descriptors as floats, made when a retrieval first counts it: a database
        # read from a sharded store's tiles reads only the views its queries are compared with
        self._views: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def _view(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """(descriptors of view ``i``'s structured keypoints as float32, half their squared norms)."""
        view = self._views.get(i)
        if view is None:
            d = np.ascontiguousarray(self._db_descriptors[i][self._rows_of(i)], np.float32)
            view = self._views[i] = (d, 0.5 * np.einsum("ij,ij->i", d, d))
        return view

    def _rows_of(self, i: int) -> np.ndarray | None:
        """Keypoint rows of view ``i`` that carry a point (None: no stored structure)."""
        if i not in self._rows:
            variants = self._structures.get(i)
            self._rows[i] = None if variants is None else structure_rows(variants)
        return self._rows[i]

    def __call__(self, query_u8: np.ndarray, key: Hashable = None) -> CountFn:
        q = np.asarray(query_u8, np.float32)
        q_sq = np.einsum("ij,ij->i", q, q)
        pairs_of: dict[int, np.ndarray] = {}

        def counts(candidates: np.ndarray) -> np.ndarray:
            out = np.zeros(len(candidates), np.int64)
            for j, i in enumerate(np.asarray(candidates, np.int64).tolist()):
                rows = self._rows_of(i)
                if rows is None or not rows.size:
                    continue
                if self.against == "image":  # the exact path's matches: every keypoint of the view
                    pairs = correspondences(query_u8, self._db_descriptors[i], self.match)
                    n_3d = int(np.isin(pairs[:, 1], rows).sum())
                else:
                    pairs = _matches(q, q_sq, *self._view(i), self.match.tau1, mutual=True)
                    pairs[:, 1] = rows[pairs[:, 1]]  # subset index -> keypoint row of the view
                    n_3d = len(pairs)
                pairs_of[i] = pairs
                out[j] = n_3d
            return out

        counts.pairs = pairs_of  # type: ignore[attr-defined]  # the retrieval hands them to the measurer
        return counts


class FastPoseMeasurer:
    """The refined measurement on stored structure (see the module docstring). Needs a retrieval counted
    by a ``StructureMatcher``, whose matches it carries (``Retrieval.pairs``)."""

    def __init__(self, db_east_north_m: np.ndarray, db_timestamps_s: np.ndarray, geometry: DatabaseGeometry,
                 structures: StoredStructures, query_camera: CameraModel | None,
                 params: RefinedParams, *, exclusion_s: float = 0.0, min_matches: int = 20,
                 query_what: str = "the query camera", db_name: str = "the database"):
        require_calibrated(geometry, query_camera, query_what)
        if not structures:
            raise InputError(f"the camera-rate path needs the stored structure of the database ({db_name}): run "
                             "'visloc ingest' on it (the database needs calibrated cameras and attitudes)")
        self.db_east_north_m = np.asarray(db_east_north_m, float)
        self.db_timestamps_s = np.asarray(db_timestamps_s, float)
        self.geometry = geometry
        self.structures = structures
        self.query_camera = query_camera
        self.params = params
        self.exclusion_s = float(exclusion_s)
        self.min_matches = int(min_matches)
        self._lookups: dict[tuple[int, str], dict] = {}

    def _lookup(self, s: ViewStructure) -> dict:
        key = (s.view, s.variant)
        if key not in self._lookups:
            self._lookups[key] = s.lookup()
        return self._lookups[key]

    def measure(self, query: Query, retrieval: Retrieval) -> Measurement:
        end = MeasurementEnd(retrieval, self.db_east_north_m)
        if retrieval.best_index is None:
            return end.no_match()
        query_xy = query_pixels(query.keypoints_f32, query.descriptors_u8)
        if query_xy is None:
            return end.fallback(end.NO_KEYPOINTS)
        allowed = None
        if self.exclusion_s > 0:
            allowed = np.abs(self.db_timestamps_s - query.timestamp_s) >= self.exclusion_s
        order = np.argsort(-retrieval.counts, kind="stable")
        matches = retrieval.pairs or {}  # what the retrieval's StructureMatcher matched, per candidate
        usable, pairs_of, lookups, neighbours_used = [], {}, {}, {}
        best = int(retrieval.counts[order[0]]) if order.size else 0
        for k in order.tolist():
            i, n = int(retrieval.candidates[k]), int(retrieval.counts[k])
            if n < self.min_matches:
                break
            s = choose_variant(self.structures.get(i, {}), allowed, query.timestamp_s > self.db_timestamps_s[i])
            if s is None:
                continue
            usable.append(i)
            pairs_of[i], lookups[i], neighbours_used[i] = matches.get(i, NO_PAIRS), self._lookup(s), s.neighbours
        base = dict(n_structure_matches=best, candidate_structure_matches={
            int(c): int(n) for c, n in zip(retrieval.candidates, retrieval.counts)})
        if not usable:
            return end.fallback(f"no candidate has {self.min_matches} matches to stored structure the query allows "
                                f"(best {best})", **base)
        posed = pose_from_views(query_xy, usable, pairs_of, lambda i: (lookups[i], 0.0), neighbours_used,
                                self.db_east_north_m, self.geometry, self.query_camera, self.params,
                                query_descriptors=query.descriptors_u8)
        return end.posed(posed, **base)
