"""Image retrieval, section 3.1: which database images a query is compared with, and the best one.

The first query (``center_timestamp_s=None``) is compared with the whole database;
later ones with the images within +-window_s of the previous best match. Images
closer in time to the query than ``exclusion_s`` are removed. The best match is
the candidate with the most correspondences; ties go to the earliest candidate,
and a best count of 0 means no measurement.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from visloc.matching import count_correspondences
from visloc.params import MatchParams, RetrievalParams


def candidate_mask(db_timestamps_s: np.ndarray, query_timestamp_s: float, center_timestamp_s: float | None,
                   params: RetrievalParams) -> np.ndarray:
    """(N,) bool over database images: inside the search window and outside the exclusion window."""
    t = np.asarray(db_timestamps_s, float)
    mask = np.ones(t.shape, bool)
    if center_timestamp_s is not None:
        mask &= np.abs(t - center_timestamp_s) <= params.window_s
    if params.exclusion_s > 0:
        mask &= np.abs(t - query_timestamp_s) >= params.exclusion_s
    return mask


@dataclass(frozen=True)
class Retrieval:
    candidates: np.ndarray  # (M,) database indices compared with the query
    counts: np.ndarray  # (M,) correspondences per candidate
    best_index: int | None  # database index of the best match, None if no candidate has a correspondence
    # every image the search area allowed, when the candidates are only a shortlist of them (fast path);
    # None: the candidates are the whole search area (the paper's path)
    allowed: np.ndarray | None = None

    @property
    def search_area(self) -> np.ndarray:
        """Database indices the retrieval could have chosen from."""
        return self.candidates if self.allowed is None else self.allowed

    @property
    def best_count(self) -> int:
        return int(self.counts.max()) if self.counts.size else 0


CountFn = Callable[[np.ndarray], np.ndarray]


def brute_force_counts(query_u8: np.ndarray, db_descriptors: Sequence[np.ndarray], params: MatchParams) -> CountFn:
    """Counter that matches the query against each candidate in turn, exactly as the paper does."""

    def counts(candidates: np.ndarray) -> np.ndarray:
        return np.array([count_correspondences(query_u8, db_descriptors[i], params) for i in candidates], np.int64)

    return counts


def retrieve(counts_of: CountFn, db_timestamps_s: np.ndarray, query_timestamp_s: float,
             center_timestamp_s: float | None, params: RetrievalParams) -> Retrieval:
    """Score the candidates with ``counts_of`` and pick the best match."""
    candidates = np.flatnonzero(candidate_mask(db_timestamps_s, query_timestamp_s, center_timestamp_s, params))
    counts = np.asarray(counts_of(candidates), np.int64) if candidates.size else np.zeros(0, np.int64)
    best = None
    if counts.size and counts.max() > 0:
        best = int(candidates[int(np.argmax(counts))])
    return Retrieval(candidates=candidates, counts=counts, best_index=best)
