"""The camera-rate refined path: structure and global vectors stored at ingest, the fast measurement,
the store migration, and ``visloc track`` run as a user runs it (on the first frames of drive 0005)."""

from __future__ import annotations

import json
import sqlite3
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

import visloc

from helpers import DRIVE_0005, DRIVE_0005_FRAMES, KITTI_DRIVE, REPO, copy_store, mcap_topics, run_cli, write_csv_drive
from helpers import error_lines
from visloc.pose.fastpose import FastPoseMeasurer, StructureMatcher
from visloc.params import PAPER_MATCH, REFINED
from visloc.pose.refined import pose_measurement
from visloc.sources.queries import extract_queries
from visloc.retrieval.retrievers import Retrieval
from visloc.sources.opening import open_source
from visloc.stats import CHI2_2DOF_999
from visloc.pose.selfcheck import CAMERA_RATE_PARAMS, self_check_settings_json
from visloc.pose.structure import VARIANTS, ViewStructure, choose_variant, view_structures
from visloc.store.build import build_global_vectors, build_structure
from visloc.retrieval.matching import count_correspondences
from visloc.store.workspace import STORE_SCHEMA_VERSION, Workspace
from visloc.results.saved import load_run

DRIVE = DRIVE_0005
SOURCE = DRIVE + "_sync"
N_FRAMES = DRIVE_0005_FRAMES


@pytest.fixture(scope="module")
def store(store_0005) -> Path:
    """The first 40 frames of drive 0005's image_00, ingested with the CLI (features, global vectors, structure),
    shared by the run: the tests that change a store copy it."""
    return store_0005


@pytest.mark.slow
def test_stored_structure_equals_structure_computed_afresh(store):
    """Views at both ends, the middle and every eighth, computed afresh by the pure function; every view is
    rebuilt by ``build_structure`` and compared with the stored one in the migration test below."""
    ws = Workspace(store)
    db = ws.load_database(SOURCE, "image_00")
    stored = ws.load_structure(db)
    geometry = db.geometry()
    assert sorted(stored) == list(range(N_FRAMES))
    assert all(set(stored[k]) == set(VARIANTS) for k in range(N_FRAMES))
    views = sorted({0, 1, N_FRAMES // 2, N_FRAMES - 2, N_FRAMES - 1, *range(0, N_FRAMES, 8)})
    n_points = 0
    for k in views:
        for fresh in view_structures(geometry, k, REFINED):
            got = stored[k][fresh.variant]
            assert got.neighbours == fresh.neighbours and got.reason == fresh.reason
            np.testing.assert_array_equal(got.rows, fresh.rows)
            np.testing.assert_array_equal(got.points_world, fresh.points_world)  # bit for bit
            np.testing.assert_array_equal(got.cov_world, fresh.cov_world)
            n_points += len(got)
    assert n_points > 50 * len(views)  # real structure, not empty rows


def test_stored_global_vectors_are_the_stored_encoders_vectors(store):
    ws = Workspace(store)
    db = ws.load_database(SOURCE, "image_00")
    index = ws.global_vectors.load_database_index(db)
    assert index is not None and index.vectors_f32.shape[0] == N_FRAMES
    np.testing.assert_array_equal(index.vectors_f32, index.encoder.encode_many(db.descriptors_u8))


def _exact_and_fast(store: Path, query_frame: int):
    """The exact refined measurement of one query against every image, and the fast measurer given the
    same candidates in the exact path's verified order with the exact path's matches."""
    ws = Workspace(store)
    db = ws.load_database(SOURCE, "image_00")
    seq = open_source(None, drive=DRIVE, camera="image_00")
    # the frame described at half scale: other descriptors than the stored ones, the same place
    (query,) = extract_queries(seq, [query_frame], ws.sift_params.replace(image_scale=0.5))
    candidates = np.arange(len(db))
    counts = np.array([count_correspondences(query.descriptors_u8, d, PAPER_MATCH) for d in db.descriptors_u8])
    retrieval = Retrieval(candidates, counts, int(candidates[np.argmax(counts)]))
    geometry = db.geometry()
    exact = pose_measurement(query.keypoints_f32, query.descriptors_u8, retrieval, db.east_north_m, geometry,
                             seq.camera_model, REFINED)
    rank = {int(i): r for r, i in enumerate(np.argsort(-counts, kind="stable"))}
    verified = sorted(exact.candidate_inliers.items(), key=lambda kv: (-kv[1], rank[kv[0]]))
    structures = ws.load_structure(db)
    matcher = StructureMatcher(db.descriptors_u8, structures, REFINED.ratio, against="image")
    fast_candidates = np.array([i for i, _ in verified])
    counts_of = matcher(query.descriptors_u8)
    counts_of(fast_candidates)
    fast_retrieval = Retrieval(fast_candidates, np.array([n for _, n in verified]), int(fast_candidates[0]),
                               pairs=counts_of.pairs)
    measurer = FastPoseMeasurer(db.east_north_m, db.timestamps_s, geometry, structures, seq.camera_model,
                                REFINED, min_matches=REFINED.min_verified_inliers)
    return exact, measurer.measure(query, fast_retrieval)


@pytest.mark.parametrize("query_frame", [14, 26])
def test_the_fast_measurement_equals_the_exact_one_on_the_same_candidates(store, query_frame):
    exact, fast = _exact_and_fast(store, query_frame)
    assert exact.source == fast.source == "geometry", (exact.fallback_reason, fast.fallback_reason)
    assert fast.view_indices == exact.view_indices and fast.neighbour_indices == exact.neighbour_indices
    np.testing.assert_array_equal(fast.east_north_m, exact.east_north_m)
    np.testing.assert_array_equal(fast.cov_m2, exact.cov_m2)
    assert fast.n_pnp_inliers == exact.n_pnp_inliers
    # each path names its own count: essential-matrix inliers (exact), matches to stored 3D points (fast)
    assert exact.n_verified_inliers == max(exact.candidate_inliers.values()) and exact.n_structure_matches is None
    assert fast.n_structure_matches == max(fast.candidate_structure_matches.values()) and fast.n_verified_inliers is None


@pytest.mark.slow
def test_guided_matching_adds_support_at_the_same_place(store):
    """On a real frame, guided matching finds more of the query's keypoints in the same views' structure than
    the descriptor matching did, and the pose it gives stays where the unguided one was."""
    ws = Workspace(store)
    db = ws.load_database(SOURCE, "image_00")
    seq = open_source(None, drive=DRIVE, camera="image_00")
    (query,) = extract_queries(seq, [26], ws.sift_params)
    counts = np.array([count_correspondences(query.descriptors_u8, d, PAPER_MATCH) for d in db.descriptors_u8])
    allowed = np.flatnonzero(np.abs(db.frames - 26) > 10)  # the 1 s exclusion: the frame's own image is not there
    retrieval = Retrieval(allowed, counts[allowed], int(allowed[np.argmax(counts[allowed])]))
    geometry = db.geometry()
    measured = {radius: pose_measurement(query.keypoints_f32, query.descriptors_u8, retrieval, db.east_north_m,
                                         geometry, seq.camera_model, REFINED.replace(guided_radius_px=radius))
                for radius in (0.0, REFINED.guided_radius_px)}
    plain, guided = measured[0.0], measured[REFINED.guided_radius_px]
    assert plain.source == guided.source == "geometry", (plain.fallback_reason, guided.fallback_reason)
    assert guided.view_indices == plain.view_indices
    assert guided.n_pnp_inliers > plain.n_pnp_inliers, (plain.n_pnp_inliers, guided.n_pnp_inliers)
    distinct = [len(np.unique(m.inliers.query_rows)) for m in (plain, guided)]
    assert distinct[1] > distinct[0]
    assert np.linalg.norm(guided.east_north_m - plain.east_north_m) < 3 * plain.sigma_m + 0.05


def test_the_self_check_poses_every_other_image(store):
    """Ingest's self-check poses every other image of the drive (adjacent ones share their errors), and the
    store's lever gain rests on those poses."""
    ws = Workspace(store)
    ids = ws.image_ids(SOURCE, "image_00").tolist()
    assert len(ids) == N_FRAMES
    assert ws.self_checked_ids(ids, self_check_settings_json(REFINED)) == set(ids[::2])
    db = ws.load_database(SOURCE, "image_00")
    gain = ws.lever_gain(db)
    assert gain is not None and 0 < gain.n_both + gain.n_one <= len(ids[::2])
    # each pose carries its image's heading (its geotag's attitude): the gains along the road and across it
    posed = [p for p in ws.self_check_poses(db) if p.error_m is not None]
    assert posed and all(0 <= p.heading_deg < 360 for p in posed)
    assert gain.both_sides_across is not None and gain.one_side_across is not None


def test_the_camera_rate_path_has_a_self_check_and_a_gain_of_its_own(store):
    """Ingest poses the same images again as the camera-rate path poses a frame (the frame's SIFT at the track's
    scale, stored structure), and the camera-rate measurer's covariance takes the gain those poses call for,
    while the refined path keeps its own."""
    ws = Workspace(store)
    ids = ws.image_ids(SOURCE, "image_00").tolist()
    settings = self_check_settings_json(CAMERA_RATE_PARAMS, camera_rate=True)
    assert settings != self_check_settings_json(REFINED)
    assert ws.self_checked_ids(ids, settings) == set(ids[::2])
    db = ws.load_database(SOURCE, "image_00")
    fast, exact = db.camera_rate_lever_gain, db.lever_gain
    assert fast.source.startswith("camera-rate self-check") and exact.source.startswith("self-check")
    assert 0 < fast.n_both + fast.n_one <= len(ids[::2])
    assert db.geometry(camera_rate=True).lever_gain == fast and db.geometry().lever_gain == exact
    # the refined path's settings are as stores made before the camera-rate self-check keep them
    assert "path" not in json.loads(self_check_settings_json(REFINED))
    # a database without the camera-rate self-check poses the camera rate with the refined path's gain
    assert replace(db, camera_rate_lever_gain=None).geometry(camera_rate=True).lever_gain == exact


def test_variants_keep_the_excluded_images_out_of_the_structure():
    def structure(variant: str, neighbours: tuple[int, ...]) -> ViewStructure:
        return ViewStructure(10, variant, neighbours, np.array([0]), np.zeros((1, 3)), np.zeros((1, 3, 3)))

    variants = {"both": structure("both", (8, 12)), "before": structure("before", (8, 6)),
                "after": structure("after", (12, 14))}
    allowed = np.ones(20, bool)
    assert choose_variant(variants, allowed, query_after_view=True).variant == "both"
    allowed[12:16] = False  # a query at frame 13, 1 s exclusion: the view's later neighbours are out
    assert choose_variant(variants, allowed, query_after_view=True).variant == "before"
    allowed[:] = True
    allowed[7:9] = False  # a query before the view: its earlier neighbours are out
    assert choose_variant(variants, allowed, query_after_view=False).variant == "after"
    allowed[:] = False
    assert choose_variant(variants, allowed, query_after_view=False) is None


@pytest.mark.slow
def test_a_schema_3_store_migrates_keeping_every_image_and_count_and_gains_structure(store, tmp_path):
    path = copy_store(store, tmp_path / "v3")
    conn = sqlite3.connect(path)
    conn.execute("INSERT INTO pair_counts VALUES (1, 2, 0.8, 0.97, 42, 3.5)")
    for table in ("structures", "global_vectors", "arrays"):  # what schema version 3 had not
        conn.execute(f"DROP TABLE {table}")
    conn.execute("UPDATE visloc_schema SET version = 3")
    conn.commit()
    before = conn.execute("SELECT * FROM images ORDER BY id").fetchall()
    counts = conn.execute("SELECT * FROM pair_counts ORDER BY query_image_id, db_image_id").fetchall()
    conn.close()
    ws = Workspace(path)  # migrated in place
    db = ws.load_database(SOURCE, "image_00")
    assert ws.load_structure(db) == {} and ws.global_vectors.load_database_index(db) is None
    # what ingest does after SIFT, for a store that lacks it
    assert build_global_vectors(ws, SOURCE, "image_00") == N_FRAMES
    assert build_structure(ws, SOURCE, "image_00") == N_FRAMES
    assert build_structure(ws, SOURCE, "image_00") == 0  # resumes: nothing left to do
    conn = sqlite3.connect(path)
    assert conn.execute("SELECT version FROM visloc_schema").fetchone() == (STORE_SCHEMA_VERSION,)
    assert conn.execute("SELECT * FROM images ORDER BY id").fetchall() == before
    assert conn.execute("SELECT * FROM pair_counts ORDER BY query_image_id, db_image_id").fetchall() == counts
    assert conn.execute("SELECT count(*) FROM structures").fetchone() == (N_FRAMES * len(VARIANTS),)
    assert conn.execute("SELECT count(DISTINCT image_id) FROM global_vectors").fetchone() == (N_FRAMES,)
    conn.close()
    original = Workspace(store).load_structure(db)
    rebuilt = ws.load_structure(db)
    assert sorted(rebuilt) == sorted(original) == list(range(N_FRAMES))
    for k, variants in rebuilt.items():  # every view, as ingest stored it, bit for bit
        assert set(variants) == set(original[k])
        for variant, s in variants.items():
            o = original[k][variant]
            assert s.neighbours == o.neighbours and s.reason == o.reason, (k, variant)
            np.testing.assert_array_equal(s.rows, o.rows)
            np.testing.assert_array_equal(s.points_world, o.points_world)
            np.testing.assert_array_equal(s.cov_world, o.cov_world)


@pytest.mark.slow
def test_an_interrupted_structure_build_resumes_where_it_stopped(store, tmp_path):
    path = copy_store(store, tmp_path / "partial")
    conn = sqlite3.connect(path)
    conn.execute("DELETE FROM structures WHERE image_id > 25")  # as if stopped after image 25
    conn.commit()
    kept = conn.execute("SELECT image_id, variant, created_at FROM structures ORDER BY image_id, variant").fetchall()
    conn.close()
    ws = Workspace(path)
    assert build_structure(ws, SOURCE, "image_00") == N_FRAMES - 25
    conn = sqlite3.connect(path)
    again = conn.execute("SELECT image_id, variant, created_at FROM structures WHERE image_id <= 25 "
                         "ORDER BY image_id, variant").fetchall()
    assert again == kept and conn.execute("SELECT count(*) FROM structures").fetchone() == (N_FRAMES * 3,)
    conn.close()


@pytest.mark.slow
def test_track_localizes_every_frame_and_writes_its_json(store, kitti_root, tmp_path):
    out = tmp_path / "track.json"
    result = run_cli("track", kitti_root, "--drive", DRIVE, "--camera", "image_00", "--db", store,
                     "--db-source", SOURCE, "--exclusion-s", "1", "--frames", "30", "--no-follow-points", "--json", out,
                     "--mcap", tmp_path / "track.mcap")
    assert result.returncode == 0, result.stderr
    exported = mcap_topics(tmp_path / "track.mcap")  # every frame, for Foxglove
    assert len(exported["/visloc/estimate"]) == len(exported["/visloc/step"]) == 30
    assert "refined fast path" in result.stdout and "sustained" in result.stdout
    run = json.loads(out.read_text())
    assert run["frames"] == 30 and len(run["per_frame"]) == 30
    assert [f["frame"] for f in run["per_frame"]] == list(range(30))
    for key in ("latency_ms",):
        assert set(run[key]) == {"p50", "p95", "max"} and 0 < run[key]["p50"] <= run[key]["p95"] <= run[key]["max"]
    for key in ("error_m", "measurement_error_m"):
        assert {"mean", "median", "p90", "max"} <= set(run[key])
    assert run["sustained_hz"] > 0 and run["params"]["track"]["exclusion_s"] == 1.0
    frame_interval_s = float(np.median(np.diff(open_source(kitti_root, drive=DRIVE, camera="image_00").timestamps_s)))
    assert run["params"]["filter"]["dt_s"] == pytest.approx(frame_interval_s)  # the filter steps frame by frame
    frame = run["per_frame"][20]
    for key in ("sift_ms", "retrieval_ms", "geometry_ms", "filter_ms"):
        assert frame[key] >= 0
    assert frame["latency_ms"] == pytest.approx(frame["sift_ms"] + frame["retrieval_ms"] + frame["geometry_ms"]
                                                + frame["filter_ms"])
    # the refined measurement works here: most frames posed, and no view within the exclusion window
    geometry = [f for f in run["per_frame"] if f["measurement_source"] == "geometry"]
    assert len(geometry) >= 15
    # the dashboard reads it back (visloc dashboard --run): every frame, in the database's frame
    saved = load_run(out)
    db_frame = Workspace(store).load_database(SOURCE, "image_00").frame
    assert run["frame_origin_deg"] == [db_frame.origin_lat_deg, db_frame.origin_lon_deg]
    assert saved.kind == "track" and saved.n_steps == 30 and saved.frame == db_frame
    assert [s.estimate_error_m for s in saved.series[0]] == [f["error_m"] for f in run["per_frame"]]
    assert [s.truth_m for s in saved.series[0]] == [tuple(f["truth_m"]) for f in run["per_frame"]]
    assert all(abs(v - f["frame"]) >= 10 for f in geometry for v in f["view_frames"])
    assert np.median([f["measurement_error_m"] for f in geometry]) < 1.0


@pytest.mark.slow
def test_track_exact_path_runs_too(store, kitti_root, tmp_path):
    out = tmp_path / "exact.json"
    result = run_cli("track", kitti_root, "--drive", DRIVE, "--camera", "image_00", "--db", store, "--exact",
                     "--db-source", SOURCE,
                     "--exclusion-s", "1", "--frames", "2", "--stride", "10", "--json", out)
    assert result.returncode == 0, result.stderr
    run = json.loads(out.read_text())
    assert run["path"] == "exact" and [f["frame"] for f in run["per_frame"]] == [0, 10]
    frame_interval_s = float(np.median(np.diff(open_source(kitti_root, drive=DRIVE, camera="image_00").timestamps_s)))
    assert run["params"]["filter"]["dt_s"] == pytest.approx(10 * frame_interval_s)
    assert run["params"]["track"]["follow_points"] is False and run["pace_hz"] == 0  # every frame in full, at once


@pytest.mark.slow
def test_track_follows_points_by_default_the_same_run_every_time_and_the_dashboard_follows_them_alike(
        store, kitti_root, tmp_path):
    """By default a track follows points and reads each frame once the relocalization asked for before it has
    come: the run is the same every time, however busy the machine, and the engine's drive run that the dashboard's
    camera-rate mode plays (``follow_drive``, on the store's query series read again from their images) is that run."""
    out = tmp_path / "a.json"
    result = run_cli("track", kitti_root, "--drive", DRIVE, "--camera", "image_00", "--db", store,
                     "--db-source", SOURCE, "--exclusion-s", "1", "--frames", "12", "--json", out)
    assert result.returncode == 0, result.stderr
    assert "following points: frames tracked" in result.stdout and "as the relocalizations keep up" in result.stdout
    run = json.loads(out.read_text())
    assert run["params"]["track"]["follow_points"] is True and run["params"]["track"]["pace_hz"] is None
    assert run["pace_hz"] == 0 and {f["kind"] for f in run["per_frame"]} >= {"relocalized", "tracked"}

    ws = Workspace(store, read_only=True)
    db, queries = ws.load_database(SOURCE, "image_00"), ws.load_queries(SOURCE, "image_00")
    drive = visloc.open_series(kitti_root, SOURCE, "image_00")
    method = visloc.REFINED_FAST_METHOD
    matches = visloc.follow_drive(
        drive, queries, db, ws.sift_params, visloc.PAPER_RETRIEVAL.replace(exclusion_s=1.0), np.arange(12),
        filter_params=visloc.track_filter(drive, visloc.TRACK), stored=ws.load_structure(db, method.pose),
        shortlist_index=ws.global_vectors.load_database_index(db, method.shortlist))
    assert list(matches.kinds) == [f["kind"] for f in run["per_frame"]]
    assert [None if m.east_north_m is None else list(m.east_north_m) for m in matches.measurements] == \
        [f["measurement_m"] for f in run["per_frame"]]
    records = visloc.track_drive(matches, queries, db, visloc.track_filter(drive, visloc.TRACK))
    assert np.median([r.estimate_error_m for r in records]) < 0.5  # the filter re-run over them, as R and Q change


def test_a_series_is_read_again_only_from_its_own_images(kitti_root, tmp_path):
    """The dashboard follows points only on the images the store's series was made from: another drive, another
    camera or a missing root is refused in one line naming it."""
    with pytest.raises(visloc.InputError, match="not found"):
        visloc.open_series(tmp_path / "nowhere", SOURCE, "image_00")
    with pytest.raises(visloc.InputError, match="image_07"):
        visloc.open_series(kitti_root, SOURCE, "image_07")
    drive = visloc.open_series(kitti_root, SOURCE, "image_00")
    other = visloc.open_series(kitti_root, KITTI_DRIVE + "_sync", "image_00")
    assert drive.name == f"{SOURCE}/image_00"
    queries = SimpleNamespace(frames=np.array([f.frame for f in drive.frames[:5]]), name=f"{SOURCE}/image_00",
                              timestamps_s=drive.timestamps_s[:5])
    assert list(visloc.drive_indices(drive, queries)) == [0, 1, 2, 3, 4]
    with pytest.raises(visloc.InputError, match="not the ones stored"):
        visloc.drive_indices(other, queries)


def test_points_are_followed_at_the_camera_rate_only():
    """Points are followed from one frame to the next: a run over every frame follows them, one below the camera's
    rate (a query a second) or of another method localizes each query in full."""
    fast, exact = visloc.REFINED_FAST_METHOD, visloc.REFINED_METHOD
    assert visloc.follows_points(fast, [3, 4, 5, 6])
    assert not visloc.follows_points(fast, [0, 10, 20]) and not visloc.follows_points(fast, [])
    assert not visloc.follows_points(exact, [3, 4, 5, 6])


def test_track_refuses_bad_input_in_one_line_before_any_work(store, kitti_root, tmp_path):
    cases = [
        (["--json", tmp_path], "is a folder"),
        (["--json", tmp_path / "no" / "x.json"], "folder does not exist"),
        (["--query-scale", "2"], "query_image_scale"),
        (["--stride", "0"], "stride"),
    ]
    for extra, message in cases:
        result = run_cli("track", kitti_root, "--drive", DRIVE, "--camera", "image_00", "--db", store,
                         "--db-source", SOURCE, *extra)
        assert result.returncode == 2 and message in result.stderr, (extra, result.stderr)
        assert len(result.stderr.strip().splitlines()) == 1


def test_track_on_a_drive_without_calibration_says_what_is_missing(tmp_path):
    csv_path = write_csv_drive(tmp_path / "drive", n_frames=6)
    result = run_cli("track", csv_path, "--db", tmp_path / "csv.sqlite", "--workers", "1")
    assert result.returncode == 2, result.stderr
    assert "calibrat" in result.stderr and len(error_lines(result.stderr)) == 1  # after ingest's progress lines


def test_the_track_command_is_documented():
    assert "visloc track" in (REPO / "README.md").read_text()


def test_optical_flow_finds_points_of_a_shifted_real_image_again(kitti_root):
    seq = open_source(kitti_root, drive=DRIVE, camera="image_00")
    from visloc.pose.flowtrack import follow_points
    from visloc.sources.drives import load_gray
    gray = load_gray(seq.frames[0].image_path)
    shift = np.float32([[1, 0, 3.0], [0, 1, -2.0]])  # the image moved 3 px right, 2 px up
    moved = cv2.warpAffine(gray, shift, (gray.shape[1], gray.shape[0]))
    corners = cv2.goodFeaturesToTrack(gray, 200, 0.01, 10).reshape(-1, 2)
    corners = corners[(corners[:, 0] > 30) & (corners[:, 1] > 30) & (corners[:, 0] < gray.shape[1] - 30)
                      & (corners[:, 1] < gray.shape[0] - 30)]
    found, ok = follow_points(gray, moved, corners, corners)  # started where they were: the flow finds the shift
    assert ok.mean() > 0.9
    np.testing.assert_allclose(np.median(found[ok] - corners[ok], axis=0), [3.0, -2.0], atol=0.05)
    # a frame of another place: the backward check refuses most of what the forward flow claims
    other = load_gray(seq.frames[N_FRAMES - 1].image_path)
    _, ok_other = follow_points(gray, np.roll(other, 150, axis=1), corners, corners)
    assert ok_other.mean() < ok.mean() - 0.3


def _follower(store: Path):
    """(database, drive, a point follower) on the store: queries and database from image_00, 1 s exclusion, full
    localizations on the calling thread."""
    from visloc.params import PAPER_FILTER, TRACK
    from visloc.protocols.track import track_filter, track_localizer
    from visloc.tracking.follower import PointFollower
    ws = Workspace(store)
    db = ws.load_database(SOURCE, "image_00")
    seq = open_source(None, drive=DRIVE, camera="image_00")
    params = TRACK.replace(exclusion_s=1.0, follow_points=True, background_relocalization=False)
    localizer, sift = track_localizer(ws, db, seq.camera_model, track_filter(seq, params, PAPER_FILTER), params)
    return db, seq, PointFollower(localizer, db.east_north_m, db.timestamps_s, db.geometry(), seq.camera_model,
                                  localizer.measurer.params, sift, params, stored=localizer.measurer.structures)


def test_a_tracked_frame_is_posed_where_the_full_path_poses_it_within_its_covariance(store):
    """Real frames: frame 10 localized in full, its map points followed into frames 11-13 by optical flow, each
    posed against them; the full path poses the same frames on its own. Each pair agrees within their
    covariances, and the tracked pose is as close to the frame's geotag as the full one, give or take."""
    from visloc.features.sift import make_sift
    from visloc.pose.flowtrack import follow, pose_tracked
    from visloc.sources.drives import load_gray
    db, seq, follower = _follower(store)
    pose = follower.pose
    engine = make_sift(follower.sift)
    start = 10
    full = follower.relocalizer._full(load_gray(seq.frames[start].image_path), seq.timestamps_s[start], None, engine, "frame")
    points = follower.relocalizer._points(full)
    assert points is not None and len(points) >= 40
    previous = full.gray
    for k in range(start + 1, start + 4):
        gray = load_gray(seq.frames[k].image_path)
        points = follower.window.allowed(follow(points, previous, gray, seq.camera_model.K, None), seq.timestamps_s[k])
        tracked, inliers = pose_tracked(points, points.pixels_px, db.east_north_m, db.geometry(), seq.camera_model,
                                        pose)
        assert inliers is not None, tracked.fallback_reason
        again = follower.relocalizer._full(gray, seq.timestamps_s[k], None, engine, "frame").measurement
        assert again.source == "geometry"
        d = tracked.east_north_m - again.east_north_m
        assert float(d @ np.linalg.solve(tracked.cov_m2 + again.cov_m2, d)) < CHI2_2DOF_999  # 99.9 % for 2 degrees
        truth = np.asarray(db.frame.to_local(seq.frames[k].lat_deg, seq.frames[k].lon_deg), float)
        assert np.linalg.norm(tracked.east_north_m - truth) < np.linalg.norm(again.east_north_m - truth) + 0.3
        assert all(abs(db.timestamps_s[v] - seq.timestamps_s[k]) >= 1.0 for v in tracked.view_indices)
        points = points.subset(inliers.query_rows)
        previous = gray


def test_a_relocalization_guided_by_the_tracked_pose_poses_where_the_full_path_does(store):
    """Real frames: frame 10's map points followed into frame 12 and the frame posed on them; relocalized guided by
    that pose, it finds the nearest views' points where they project (no retrieval, SIFT describing only the
    keypoints there), enough of them to follow on, and is posed where the full path poses it within their
    covariances, on no view inside the exclusion window."""
    from visloc.features.sift import make_sift
    from visloc.pose.flowtrack import follow
    from visloc.sources.drives import load_gray
    from visloc.tracking.relocalize import GUIDED

    db, seq, follower = _follower(store)
    follower.params = follower.params.replace(guided_relocalization=True)
    engine = make_sift(follower.sift)
    full = follower.relocalizer._full(load_gray(seq.frames[10].image_path), seq.timestamps_s[10], None, engine, "frame")
    points, previous = follower.relocalizer._points(full), full.gray
    for k in (11, 12):
        gray = load_gray(seq.frames[k].image_path)
        points = follower.window.allowed(follow(points, previous, gray, seq.camera_model.K, None), seq.timestamps_s[k])
        previous = gray
    t_s = seq.timestamps_s[12]
    tracked, kept, _ = follower._pose(points, t_s, None)
    assert kept is not None, tracked.fallback_reason
    done = follower._relocalize(previous, t_s, None, (engine, make_sift(follower.sift.replace(n_features=0))), "frame",
                                kept)
    assert done.how == GUIDED and done.full.retrieval_ms == 0 and not len(done.full.retrieval.candidates)
    guided = done.full.measurement
    again = follower.relocalizer.relocalize(previous, t_s, None, engine, "frame")
    assert guided.source == again.full.measurement.source == "geometry"
    assert done.points.n_tracks >= follower.params.min_followed_points
    d = guided.east_north_m - again.full.measurement.east_north_m
    assert float(d @ np.linalg.solve(guided.cov_m2 + again.full.measurement.cov_m2, d)) < CHI2_2DOF_999
    assert all(abs(db.timestamps_s[v] - t_s) >= 1.0 for v in np.unique(done.points.view_of))


def test_a_frame_followed_on_a_few_image_tracks_is_not_posed_however_many_views_repeat_them(store):
    """Real frames: frame 10's map points followed into frame 11 and linked into the views nearest it, so that one
    keypoint meets its map point in several views' structure. On every track the frame is posed; on the ten tracks
    with most views, more 2D-3D pairs than a pose needs but fewer keypoints, it is not, and says why."""
    from visloc.features.sift import make_sift
    from visloc.pose.flowtrack import follow, pose_tracked
    from visloc.sources.drives import load_gray
    db, seq, follower = _follower(store)
    pose = follower.pose
    full = follower.relocalizer._full(load_gray(seq.frames[10].image_path), seq.timestamps_s[10], None, make_sift(follower.sift),
                          "frame")
    t_s = seq.timestamps_s[11]
    followed = follow(follower.relocalizer._points(full), full.gray, load_gray(seq.frames[11].image_path), seq.camera_model.K, None)
    points = follower.window.allowed(follower._linked(follower.window.allowed(followed, t_s), t_s, None), t_s)
    tracked, inliers = pose_tracked(points, points.pixels_px, db.east_north_m, db.geometry(), seq.camera_model, pose)
    assert inliers is not None, tracked.fallback_reason
    tracks, views_per_track = np.unique(points.track_of, return_counts=True)
    few = tracks[np.argsort(-views_per_track, kind="stable")[:10]]
    thin = points.subset(np.isin(points.track_of, few))
    assert thin.n_tracks == 10 and len(thin) >= pose.min_pnp_inliers  # a count of pairs would let it pose
    tracked, inliers = pose_tracked(thin, thin.pixels_px, db.east_north_m, db.geometry(), seq.camera_model, pose)
    assert inliers is None and tracked.east_north_m is None
    assert "image tracks among the PnP inliers" in tracked.fallback_reason


@pytest.mark.slow
def test_track_following_points_splits_its_frames_and_is_reproducible_without_a_background_thread(
        store, kitti_root, tmp_path):
    runs = []
    for name in ("a", "b"):
        out = tmp_path / f"{name}.json"
        result = run_cli("track", kitti_root, "--drive", DRIVE, "--camera", "image_00", "--db", store,
                         "--db-source", SOURCE, "--exclusion-s", "1", "--frames", "25", "--follow-points",
                         "--no-background-relocalization", "--no-guided-relocalization", "--json", out)
        assert result.returncode == 0, result.stderr
        assert "following points: frames tracked" in result.stdout and "of one core" in result.stdout
        assert "relocalizations: " in result.stdout and "guided" not in result.stdout  # full ones, as asked
        runs.append(json.loads(out.read_text()))
    run = runs[0]
    kinds = [f["kind"] for f in run["per_frame"]]
    assert kinds[0] == "relocalized" and "tracked" in kinds and set(kinds) <= {"tracked", "relocalized"}
    assert run["kinds"]["tracked"]["frames"] + run["kinds"]["relocalized"]["frames"] == 25
    assert 0 < run["cpu_share_of_one_core"] and run["params"]["track"]["follow_points"] is True
    for f in run["per_frame"]:
        if f["kind"] == "tracked":
            assert f["sift_ms"] == 0 and f["followed_points"] >= 15
            # the wall time from the image read to the filter step: the flow, the pose and the filter in it
            assert f["latency_ms"] >= f["flow_ms"] + f["geometry_ms"] + f["filter_ms"] - 1e-6
        if f["measurement_source"] == "geometry":  # no view inside the exclusion window, tracked or not
            assert all(abs(v - f["frame"]) >= 10 for v in f["view_frames"])
    assert [f["estimate_m"] for f in run["per_frame"]] == [f["estimate_m"] for f in runs[1]["per_frame"]]
    assert np.median([f["error_m"] for f in run["per_frame"]]) < 1.0
    assert load_run(tmp_path / "a.json").n_steps == 25  # the dashboard plays it like any track run


@pytest.mark.slow
def test_track_relocalizes_guided_by_the_tracked_pose_by_default_and_says_how_many(store, kitti_root, tmp_path):
    out = tmp_path / "guided.json"
    result = run_cli("track", kitti_root, "--drive", DRIVE, "--camera", "image_00", "--db", store, "--db-source", SOURCE,
                     "--exclusion-s", "1", "--frames", "14", "--no-background-relocalization", "--json", out)
    assert result.returncode == 0, result.stderr
    run = json.loads(out.read_text())
    guided = [f for f in run["per_frame"] if f["relocalized_by"] == "guided"]
    assert guided and run["relocalizations"]["guided"] == len(guided) and run["params"]["track"]["guided_relocalization"]
    assert f"{len(guided)} guided by the tracked pose" in result.stdout
    assert all(f["relocalization_ms"]["retrieval_ms"] == 0 < f["relocalization_ms"]["sift_ms"] for f in guided)
    assert run["per_frame"][0]["relocalized_by"] == "full"  # the first frame has no pose to be guided by
    assert np.median([f["error_m"] for f in run["per_frame"]]) < 1.0


@pytest.mark.slow
def test_a_frame_that_loses_its_points_is_predicted_while_the_relocalization_beside_it_is_held(store, monkeypatch):
    """Real frames of drive 0005 followed with the relocalization beside the tracker, every relocalization in that
    thread held until frame 14 is out, and frames 12-14 dark (a camera blinded for a moment): the dark frames are
    not posed and do not wait, the filter predicts them, and the run goes on to its last frame once the
    relocalizations are let go."""
    import threading

    import visloc.tracking.follower as follower_module
    from visloc.params import PAPER_FILTER, TRACK
    from visloc.protocols.track import track_filter, track_localizer
    from visloc.tracking.follower import PREDICTED, PointFollower

    class HeldFollower(PointFollower):
        gate = threading.Event()

        def _relocalize(self, *args, **kwargs):
            if threading.current_thread() is not threading.main_thread():  # the thread beside the tracker
                assert self.gate.wait(timeout=120)
            return super()._relocalize(*args, **kwargs)

    ws = Workspace(store)
    db = ws.load_database(SOURCE, "image_00")
    seq = open_source(None, drive=DRIVE, camera="image_00")
    params = TRACK.replace(exclusion_s=1.0, follow_points=True, background_relocalization=True, max_lost_wait_ms=0.0,
                           pace_hz=0.0)  # as fast as possible: the frames do not wait for the relocalization
    localizer, sift = track_localizer(ws, db, seq.camera_model, track_filter(seq, params, PAPER_FILTER), params)
    follower = HeldFollower(localizer, db.east_north_m, db.timestamps_s, db.geometry(), seq.camera_model,
                            localizer.measurer.params, sift, params, stored=localizer.measurer.structures)
    dark = {str(seq.frames[k].image_path) for k in (12, 13, 14)}
    real_load = follower_module.load_gray
    monkeypatch.setattr(follower_module, "load_gray",
                        lambda path: np.zeros_like(real_load(path)) if str(path) in dark else real_load(path))
    steps = []
    for step in follower.steps(seq, range(DRIVE_0005_FRAMES)):
        steps.append(step)
        if len(steps) == 15:
            assert not follower.gate.is_set()  # frames 12-14 came out while every relocalization was held
            follower.gate.set()
    assert len(steps) == DRIVE_0005_FRAMES
    for k in (12, 13, 14):
        s = steps[k]
        assert s.kind == PREDICTED and s.result.measurement_m is None, (k, s.kind)
        assert s.result.filter.innovation is None and np.allclose(s.result.filter.x, s.result.filter.x_prior)
    assert {s.kind for s in steps} <= {"tracked", "relocalized", PREDICTED} and steps[0].kind == "relocalized"
    assert all(np.all(np.isfinite(s.result.filter.x[:2])) for s in steps)


@pytest.mark.slow
def test_a_frame_left_with_nothing_to_follow_by_a_relocalization_that_found_nothing_is_predicted(store):
    """Real frames of drive 0005 with the relocalization beside the tracker; while the camera is blinded (frames
    8-16) no followed point is found again and every full localization comes back with no points. The frames after
    the first blinded one have nothing to follow; they wait for the relocalization under way, which brings nothing,
    and are predicted instead of failing; the run goes on to its last frame, posed again once the camera sees."""
    from visloc.params import PAPER_FILTER, TRACK
    from visloc.pose.measurement import Measurement
    from visloc.protocols.track import track_filter, track_localizer
    from visloc.tracking.follower import PREDICTED, PointFollower

    ws = Workspace(store)
    db = ws.load_database(SOURCE, "image_00")
    seq = open_source(None, drive=DRIVE, camera="image_00")
    blind = {float(seq.timestamps_s[k]) for k in range(8, 17)}

    class Blinded(PointFollower):
        def _relocalize(self, gray, timestamp_s, *args, **kwargs):
            done = super()._relocalize(gray, timestamp_s, *args, **kwargs)
            return replace(done, points=None) if float(timestamp_s) in blind else done

        def _linked(self, points, timestamp_s, displacement_m):
            if float(timestamp_s) in blind:  # the flow finds none of them again
                return points.subset(np.zeros(len(points), bool))
            return super()._linked(points, timestamp_s, displacement_m)

        def _pose(self, points, *args):
            if self.now in blind:
                return Measurement(None, None, None, fallback_reason="tracked points: no pose"), None, False
            return super()._pose(points, *args)

    params = TRACK.replace(exclusion_s=1.0, follow_points=True, background_relocalization=True,
                           max_lost_wait_ms=10_000.0, pace_hz=0.0)
    localizer, sift = track_localizer(ws, db, seq.camera_model, track_filter(seq, params, PAPER_FILTER), params)
    follower = Blinded(localizer, db.east_north_m, db.timestamps_s, db.geometry(), seq.camera_model,
                       localizer.measurer.params, sift, params, stored=localizer.measurer.structures)
    steps = []
    follower.now = float(seq.timestamps_s[0])
    for k, step in enumerate(follower.steps(seq, range(DRIVE_0005_FRAMES))):
        steps.append(step)
        follower.now = float(seq.timestamps_s[min(k + 1, DRIVE_0005_FRAMES - 1)])
    assert len(steps) == DRIVE_0005_FRAMES
    assert [s.kind for s in steps[8:17]] == [PREDICTED] * 9
    # frames that had nothing to follow, the relocalization they waited for bringing nothing
    assert all(s.followed_points == 0 for s in steps[9:17])
    assert any(s.kind == "tracked" for s in steps[17:])
    assert all(np.all(np.isfinite(s.result.filter.x[:2])) for s in steps)


def test_a_first_fix_refuses_a_lone_far_candidate():
    from visloc.pose.measurement import Measurement
    from visloc.tracking.localizer import first_fix
    db_en = np.array([[0.0, 0], [1, 0], [2, 0], [3, 0], [80, 0]])
    retrieval = Retrieval(np.arange(5), np.array([30, 28, 27, 25, 40]), 4)
    lone = Measurement(db_en[4], None, "geotag", fallback_reason="no pose")
    fixed = first_fix(lone, retrieval, db_en)
    np.testing.assert_allclose(fixed.east_north_m, [2.0, 0.0])
    assert "first fix" in fixed.fallback_reason
    near = Measurement(db_en[0], None, "geotag", fallback_reason="no pose")
    assert first_fix(near, Retrieval(np.arange(5), np.array([40, 28, 27, 25, 3]), 0), db_en) is near
    posed = Measurement(db_en[4], np.eye(2), "geometry")
    assert first_fix(posed, retrieval, db_en) is posed


def test_a_camera_rate_track_runs_one_blas_thread_and_gives_the_process_its_threads_back(store, kitti_root):
    """BLAS's own threads made the camera-rate path no faster and, waiting between frames, took a large part of a
    core; the run holds BLAS to one thread while it steps and hands back what the process had."""
    from threadpoolctl import threadpool_info

    from visloc.params import TRACK
    from visloc.protocols.track import run_track, track_filter, track_localizer

    def blas_threads() -> list[int]:
        return [i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"]

    before = blas_threads()
    seq = open_source(kitti_root, drive=DRIVE, camera="image_00")
    ws = Workspace(store, read_only=True)
    db = ws.load_database(SOURCE, "image_00")
    params = TRACK.replace(fast=True, exclusion_s=1.0)
    localizer, sift = track_localizer(ws, db, seq.camera_model, track_filter(seq, params), params)
    during: list[list[int]] = []
    run = run_track(localizer, seq, sift, db, params, indices=[0, 1, 2],
                    progress=lambda done, total: during.append(blas_threads()))
    assert len(run.frames) == 3 and len(during) == 3
    assert all(set(threads) == {1} for threads in during), during
    assert blas_threads() == before


def test_a_tracked_frame_asks_for_new_points_when_nearer_views_serve():
    """Every reason the followed points stop serving, and the nearer views: a frame whose points stand farther
    from their views than a full localization's would asks for new ones."""
    from visloc.pose.flowtrack import needs_relocalization

    limits = dict(min_points=40, min_cells=4, max_lever_m=15.0, max_sigma_m=1.0, every_frames=10,
                  max_lever_excess_m=1.0)
    serving = dict(n_points=200, cells_occupied=9, lever_m=6.0, estimate_sigma_m=0.2, frames_since_full=3)
    assert needs_relocalization(**serving, **limits, nearest_view_m=5.5) is None
    assert needs_relocalization(**serving, **limits) is None  # no view nearer known
    far = needs_relocalization(**serving, **limits, nearest_view_m=4.5)
    assert far is not None and "6.0 m from the nearest view of its points" in far and "4.5 m away" in far
    for change, words in (({"n_points": 39}, "39 points followed"), ({"cells_occupied": 3}, "3 of 16 image cells"),
                          ({"lever_m": 15.5}, "more than 15 m"), ({"estimate_sigma_m": 1.5}, "estimate sigma"),
                          ({"frames_since_full": 10}, "10 frames since")):
        assert words in needs_relocalization(**{**serving, **change}, **limits, nearest_view_m=5.5)
    # posed on views behind it only: it asks once enough frames have passed, and not before, nor when told never
    behind = dict(serving, views_ahead=False)
    assert "views behind it only, 3 frames since" in needs_relocalization(**behind, **limits, behind_only_every_frames=2)
    assert needs_relocalization(**behind, **limits, behind_only_every_frames=4) is None
    assert needs_relocalization(**behind, **limits, behind_only_every_frames=0) is None
    assert needs_relocalization(**serving, **limits, behind_only_every_frames=2) is None  # a view ahead: it serves
