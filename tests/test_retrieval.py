"""Retrieval windows, best-match choice, the localizer loop and the evaluation schedule."""

import numpy as np
import pytest

from visloc.errors import ParameterError
from visloc.protocols.evaluation import series_schedule
from visloc.features.sift import Query
from visloc.tracking.localizer import Localizer
from visloc.retrieval.matching import PairCountCache, brute_force_counter
from visloc.pose.measurement import GeotagMeasurer
from visloc.params import FilterParams, MatchParams, RetrievalParams
from visloc.retrieval.retrievers import WindowRetriever, candidate_mask, retrieve

T = np.arange(0.0, 100.0, 1.0)  # database timestamps, one image per second


def test_first_query_scans_everything_later_ones_the_window():
    assert candidate_mask(T, 50.0, None, RetrievalParams(window_s=20)).all()
    mask = candidate_mask(T, 50.0, 30.0, RetrievalParams(window_s=20))
    assert np.flatnonzero(mask).tolist() == list(range(10, 51))  # |t - 30| <= 20


def test_exclusion_removes_images_closer_than_the_window():
    mask = candidate_mask(T, 50.0, None, RetrievalParams(exclusion_s=1.0))
    assert np.flatnonzero(~mask).tolist() == [50]  # 49 and 51 are exactly 1 s away: kept
    mask = candidate_mask(T, 50.5, None, RetrievalParams(exclusion_s=1.0))
    assert np.flatnonzero(~mask).tolist() == [50, 51]


def test_best_match_has_most_correspondences_ties_go_to_the_earliest():
    counts = {3: 5, 7: 9, 8: 9, 9: 1}
    r = retrieve(lambda c: np.array([counts.get(int(i), 0) for i in c]), T[:10], 0.0, None, RetrievalParams())
    assert r.best_index == 7 and r.best_count == 9 and r.candidates.size == 10


def test_no_correspondence_anywhere_means_no_measurement():
    r = retrieve(lambda c: np.zeros(len(c), int), T[:10], 0.0, None, RetrievalParams())
    assert r.best_index is None and r.best_count == 0


def _db(n=30, seed=0):
    rng = np.random.default_rng(seed)
    return [rng.integers(0, 256, (40, 128), dtype=np.uint8) for _ in range(n)]


def test_localizer_follows_the_window_and_rescans_when_lost():
    descriptors = _db()
    en = np.stack([np.arange(30.0) * 10, np.zeros(30)], axis=1)
    retriever = WindowRetriever(T[:30], brute_force_counter(descriptors, MatchParams(0.8, 0.9)),
                                RetrievalParams(window_s=5.0))
    loc = Localizer(retriever, GeotagMeasurer(en), FilterParams())
    first = loc.step(Query(descriptors[12], 12.0))
    assert first.best_index == 12 and first.retrieval.candidates.size == 30
    np.testing.assert_allclose(first.measurement_m, [120, 0])
    second = loc.step(Query(descriptors[14], 13.0))
    assert second.best_index == 14 and second.retrieval.candidates.tolist() == list(range(7, 18))
    lost = loc.step(Query(np.zeros((5, 128), np.uint8), 14.0))  # zero vectors never correspond
    assert lost.best_index is None and lost.measurement_m is None and lost.filter.innovation is None
    again = loc.step(Query(descriptors[29], 15.0))
    assert again.retrieval.candidates.size == 30 and again.best_index == 29  # whole database again
    loc.reset()  # a new track: the window is forgotten too
    assert loc.step(Query(descriptors[3], 16.0)).retrieval.candidates.size == 30


def test_pair_cache_computes_each_pair_once_and_seeds_from_known_counts():
    descriptors = _db(5)
    cache = PairCountCache(descriptors, MatchParams(0.8, 0.9), db_keys=[100, 101, 102, 103, 104])
    counts = cache(descriptors[2], "q")
    first = counts(np.arange(5))
    entries = cache.take_new_entries()
    assert first[2] == 40 and len(entries) == 5 and cache.take_new_entries() == {}
    again = cache(descriptors[2], "q")(np.arange(5))
    assert again.tolist() == first.tolist() and cache.fresh_ms == 0.0
    seeded = PairCountCache(descriptors, MatchParams(0.8, 0.9), db_keys=[100, 101, 102, 103, 104],
                            known=entries)
    assert seeded(descriptors[2], "q")(np.arange(5)).tolist() == first.tolist()
    assert seeded.take_new_entries() == {}
    assert seeded.cost_ms("q", np.arange(5)) == pytest.approx(cache.cost_ms("q", np.arange(5)))
    with pytest.raises(ValueError, match="needs queries with a key"):
        cache(descriptors[2], None)
    with pytest.raises(ParameterError, match="cache holds counts for"):
        cache.check_thresholds(MatchParams(0.7, 0.9))


def test_stride_schedule_takes_every_tenth_frame_of_kitti():
    t = np.arange(108) * 0.1031  # KITTI drive 0001 runs at 9.7 Hz
    schedule = series_schedule(t, 1.0, 6, "stride")
    assert schedule[0] == [0, 10, 20, 30, 40, 50] and schedule[-1] == [57, 67, 77, 87, 97, 107]
    assert len(schedule) == 58


def test_time_schedule_takes_the_frame_nearest_each_second():
    t = np.arange(108) * 0.1031
    schedule = series_schedule(t, 1.0, 6, "time")
    assert schedule[0] == [0, 10, 19, 29, 39, 48]
    for s in schedule:
        assert np.all(np.abs(t[s] - t[s[0]] - np.arange(6)) <= 0.0516)
    with pytest.raises(ParameterError, match="sampling='daily'"):
        series_schedule(t, 1.0, 6, "daily")


def test_too_short_sequences_have_no_series():
    assert series_schedule(np.arange(5) * 0.1, 1.0, 6) == []
    assert series_schedule(np.array([0.0]), 1.0, 1) == []
