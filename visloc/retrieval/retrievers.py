"""Image retrieval, section 3.1: which database images a query is compared with, and the best one.

Two retrievers give the same ``Retrieval``:

* ``WindowRetriever``, the paper's. The first query (and any query after one without a
  match) is compared with the whole database; later ones with the images within
  +-window_s of the previous best match.
* ``ShortlistRetriever``, the fast path. Candidates are the images inside the filter's
  gate (``gate_mask``: within ``gate_sigmas`` standard deviations of the predicted
  position); their global vectors (``visloc.features.vlad``) shortlist the ``shortlist_size`` most
  similar, and only those are counted exactly. A first query, a lost track (no
  prediction) or a gate in which no candidate has a correspondence widens to every
  allowed image (and a shortlist of ``lost_shortlist_size``).

In both, images closer in time to the query than ``exclusion_s`` are removed. The best
match is the candidate with the most correspondences; ties go to the earliest candidate,
and a best count of 0 means no measurement.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from visloc.features.sift import Query, at_contrast
from visloc.retrieval.matching import Counter, CountFn
from visloc.params import FastParams, RetrievalParams
from visloc.features.vlad import GlobalIndex, shortlist

# the filter's predicted position (east_m, north_m) and its 2x2 covariance (m^2); None before the track starts
Prediction = tuple[np.ndarray, np.ndarray] | None


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
    gated: bool = False  # fast path: the filter's gate chose the search area
    widened: bool = False  # fast path: the gate held no image with a correspondence, so every image was searched
    # the matches behind the counts, where the count function keeps them (the camera-rate path's
    # StructureMatcher): candidate -> (M, 2) (query row, keypoint row of the candidate); None otherwise
    pairs: dict[int, np.ndarray] | None = None

    @property
    def search_area(self) -> np.ndarray:
        """Database indices the retrieval could have chosen from."""
        return self.candidates if self.allowed is None else self.allowed

    @property
    def best_count(self) -> int:
        return int(self.counts.max()) if self.counts.size else 0


def retrieve(counts_of: CountFn, db_timestamps_s: np.ndarray, query_timestamp_s: float,
             center_timestamp_s: float | None, params: RetrievalParams) -> Retrieval:
    """The paper's retrieval: score the candidates with ``counts_of`` and pick the best match."""
    candidates = np.flatnonzero(candidate_mask(db_timestamps_s, query_timestamp_s, center_timestamp_s, params))
    counts = np.asarray(counts_of(candidates), np.int64) if candidates.size else np.zeros(0, np.int64)
    best = None
    if counts.size and counts.max() > 0:
        best = int(candidates[int(np.argmax(counts))])
    return Retrieval(candidates=candidates, counts=counts, best_index=best, pairs=getattr(counts_of, "pairs", None))


# -- the filter's gate ----------------------------------------------------------------------

def gate_radius_m(position_cov_m2: np.ndarray, params: FastParams) -> float:
    """Gate radius around a predicted position with covariance ``position_cov_m2`` (2x2, m^2), metres."""
    sigma_m = float(np.sqrt(max(np.linalg.eigvalsh(np.asarray(position_cov_m2, float)).max(), 0.0)))
    return max(params.gate_sigmas * sigma_m, params.gate_min_radius_m)


def gate_mask(db_east_north_m: np.ndarray, predicted_m: np.ndarray, position_cov_m2: np.ndarray,
              params: FastParams) -> np.ndarray:
    """(N,) bool: database images within the gate radius of the predicted position."""
    offset = np.asarray(db_east_north_m, float) - np.asarray(predicted_m, float).reshape(1, 2)
    return np.einsum("ij,ij->i", offset, offset) <= gate_radius_m(position_cov_m2, params) ** 2


def shortlist_retrieve(query_vector_f32: np.ndarray, counts_of: CountFn, db_timestamps_s: np.ndarray,
                       db_east_north_m: np.ndarray, db_vectors_f32: np.ndarray, params: FastParams,
                       query_timestamp_s: float, retrieval_params: RetrievalParams,
                       prediction: Prediction = None) -> Retrieval:
    """Gate, shortlist by global vector, then the paper's exact counts on the shortlist.

    Without a prediction (first or lost query) every image the exclusion window allows is
    searched (no +-window_s: there is no previous match to centre it on).
    """
    allowed = candidate_mask(db_timestamps_s, query_timestamp_s, None, retrieval_params)

    def search(area: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
        chosen = shortlist(db_vectors_f32, query_vector_f32, size, among=np.flatnonzero(area))
        counts = np.asarray(counts_of(chosen), np.int64) if chosen.size else np.zeros(0, np.int64)
        return chosen, counts

    lost_size = params.lost_shortlist_size or params.shortlist_size
    gated = prediction is not None and bool(np.all(np.isfinite(prediction[0])))
    area = allowed & gate_mask(db_east_north_m, prediction[0], prediction[1], params) if gated else allowed
    chosen, counts = search(area, params.shortlist_size if gated else lost_size)
    widened = False
    if gated and (counts.size == 0 or counts.max() == 0):
        widened, area = True, allowed
        chosen, counts = search(area, lost_size)
    best = None
    if counts.size and counts.max() > 0:
        best = int(chosen[counts == counts.max()].min())  # ties go to the earliest image, as in the paper's path
    return Retrieval(candidates=chosen, counts=counts, best_index=best, allowed=np.flatnonzero(area),
                     gated=gated and not widened, widened=widened, pairs=getattr(counts_of, "pairs", None))


# -- the retrievers ---------------------------------------------------------------------------

class WindowRetriever:
    """The paper's retrieval, one query at a time: it remembers the previous best match's time."""

    def __init__(self, db_timestamps_s: np.ndarray, counter: Counter, params: RetrievalParams):
        self.db_timestamps_s = np.asarray(db_timestamps_s, float)
        self.counter = counter
        self.params = params
        self.reset()

    def reset(self) -> None:
        """Forget the previous match: the next query scans the whole database."""
        self._center_timestamp_s: float | None = None

    def retrieve(self, query: Query, prediction: Prediction = None) -> Retrieval:
        """``prediction`` is not used: the paper's window follows the previous best match."""
        retrieval = retrieve(self.counter(query.descriptors_u8, query.key), self.db_timestamps_s,
                             query.timestamp_s, self._center_timestamp_s, self.params)
        best = retrieval.best_index
        self._center_timestamp_s = None if best is None else float(self.db_timestamps_s[best])  # None: lost
        return retrieval


def build_global_index(db_descriptors: Sequence[np.ndarray], params: FastParams) -> GlobalIndex:
    """The fast retrieval's global vectors of a database, as ``params`` describe them."""
    return GlobalIndex.build(db_descriptors, n_words=params.n_words, pca_dim=params.pca_dim,
                             train_descriptors=params.train_descriptors, seed=params.seed)


class ShortlistRetriever:
    """The fast retrieval, one query at a time: the filter's prediction gates the candidates, the
    global vectors of ``index`` shortlist them, ``counter`` counts the shortlist exactly."""

    def __init__(self, db_timestamps_s: np.ndarray, db_east_north_m: np.ndarray, index: GlobalIndex,
                 params: FastParams, counter: Counter, retrieval_params: RetrievalParams):
        self.db_timestamps_s = np.asarray(db_timestamps_s, float)
        self.db_east_north_m = np.asarray(db_east_north_m, float)
        self.index = index
        self.params = params
        self.counter = counter
        self.retrieval_params = retrieval_params

    def reset(self) -> None:
        """Nothing to forget: the gate follows the filter's prediction."""

    def retrieve(self, query: Query, prediction: Prediction = None) -> Retrieval:
        return shortlist_retrieve(self.index.encoder.encode(query.descriptors_u8),
                                  self.counter(query.descriptors_u8, query.key), self.db_timestamps_s,
                                  self.db_east_north_m, self.index.vectors_f32, self.params, query.timestamp_s,
                                  self.retrieval_params, prediction)


class ContrastSelecting:
    """``retriever`` counting with a query's features SIFT keeps at ``contrast_threshold`` only, as the database's
    ``retrieval_descriptors_u8`` are: the paper's retrieval on a store described at a lower threshold."""

    def __init__(self, retriever, contrast_threshold: float, n_octave_layers: int):
        self.retriever, self.contrast_threshold, self.n_octave_layers = retriever, contrast_threshold, n_octave_layers

    def reset(self) -> None:
        self.retriever.reset()

    def retrieve(self, query: Query, prediction: Prediction = None) -> Retrieval:
        return self.retriever.retrieve(at_contrast(query, self.contrast_threshold, self.n_octave_layers), prediction)
