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


def test_counts_of_selected_features_are_kept_apart_from_those_of_the_features_as_stored(dense_store, tmp_path):
    store = copy_store(dense_store, tmp_path)
    counted = {}
    for sift in (PAPER_SIFT, None):  # the paper's selection, then the features as stored
        ws = Workspace(store)
        db, queries = ws.load_database(SOURCE, "image_00", sift), ws.load_queries(SOURCE, "image_00", sift)
        cache = ws.pair_cache(db, queries, PAPER_MATCH)
        [counted[sift]] = cache(queries.descriptors_u8[0], queries.key(0))([2])
        assert ws.save_pair_counts(cache) == 1
        assert counted[sift] == count_correspondences(queries.descriptors_u8[0], db.descriptors_u8[2], PAPER_MATCH)
    # each is read back from its own table (a cache seeded from the store computes nothing)
    for sift in (PAPER_SIFT, None):
        ws = Workspace(store, read_only=True)
        db, queries = ws.load_database(SOURCE, "image_00", sift), ws.load_queries(SOURCE, "image_00", sift)
        cache = ws.pair_cache(db, queries, PAPER_MATCH)
        assert list(cache(queries.descriptors_u8[0], queries.key(0))([2])) == [counted[sift]]
        assert cache.take_new_entries() == {}
    assert counted[None] > counted[PAPER_SIFT]
    assert Workspace(store).clear_pair_counts() == 2


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
    reference = Workspace(folder / "kitti.sqlite", read_only=True)
    left = next(d for d in reference.drives() if d.camera == "image_00")
    assert load_features(reference, left, left)[2] is None  # a store at the paper's threshold is the paper's
