"""Keypoint correspondences between two images: the paper's equations (1) and (2).

For every query descriptor g we find its nearest and second-nearest descriptors
f1, f2 in one database image (exact, brute force). g and f1 correspond when

    (1)  d^2(g, f1) / d^2(g, f2) < tau1^2      (Lowe's ratio test)
    (2)  cos(g, f1) = f1.g / (|f1| |g|) > tau2  (cosine similarity)

The number of correspondences is the database image's score.

Exactness: SIFT descriptors are whole numbers 0..255 with L2 norm about 512, so
every dot product is an integer below 2^24 and float32 arithmetic is exact here:
the same descriptors always give the same neighbours and distances.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from visloc.params import MatchParams


@dataclass(frozen=True)
class NearestTwo:
    """Nearest and second-nearest database descriptors of each query descriptor.

    index1:    (N,) int64, row of the nearest database descriptor.
    dist1_sq:  (N,) float32, squared L2 distance to it.
    dist2_sq:  (N,) float32, squared L2 distance to the second nearest
               (inf when the database image has a single descriptor).
    cosine1:   (N,) float32, cosine similarity with the nearest; NaN when either
               vector is zero (undefined, so it never passes equation (2)).
    """

    index1: np.ndarray
    dist1_sq: np.ndarray
    dist2_sq: np.ndarray
    cosine1: np.ndarray


def nearest_two(query_u8: np.ndarray, database_u8: np.ndarray) -> NearestTwo:
    """Exact two nearest neighbours of every query row among the database rows."""
    q = np.asarray(query_u8, dtype=np.float32)
    d = np.asarray(database_u8, dtype=np.float32)
    n_query, n_db = q.shape[0], d.shape[0]
    if n_query == 0 or n_db == 0:
        empty_f = np.zeros(n_query, np.float32)
        return NearestTwo(np.full(n_query, -1, np.int64), np.full(n_query, np.inf, np.float32),
                          np.full(n_query, np.inf, np.float32), empty_f)
    q_sq = np.einsum("ij,ij->i", q, q)
    d_sq = np.einsum("ij,ij->i", d, d)
    # |g - f|^2 = |g|^2 + |f|^2 - 2 g.f; per row |g|^2 is constant, so the nearest f
    # maximises score = g.f - |f|^2 / 2 (exact in float32, see the module docstring).
    score = q @ d.T
    score -= 0.5 * d_sq
    rows = np.arange(n_query)
    index1 = np.argmax(score, axis=1)
    best = score[rows, index1]
    if n_db > 1:
        score[rows, index1] = -np.inf
        second = score.max(axis=1)
    else:
        second = np.full(n_query, -np.inf, np.float32)
    dist1_sq = np.maximum(q_sq - 2.0 * best, 0.0).astype(np.float32)
    dist2_sq = np.maximum(q_sq - 2.0 * second, 0.0).astype(np.float32)
    dot1 = best + 0.5 * d_sq[index1]
    norms = np.sqrt(q_sq) * np.sqrt(d_sq[index1])
    with np.errstate(invalid="ignore", divide="ignore"):
        cosine1 = np.where(norms > 0, dot1 / norms, np.nan).astype(np.float32)
    return NearestTwo(index1.astype(np.int64), dist1_sq, dist2_sq, cosine1)


def correspondence_mask(nn: NearestTwo, params: MatchParams) -> np.ndarray:
    """(N,) bool: which query descriptors pass equations (1) and (2)."""
    ratio_ok = nn.dist1_sq < (params.tau1 ** 2) * nn.dist2_sq  # (1), no division: d2 = 0 fails
    cosine_ok = nn.cosine1 > params.tau2  # (2); NaN (zero vector) compares False
    return ratio_ok & cosine_ok & (nn.index1 >= 0)


def correspondences(query_u8: np.ndarray, database_u8: np.ndarray, params: MatchParams) -> np.ndarray:
    """(M, 2) int64 pairs (query row, database row) that correspond."""
    nn = nearest_two(query_u8, database_u8)
    mask = correspondence_mask(nn, params)
    return np.stack([np.flatnonzero(mask), nn.index1[mask]], axis=1)


def count_correspondences(query_u8: np.ndarray, database_u8: np.ndarray, params: MatchParams) -> int:
    """The paper's score of one database image for one query."""
    return int(correspondence_mask(nearest_two(query_u8, database_u8), params).sum())
