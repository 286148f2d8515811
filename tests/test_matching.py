"""Equations (1) and (2) on hand-made descriptors with known answers."""

import numpy as np
import pytest

from visloc.retrieval.matching import (correspondence_mask, correspondences, correspondences_both_ways,
                                      count_correspondences, nearest_two, nearest_two_both_ways)
from visloc.params import MatchParams


def desc(*rows):
    """uint8 descriptors from short rows, zero-padded to 128 dimensions."""
    out = np.zeros((len(rows), 128), np.uint8)
    for i, r in enumerate(rows):
        out[i, : len(r)] = r
    return out


def test_clear_match_passes_both_tests():
    query = desc([10, 0])
    database = desc([9, 0], [0, 10])  # d1^2 = 1, d2^2 = 200, cos = 1
    nn = nearest_two(query, database)
    assert nn.index1.tolist() == [0]
    assert nn.dist1_sq.tolist() == [1.0] and nn.dist2_sq.tolist() == [200.0]
    assert nn.cosine1[0] == pytest.approx(1.0)
    assert count_correspondences(query, database, MatchParams(0.8, 0.97)) == 1


def test_ambiguous_match_fails_ratio_test():
    query = desc([10, 10])
    database = desc([10, 0], [0, 10])  # both at d^2 = 100: ratio 1
    assert count_correspondences(query, database, MatchParams(0.8, -1.0)) == 0


def test_ratio_is_strict_at_the_threshold():
    query = desc([0, 0, 4])
    database = desc([0, 0, 5], [0, 0, 6])  # d1^2 = 1, d2^2 = 4: ratio^2 = 0.25 = tau1^2
    assert count_correspondences(query, database, MatchParams(tau1=0.5, tau2=-1.0)) == 0
    assert count_correspondences(query, database, MatchParams(tau1=0.51, tau2=-1.0)) == 1


def test_low_cosine_fails_even_when_ratio_passes():
    query = desc([100, 0])
    database = desc([100, 60], [0, 0])  # d1^2 = 3600 < 0.64 * 10000; cos = 100/116.6 = 0.857
    nn = nearest_two(query, database)
    assert nn.cosine1[0] == pytest.approx(100 / np.hypot(100, 60), abs=1e-6)
    assert count_correspondences(query, database, MatchParams(0.8, 0.97)) == 0
    assert count_correspondences(query, database, MatchParams(0.8, 0.85)) == 1


def test_zero_descriptor_never_corresponds():
    query = desc([0, 0])
    database = desc([0, 0], [50, 50])
    # (1) passes (d1 = 0), but the cosine of a zero vector is undefined: NaN, never > tau2
    assert np.isnan(nearest_two(query, database).cosine1[0])
    assert count_correspondences(query, database, MatchParams(1.0, -1.0)) == 0


def test_single_database_descriptor_has_no_second_neighbour():
    nn = nearest_two(desc([5, 5]), desc([5, 4]))
    assert np.isinf(nn.dist2_sq[0])
    assert count_correspondences(desc([5, 5]), desc([5, 4]), MatchParams(0.8, 0.97)) == 1


def test_empty_inputs_give_no_correspondences():
    assert count_correspondences(desc([1]), np.zeros((0, 128), np.uint8), MatchParams()) == 0
    assert count_correspondences(np.zeros((0, 128), np.uint8), desc([1], [2]), MatchParams()) == 0


def test_pairs_name_query_and_database_rows():
    query = desc([10, 0], [0, 0, 10], [7, 7])
    database = desc([0, 0, 11], [50, 50], [11, 0])
    pairs = correspondences(query, database, MatchParams(0.8, 0.97))
    assert pairs.tolist() == [[0, 2], [1, 0]]


def test_nearest_two_is_exact_against_float64_brute_force():
    rng = np.random.default_rng(0)
    query = rng.integers(0, 256, (300, 128), dtype=np.uint8)
    database = rng.integers(0, 256, (400, 128), dtype=np.uint8)
    database[17] = query[5]  # an exact duplicate: distance 0
    nn = nearest_two(query, database)
    q, d = query.astype(np.float64), database.astype(np.float64)
    dist = ((q[:, None, :] - d[None, :, :]) ** 2).sum(-1)
    ordered = np.sort(dist, axis=1)
    np.testing.assert_array_equal(nn.dist1_sq, ordered[:, 0])
    np.testing.assert_array_equal(nn.dist2_sq, ordered[:, 1])
    np.testing.assert_array_equal(dist[np.arange(300), nn.index1], ordered[:, 0])
    cos = (q * d[nn.index1]).sum(1) / np.linalg.norm(q, axis=1) / np.linalg.norm(d[nn.index1], axis=1)
    np.testing.assert_allclose(nn.cosine1, cos, rtol=1e-6)
    assert nn.index1[5] == 17 and nn.dist1_sq[5] == 0


def test_nearest_two_by_blocks_of_query_rows_equals_one_product_of_all_rows(monkeypatch):
    """The query rows go a block at a time (the scores stay in cache): every array comes out the same as from
    one product of all rows, ties and zero vectors included, with a last block shorter than the others."""
    import visloc.retrieval.matching as matching

    rng = np.random.default_rng(2)
    query = rng.integers(0, 4, (300, 128), dtype=np.uint8)  # few values: many ties
    database = rng.integers(0, 4, (400, 128), dtype=np.uint8)
    database[7], query[3] = database[6], 0
    monkeypatch.setattr(matching, "_SCORE_BLOCK_BYTES", 1 << 40)
    whole = nearest_two(query, database)
    monkeypatch.setattr(matching, "_SCORE_BLOCK_BYTES", 4 * 400 * 7)  # 7 rows a block: 42 blocks and one of 6
    blocks = nearest_two(query, database)
    for name in ("index1", "dist1_sq", "dist2_sq", "cosine1"):
        a, b = getattr(whole, name), getattr(blocks, name)
        assert a.dtype == b.dtype and np.array_equal(a, b, equal_nan=True), name


def same_neighbours(a, b) -> None:
    for name in ("index1", "dist1_sq", "dist2_sq", "cosine1"):
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype and x.shape == y.shape and np.array_equal(x, y, equal_nan=True), name


@pytest.mark.parametrize("n_a,n_b", [(0, 5), (5, 0), (1, 1), (1, 9), (9, 1), (300, 400), (400, 300)])
@pytest.mark.parametrize("block_rows", [None, 7])
@pytest.mark.parametrize("threads", [1, 2])
def test_both_ways_from_one_product_equal_two_searches(monkeypatch, n_a, n_b, block_rows, threads):
    """A pair's nearest two both ways from one product are those of two searches, array for array: ties (few
    values), duplicated and zero rows, one row on either side, blocks of query rows with a short last one, and
    the rows shared among threads."""
    import visloc.retrieval.matching as matching

    rng = np.random.default_rng(n_a * 1000 + n_b)
    a = rng.integers(0, 4, (n_a, 128), dtype=np.uint8)
    b = rng.integers(0, 4, (n_b, 128), dtype=np.uint8)
    if n_a > 3 and n_b > 3:
        b[:2], a[3] = a[:2], 0
    if block_rows:
        monkeypatch.setattr(matching, "_SCORE_BLOCK_BYTES", 4 * max(n_a, n_b) * block_rows)
    monkeypatch.setattr(matching, "_blas_threads", lambda: threads)
    forward, backward = nearest_two_both_ways(a, b)
    same_neighbours(forward, nearest_two(a, b))
    same_neighbours(backward, nearest_two(b, a))
    params = MatchParams(tau1=0.9, tau2=-1.0)
    a_to_b, b_to_a = correspondences_both_ways(a, b, params)
    assert np.array_equal(a_to_b, correspondences(a, b, params)) and np.array_equal(b_to_a, correspondences(b, a, params))


@pytest.mark.parametrize("tau1,tau2", [(0.6, 0.9), (0.8, 0.97), (1.0, -1.0)])
def test_mask_equals_the_equations_elementwise(tau1, tau2):
    rng = np.random.default_rng(1)
    base = rng.integers(0, 200, (200, 128), dtype=np.uint8)
    query = np.clip(base[:120].astype(int) + rng.integers(-8, 9, (120, 128)), 0, 255).astype(np.uint8)
    nn = nearest_two(query, base)
    mask = correspondence_mask(nn, MatchParams(tau1, tau2))
    expected = (nn.dist1_sq / nn.dist2_sq < tau1**2) & (nn.cosine1 > tau2)
    np.testing.assert_array_equal(mask, expected)
