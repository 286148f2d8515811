"""The fast path gives the paper's answers: same neighbours, same counts, the exact best match
whenever the truth is inside the gate or the shortlist. No timing here: that is ``visloc bench``'s job."""

from __future__ import annotations

import numpy as np
import pytest

from visloc.bench.synthetic import SyntheticSpec, database_image, query_image
from visloc.db import ImageRecord, VectorTable
from visloc.errors import ParameterError
from visloc.features.sift import Query, extract_sift
from visloc.tracking.localizer import Localizer
from visloc.retrieval.matching import (backend_counter, backend_counts, brute_force_counter, brute_force_counts,
                             count_correspondences, count_correspondences_with, count_many, nearest_two,
                             nearest_two_faiss)
from visloc.pose.measurement import GeotagMeasurer
from visloc.params import PAPER_FILTER, PAPER_MATCH, FastParams, MatchParams, RetrievalParams, SiftParams
from visloc.retrieval.retrievers import (ShortlistRetriever, WindowRetriever, build_global_index, gate_mask, gate_radius_m,
                              retrieve, shortlist_retrieve)
from visloc.features.vlad import shortlist

from helpers import panorama

SPEC = SyntheticSpec(n_images=300, descriptors_per_image=64, seed=3)


def sift_like(rng: np.random.Generator, n: int) -> np.ndarray:
    """Non-negative vectors of L2 norm about 512 in whole numbers 0..255, as SIFT's."""
    x = rng.gamma(0.6, 1.0, size=(n, 128))
    x *= 512.0 / np.linalg.norm(x, axis=1, keepdims=True)
    return np.clip(np.rint(x), 0, 255).astype(np.uint8)


@pytest.fixture(scope="module")
def sift_pair():
    """Real SIFT descriptors of two overlapping crops of a textured panorama."""
    pano = panorama(seed=11)
    a = extract_sift(np.ascontiguousarray(pano[:, 0:400]), SiftParams())
    b = extract_sift(np.ascontiguousarray(pano[:, 60:460]), SiftParams())
    return a, b


def test_faiss_nearest_two_equals_brute_force_on_real_sift(sift_pair):
    a, b = sift_pair
    ref, got = nearest_two(a.descriptors_u8, b.descriptors_u8), nearest_two_faiss(a.descriptors_u8, b.descriptors_u8)
    assert len(a) > 200 and len(b) > 200
    np.testing.assert_array_equal(got.dist1_sq, ref.dist1_sq)
    np.testing.assert_array_equal(got.dist2_sq, ref.dist2_sq)
    unique = ref.dist1_sq < ref.dist2_sq  # with a tie the nearest is either; elsewhere it is one row
    np.testing.assert_array_equal(got.index1[unique], ref.index1[unique])
    np.testing.assert_array_equal(got.cosine1[unique], ref.cosine1[unique])
    for match in (PAPER_MATCH, MatchParams(tau1=0.8, tau2=-1.0)):
        n = count_correspondences(a.descriptors_u8, b.descriptors_u8, match)
        assert n > 20
        assert count_correspondences_with("faiss", a.descriptors_u8, b.descriptors_u8, match) == n


def test_structure_matches_pass_the_ratio_and_the_cross_check_as_a_brute_force_does():
    """The camera-rate path's matches of a query to a view's 3D-carrying keypoints against a loop over every pair:
    a query descriptor's nearest keypoint, nearer than 0.8 times the next one, whose own nearest query is it."""
    from visloc.pose.fastpose import _matches

    rng = np.random.default_rng(21)
    view = sift_like(rng, 300).astype(np.float32)
    query = sift_like(rng, 200).astype(np.float32)
    query[:120] = np.clip(view[:120] + rng.integers(-4, 5, (120, 128)), 0, 255)  # seen again, a little changed
    query[120:130] = np.clip(view[:10] + rng.integers(-9, 10, (10, 128)), 0, 255)  # a second, worse look at 0-9
    got = _matches(query, np.einsum("ij,ij->i", query, query), view, 0.5 * np.einsum("ij,ij->i", view, view), 0.8,
                   mutual=True)
    d2 = ((query[:, None, :].astype(np.float64) - view[None, :, :]) ** 2).sum(axis=2)
    nearest, second = np.argsort(d2, axis=1)[:, 0], np.sort(d2, axis=1)[:, 1]
    back = np.argmin(d2, axis=0)
    want = [[i, int(nearest[i])] for i in range(len(query))
            if d2[i, nearest[i]] < 0.8**2 * second[i] and back[nearest[i]] == i]
    assert got.tolist() == want
    assert 100 < len(want) < 130 and not any(i in range(120, 130) for i, _ in want)  # the worse looks lose


def test_batched_counts_equal_one_by_one_counts():
    rng = np.random.default_rng(5)
    query = sift_like(rng, 300)
    base = sift_like(rng, 400)
    images = [np.clip(base[rng.choice(400, n, replace=False)].astype(int) + rng.integers(-6, 7, (n, 128)), 0, 255)
              .astype(np.uint8) for n in (350, 120, 400, 37)]
    images[1][:80] = query[:80]  # exact duplicates: distance 0 to the nearest
    images += [np.zeros((0, 128), np.uint8), sift_like(rng, 1), np.zeros((5, 128), np.uint8)]  # edge cases
    query[-3:] = 0  # zero vectors: cosine undefined, never a correspondence
    candidates = np.arange(len(images))[::-1]
    for match in (PAPER_MATCH, MatchParams(tau1=0.9, tau2=0.9), MatchParams(tau1=0.8, tau2=-1.0)):
        want = [count_correspondences(query, images[i], match) for i in candidates]
        assert max(want) > 50
        # a tiny block forces several blocks with different padding widths
        for block in (64 << 20, 300 * 400 * 4):
            got = count_many(query, images, candidates, match, block_bytes=block)
            np.testing.assert_array_equal(got, want)
        np.testing.assert_array_equal(backend_counts("batched", query, images, match)(candidates), want)


def test_gate_contains_exactly_the_images_within_the_radius():
    east_north = np.c_[np.arange(0.0, 100.0, 1.0), np.zeros(100)]
    params = FastParams(gate_sigmas=3.0, gate_min_radius_m=5.0)
    cov = np.diag([16.0, 1.0])  # sigma 4 m on the long axis: radius 12 m
    assert gate_radius_m(cov, params) == pytest.approx(12.0)
    inside = np.flatnonzero(gate_mask(east_north, np.array([50.0, 0.0]), cov, params))
    np.testing.assert_array_equal(inside, np.arange(38, 63))
    tiny = gate_mask(east_north, np.array([50.0, 0.0]), np.eye(2) * 1e-6, params)
    np.testing.assert_array_equal(np.flatnonzero(tiny), np.arange(45, 56))  # the minimum radius holds


def synthetic_db(n: int = SPEC.n_images):
    descriptors = [database_image(p, SPEC) for p in range(n)]
    east_north = np.c_[np.arange(n, dtype=float), np.zeros(n)]  # 1 m apart, as the synthetic road
    return descriptors, east_north, np.arange(n, dtype=float)


def fast_retrieval(q, descriptors, east_north, times, index, params, query_s, prediction=None):
    counts = backend_counts("batched", q, descriptors, PAPER_MATCH)
    return shortlist_retrieve(index.encoder.encode(q), counts, times, east_north, index.vectors_f32, params, query_s,
                              RetrievalParams(window_s=1e9, exclusion_s=0.0), prediction)


@pytest.mark.slow
def test_gated_retrieval_returns_the_exact_answer_when_the_truth_is_inside_the_gate():
    descriptors, east_north, times = synthetic_db()
    params = FastParams(shortlist_size=0, n_words=16)
    index = build_global_index(descriptors, params)
    for place in (20, 151, 280):
        q = query_image(place, SPEC)
        exact = retrieve(brute_force_counts(q, descriptors, PAPER_MATCH), times, float(place), None,
                         RetrievalParams(window_s=1e9, exclusion_s=0.0))
        assert abs(exact.best_index - place) <= 1
        got = fast_retrieval(q, descriptors, east_north, times, index, params, float(place),
                             (np.array([place + 6.0, 0.0]), np.eye(2) * 9.0))
        assert got.gated and not got.widened
        assert got.best_index == exact.best_index
        assert got.best_count == exact.best_count
        in_gate = np.flatnonzero(np.abs(east_north[:, 0] - place - 6) <= 20)  # the minimum radius, 20 m
        np.testing.assert_array_equal(got.allowed, in_gate)
        assert in_gate.size < len(descriptors)


def test_retrieval_widens_when_lost_or_when_the_gate_sees_nothing():
    descriptors, east_north, times = synthetic_db()
    params = FastParams(shortlist_size=8, n_words=16)
    index = build_global_index(descriptors, params)
    q = query_image(200, SPEC)
    lost = fast_retrieval(q, descriptors, east_north, times, index, params, 200.0)  # no prediction: first or lost
    assert not lost.gated and lost.allowed.size == len(descriptors) and abs(lost.best_index - 200) <= 1
    assert lost.candidates.size == 8
    # a confident prediction 100 m off: nothing in the gate matches, so the search widens to everything
    wrong = fast_retrieval(q, descriptors, east_north, times, index, params, 200.0, (np.array([60.0, 0.0]), np.eye(2)))
    assert wrong.widened and not wrong.gated
    assert wrong.best_index == lost.best_index


def test_global_shortlist_finds_the_right_place_on_a_synthetic_database():
    descriptors, _, _ = synthetic_db()
    index = build_global_index(descriptors, FastParams(n_words=16, pca_dim=64))
    assert index.vectors_f32.shape == (SPEC.n_images, 64)
    hits = []
    for place in range(5, SPEC.n_images, 37):
        top = shortlist(index.vectors_f32, index.encoder.encode(query_image(place, SPEC)), 8)
        assert len(top) == 8
        hits.append(abs(int(top[0]) - place) <= 2)
    assert np.mean(hits) >= 0.9
    among = np.arange(100, 140)
    assert set(shortlist(index.vectors_f32, index.encoder.encode(query_image(120, SPEC)), 5, among=among)) <= set(among)


@pytest.mark.slow
def test_fast_localizer_tracks_like_the_paper_on_a_synthetic_road():
    descriptors, east_north, times = synthetic_db()
    retrieval = RetrievalParams(window_s=20.0, exclusion_s=0.0)
    params = FastParams(n_words=16)
    paper = Localizer(WindowRetriever(times, brute_force_counter(descriptors, PAPER_MATCH), retrieval),
                      GeotagMeasurer(east_north), PAPER_FILTER)
    fast = Localizer(ShortlistRetriever(times, east_north, build_global_index(descriptors, params), params,
                                        backend_counter("batched", descriptors, PAPER_MATCH), retrieval),
                     GeotagMeasurer(east_north), PAPER_FILTER)
    for place in range(30, 90, 10):  # 10 m per second: the filter's gate follows
        q = Query(query_image(place, SPEC), float(place))
        a, b = paper.step(q), fast.step(q)
        assert b.best_index == a.best_index
        assert b.retrieval.candidates.size <= 8 < a.retrieval.candidates.size
        assert b.retrieval.gated == (place > 30)  # the first query has no prediction to gate with


@pytest.mark.parametrize("field,value", [("gate_sigmas", 0), ("shortlist_size", -1), ("nn_backend", "annoy"),
                                         ("n_words", 0), ("pca_dim", 1.5)])
def test_fast_params_name_the_bad_parameter(field, value):
    with pytest.raises(ParameterError, match=field):
        FastParams(**{field: value})


def test_store_streams_only_the_shortlist(tmp_store):
    rng = np.random.default_rng(1)
    descs = [sift_like(rng, int(n)) for n in rng.integers(5, 40, 30)]
    tmp_store.add_images([(ImageRecord("s", "c", i, f"p{i}", float(i), 49.0, 8.0 + i * 1e-5), np.zeros((len(d), 6)),
                           d) for i, d in enumerate(descs)])
    ids = tmp_store.image_ids("s", "c")
    assert ids.size == 30
    seen_sql = []
    tmp_store.db.conn.set_trace_callback(seen_sql.append)
    wanted = ids[[7, 3, 22, 15, 9]]
    got = list(tmp_store.iter_descriptors(wanted.tolist(), chunk_size=2))
    tmp_store.db.conn.set_trace_callback(None)
    assert [i for i, _ in got] == wanted.tolist()
    for (_, d), k in zip(got, [7, 3, 22, 15, 9]):
        np.testing.assert_array_equal(d, descs[k])
    selects = [s for s in seen_sql if "descriptors_u8" in s]
    assert len(selects) == 3 and all(s.split("IN (")[1].count(",") <= 1 for s in selects)  # at most 2 ids per query
    vectors = rng.normal(size=(30, 16)).astype(np.float32)
    VectorTable(tmp_store).add_global_vectors("vlad", ids.tolist(), vectors)
    got_ids, got_vectors = VectorTable(tmp_store).global_vectors("vlad")
    np.testing.assert_array_equal(got_ids, ids)
    np.testing.assert_array_equal(got_vectors, vectors)
    VectorTable(tmp_store).put_array("codebook", vectors[:4])
    np.testing.assert_array_equal(VectorTable(tmp_store).get_array("codebook"), vectors[:4])
    assert VectorTable(tmp_store).get_array("missing") is None


def test_scaled_sift_reports_full_resolution_pixels():
    image = np.ascontiguousarray(panorama(seed=3)[:, :480])
    full = extract_sift(image, SiftParams())
    half = extract_sift(image, SiftParams(image_scale=0.5))
    assert 0 < len(half) < len(full)
    # every half-scale keypoint lies on the full image, near a full-scale keypoint
    assert half.xy_px[:, 0].max() < image.shape[1] and half.xy_px[:, 1].max() < image.shape[0]
    d = np.linalg.norm(half.xy_px[:, None, :] - full.xy_px[None, :, :], axis=2).min(axis=1)
    assert np.median(d) < 1.5
    assert "image_scale" not in SiftParams().as_dict() and SiftParams(image_scale=0.5).as_dict()["image_scale"] == 0.5
    with pytest.raises(ParameterError, match="image_scale"):
        SiftParams(image_scale=1.5)


def test_store_written_before_image_scale_still_matches(memory_store):
    from visloc.store.ingest import check_sift_settings

    memory_store.require_setting("sift", {"n_features": 0, "n_octave_layers": 3, "contrast_threshold": 0.04,
                                          "edge_threshold": 10.0, "sigma": 1.6})
    memory_store.add_images([(ImageRecord("s", "c", 0, "p", 0.0, 49.0, 8.0), np.zeros((1, 6)),
                              np.zeros((1, 128), np.uint8))])
    check_sift_settings(memory_store, SiftParams())  # no error
    with pytest.raises(Exception, match="image_scale"):
        check_sift_settings(memory_store, SiftParams(image_scale=0.5))
