"""Multi-view triangulation of points seen by several posed views of one camera (numpy, batched).

The refined mode's database structure: each point of a view is triangulated from its observations in
every neighbour at once (linear, then Gauss-Newton on the reprojection error), with its covariance.
Conventions as in ``visloc.geometry.projective``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from visloc.geometry.projective import invert, projection_matrix


@dataclass(frozen=True)
class Tracks:
    """Points triangulated from several posed views, each seen in the first (reference) view.

    points_world: (M, 3) metres; n_views: (M,) views whose observation fits the point
    (reference included); parallax_deg: (M,) widest angle between the reference ray and
    another fitting ray; keep: (M,) bool, the trustworthy ones; cov_world: (M, 3, 3) each
    point's covariance, m^2: sigma^2 (J'J)^-1 over its fitting observations, with sigma^2 the
    kept points' residual variance per pixel coordinate (``sigma_px``).
    """

    points_world: np.ndarray
    n_views: np.ndarray
    parallax_deg: np.ndarray
    keep: np.ndarray
    cov_world: np.ndarray | None = None
    sigma_px: float | None = None


def _dlt(P: np.ndarray, xy: np.ndarray, used: np.ndarray) -> np.ndarray:
    """Linear triangulation of M points over C views at once: P (C, 3, 4), xy (M, C, 2), used (M, C)."""
    rows_x = xy[..., 0:1] * P[None, :, 2, :] - P[None, :, 0, :]  # (M, C, 4)
    rows_y = xy[..., 1:2] * P[None, :, 2, :] - P[None, :, 1, :]
    A = np.concatenate([rows_x, rows_y], axis=1) * np.concatenate([used, used], axis=1)[..., None]
    A = np.nan_to_num(A)
    scale = np.linalg.norm(A, axis=2, keepdims=True)
    A = A / np.where(scale > 0, scale, 1.0)
    # the right singular vector of A with the smallest singular value is the eigenvector of A'A with the
    # smallest eigenvalue: a 4x4 symmetric eigenproblem per point, far cheaper than an SVD of A (2C x 4),
    # and the start Gauss-Newton refines
    _, V = np.linalg.eigh(np.einsum("mki,mkj->mij", A, A))
    Xh = np.where(used.sum(axis=1)[:, None] >= 2, V[:, :, 0], [0.0, 0.0, 0.0, 1.0])  # seen once: no point
    with np.errstate(divide="ignore", invalid="ignore"):
        return Xh[:, :3] / Xh[:, 3:4]


def _refine_points(K: np.ndarray, T_camera_world: np.ndarray, X: np.ndarray, xy: np.ndarray, used: np.ndarray,
                   iterations: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """Gauss-Newton on the reprojection error of each point over its used observations (M points at once).

    Returns the points and their normal matrices J'J (M, 3, 3) at the solution, pixels^2 per m^2."""
    R, t = T_camera_world[:, :3, :3], T_camera_world[:, :3, 3]
    f = np.array([K[0, 0], K[1, 1]])
    c = np.array([K[0, 2], K[1, 2]])
    w = used.astype(float)
    for _ in range(iterations):
        Xc = np.tensordot(X, R, axes=([1], [2])) + t[None]  # (M, C, 3): R_c X_m + t_c
        z = Xc[..., 2:3]
        with np.errstate(divide="ignore", invalid="ignore"):
            r = f * Xc[..., :2] / z + c - xy  # (M, C, 2)
            J = np.zeros(Xc.shape[:2] + (2, 3))
            J[..., 0, 0] = f[0] / z[..., 0]
            J[..., 1, 1] = f[1] / z[..., 0]
            J[..., 0, 2] = -f[0] * Xc[..., 0] / z[..., 0] ** 2
            J[..., 1, 2] = -f[1] * Xc[..., 1] / z[..., 0] ** 2
            J = J @ R[None]  # d pixel / d X (M, C, 2, 3); a point on a camera's plane: not finite, made so next
        J = np.nan_to_num(J) * w[..., None, None]
        r = np.nan_to_num(r) * w[..., None]
        Jm = J.reshape(len(X), -1, 3)  # (M, 2C, 3)
        H = np.swapaxes(Jm, 1, 2) @ Jm
        g = (np.swapaxes(Jm, 1, 2) @ r.reshape(len(X), -1, 1))[..., 0]
        ok = np.linalg.det(H) > 1e-12
        step = np.zeros_like(X)
        step[ok] = np.linalg.solve(H[ok], g[ok][..., None])[..., 0]
        X = X - step
    return X, H


def triangulate_tracks(K: np.ndarray, T_world_cameras: np.ndarray, xy_px: np.ndarray, *,
                       max_reprojection_px: float = 1.0, min_parallax_deg: float = 0.5, min_depth_m: float = 0.5,
                       max_depth_m: float = 80.0) -> Tracks:
    """Triangulate M points observed in C posed views of one camera (K), view 0 the reference.

    ``xy_px`` (M, C, 2) holds each point's pixel in each view, NaN where a view does not see it;
    every point must be seen in view 0. Linear triangulation over every observation, refined by
    Gauss-Newton on the reprojection error; observations
    that then reproject farther than ``max_reprojection_px`` are dropped and the point triangulated
    again from the rest. A point is kept when view 0 and at least one other view still fit it, it
    lies in front of every fitting view within [min_depth_m, max_depth_m] (depth in view 0), and its
    widest ray angle to view 0 is at least ``min_parallax_deg``.
    """
    T = np.asarray(T_world_cameras, float)
    xy = np.asarray(xy_px, float)
    M, C = xy.shape[:2]
    if M == 0:
        z = np.zeros(0)
        return Tracks(np.zeros((0, 3)), z.astype(int), z, np.zeros(0, bool), np.zeros((0, 3, 3)), None)
    P = np.stack([projection_matrix(K, T[c]) for c in range(C)])
    used = np.all(np.isfinite(xy), axis=2)
    T_camera_world = invert(T)
    for _ in range(2):
        X, _ = _refine_points(K, T_camera_world, _dlt(P, xy, used), xy, used)
        Xh = np.c_[X, np.ones(M)]
        proj = np.einsum("cij,mj->mci", P, Xh)
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = proj[..., :2] / proj[..., 2:3]
            err = np.linalg.norm(uv - xy, axis=2)
        fits = used & (err <= max_reprojection_px) & (proj[..., 2] > 0)
        if np.array_equal(fits, used):
            break
        used = fits & fits[:, :1]  # the reference observation must fit, else the point is dropped
    centres = T[:, :3, 3]
    rays = X[:, None, :] - centres[None, :, :]  # (M, C, 3)
    with np.errstate(divide="ignore", invalid="ignore"):
        unit = rays / np.linalg.norm(rays, axis=2, keepdims=True)
        cos = np.einsum("mk,mck->mc", unit[:, 0, :], unit)
    angles = np.degrees(np.arccos(np.clip(np.nan_to_num(cos, nan=1.0), -1.0, 1.0)))
    parallax = np.where(fits, angles, 0.0).max(axis=1)
    depth = proj[:, 0, 2]  # K's last row is (0, 0, 1): the third coordinate is depth in view 0
    n_views = fits.sum(axis=1)
    keep = (np.all(np.isfinite(X), axis=1) & fits[:, 0] & (n_views >= 2) & (parallax >= min_parallax_deg)
            & (depth >= min_depth_m) & (depth <= max_depth_m))
    # covariance of each point from its final fitting observations and the kept points' residuals
    X, H = _refine_points(K, T_camera_world, X, xy, fits, iterations=1)
    residual_px = np.where(fits[keep], err[keep], 0.0)
    dof = 2 * int(fits[keep].sum()) - 3 * int(keep.sum())
    sigma_px = float(np.sqrt((residual_px**2).sum() / dof)) if dof > 0 else None
    cov = np.full((M, 3, 3), np.nan)
    invertible = keep & (np.linalg.det(H) > 1e-12)
    if sigma_px is not None and invertible.any():
        cov[invertible] = sigma_px**2 * np.linalg.inv(H[invertible])
    keep &= invertible
    return Tracks(X, n_views, parallax, keep, cov, sigma_px)
