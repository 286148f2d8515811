"""A store built at a lower SIFT contrast threshold serves a higher one: its features selected by their
response are the ones SIFT finds at the higher threshold, so the paper's method reads its own features
from a denser store. Checked on real KITTI frames against the session's store (built at the default)."""

import numpy as np
import pytest

import visloc

from visloc import PAPER_SIFT, Workspace
from visloc.features.sift import contrast_kept
from visloc.retrieval.matching import count_correspondences
from visloc.params import PAPER_MATCH
from helpers import KITTI_DRIVE, copy_store, run_cli

pytestmark = [pytest.mark.slow]

DENSE_CONTRAST = 0.02
N_FRAMES = 3
SOURCE = f"{KITTI_DRIVE}_sync"


@pytest.fixture(scope="module")
def dense_store(kitti_root, tmp_path_factory):
    """The drive's first frames of the left camera, described at half the default contrast threshold."""
    store = tmp_path_factory.mktemp("dense") / "dense.sqlite"
    result = run_cli("ingest", kitti_root, "--drive", KITTI_DRIVE, "--camera", "image_00", "--db", store,
                     "--limit", str(N_FRAMES), "--features-only", "--sift-contrast", str(DENSE_CONTRAST),
                     "--workers", "1", timeout=600)
    assert result.returncode == 0, result.stderr
    return store


def test_the_selected_features_are_the_ones_sift_finds_at_the_higher_threshold(dense_store, kitti_evaluation):
    folder, _, _ = kitti_evaluation
    dense = Workspace(dense_store, read_only=True)
    selected = dense.load_queries(SOURCE, "image_00", PAPER_SIFT)
    as_stored = dense.load_queries(SOURCE, "image_00")
    reference = Workspace(folder / "kitti.sqlite", read_only=True).load_queries(SOURCE, "image_00")
    assert selected.selected_contrast == PAPER_SIFT.contrast_threshold and as_stored.selected_contrast is None
    for k in range(N_FRAMES):
        ref_kp, sel_kp = reference.keypoints_f32[k], selected.keypoints_f32[k]
        assert len(as_stored.keypoints_f32[k]) > 1.3 * len(ref_kp)  # the lower threshold finds many more
        # every keypoint SIFT keeps at the default threshold is among the selected ones, descriptor and all ...
        ref_rows = {tuple(r) for r in np.c_[ref_kp[:, :4], reference.descriptors_u8[k]].tolist()}
        sel_rows = {tuple(r) for r in np.c_[sel_kp[:, :4], selected.descriptors_u8[k]].tolist()}
        assert ref_rows <= sel_rows
        # ... and only a few more (extrema the higher threshold skips before refining them)
        assert len(sel_rows) - len(ref_rows) <= 0.002 * len(ref_rows)
        assert contrast_kept(sel_kp, PAPER_SIFT.contrast_threshold, PAPER_SIFT.n_octave_layers).all()
    # the paper's correspondence counts are the same, to a few of hundreds
    for a, b in ((0, 1), (0, 2)):
        ours = count_correspondences(selected.descriptors_u8[a], selected.descriptors_u8[b], PAPER_MATCH)
        theirs = count_correspondences(reference.descriptors_u8[a], reference.descriptors_u8[b], PAPER_MATCH)
        assert theirs > 100 and abs(ours - theirs) <= 0.01 * theirs


def test_info_says_which_features_each_method_reads(dense_store):
    result = run_cli("info", "--db", dense_store)
    assert result.returncode == 0, result.stderr
    assert "'contrast_threshold': 0.02" in result.stdout
    assert ("the paper's method, and the refined mode's retrieval, read the keypoints SIFT keeps at contrast 0.04; "
            "the refined measurements and the camera-rate path read all of them") in result.stdout


def test_a_selection_is_refused_where_the_store_cannot_serve_it(dense_store, kitti_evaluation):
    folder, _, _ = kitti_evaluation
    dense = Workspace(dense_store, read_only=True)
    db = dense.load_database(SOURCE, "image_00", PAPER_SIFT)
    # the stored structure indexes the features as stored: it says how to read them so
    with pytest.raises(Exception, match="--sift-contrast 0.02"):
        dense.load_structure(db)
    # a store never serves a lower threshold than its own, nor other settings
    reference = Workspace(folder / "kitti.sqlite", read_only=True)
    with pytest.raises(Exception, match="contrast_threshold: store 0.04, asked 0.02"):
        reference.load_queries(SOURCE, "image_00", PAPER_SIFT.replace(contrast_threshold=DENSE_CONTRAST))
    with pytest.raises(Exception, match="edge_threshold"):
        dense.load_queries(SOURCE, "image_00", PAPER_SIFT.replace(edge_threshold=12.0))


def test_retrieval_counts_the_papers_features_whatever_the_mode_and_keeps_its_counts(dense_store, tmp_path):
    """On a denser store the refined modes measure on every stored feature, but retrieve as the paper's method
    does: the same counts, kept once, in the store's table of counts of selected features."""
    store = copy_store(dense_store, tmp_path)
    ws = Workspace(store)
    paper_db, paper_queries = ws.load_database(SOURCE, "image_00", PAPER_SIFT), ws.load_queries(SOURCE, "image_00",
                                                                                                PAPER_SIFT)
    db, queries = ws.load_database(SOURCE, "image_00"), ws.load_queries(SOURCE, "image_00")  # the refined modes'
    assert db.retrieval_contrast == PAPER_SIFT.contrast_threshold and paper_db.retrieval_contrast is None
    for k in range(N_FRAMES):
        assert np.array_equal(db.retrieval_descriptors_u8[k], paper_db.descriptors_u8[k])
        assert len(db.descriptors_u8[k]) > len(paper_db.descriptors_u8[k])
    cache = ws.pair_cache(paper_db, paper_queries, PAPER_MATCH)
    [n] = cache(paper_queries.descriptors_u8[0], paper_queries.key(0))([2])
    assert ws.save_pair_counts(cache) == 1
    assert n == count_correspondences(paper_queries.descriptors_u8[0], paper_db.descriptors_u8[2], PAPER_MATCH)
    # the refined mode's retrieval reads that count back (a cache seeded from the store computes nothing) ...
    counter = ws.pair_cache(db, queries, PAPER_MATCH)
    refined = visloc.build_localizer(visloc.REFINED_METHOD, db, PAPER_MATCH, visloc.PAPER_RETRIEVAL,
                                     visloc.PAPER_FILTER, query_camera=queries.camera_model, counter=counter)
    retrieval, _, _, _ = refined.measure(queries.query(0))
    assert retrieval.counts[list(retrieval.candidates).index(2)] == n
    assert (queries.key(0), db.images[2].image_id) not in counter.take_new_entries()
    # ... and counts the query's paper features, as the paper's method does, against every candidate
    assert n < count_correspondences(queries.descriptors_u8[0], db.descriptors_u8[2], PAPER_MATCH)
    assert Workspace(store).clear_pair_counts() == 1


def test_the_dashboard_matches_the_papers_method_on_its_own_features(dense_store, kitti_evaluation):
    from visloc.dashboard.state import Shown, load_features

    folder, _, _ = kitti_evaluation
    dense = Workspace(dense_store, read_only=True)
    [drive] = dense.drives()
    db, queries, paper = load_features(dense, drive, drive)
    shown = Shown(db=db, queries=queries, paper_features=paper)
    paper_db, paper_queries = shown.features(visloc.PAPER_METHOD)
    assert paper_db.selected_contrast == paper_queries.selected_contrast == PAPER_SIFT.contrast_threshold
    assert paper_db.frame == db.frame and len(paper_db.descriptors_u8[0]) < len(db.descriptors_u8[0])
    assert shown.features(visloc.REFINED_METHOD) == (db, queries)  # the refined modes read the store's own
    # a step's picture joins the features retrieval counted, in every mode: the count its table shows
    for k in range(N_FRAMES):
        assert np.array_equal(db.as_retrieved(queries.keypoints_f32[k], queries.descriptors_u8[k])[1],
                              paper_queries.descriptors_u8[k])
    reference = Workspace(folder / "kitti.sqlite", read_only=True)
    left = next(d for d in reference.drives() if d.camera == "image_00")
    assert load_features(reference, left, left)[2] is None  # a store at the paper's threshold is the paper's
