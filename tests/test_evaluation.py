"""The evaluation protocol end to end on a synthetic drive with a known answer."""

import json

import numpy as np
import pytest

from visloc import (PAPER_FILTER, MatchParams, PairCountCache, RetrievalParams, STORE_SIFT, Workspace, evaluate,
                    ingest_sequence, open_csv)
from visloc.results.report import (PAPER_DATABASE, PAPER_QUERIES, evaluation_json, save_error_plot, series_tables, summary_text,
                           write_json)

from helpers import copy_store


@pytest.fixture(scope="module")
def drives(csv_pair, tmp_path_factory):
    """The shared synthetic pair (14 frames each), both drives in a store of this module's own."""
    tmp = tmp_path_factory.mktemp("eval")
    ws = Workspace(copy_store(csv_pair.store, tmp))
    ingest_sequence(ws, open_csv(csv_pair.query_csv), STORE_SIFT, workers=1)  # as visloc ingest made the pair's store
    return tmp, ws, ws.load_database("dbdrive", "camera"), ws.load_queries("querydrive", "camera", STORE_SIFT)


def test_every_series_finds_its_own_frame_without_exclusion(drives):
    _, _, db, queries = drives
    result = evaluate(queries, db, MatchParams(), RetrievalParams(), PAPER_FILTER, n_steps=3)
    # 14 frames at 2 Hz, a query every second (stride 2), 3 steps: starts 0..9
    assert [s[0].query_frame for s in result.series] == list(range(10))
    for series in result.series:
        assert [r.best_db_frame for r in series] == [r.query_frame for r in series]
    summary = result.summary()
    assert summary["n_series"] == 10 and summary["steps"] == ["t-2", "t-1", "t"]
    assert max(summary["measurement_error_m"]) < 0.01
    # the vehicle moves 2 m per query; a constant-velocity filter fed exact positions stays within centimetres
    assert summary["final_error_m"]["mean"] < 0.2
    assert summary["latency_ms"]["p50"] > 0
    assert summary["best_match_offset_s"]["median"] == pytest.approx(0.0)
    assert max(summary["nearest_candidate_error_m"]) < 0.01


def test_exclusion_pushes_the_match_to_a_neighbour(drives):
    _, _, db, queries = drives
    result = evaluate(queries, db, MatchParams(), RetrievalParams(exclusion_s=0.5), PAPER_FILTER, n_steps=3)
    offsets = [abs(r.best_offset_s) for s in result.series for r in s]
    assert min(offsets) >= 0.5
    # the neighbouring frame 0.5 s away shares most of the view: 1 m off
    assert np.mean(result.summary()["measurement_error_m"]) == pytest.approx(1.0, abs=0.05)
    # and that is the floor: no allowed image is closer to the truth
    np.testing.assert_allclose(result.summary()["nearest_candidate_error_m"], 1.0, atol=0.05)


def test_cached_counts_give_identical_results(drives):
    _, ws, db, queries = drives
    match = MatchParams(tau1=0.79)  # thresholds no other test caches counts for
    cold = ws.pair_cache(db, queries, match)
    first = evaluate(queries, db, match, RetrievalParams(), PAPER_FILTER, n_steps=3, cache=cold)
    assert ws.save_pair_counts(cold) > 0
    warm = ws.pair_cache(db, queries, match)
    second = evaluate(queries, db, match, RetrievalParams(), PAPER_FILTER, n_steps=3, cache=warm)
    assert warm.take_new_entries() == {}
    for a, b in zip(first.series, second.series):
        assert [r.best_db_frame for r in a] == [r.best_db_frame for r in b]
        assert [r.estimate_error_m for r in a] == [r.estimate_error_m for r in b]


def test_reports_are_written(drives, tmp_path):
    _, _, db, queries = drives
    result = evaluate(queries, db, MatchParams(), RetrievalParams(), PAPER_FILTER, n_steps=3, start_indices=[2])
    summary = result.summary()
    text = summary_text(summary)
    assert "final estimate error (m)" in text and "series evaluated: 1" in text
    assert "paper on this drive" not in text  # not the paper's drive: no comparison
    # on the paper's drive and protocol, its numbers (Table 3's measurement errors, averaged, and Figure 4's)
    paper = {**summary, "params": {**summary["params"], "database": PAPER_DATABASE, "queries": PAPER_QUERIES}}
    assert ("the paper on this drive and protocol (its Table 3 and Figure 4): measurement about 18 m (Haversine), "
            "final estimate 1.85 m") in summary_text(paper).splitlines()
    tables = series_tables(result.series[0], db.frame)
    assert "Table 2" in tables and "Table 3" in tables and tables.count("\n") > 10
    write_json(tmp_path / "r.json", evaluation_json(result))
    loaded = json.loads((tmp_path / "r.json").read_text())
    first = loaded["series"][0][0]
    assert first["query_frame"] == 2
    # positions leave the engine as latitude and longitude: the truth is the query's own geotag
    assert (first["truth_lat_deg"], first["truth_lon_deg"]) == (queries.lat_deg[2], queries.lon_deg[2])
    assert abs(first["estimate_lat_deg"] - queries.lat_deg[2]) < 1e-6 and "truth_m" not in first
    save_error_plot(summary, tmp_path / "r.png", "test")
    assert (tmp_path / "r.png").read_bytes()[:4] == b"\x89PNG"


def test_a_cache_for_other_thresholds_is_refused(drives):
    from visloc.errors import ParameterError

    _, _, db, queries = drives
    cache = PairCountCache(db.descriptors_u8, MatchParams(tau1=0.7))
    with pytest.raises(ParameterError, match="cache holds counts for"):
        evaluate(queries, db, MatchParams(), RetrievalParams(), PAPER_FILTER, n_steps=3, cache=cache)


def test_a_truth_that_is_no_fix_is_held_to_the_unknown_accuracy_and_not_to_the_map():
    """A query whose recorded geotag states no accuracy where its drive's others do (an OXTS record KITTI filled
    in) is not the receiver's fix: its own error counts beside the measurement's, and it does not share the map's."""
    from visloc.params import REFINED
    from visloc.protocols.records import QueryTruth

    frames, coords = np.arange(3), np.zeros(3)
    truth = QueryTruth(frames, coords, coords, np.array([np.nan, 0.05, 0.05]), shares_map=True)
    assert (truth.sigma(0), truth.shares_map_at(0)) == (REFINED.geotag_sigma_m, False)
    assert (truth.sigma(1), truth.shares_map_at(1)) == (0.05, True)
    alike = QueryTruth(frames, coords, coords, np.full(3, np.nan), shares_map=True)  # a drive stating none
    assert (alike.sigma(0), alike.shares_map_at(0)) == (None, True)
    other = QueryTruth(frames, coords, coords, np.array([np.nan, 0.05, 0.05]), shares_map=False)
    assert other.shares_map_at(1) is False
    # a run that assumes another accuracy for geotags stating none holds such a truth to that one
    assert QueryTruth(frames, coords, coords, np.array([np.nan, 0.05, 0.05]), True, unstated_sigma_m=2.5).sigma(0) == 2.5


def test_one_rule_holds_every_position_to_its_truth():
    """The NEES of a measurement and of an estimate, in evaluations and camera-rate runs alike: the covariance
    alone where the truth shares the map's receiver, else with the map's and the truth's errors added."""
    from visloc.protocols.records import nees_against_truth, truth_extra_m2

    assert truth_extra_m2(0.3, 0.1, truth_shares_map=True) == 0.0
    assert truth_extra_m2(0.3, 0.1, truth_shares_map=False) == pytest.approx(0.1)
    assert truth_extra_m2(None, float("nan"), truth_shares_map=False) == 0.0
    cov = np.diag([0.04, 0.01])
    assert nees_against_truth([0.2, 0.1], cov, [0.0, 0.0], 0.0) == pytest.approx(2.0)
    assert nees_against_truth([0.2, 0.1], cov, [0.0, 0.0], 0.01) == pytest.approx(0.04 / 0.05 + 0.01 / 0.02)
    assert nees_against_truth(None, cov, [0.0, 0.0], 0.0) is None
    assert nees_against_truth([np.nan, 0.0], cov, [0.0, 0.0], 0.0) is None
    assert nees_against_truth([0.2, 0.1], None, [0.0, 0.0], 0.0) is None
