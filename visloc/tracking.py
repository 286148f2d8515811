"""Constant-velocity Kalman filter of the paper's equations (3)-(7).

State X = [x, y, vx, vy] (east m, north m, east m/s, north m/s) in the local frame
of ``visloc.geo``; measurement y = [x, y], the geotag of the best database match.

    F = [[1, 0, dt, 0], [0, 1, 0, dt], [0, 0, 1, 0], [0, 0, 0, 1]]   (6)
    H = [[1, 0, 0, 0], [0, 1, 0, 0]]                                 (7)

The first measurement initialises the position (velocity 0) with covariance P0
and is then applied as an ordinary update, so the first estimate equals the first
measurement and its covariance is (P0^-1 + R^-1)^-1 on the position.
A missing measurement (``None``: no database image had a correspondence) only
predicts. Covariances are updated in Joseph form, which stays symmetric and
positive semi-definite.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from visloc.params import FilterParams

STATE_DIM = 4
MEAS_DIM = 2
H = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0]])  # (7)


def transition_matrix(dt_s: float) -> np.ndarray:
    """F of equation (6)."""
    F = np.eye(STATE_DIM)
    F[0, 2] = F[1, 3] = dt_s
    return F


def process_noise(dt_s: float, accel_var_m2_s4: float) -> np.ndarray:
    """Q for piecewise-constant white acceleration: sigma_a^2 G G^T, G = [dt^2/2, dt] per axis."""
    g = np.array([0.5 * dt_s**2, dt_s])
    block = accel_var_m2_s4 * np.outer(g, g)
    Q = np.zeros((STATE_DIM, STATE_DIM))
    Q[np.ix_([0, 2], [0, 2])] = block
    Q[np.ix_([1, 3], [1, 3])] = block
    return Q


def predict(x: np.ndarray, P: np.ndarray, F: np.ndarray, Q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    # x = F x
    x = F @ x
    # P = F P F' + Q
    P = F @ P @ F.T + Q
    return x, P


@dataclass(frozen=True)
class Innovation:
    y: np.ndarray  # (2,) residual z - H x, m
    S: np.ndarray  # (2, 2) residual covariance, m^2
    K: np.ndarray  # (4, 2) Kalman gain
    mahalanobis: float  # sqrt(y' S^-1 y)


def update(x: np.ndarray, P: np.ndarray, z: np.ndarray, R: np.ndarray) -> tuple[np.ndarray, np.ndarray, Innovation]:
    # y = z - H x
    y = np.asarray(z, float).reshape(MEAS_DIM) - H @ x
    # S = H P H' + R
    S = H @ P @ H.T + R
    # K = P H' S^-1   (solve instead of inverting S)
    K = np.linalg.solve(S.T, (P @ H.T).T).T
    # x = x + K y
    x = x + K @ y
    # P = (I - K H) P (I - K H)' + K R K'   (Joseph form)
    I_KH = np.eye(STATE_DIM) - K @ H
    P = I_KH @ P @ I_KH.T + K @ R @ K.T
    mahalanobis = float(np.sqrt(max(y @ np.linalg.solve(S, y), 0.0)))
    return x, P, Innovation(y=y, S=S, K=K, mahalanobis=mahalanobis)


@dataclass(frozen=True)
class FilterStep:
    """One step of the filter: prior, posterior and the innovation (None without a measurement)."""

    x_prior: np.ndarray
    P_prior: np.ndarray
    x: np.ndarray
    P: np.ndarray
    innovation: Innovation | None

    @property
    def position_m(self) -> np.ndarray:
        return self.x[:2]

    @property
    def position_cov_m2(self) -> np.ndarray:
        return self.P[:2, :2]


class ConstantVelocityKalman:
    """The paper's filter, one ``step(z)`` per query.

    ``z`` is the measured (east_m, north_m) or None. Before the first measurement
    the filter has no state; a ``None`` then yields an empty step (``x`` all NaN).
    """

    def __init__(self, params: FilterParams):
        self.params = params
        self.F = transition_matrix(params.dt_s)
        self.Q = process_noise(params.dt_s, params.accel_var_m2_s4)
        self.R = params.meas_var_m2 * np.eye(MEAS_DIM)
        self.P0 = params.init_var * np.eye(STATE_DIM)
        self.x: np.ndarray | None = None
        self.P: np.ndarray | None = None
        assert self.F.shape == (STATE_DIM, STATE_DIM) and self.Q.shape == (STATE_DIM, STATE_DIM)
        assert self.R.shape == (MEAS_DIM, MEAS_DIM) and H.shape == (MEAS_DIM, STATE_DIM)

    @property
    def initialised(self) -> bool:
        return self.x is not None

    def step(self, z: np.ndarray | None) -> FilterStep:
        if self.x is None:
            if z is None:
                nan = np.full(STATE_DIM, np.nan)
                nan_p = np.full((STATE_DIM, STATE_DIM), np.nan)
                return FilterStep(nan, nan_p, nan, nan_p, None)
            x_prior = np.concatenate([np.asarray(z, float).reshape(MEAS_DIM), np.zeros(2)])
            P_prior = self.P0.copy()
        else:
            x_prior, P_prior = predict(self.x, self.P, self.F, self.Q)
        if z is None:
            self.x, self.P = x_prior, P_prior
            return FilterStep(x_prior, P_prior, x_prior, P_prior, None)
        self.x, self.P, innovation = update(x_prior, P_prior, z, self.R)
        return FilterStep(x_prior, P_prior, self.x.copy(), self.P.copy(), innovation)


def run_filter(measurements_m: list[np.ndarray | None], params: FilterParams) -> list[FilterStep]:
    """Filter a whole sequence of measurements (east_m, north_m) or None."""
    kf = ConstantVelocityKalman(params)
    return [kf.step(z) for z in measurements_m]


def covariance_ellipse_m(center_m: np.ndarray, cov_m2: np.ndarray, n_sigma: float = 2.0,
                         n_points: int = 48) -> np.ndarray:
    """(n_points, 2) points on the n_sigma ellipse of a 2x2 position covariance around center_m.

    The ellipse is {c + n_sigma * L u : |u| = 1} with L L^T = cov (eigen decomposition),
    so a 2-sigma ellipse holds about 86% of a 2-D Gaussian's mass.
    """
    cov = np.asarray(cov_m2, float)
    if cov.shape != (2, 2) or not np.all(np.isfinite(cov)):
        raise ValueError(f"covariance must be a finite 2x2 matrix, got {cov.shape}")
    eigval, eigvec = np.linalg.eigh(0.5 * (cov + cov.T))
    radii_m = n_sigma * np.sqrt(np.clip(eigval, 0.0, None))
    angle = np.linspace(0.0, 2.0 * np.pi, n_points, endpoint=False)
    unit = np.stack([np.cos(angle), np.sin(angle)], axis=1)
    return np.asarray(center_m, float)[None, :2] + (unit * radii_m) @ eigvec.T
