"""Multi-view geometry of the refined mode, as pure functions over numpy arrays (OpenCV underneath).

Conventions (also in the README)
--------------------------------
* ``T_a_b`` is a 4x4 rigid transform in metres that maps points given in frame b
  into frame a: ``X_a = T_a_b @ X_b`` (homogeneous). ``T_world_camera`` is therefore
  the pose of a camera in the world: its translation is the camera centre.
* world: local east, north, up (ENU) in metres; east/north are the engine's local
  frame (``visloc.geo.LocalFrame``: azimuthal equidistant, origin at the first
  database image's geotag), up is altitude minus that image's altitude.
* imu: the geotag's reference frame (KITTI: the OXTS unit), x forward, y left, z up.
  Its attitude is (roll, pitch, yaw) as OXTS records give it: yaw 0 = east,
  counter-clockwise; ``R_world_imu = Rz(yaw) Ry(pitch) Rx(roll)``.
* camera: the rectified pinhole camera, x right, y down, z forward (optical axis);
  pixels are ``K @ X_camera`` divided by depth, with no distortion (rectified images).

Every RANSAC is seeded with ``cv2.setRNGSeed`` so a run gives the same answer twice.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np


# -- rigid transforms -----------------------------------------------------------------

def rotation_from_rpy(roll_rad: float, pitch_rad: float, yaw_rad: float) -> np.ndarray:
    """R_world_imu = Rz(yaw) Ry(pitch) Rx(roll) (KITTI OXTS convention), 3x3."""
    cr, sr = math.cos(roll_rad), math.sin(roll_rad)
    cp, sp = math.cos(pitch_rad), math.sin(pitch_rad)
    cy, sy = math.cos(yaw_rad), math.sin(yaw_rad)
    Rx = np.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
    Ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    Rz = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
    return Rz @ Ry @ Rx


def rpy_from_rotation(R: np.ndarray) -> tuple[float, float, float]:
    """(roll, pitch, yaw) in radians of R_world_imu = Rz(yaw) Ry(pitch) Rx(roll): ``rotation_from_rpy``'s inverse."""
    R = np.asarray(R, float)
    return (math.atan2(R[2, 1], R[2, 2]), math.atan2(-R[2, 0], math.hypot(R[2, 1], R[2, 2])),
            math.atan2(R[1, 0], R[0, 0]))


def rotation_from_quaternion(q_xyzw: np.ndarray) -> np.ndarray:
    """3x3 rotation of a quaternion (x, y, z, w), normalised first."""
    x, y, z, w = np.asarray(q_xyzw, float) / np.linalg.norm(q_xyzw)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def quaternion_from_rotation(R: np.ndarray) -> tuple[float, float, float, float]:
    """Unit quaternion (x, y, z, w) of a 3x3 rotation (Shepperd's method): ``rotation_from_quaternion``'s inverse."""
    m = np.asarray(R, float)
    t = float(np.trace(m))
    if t > 0:
        s = math.sqrt(t + 1.0) * 2
        return ((m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s)
    i = int(np.argmax(np.diag(m)))
    j, k = (i + 1) % 3, (i + 2) % 3
    s = math.sqrt(1.0 + m[i, i] - m[j, j] - m[k, k]) * 2
    q = [0.0, 0.0, 0.0, (m[k, j] - m[j, k]) / s]
    q[i], q[j], q[k] = 0.25 * s, (m[j, i] + m[i, j]) / s, (m[k, i] + m[i, k]) / s
    return (q[0], q[1], q[2], q[3])


def rigid(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t, float).reshape(3)
    return T


def invert(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid transform (or a stack of them, (..., 4, 4))."""
    T = np.asarray(T, float)
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    out = np.zeros_like(T)
    Rt = np.swapaxes(R, -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, t)
    out[..., 3, 3] = 1.0
    return out


def imu_poses(east_north_up_m: np.ndarray, rpy_rad: np.ndarray) -> np.ndarray:
    """(N, 4, 4) T_world_imu from positions (N, 3) and attitudes (N, 3); rows with NaN give NaN poses."""
    enu = np.asarray(east_north_up_m, float).reshape(-1, 3)
    rpy = np.asarray(rpy_rad, float).reshape(-1, 3)
    out = np.full((enu.shape[0], 4, 4), np.nan)
    for k in range(enu.shape[0]):
        if np.all(np.isfinite(enu[k])) and np.all(np.isfinite(rpy[k])):
            out[k] = rigid(rotation_from_rpy(*rpy[k]), enu[k])
    return out


def headings_deg_of(T_world_imu: np.ndarray) -> np.ndarray:
    """(N,) compass headings (0 = north, clockwise, degrees) of the x axes (forward) of (N, 4, 4) imu poses
    (NaN where a pose is unknown)."""
    forward = np.asarray(T_world_imu, float).reshape(-1, 4, 4)[:, :3, 0]
    return (90.0 - np.degrees(np.arctan2(forward[:, 1], forward[:, 0]))) % 360.0


def heading_deg_of(T_world_imu: np.ndarray) -> float:
    """Compass heading of one imu pose (``headings_deg_of``)."""
    return float(headings_deg_of(T_world_imu)[0])


def heading_difference_deg(a_deg: float, b_deg: float) -> float:
    """How far apart two compass headings are, degrees in [0, 180]."""
    return abs((float(a_deg) - float(b_deg) + 180.0) % 360.0 - 180.0)


@dataclass(frozen=True)
class CameraModel:
    """A rectified camera: intrinsics ``K`` (3x3, pixels) and extrinsics ``T_camera_imu`` (4x4, metres)."""

    K: np.ndarray
    T_camera_imu: np.ndarray

    def __post_init__(self) -> None:
        K = np.asarray(self.K, float)
        T = np.asarray(self.T_camera_imu, float)
        if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise ValueError(f"K must be a finite 3x3 matrix with positive focal lengths, got {K.tolist()}")
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise ValueError(f"T_camera_imu must be a finite 4x4 matrix, got shape {T.shape}")
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "T_camera_imu", T)

    @classmethod
    def from_projection(cls, P_rect: np.ndarray, T_camera_imu: np.ndarray) -> "CameraModel":
        """From a rectified projection matrix (its baseline column is already in ``T_camera_imu``)."""
        return cls(K=np.asarray(P_rect, float)[:, :3], T_camera_imu=T_camera_imu)


def projection_matrix(K: np.ndarray, T_world_camera: np.ndarray) -> np.ndarray:
    """3x4 P = K [R | t] of T_camera_world: pixels of world points."""
    return K @ invert(T_world_camera)[:3]


def project(K: np.ndarray, T_world_camera: np.ndarray, points_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (N, 2) and depths (N,) (z in the camera, metres) of world points (N, 3)."""
    X = np.asarray(points_world, float).reshape(-1, 3)
    Xc = X @ invert(T_world_camera)[:3, :3].T + invert(T_world_camera)[:3, 3]
    depth = Xc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = (Xc @ np.asarray(K, float).T)[:, :2] / depth[:, None]
    return uv, depth


# -- two-view verification --------------------------------------------------------------

def _normalised(xy_px: np.ndarray, K: np.ndarray) -> np.ndarray:
    xy = np.asarray(xy_px, float).reshape(-1, 2)
    h = np.c_[xy, np.ones(len(xy))] @ np.linalg.inv(K).T
    return h[:, :2] / h[:, 2:3]


def essential_inliers(xy1_px: np.ndarray, xy2_px: np.ndarray, K1: np.ndarray, K2: np.ndarray, *,
                      threshold_px: float = 1.0, confidence: float = 0.999, seed: int = 0) -> np.ndarray:
    """(N,) bool: which correspondences agree with one essential matrix (RANSAC, calibrated).

    Points are normalised with each camera's own K, so the two cameras may differ;
    ``threshold_px`` is converted with the mean focal length. Fewer than 5
    correspondences (the minimal sample) give no inliers.
    """
    n = len(xy1_px)
    if n < 5:
        return np.zeros(n, bool)
    p1, p2 = _normalised(xy1_px, K1), _normalised(xy2_px, K2)
    focal = 0.25 * (K1[0, 0] + K1[1, 1] + K2[0, 0] + K2[1, 1])
    cv2.setRNGSeed(int(seed))
    E, mask = cv2.findEssentialMat(p1, p2, np.eye(3), method=cv2.USAC_DEFAULT, prob=confidence,
                                   threshold=threshold_px / focal)
    if E is None or mask is None:
        return np.zeros(n, bool)
    return mask.ravel().astype(bool)


# -- triangulation ---------------------------------------------------------------------

@dataclass(frozen=True)
class Triangulation:
    """Points triangulated from two posed views; ``keep`` marks the trustworthy ones.

    points_world: (N, 3) metres; reprojection_px: (N,) the larger of the two views'
    reprojection errors; parallax_deg: (N,) angle between the two viewing rays;
    depth_m: (N, 2) depth in each view.
    """

    points_world: np.ndarray
    reprojection_px: np.ndarray
    parallax_deg: np.ndarray
    depth_m: np.ndarray
    keep: np.ndarray


def triangulate(K_a: np.ndarray, T_world_camera_a: np.ndarray, xy_a_px: np.ndarray,
                K_b: np.ndarray, T_world_camera_b: np.ndarray, xy_b_px: np.ndarray, *,
                max_reprojection_px: float = 1.0, min_parallax_deg: float = 0.5,
                min_depth_m: float = 0.5, max_depth_m: float = 80.0) -> Triangulation:
    """Linear (DLT) triangulation of correspondences between two views with known poses.

    A point is kept when it lies in front of both cameras within [min_depth_m,
    max_depth_m], reprojects within ``max_reprojection_px`` in both views, and its two
    rays meet at ``min_parallax_deg`` or more (tiny parallax = unknown depth).
    """
    xa = np.asarray(xy_a_px, float).reshape(-1, 2)
    xb = np.asarray(xy_b_px, float).reshape(-1, 2)
    n = len(xa)
    if n == 0:
        z = np.zeros(0)
        return Triangulation(np.zeros((0, 3)), z, z, np.zeros((0, 2)), np.zeros(0, bool))
    Pa, Pb = projection_matrix(K_a, T_world_camera_a), projection_matrix(K_b, T_world_camera_b)
    Xh = cv2.triangulatePoints(Pa, Pb, xa.T.copy(), xb.T.copy())
    with np.errstate(divide="ignore", invalid="ignore"):
        X = (Xh[:3] / Xh[3]).T
    uva, za = project(K_a, T_world_camera_a, X)
    uvb, zb = project(K_b, T_world_camera_b, X)
    err = np.maximum(np.linalg.norm(uva - xa, axis=1), np.linalg.norm(uvb - xb, axis=1))
    ra = X - T_world_camera_a[:3, 3]
    rb = X - T_world_camera_b[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        cos = np.einsum("ij,ij->i", ra, rb) / (np.linalg.norm(ra, axis=1) * np.linalg.norm(rb, axis=1))
    parallax = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    depth = np.stack([za, zb], axis=1)
    keep = (np.all(np.isfinite(X), axis=1) & (err <= max_reprojection_px) & (parallax >= min_parallax_deg)
            & np.all(depth >= min_depth_m, axis=1) & np.all(depth <= max_depth_m, axis=1))
    return Triangulation(X, np.where(np.isfinite(err), err, np.inf), np.nan_to_num(parallax), depth, keep)


# -- absolute pose ---------------------------------------------------------------------

@dataclass(frozen=True)
class PnPResult:
    """A camera pose from 2D-3D correspondences.

    T_world_camera: (4, 4) the camera's pose; inliers: (M,) indices into the input
    correspondences; reprojection_rms_px: RMS of the inliers' residuals after
    refinement; pose_cov: (6, 6) covariance of (rvec, tvec) of T_camera_world from the
    Gauss-Newton normal equations, sigma^2 (J'J)^-1 with sigma^2 the inliers' residual
    variance (pixels^2 per coordinate, 2M - 6 degrees of freedom).
    """

    T_world_camera: np.ndarray
    rvec: np.ndarray
    tvec: np.ndarray
    inliers: np.ndarray
    reprojection_rms_px: float
    pose_cov: np.ndarray


REFINE_ROUNDS = 10  # PnP: inliers selected again and refined until they settle, at most this many times


def solve_pnp(points_world: np.ndarray, xy_px: np.ndarray, K: np.ndarray, *, reprojection_px: float = 2.0,
              iterations: int = 1000, confidence: float = 0.999, seed: int = 0,
              min_inliers: int = 12, points_cov: np.ndarray | None = None, kernel: int = cv2.SOLVEPNP_AP3P,
              refine_rounds: int = REFINE_ROUNDS) -> PnPResult | str:
    """Camera pose by PnP RANSAC, refined with Levenberg-Marquardt on the inliers until they settle.

    The RANSAC hypotheses come from ``kernel``, by default AP3P on four points each: where many of a query's
    correspondences are wrong, it reaches RANSAC's confidence in fewer and cheaper samples than a five-point
    kernel (OpenCV's RANSAC with the EPnP or SQPnP flag): where fewer than half fit, 6-7 ms against 26-29 ms
    on the shared drives' camera-rate tracks (``benchmarks/pnp_kernels.py``). A minimal sample is noisier than
    a larger one, so the pose is then refined on its inliers, and the inliers are chosen again at
    ``reprojection_px`` and refined until they no longer change (at most ``refine_rounds`` rounds): the
    consensus settles where the data put it, not where one sample did.

    Returns a ``PnPResult``, or a one-line reason (str) when there are too few
    correspondences or inliers, or the solver fails. With ``points_cov`` (N, 3, 3), each
    point's own uncertainty is propagated into the pose covariance (see ``pose_covariance``).
    """
    X = np.ascontiguousarray(points_world, dtype=np.float64).reshape(-1, 3)
    x = np.ascontiguousarray(xy_px, dtype=np.float64).reshape(-1, 2)
    if len(X) < max(min_inliers, 6):
        return f"only {len(X)} 2D-3D correspondences (need {max(min_inliers, 6)})"
    cv2.setRNGSeed(int(seed))
    try:
        ok, rvec, tvec, inliers = cv2.solvePnPRansac(X, x, K, None, iterationsCount=int(iterations),
                                                     reprojectionError=float(reprojection_px), confidence=confidence,
                                                     flags=int(kernel))
    except cv2.error:  # the solver asserts on degenerate samples (points nearly coincident)
        return "PnP RANSAC: degenerate points"
    if not ok or inliers is None:
        return "PnP RANSAC found no pose"
    inliers = inliers.ravel()
    if len(inliers) < min_inliers:
        return f"PnP RANSAC: {len(inliers)} inliers (need {min_inliers})"
    rvec, tvec = cv2.solvePnPRefineLM(X[inliers], x[inliers], K, None, rvec.copy(), tvec.copy())
    # the refined pose may change which correspondences fit: select them again and refine, until they settle
    for _ in range(max(int(refine_rounds), 1)):
        uv, _ = cv2.projectPoints(X, rvec, tvec, K, None)
        selected = np.flatnonzero(np.linalg.norm(uv.reshape(-1, 2) - x, axis=1) <= reprojection_px)
        if len(selected) < min_inliers:
            return f"PnP refinement: {len(selected)} inliers (need {min_inliers})"
        if np.array_equal(selected, inliers):
            break
        inliers = selected
        rvec, tvec = cv2.solvePnPRefineLM(X[inliers], x[inliers], K, None, rvec, tvec)
    uv, J = cv2.projectPoints(X[inliers], rvec, tvec, K, None)
    res = (uv.reshape(-1, 2) - x[inliers]).ravel()
    dof = max(res.size - 6, 1)
    sigma2 = float(res @ res) / dof
    J = J[:, :6]  # d(pixels)/d(rvec, tvec)
    R, _ = cv2.Rodrigues(rvec)
    try:
        if points_cov is None:
            pose_cov = sigma2 * np.linalg.inv(J.T @ J)
        else:
            pose_cov = pose_covariance(J, res, X[inliers], np.asarray(points_cov)[inliers], K, R, tvec.ravel())
    except np.linalg.LinAlgError:
        return "PnP: degenerate geometry (singular normal equations)"
    T_world_camera = invert(rigid(R, tvec.ravel()))
    return PnPResult(T_world_camera=T_world_camera, rvec=rvec.ravel().copy(), tvec=tvec.ravel().copy(),
                     inliers=inliers, reprojection_rms_px=float(np.sqrt(np.mean(res**2) * 2)),
                     pose_cov=pose_cov)


def pose_covariance(J: np.ndarray, residual_px: np.ndarray, points_world: np.ndarray, points_cov: np.ndarray,
                    K: np.ndarray, R_camera_world: np.ndarray, t_camera_world: np.ndarray) -> np.ndarray:
    """(6, 6) covariance of (rvec, tvec) when both the pixels and the 3D points are uncertain.

    Each correspondence's pixel error has covariance s^2 I + A S A' (A = d pixel / d point, S the
    point's covariance): weighted least squares gives (sum J_i' W_i J_i)^-1 with W_i the inverse.
    s^2, the pixels' own variance, and the a-posteriori variance factor are both taken from the
    residuals: s^2 is what the residuals hold beyond the points' projected variance (never below
    0.1 px^2), and if the weighted residuals are still larger than their degrees of freedom the
    covariance is scaled up by their ratio.
    """
    Xc = points_world @ R_camera_world.T + t_camera_world
    z = Xc[:, 2]
    A = np.zeros((len(Xc), 2, 3))
    A[:, 0, 0] = K[0, 0] / z
    A[:, 1, 1] = K[1, 1] / z
    A[:, 0, 2] = -K[0, 0] * Xc[:, 0] / z**2
    A[:, 1, 2] = -K[1, 1] * Xc[:, 1] / z**2
    A = A @ R_camera_world
    projected = A @ points_cov @ np.swapaxes(A, 1, 2)  # (M, 2, 2)
    r = residual_px.reshape(-1, 2)
    pixel_var = max(float(np.mean(r**2)) - float(np.mean(np.trace(projected, axis1=1, axis2=2))) / 2.0, 0.1)
    W = np.linalg.inv(pixel_var * np.eye(2) + projected)
    Ji = J.reshape(-1, 2, 6)
    information = np.einsum("mai,mab,mbj->ij", Ji, W, Ji)
    chi2 = float(np.einsum("ma,mab,mb->", r, W, r))
    factor = max(1.0, chi2 / max(r.size - 6, 1))
    return factor * np.linalg.inv(information)


def refine_pose(points_world: np.ndarray, xy_px: np.ndarray, K: np.ndarray, start: PnPResult) -> np.ndarray:
    """T_world_camera refined by Levenberg-Marquardt on these correspondences only, from ``start``'s pose."""
    rvec, tvec = cv2.solvePnPRefineLM(np.ascontiguousarray(points_world, dtype=np.float64).reshape(-1, 3),
                                      np.ascontiguousarray(xy_px, dtype=np.float64).reshape(-1, 2), K, None,
                                      start.rvec.reshape(3, 1).copy(), start.tvec.reshape(3, 1).copy())
    R, _ = cv2.Rodrigues(rvec)
    return invert(rigid(R, tvec.ravel()))


def imu_pose_from_camera(T_world_camera: np.ndarray, T_camera_imu: np.ndarray) -> np.ndarray:
    """T_world_imu of the vehicle whose camera has pose ``T_world_camera``."""
    return T_world_camera @ T_camera_imu


def imu_east_north_covariance(pnp: PnPResult, T_camera_imu: np.ndarray, step: float = 1e-6) -> np.ndarray:
    """2x2 covariance (m^2) of the imu's east/north position, propagated from PnP's pose covariance.

    f(rvec, tvec) = east/north of T_world_camera(rvec, tvec) @ T_camera_imu; its
    Jacobian is taken by central differences.
    """
    def position(p: np.ndarray) -> np.ndarray:
        R, _ = cv2.Rodrigues(p[:3])
        return (invert(rigid(R, p[3:])) @ T_camera_imu)[:2, 3]

    p0 = np.concatenate([pnp.rvec, pnp.tvec])
    J = np.zeros((2, 6))
    for k in range(6):
        d = np.zeros(6)
        d[k] = step
        J[:, k] = (position(p0 + d) - position(p0 - d)) / (2 * step)
    cov = J @ pnp.pose_cov @ J.T
    return 0.5 * (cov + cov.T)
