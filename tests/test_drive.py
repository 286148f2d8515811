"""Whole-drive runs (what the dashboard shows), the store facade, figures and the job runner,
on a synthetic drive with a known answer."""

import threading
import time

import numpy as np
import pytest

from visloc import (
    ingest_sequence,
    PAPER_FILTER,
    PAPER_METHOD,
    FilterParams,
    InputError,
    MatchCancelled,
    MatchParams,
    ParameterError,
    RetrievalParams,
    STORE_SIFT,
    Workspace,
    build_localizer,
    correspondence_figure,
    covariance_ellipse_m,
    drive_query_indices,
    drive_summary,
    match_drive,
    open_csv,
    run_filter,
    track_drive,
)

from helpers import copy_store


@pytest.fixture(scope="module")
def workspace(csv_pair, tmp_path_factory):
    """The shared synthetic pair (14 frames each), both drives in a store of this module's own."""
    ws = Workspace(copy_store(csv_pair.store, tmp_path_factory.mktemp("drive")))
    ingest_sequence(ws, open_csv(csv_pair.query_csv), STORE_SIFT, workers=1)  # as visloc ingest made the pair's store
    return ws, ws.load_database("dbdrive", "camera"), ws.load_queries("querydrive", "camera")


def test_query_indices_follow_start_and_interval():
    t = 1000.0 + np.arange(20) / 2.0  # 2 Hz, 9.5 s
    assert drive_query_indices(t, 0.0, 1.0).tolist() == list(range(0, 20, 2))
    assert drive_query_indices(t, 1.5, 1.0).tolist() == list(range(3, 20, 2))
    assert drive_query_indices(t, 0.0, 0.5).tolist() == list(range(20))
    assert drive_query_indices(t, 0.0, 0.1).tolist() == list(range(20))  # never finer than a frame
    with pytest.raises(ParameterError, match=r"start_s=12: after the end of the drive \(9.5 s long\)"):
        drive_query_indices(t, 12.0, 1.0)
    with pytest.raises(ParameterError, match="interval_s"):
        drive_query_indices(t, 0.0, 0.0)


def test_workspace_describes_the_store(workspace):
    ws, db, queries = workspace
    names = [d.name for d in ws.drives()]
    assert names == ["dbdrive/camera", "querydrive/camera"]
    assert all(d.n_images == 14 and d.duration_s == pytest.approx(6.5) for d in ws.drives())
    assert ws.sift_params == STORE_SIFT  # a new store, made by visloc ingest
    assert len(queries.keypoints_f32) == 14 and queries.keypoints_f32[0].shape[1] == 6
    assert np.allclose(queries.heading_deg, 90.0)


def test_workspace_refuses_bad_files_with_their_name(tmp_path):
    with pytest.raises(InputError, match=r"missing.sqlite: database file does not exist"):
        Workspace(tmp_path / "missing.sqlite")
    bad = tmp_path / "notes.sqlite"
    bad.write_text("hello")
    with pytest.raises(InputError, match=r"notes.sqlite: not a SQLite database"):
        Workspace(bad)
    assert bad.read_text() == "hello"


def test_match_then_track_equals_the_localizer(workspace):
    ws, db, queries = workspace
    match, retrieval = MatchParams(), RetrievalParams(exclusion_s=0.5)
    indices = drive_query_indices(queries.timestamps_s, 0.0, 1.0)
    matches = match_drive(queries, db, match, retrieval, indices)
    records = track_drive(matches, queries, db, PAPER_FILTER)
    loc = build_localizer(PAPER_METHOD, db, match, retrieval, PAPER_FILTER)
    for k, q in enumerate(indices):
        result = loc.step(queries.query(q))
        assert records[k].best_db_frame == db.images[result.best_index].frame
        np.testing.assert_array_equal(records[k].estimate_m, result.filter.x[:2])  # metres, not degrees
        np.testing.assert_allclose(records[k].estimate_cov_m2, result.filter.position_cov_m2)
    # the exclusion holds and the neighbour 0.5 s away is 1 m off
    assert all(abs(r.best_offset_s) >= 0.5 for r in records)
    summary = drive_summary(records)
    assert summary["n_steps"] == 7 and summary["steps_without_measurement"] == 0
    assert 0.9 < summary["mean_measurement_error_m"] < 1.1


def test_refiltering_changes_estimates_not_measurements(workspace):
    _, db, queries = workspace
    indices = drive_query_indices(queries.timestamps_s, 0.0, 1.0)
    matches = match_drive(queries, db, MatchParams(), RetrievalParams(exclusion_s=0.5), indices)
    a = track_drive(matches, queries, db, PAPER_FILTER)
    b = track_drive(matches, queries, db, FilterParams(meas_var_m2=0.01))
    assert [r.measurement_error_m for r in a] == [r.measurement_error_m for r in b]
    assert [r.estimate_error_m for r in a] != [r.estimate_error_m for r in b]
    # with R tiny, the estimate follows the measurement
    assert b[-1].estimate_error_m == pytest.approx(b[-1].measurement_error_m, abs=0.05)


def test_cancelled_matching_stops_and_keeps_its_counts(workspace):
    ws, db, queries = workspace
    match = MatchParams(tau1=0.75)
    cache = ws.pair_cache(db, queries, match)
    calls = []

    def cancelled() -> bool:
        calls.append(1)
        return len(calls) > 3

    with pytest.raises(MatchCancelled):
        match_drive(queries, db, match, RetrievalParams(), [0, 2, 4], cache=cache, cancelled=cancelled)
    computed = len(cache.take_new_entries())
    assert computed == 12  # three groups of four pairs before the fourth check said stop
    assert ws.save_pair_counts(cache) == 0


def test_pair_counts_persist_through_the_workspace(workspace):
    ws, db, queries = workspace
    match = MatchParams(tau1=0.7)
    cache = ws.pair_cache(db, queries, match)
    first = match_drive(queries, db, match, RetrievalParams(), [0, 2], cache=cache)
    assert ws.save_pair_counts(cache) > 0
    again = ws.pair_cache(db, queries, match)
    second = match_drive(queries, db, match, RetrievalParams(), [0, 2], cache=again)
    assert again.take_new_entries() == {}  # everything came from the store
    for r1, r2 in zip(first.retrievals, second.retrievals):
        assert r1.best_index == r2.best_index and np.array_equal(r1.counts, r2.counts)
    with pytest.raises(ParameterError, match="cache holds counts"):
        match_drive(queries, db, MatchParams(), RetrievalParams(), [0], cache=again)


def test_covariance_ellipse_has_the_right_radii():
    cov = np.array([[9.0, 0.0], [0.0, 1.0]])  # sigma 3 m east, 1 m north
    pts = covariance_ellipse_m(np.array([10.0, -5.0]), cov, n_sigma=2.0, n_points=360)
    d = pts - [10.0, -5.0]
    assert np.abs(d[:, 0]).max() == pytest.approx(6.0, abs=1e-3)
    assert np.abs(d[:, 1]).max() == pytest.approx(2.0, abs=1e-3)
    # every point satisfies d^T cov^-1 d = n_sigma^2
    np.testing.assert_allclose(np.einsum("ni,ij,nj->n", d, np.linalg.inv(cov), d), 4.0)
    step = run_filter([np.zeros(2)], PAPER_FILTER)[0]
    assert covariance_ellipse_m(np.zeros(2), step.position_cov_m2).shape == (48, 2)
    with pytest.raises(ValueError, match="2x2"):
        covariance_ellipse_m(np.zeros(2), np.eye(3))


def test_correspondence_figure_stacks_the_images_and_draws_lines():
    top = np.full((50, 80), 40, np.uint8)
    bottom = np.full((50, 80), 200, np.uint8)
    q = np.array([[10.0, 10.0], [70.0, 40.0]])
    d = np.array([[10.0, 10.0], [60.0, 20.0]])
    fig = correspondence_figure(top, bottom, q, d)
    assert fig.shape == (100, 80, 3) and fig.dtype == np.uint8
    # the line of the first pair runs straight down x = 10 through both images
    column = fig[15:55, 10].astype(int)
    assert np.all(np.abs(column - [40, 40, 40]).sum(axis=1)[:30] > 30)
    assert np.all(fig[5, 40] == 40) and np.all(fig[95, 40] == 200)  # untouched pixels keep their gray
    assert correspondence_figure(top, bottom, q, d, width_px=40).shape == (50, 40, 3)
    with pytest.raises(ValueError, match="differ in shape"):
        correspondence_figure(top, bottom, q, d[:1])


def test_latest_job_supersedes_older_ones():
    from visloc.dashboard.jobs import LatestJobRunner

    errors, finished, stopped = [], [], []
    runner = LatestJobRunner(on_error=lambda name, exc: errors.append((name, str(exc))))
    started, all_submitted = threading.Event(), threading.Event()

    def slow(cancelled):
        started.set()
        all_submitted.wait(5)
        while not cancelled():
            time.sleep(0.01)
        stopped.append("slow")

    runner.submit("slow", slow)
    started.wait(5)
    runner.submit("queued", lambda cancelled: finished.append("queued"))  # superseded before it runs
    runner.submit("latest", lambda cancelled: finished.append("latest"))
    runner.submit("broken", lambda cancelled: 1 / 0)
    all_submitted.set()
    assert runner.wait_idle(10)
    # the running job saw it was superseded; the queued ones never ran; only the newest did
    assert stopped == ["slow"] and finished == []
    assert errors == [("broken", "division by zero")]
    runner.submit("after", lambda cancelled: finished.append("after"))
    assert runner.wait_idle(10) and finished == ["after"]
    runner.shutdown()
