"""Global descriptors: one small vector per image, for a shortlist that skips most exact matching.

VLAD over SIFT: a k-means codebook trained on the database (faiss, seeded), residuals
summed per word, signed square root, per-word then global L2 normalisation, and
optionally a PCA projection. Pure functions over numpy arrays; ``GlobalIndex`` bundles
an encoder with the database's vectors.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from visloc.errors import ParameterError


@dataclass(frozen=True)
class GlobalEncoder:
    """Turns an image's SIFT descriptors into one unit-length global vector.

    codebook_f32:    (K, 128) k-means centres
    pca_mean_f32:    (K*128,) or None; pca_basis_f32: (D, K*128) or None (rows orthonormal)
    """

    codebook_f32: np.ndarray
    pca_mean_f32: np.ndarray | None = None
    pca_basis_f32: np.ndarray | None = None

    @property
    def dim(self) -> int:
        return int(self.pca_basis_f32.shape[0]) if self.pca_basis_f32 is not None else self.codebook_f32.size

    def vlad(self, descriptors_u8: np.ndarray) -> np.ndarray:
        """(K*128,) float32 VLAD: residuals to the nearest word summed per word, signed square root,
        per-word then global L2 normalisation."""
        c = self.codebook_f32
        x = np.asarray(descriptors_u8, np.float32)
        out = np.zeros(c.shape, np.float32)
        if x.shape[0]:
            # nearest word by |x - c|^2 = |c|^2 - 2 x.c + const
            words = np.argmin((c * c).sum(1)[None, :] - 2.0 * (x @ c.T), axis=1)
            onehot = np.zeros((x.shape[0], c.shape[0]), np.float32)
            onehot[np.arange(x.shape[0]), words] = 1.0
            out = onehot.T @ x - onehot.sum(axis=0)[:, None] * c
        out = np.sign(out) * np.sqrt(np.abs(out))
        norms = np.linalg.norm(out, axis=1, keepdims=True)
        out = np.divide(out, norms, out=np.zeros_like(out), where=norms > 0).ravel()
        n = np.linalg.norm(out)
        return out / n if n > 0 else out

    def encode(self, descriptors_u8: np.ndarray) -> np.ndarray:
        """(dim,) float32 unit vector (zero for an image without descriptors)."""
        v = self.vlad(descriptors_u8)
        if self.pca_basis_f32 is not None:
            v = self.pca_basis_f32 @ (v - self.pca_mean_f32)
            n = np.linalg.norm(v)
            v = v / n if n > 0 else v
        return v.astype(np.float32)

    def encode_many(self, descriptors: Sequence[np.ndarray]) -> np.ndarray:
        """(N, dim) float32, one row per image."""
        out = np.zeros((len(descriptors), self.dim), np.float32)
        for i, d in enumerate(descriptors):
            out[i] = self.encode(d)
        return out


def train_codebook(sample_u8: np.ndarray, n_words: int, seed: int) -> np.ndarray:
    """(n_words, 128) float32 k-means centres of ``sample_u8`` (faiss k-means, seeded)."""
    x = np.ascontiguousarray(sample_u8, np.float32)
    if x.shape[0] < n_words:
        raise ParameterError(f"n_words={n_words}: the training sample has only {x.shape[0]} descriptors")
    import faiss  # here: only training needs it, and it costs every command's start-up

    km = faiss.Kmeans(x.shape[1], n_words, niter=20, seed=seed, verbose=False)
    km.train(x)
    return np.ascontiguousarray(km.centroids, np.float32)


def sample_descriptors(descriptors: Sequence[np.ndarray], n: int, seed: int) -> np.ndarray:
    """Up to ``n`` descriptor rows drawn uniformly from the images, without replacement (seeded)."""
    sizes = np.array([len(d) for d in descriptors])
    total = int(sizes.sum())
    rng = np.random.default_rng(seed)
    pick = np.sort(rng.choice(total, size=min(n, total), replace=False))
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    image = np.searchsorted(starts, pick, side="right") - 1
    return np.stack([descriptors[i][r] for i, r in zip(image, pick - starts[image])]) if total else \
        np.zeros((0, 128), np.uint8)


def fit_pca(vectors_f32: np.ndarray, dim: int) -> tuple[np.ndarray, np.ndarray]:
    """Mean (D0,) and the ``dim`` leading principal directions (dim, D0) of the rows of ``vectors_f32``."""
    x = np.asarray(vectors_f32, np.float64)
    if dim > min(x.shape):
        raise ParameterError(f"pca_dim={dim}: at most {min(x.shape)} with {x.shape[0]} training images")
    mean = x.mean(axis=0)
    _, _, vt = np.linalg.svd(x - mean, full_matrices=False)
    return mean.astype(np.float32), np.ascontiguousarray(vt[:dim], np.float32)


def train_encoder(descriptors: Sequence[np.ndarray], n_words: int, pca_dim: int, train_descriptors: int,
                  seed: int) -> GlobalEncoder:
    """Codebook (and PCA when ``pca_dim`` > 0) trained on the database images ``descriptors``."""
    codebook = train_codebook(sample_descriptors(descriptors, train_descriptors, seed), n_words, seed)
    encoder = GlobalEncoder(codebook)
    if pca_dim:
        mean, basis = fit_pca(np.stack([encoder.vlad(d) for d in descriptors]), pca_dim)
        encoder = GlobalEncoder(codebook, mean, basis)
    return encoder


def shortlist(db_vectors_f32: np.ndarray, query_vector_f32: np.ndarray, size: int,
              among: np.ndarray | None = None) -> np.ndarray:
    """Indices of the ``size`` database rows most similar (inner product) to the query, best first.

    ``among`` restricts the search to those row indices. ``size`` 0 ranks them all. Ties keep
    the lower index.
    """
    rows = np.arange(db_vectors_f32.shape[0]) if among is None else np.asarray(among, np.int64)
    if rows.size == 0:
        return rows
    scores = np.asarray(db_vectors_f32[rows] if among is not None else db_vectors_f32) @ query_vector_f32
    if size <= 0 or size >= rows.size:
        order = np.argsort(-scores, kind="stable")
    else:
        top = np.argpartition(-scores, size - 1)[:size]
        order = top[np.lexsort((rows[top], -scores[top]))]
    return rows[order]


@dataclass(frozen=True)
class GlobalIndex:
    """A database's global vectors and the encoder that made them (queries are encoded the same way)."""

    encoder: GlobalEncoder
    vectors_f32: np.ndarray  # (N, dim), one row per database image

    @classmethod
    def build(cls, descriptors: Sequence[np.ndarray], *, n_words: int, pca_dim: int, train_descriptors: int,
              seed: int) -> "GlobalIndex":
        """Train the encoder on the database ``descriptors`` and encode every image."""
        encoder = train_encoder(descriptors, n_words, pca_dim, train_descriptors, seed)
        return cls(encoder, encoder.encode_many(descriptors))
