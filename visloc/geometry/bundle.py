"""Bundle adjustment of a few posed database cameras and the points they share, with priors on the poses.

The refined method's structure is triangulated from database cameras posed by their geotags and
attitudes. Those are not consistent with each other to the pixel: a GNSS/INS attitude can be off
by a few tenths of a degree in a turn (its samples are not taken at the shutter's instant), a
position by centimetres to decimetres, and a structure built on them is bent accordingly. Here
the cameras' poses are refined jointly with the points by Gauss-Newton with Levenberg-Marquardt
damping, so that the images agree with each other, while priors keep every pose near its geotag
and attitude; the priors also fix the gauge (where the structure sits, how it is oriented, its
scale), so the refined structure stays in the geotags' frame.

Cost, in units of each term's standard deviation (Huber on the reprojection terms):

    sum_obs  rho(|pi(R_k' (X_m - C_k)) - x_mk|^2 / sigma_px^2)
  + sum_k    |C_k - C0_k|^2_(sigma_pos, sigma_pos, sigma_up)  +  |log(R_k R0_k')|^2 / sigma_rot^2

with R_k the camera-to-world rotation, C_k the camera centre, pi the pinhole projection of K.
The points are eliminated by the Schur complement (each point is a 3x3 block), so a step costs a
(6C x 6C) solve for C cameras. Pure numpy; conventions as in ``visloc.geometry.projective``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def _skew(v: np.ndarray) -> np.ndarray:
    """(..., 3) -> (..., 3, 3) cross-product matrices [v]x."""
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def rotation_exp(w: np.ndarray) -> np.ndarray:
    """Rodrigues' formula for (..., 3) rotation vectors (radians) -> (..., 3, 3)."""
    w = np.asarray(w, float)
    theta = np.linalg.norm(w, axis=-1)[..., None, None]
    k = _skew(w / np.maximum(np.linalg.norm(w, axis=-1, keepdims=True), 1e-300))
    return np.eye(3) + np.sin(theta) * k + (1.0 - np.cos(theta)) * (k @ k)


def rotation_log(R: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotations -> (..., 3) rotation vectors (radians); angles below pi."""
    R = np.asarray(R, float)
    cos = np.clip((np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    theta = np.arccos(cos)
    v = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], axis=-1)
    sin = np.sin(theta)
    scale = np.where(sin > 1e-12, theta / np.where(sin > 1e-12, 2.0 * sin, 1.0), 0.5)
    return v * scale[..., None]


@dataclass(frozen=True)
class PosePriors:
    """Standard deviations of the priors on each camera's pose.

    sigma_pos_m: (C,) horizontal position, per axis, metres; sigma_up_m: vertical position, metres;
    sigma_rot_rad: attitude, per axis, radians; sigma_px: the reprojection error of a fitting
    observation, pixels (the scale of the Huber loss is ``huber`` times it)."""

    sigma_pos_m: np.ndarray
    sigma_up_m: float
    sigma_rot_rad: float
    sigma_px: float = 1.0
    huber: float = 2.0


@dataclass(frozen=True)
class BundleResult:
    """Refined camera poses and how much the images had to move them.

    T_world_camera: (C, 4, 4); points_world: (M, 3) of the points used (NaN where a point was
    left out, fewer than two observations); moved_m: (C,) how far each camera centre moved;
    turned_rad: (C,) how far each attitude turned; prior_chi2: the priors' part of the cost at
    the solution (what the images disagree with the geotags and attitudes, in their units);
    iterations: Gauss-Newton steps taken."""

    T_world_camera: np.ndarray
    points_world: np.ndarray
    moved_m: np.ndarray
    turned_rad: np.ndarray
    prior_chi2: float
    iterations: int


def _observation_jacobians(K: np.ndarray, R: np.ndarray, C: np.ndarray, X: np.ndarray, obs_m: np.ndarray,
                           obs_c: np.ndarray, obs_xy: np.ndarray):
    """Residuals (N, 2) and Jacobians wrt camera (N, 2, 6: rotation, centre) and point (N, 2, 3)."""
    Rk = R[obs_c]
    d = X[obs_m] - C[obs_c]
    p = np.einsum("nji,nj->ni", Rk, d)  # R' (X - C)
    z = p[:, 2]
    f = np.array([K[0, 0], K[1, 1]])
    r = f * p[:, :2] / z[:, None] + K[:2, 2] - obs_xy
    dpi = np.zeros((len(p), 2, 3))
    dpi[:, 0, 0] = f[0] / z
    dpi[:, 1, 1] = f[1] / z
    dpi[:, 0, 2] = -f[0] * p[:, 0] / z**2
    dpi[:, 1, 2] = -f[1] * p[:, 1] / z**2
    Rt = np.swapaxes(Rk, 1, 2)
    J_point = dpi @ Rt  # d p / d X = R'
    J_rot = dpi @ Rt @ _skew(d)  # d p / d w = R' [X - C]x  (rotation perturbed in the world frame)
    J_cam = np.concatenate([J_rot, -J_point], axis=2)
    return r, J_cam, J_point, z


class _Groups:
    """Sums of observation rows per camera (or per point): what ``np.add.at`` on zeros gives, by one
    ``np.add.reduceat`` over the rows in group order, the grouping worked out once per adjustment."""

    def __init__(self, index: np.ndarray, n: int):
        self.order = np.argsort(index, kind="stable")
        counts = np.bincount(index, minlength=n)
        self.present = counts > 0
        self.starts = (np.cumsum(counts) - counts)[self.present]
        self.n = n

    def sum(self, rows: np.ndarray) -> np.ndarray:
        out = np.zeros((self.n,) + rows.shape[1:])
        if len(self.starts):
            out[self.present] = np.add.reduceat(rows[self.order], self.starts, axis=0)
        return out


def bundle_adjust(K: np.ndarray, T_world_cameras: np.ndarray, points_world: np.ndarray, xy_px: np.ndarray,
                  used: np.ndarray, priors: PosePriors, *, iterations: int = 15) -> BundleResult:
    """Refine C camera poses and M points, ``xy_px`` (M, C, 2) observed where ``used`` (M, C).

    ``T_world_cameras`` (C, 4, 4) are the prior poses and the start; ``points_world`` (M, 3) the
    starting points (rows with NaN, or seen fewer than twice, are left out and come back NaN)."""
    T0 = np.asarray(T_world_cameras, float)
    n_cam = len(T0)
    R0, C0 = T0[:, :3, :3], T0[:, :3, 3]
    X = np.array(points_world, float)
    ok = np.all(np.isfinite(X), axis=1) & (used.sum(axis=1) >= 2)
    pts = np.flatnonzero(ok)
    obs_m_all, obs_c = np.nonzero(used[pts])
    obs_xy = xy_px[pts][obs_m_all, obs_c]
    Xp = X[pts]
    n_pts = len(pts)
    s_pos = np.c_[np.broadcast_to(np.asarray(priors.sigma_pos_m, float), (n_cam,))[:, None].repeat(2, 1),
                  np.full(n_cam, priors.sigma_up_m)]  # (C, 3)
    s_rot = priors.sigma_rot_rad
    R, C = R0.copy(), C0.copy()
    by_camera, by_point = _Groups(obs_c, n_cam), _Groups(obs_m_all, n_pts)

    def cost(R, C, X) -> tuple[float, np.ndarray]:
        r, *_ = _observation_jacobians(K, R, C, X, obs_m_all, obs_c, obs_xy)
        u = np.linalg.norm(r, axis=1) / priors.sigma_px
        k = priors.huber
        rho = np.where(u <= k, u**2, 2 * k * u - k**2)
        prior = np.sum(((C - C0) / s_pos) ** 2) + np.sum((rotation_log(R @ np.swapaxes(R0, 1, 2)) / s_rot) ** 2)
        return float(rho.sum() + prior), prior

    current, prior_chi2 = cost(R, C, Xp)
    lam = 1e-3
    done = 0
    converged = False
    for done in range(1, iterations + 1):
        r, J_cam, J_pt, z = _observation_jacobians(K, R, C, Xp, obs_m_all, obs_c, obs_xy)
        u = np.linalg.norm(r, axis=1) / priors.sigma_px
        w = np.where(u <= priors.huber, 1.0, priors.huber / np.maximum(u, 1e-12)) / priors.sigma_px**2
        w = np.where(z > 0, w, 0.0)
        # normal equations: cameras (block diagonal A), points (block diagonal D), coupling B
        wJ_cam_t = np.swapaxes(J_cam, 1, 2) * w[:, None, None]  # (N, 6, 2)
        wJ_pt_t = np.swapaxes(J_pt, 1, 2) * w[:, None, None]  # (N, 3, 2)
        A = by_camera.sum(wJ_cam_t @ J_cam)
        g_cam = by_camera.sum((wJ_cam_t @ r[:, :, None])[..., 0])
        D = by_point.sum(wJ_pt_t @ J_pt)
        g_pt = by_point.sum((wJ_pt_t @ r[:, :, None])[..., 0])
        B = np.zeros((n_pts, n_cam, 6, 3))
        B[obs_m_all, obs_c] = wJ_cam_t @ J_pt  # each (point, camera) is observed once
        # priors: centre (identity Jacobian), attitude (about identity for small corrections)
        rot_res = rotation_log(R @ np.swapaxes(R0, 1, 2))
        A[:, 3:, 3:] += np.einsum("ij,ci->cij", np.eye(3), 1.0 / s_pos**2)
        A[:, :3, :3] += np.eye(3) / s_rot**2
        g_cam[:, 3:] += (C - C0) / s_pos**2
        g_cam[:, :3] += rot_res / s_rot**2
        while True:
            Dd = D + lam * np.einsum("nii->ni", D)[:, :, None] * np.eye(3) + 1e-9 * np.eye(3)
            D_inv = np.linalg.inv(Dd)
            Ad = A + lam * np.einsum("cii->ci", A)[:, :, None] * np.eye(6)
            S = np.zeros((n_cam, 6, n_cam, 6))
            S[np.arange(n_cam), :, np.arange(n_cam), :] = Ad
            # S -= sum_m B_m D_m^-1 B_m' (one matrix product over every point)
            Bf = B.reshape(n_pts, 6 * n_cam, 3)
            BD = Bf @ D_inv  # (M, 6C, 3)
            S -= (np.swapaxes(BD, 0, 1).reshape(6 * n_cam, 3 * n_pts)
                  @ np.swapaxes(Bf, 0, 1).reshape(6 * n_cam, 3 * n_pts).T).reshape(n_cam, 6, n_cam, 6)
            rhs = g_cam - (BD @ g_pt[:, :, None]).sum(axis=0).reshape(n_cam, 6)
            try:
                step_cam = np.linalg.solve(S.reshape(6 * n_cam, 6 * n_cam), rhs.reshape(-1)).reshape(n_cam, 6)
            except np.linalg.LinAlgError:
                lam *= 10.0
                if lam > 1e8:
                    break
                continue
            step_pt = (D_inv @ (g_pt - np.swapaxes(Bf, 1, 2) @ step_cam.reshape(-1))[:, :, None])[..., 0]
            R_new = rotation_exp(-step_cam[:, :3]) @ R
            C_new = C - step_cam[:, 3:]
            X_new = Xp - step_pt
            new, new_prior = cost(R_new, C_new, X_new)
            if new < current:
                converged = current - new < 1e-4 * current
                R, C, Xp, current, prior_chi2 = R_new, C_new, X_new, new, new_prior
                lam = max(lam / 10.0, 1e-7)
                break
            lam *= 10.0
            if lam > 1e8:
                break
        if lam > 1e8 or converged:
            break
    T = T0.copy()
    T[:, :3, :3] = R
    T[:, :3, 3] = C
    out_points = np.full_like(X, np.nan)
    out_points[pts] = Xp
    return BundleResult(T, out_points, np.linalg.norm(C - C0, axis=1),
                        np.linalg.norm(rotation_log(R @ np.swapaxes(R0, 1, 2)), axis=1), prior_chi2, done)


def refine_database_poses(K: np.ndarray, T_world_cameras: np.ndarray, xy_px: np.ndarray, used: np.ndarray,
                          priors: PosePriors, *, start_px: float = 4.0, min_parallax_deg: float = 0.3,
                          max_depth_m: float = 100.0, min_points: int = 20,
                          max_points: int = 0) -> BundleResult | None:
    """The poses of cameras that see common points (``xy_px`` (M, C, 2) where ``used``), refined by
    ``bundle_adjust`` from points triangulated at their prior poses (observations within ``start_px``
    of them; a looser cut than the final one, so that a bent structure still has points to straighten).
    ``max_points`` (0: all): adjust on at most this many points, those most cameras see (the first rows
    among equals), triangulated from the twice as many most seen (from all, when those start too few): a
    few hundred fix the poses, and the adjustment's cost grows with the points and the cameras together.
    None when fewer than ``min_points`` points can start it."""
    from visloc.geometry.multiview import triangulate_tracks  # multiview imports geometry only: no cycle

    T = np.asarray(T_world_cameras, float)

    def start_from(rows: np.ndarray):
        return rows, triangulate_tracks(K, T, xy_px[rows], max_reprojection_px=start_px,
                                        min_parallax_deg=min_parallax_deg, max_depth_m=max_depth_m)

    every_row = np.arange(len(xy_px))
    if max_points <= 0:
        rows, start = start_from(every_row)
    else:  # twice as many as it takes, the most seen; every row when those start too few
        rows, start = start_from(np.sort(_most_seen(used.sum(axis=1), 2 * max_points)))
        if len(rows) < len(every_row) and int(start.keep.sum()) < max_points:
            rows, start = start_from(every_row)
    if int(start.keep.sum()) < min_points:
        return None
    chosen = rows[start.keep]
    if 0 < max_points < len(chosen):
        chosen = np.sort(chosen[_most_seen(used[chosen].sum(axis=1), max_points)])
    points = np.full((len(xy_px), 3), np.nan)
    points[chosen] = start.points_world[np.searchsorted(rows, chosen)]
    keep = np.zeros(len(xy_px), bool)
    keep[chosen] = True
    return bundle_adjust(K, T, points, xy_px, used & keep[:, None], priors)


def _most_seen(seen_by: np.ndarray, n: int) -> np.ndarray:
    """Indices of the ``n`` largest of ``seen_by``, the first among equals."""
    return np.lexsort((np.arange(len(seen_by)), -seen_by))[:n]


def heading_spread_rad(east_north_m: np.ndarray, yaw_rad: np.ndarray, *, min_step_m: float = 5.0) -> float | None:
    """How far a drive's recorded headings stray from its course over ground, radians.

    The course at image i is the direction of the chord between the images ``a`` before and ``a``
    after it, with ``a`` the smallest number of images that makes the chord at least ``min_step_m``
    long (on a circular arc, the chord between points symmetric about i is parallel to the tangent
    at i). A heading (the yaw of the geotag's reference frame, ``visloc.geometry.projective``'s convention)
    that an INS gets right differs from it by a constant only (the mounting; the car's slip is
    small). Returns the standard deviation of heading minus course about its mean (not a robust one:
    the turns, where an INS strays most, are what a structure must survive), or None with fewer
    than 5 usable images."""
    en = np.asarray(east_north_m, float)
    yaw = np.asarray(yaw_rad, float)
    diffs = []
    for i in range(len(en)):
        if not (np.all(np.isfinite(en[i])) and np.isfinite(yaw[i])):
            continue
        for a in range(1, len(en)):
            if i - a < 0 or i + a >= len(en):
                break
            chord = en[i + a] - en[i - a]
            if not np.all(np.isfinite(chord)):
                break
            if np.hypot(*chord) >= min_step_m:
                diffs.append(np.angle(np.exp(1j * (yaw[i] - np.arctan2(chord[1], chord[0])))))
                break
    if len(diffs) < 5:
        return None
    d = np.asarray(diffs)
    centre = np.angle(np.mean(np.exp(1j * d)))
    dev = np.angle(np.exp(1j * (d - centre)))
    return float(np.sqrt(np.mean(dev**2)))
