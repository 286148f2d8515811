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

Beyond the paper (the refined mode): a step may bring its own measurement
covariance ``R`` (``step(z, R)``; None = the filter's constant R), and with
``gate_chi2 > 0`` a measurement whose squared Mahalanobis distance to the prediction,
y' S^-1 y, exceeds ``gate_chi2`` is not applied: the step only predicts and is marked
``gated`` (its innovation is kept for diagnostics). Every measurement is also tested against
two other predictions, and applied with the likeliest of the three (the Gaussian density of its
innovation, which weighs how far off it is against how loose each prediction is); beyond the gate
it must fit one of the other two. The first is a *maneuver* prediction, made with the process noise of a firm brake or a
tight turn (``FilterParams.maneuver_accel_var_m2_s4``) instead of Q: a measurement that fits
that one is applied with it (marked ``maneuver``), since what was wrong was the constant-velocity
prediction, not the measurement. Before that, it is tested against the track without the
previous measurement (predicted from the state before it): a bad measurement that got into the
state (one that claimed to be precise and was not) is taken out as soon as the next one
contradicts it, marked ``retracted_previous``, and the good ones are never locked out. With
``reinit_after_gated = n``, the n-th gated measurement in a row restarts the track at that
measurement instead (its velocity from the previous gated one), marked ``restarted``: an
outlier neither enters the track nor locks the measurements that follow out of it, and a first
measurement that was an outlier is replaced as soon as the measurements after it agree with
each other. ``rts_smooth`` is the Rauch-Tung-Striebel smoother over a finished run's steps,
run on each segment between restarts on its own.

At any rate: Q's acceleration variance is the paper's over its 1 s query interval, and a filter
stepped faster scales it by 1 s / dt, so the velocity may change as much in a second at 10 Hz as at
1 Hz (``process_noise``); at 1 s, Q is the paper's.

Beyond the paper (the refined modes at any rate): consecutive pose measurements share part of their
errors (the same database views, the same stored structure), so ten of them a second are not ten
independent looks. With ``corr_fraction`` c > 0 the state gains a measurement-bias state u (2,
unitless), a first-order Gauss-Markov process of unit variance and correlation time ``corr_time_s`` τ:

    u_k+1 = φ u_k + w,  φ = exp(-dt/τ),  w ~ N(0, (1 - φ²) I)

and a measurement z with covariance R (L L' = R, its symmetric square root) is read as

    z = p + sqrt(c) L u + e,  e ~ N(0, (1 - c) R),   so H = [I, 0, sqrt(c) L]

Each measurement alone still has covariance R, and two of them dt apart correlate by c φ (in
each one's own units). The estimate's covariance then stops shrinking like R/n when the
measurements come faster than τ: it tends to c R, the part they share. A step marked
``correlated=False`` (a geotag fallback, whose error has nothing to do with the poses') is read
without u. With c = 0 (the paper's method) the state is the paper's four numbers.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from visloc.errors import ParameterError
from visloc.params import FilterParams

STATE_DIM = 4
MEAS_DIM = 2
REFERENCE_INTERVAL_S = 1.0  # the interval over which Q's acceleration variance holds (the paper's query interval)

H = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0]])  # (7)


def transition_matrix(dt_s: float) -> np.ndarray:
    """F of equation (6)."""
    F = np.eye(STATE_DIM)
    F[0, 2] = F[1, 3] = dt_s
    return F


def process_noise(dt_s: float, accel_var_m2_s4: float) -> np.ndarray:
    """Q for piecewise-constant white acceleration: sigma_a^2 (T / dt) G G^T, G = [dt^2/2, dt] per axis, where
    sigma_a^2 = ``accel_var_m2_s4`` is the variance of the acceleration held over one reference interval T
    (``REFERENCE_INTERVAL_S``, the paper's 1 s query interval: there Q is the paper's sigma_a^2 G G^T). At any
    other step the velocity's variance then grows by sigma_a^2 T per second, as at 1 s: the same vehicle, however
    often it is measured. Without the T / dt, ten steps of 0.1 s would let the velocity change a tenth as much in
    a second as one step of 1 s, and at the camera's rate the estimate would lag every turn and brake."""
    g = np.array([0.5 * dt_s**2, dt_s])
    block = accel_var_m2_s4 * (REFERENCE_INTERVAL_S / dt_s) * np.outer(g, g)
    Q = np.zeros((STATE_DIM, STATE_DIM))
    Q[np.ix_([0, 2], [0, 2])] = block
    Q[np.ix_([1, 3], [1, 3])] = block
    return Q


def bias_decay(dt_s: float, corr_time_s: float) -> float:
    """φ = exp(-dt/τ): how much of the measurement bias survives one step."""
    return float(np.exp(-dt_s / corr_time_s))


def augmented_transition(dt_s: float, corr_time_s: float) -> np.ndarray:
    """F of the state with the measurement bias: equation (6)'s block, then φ I on u."""
    F = np.eye(STATE_DIM + MEAS_DIM)
    F[:STATE_DIM, :STATE_DIM] = transition_matrix(dt_s)
    F[STATE_DIM:, STATE_DIM:] *= bias_decay(dt_s, corr_time_s)
    return F


def augmented_noise(Q: np.ndarray, dt_s: float, corr_time_s: float) -> np.ndarray:
    """Q of the state with the measurement bias: ``Q``, then (1 - φ²) I on u (unit variance kept)."""
    out = np.zeros((STATE_DIM + MEAS_DIM, STATE_DIM + MEAS_DIM))
    out[:STATE_DIM, :STATE_DIM] = Q
    out[STATE_DIM:, STATE_DIM:] = (1.0 - bias_decay(dt_s, corr_time_s) ** 2) * np.eye(MEAS_DIM)
    return out


def _sqrt_psd(R: np.ndarray) -> np.ndarray:
    """The symmetric square root of a 2x2 covariance (negative eigenvalues clipped at 0)."""
    w, V = np.linalg.eigh(0.5 * (R + R.T))
    return (V * np.sqrt(np.clip(w, 0.0, None))) @ V.T


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
    K: np.ndarray  # (n, 2) Kalman gain (n: 4, or 6 with the measurement bias)
    mahalanobis: float  # sqrt(y' S^-1 y)


def _log_likelihood(innovation: "Innovation") -> float:
    """ln of the Gaussian density of an innovation y under its covariance S, up to a constant:
    -(y' S^-1 y + ln det S) / 2."""
    return -0.5 * (innovation.mahalanobis**2 + float(np.log(np.linalg.det(innovation.S))))


def update(x: np.ndarray, P: np.ndarray, z: np.ndarray, R: np.ndarray,
           H: np.ndarray = H) -> tuple[np.ndarray, np.ndarray, Innovation]:
    # y = z - H x
    y = np.asarray(z, float).reshape(MEAS_DIM) - H @ x
    # S = H P H' + R
    S = H @ P @ H.T + R
    # K = P H' S^-1   (solve instead of inverting S)
    try:
        K = np.linalg.solve(S.T, (P @ H.T).T).T
    except np.linalg.LinAlgError:  # R = 0 where P = 0 on the position: FilterParams refuses the constant cases
        raise ParameterError("the filter's innovation covariance S = P + R is singular: a measurement variance R of "
                             "0 met a position variance P of 0 (for example --geotag-sigma-m 0 with --init-var 0); "
                             "give R or the initial variance P0 a value > 0") from None
    # x = x + K y
    x = x + K @ y
    # P = (I - K H) P (I - K H)' + K R K'   (Joseph form)
    I_KH = np.eye(x.size) - K @ H
    P = I_KH @ P @ I_KH.T + K @ R @ K.T
    mahalanobis = float(np.sqrt(max(y @ np.linalg.solve(S, y), 0.0)))
    return x, P, Innovation(y=y, S=S, K=K, mahalanobis=mahalanobis)


class PositionOfState:
    """The position part of a constant-velocity state ``x`` (east, north, their velocities) and of its
    covariance ``P``."""

    x: np.ndarray
    P: np.ndarray

    @property
    def position_m(self) -> np.ndarray:
        return self.x[:2]

    @property
    def position_cov_m2(self) -> np.ndarray:
        return self.P[:2, :2]


@dataclass(frozen=True)
class FilterStep(PositionOfState):
    """One step of the filter: prior, posterior and the innovation (None without a measurement)."""

    x_prior: np.ndarray
    P_prior: np.ndarray
    x: np.ndarray
    P: np.ndarray
    innovation: Innovation | None
    gated: bool = False  # the measurement was rejected by the Mahalanobis gate (x, P are the prediction)
    R: np.ndarray | None = None  # the measurement covariance this step used, m^2 (None: no measurement)
    restarted: bool = False  # the track was lost and started again at this measurement
    maneuver: bool = False  # the measurement fitted only the maneuver prediction, and was applied with it
    retracted_previous: bool = False  # the previous step's measurement was taken out: this one fitted the track
    #                                   without it (x_prior, P_prior predict from the step before it)
    F: np.ndarray | None = None  # the transition x_prior was predicted with (None: the paper's, equation (6))


class ConstantVelocityKalman:
    """The paper's filter, one ``step(z)`` per query.

    ``z`` is the measured (east_m, north_m) or None. Before the first measurement
    the filter has no state; a ``None`` then yields an empty step (``x`` all NaN). ``corr_fraction``
    and ``corr_time_s``: the measurement bias of the module docstring (0: none, the paper's state).
    """

    def __init__(self, params: FilterParams, *, gate_chi2: float = 0.0, reinit_after_gated: int = 0,
                 corr_fraction: float = 0.0, corr_time_s: float = 1.0):
        if not (0.0 <= corr_fraction < 1.0) or not corr_time_s > 0:
            raise ParameterError(f"corr_fraction={corr_fraction!r} must lie in [0, 1) and corr_time_s="
                                 f"{corr_time_s!r} be > 0")
        self.params = params
        self.gate_chi2 = float(gate_chi2)  # 0: no gating
        self.reinit_after_gated = int(reinit_after_gated)  # 0: never re-initialise
        self._gated: list[np.ndarray] = []  # consecutive gated measurements (east_m, north_m)
        self._before: tuple[np.ndarray, np.ndarray] | None = None  # (x, P) before the last applied update
        self._applied = 0  # measurements applied since the track (re)started
        self.corr_fraction = float(corr_fraction)
        self.F = transition_matrix(params.dt_s)
        self.Q = process_noise(params.dt_s, params.accel_var_m2_s4)
        self.Q_maneuver = process_noise(params.dt_s, max(params.maneuver_accel_var_m2_s4, params.accel_var_m2_s4))
        self.R = params.meas_var_m2 * np.eye(MEAS_DIM)
        self.P0 = params.init_var * np.eye(STATE_DIM)
        if self.corr_fraction > 0:  # the measurement bias u: unit variance to start with
            self.F = augmented_transition(params.dt_s, corr_time_s)
            self.Q, self.Q_maneuver = (augmented_noise(Q, params.dt_s, corr_time_s) for Q in (self.Q, self.Q_maneuver))
            self.P0 = np.diag(np.r_[np.full(STATE_DIM, params.init_var), np.ones(MEAS_DIM)])
        self.n = self.F.shape[0]  # state size: 4, or 6 with the measurement bias
        self.x: np.ndarray | None = None
        self.P: np.ndarray | None = None
        assert self.Q.shape == self.F.shape == self.P0.shape == (self.n, self.n)
        assert self.R.shape == (MEAS_DIM, MEAS_DIM) and H.shape == (MEAS_DIM, STATE_DIM)

    def _model(self, R: np.ndarray, correlated: bool) -> tuple[np.ndarray, np.ndarray]:
        """(H, the white part of R) for a measurement of covariance ``R``: with the measurement bias and
        ``correlated``, H = [I, 0, sqrt(c) L] and (1 - c) R; otherwise H = [I, 0] and R."""
        Hk = np.zeros((MEAS_DIM, self.n))
        Hk[:, :MEAS_DIM] = np.eye(MEAS_DIM)
        if self.n == STATE_DIM or not correlated:
            return Hk, R
        Hk[:, STATE_DIM:] = np.sqrt(self.corr_fraction) * _sqrt_psd(R)
        return Hk, (1.0 - self.corr_fraction) * R

    def prediction(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The next step's predicted position (east_m, north_m) and its 2x2 covariance (m^2);
        None before the first measurement."""
        if self.x is None:
            return None
        x, P = predict(self.x, self.P, self.F, self.Q)
        return x[:2], P[:2, :2]

    def step(self, z: np.ndarray | None, R: np.ndarray | None = None, *, correlated: bool = True) -> FilterStep:
        """One query: predict, then update with ``z`` (east_m, north_m) using ``R`` (2x2, m^2) or the filter's R.
        ``correlated``: the measurement shares the measurement bias (module docstring); a geotag fallback does not."""
        R = self.R if R is None else np.asarray(R, float)
        if R.shape != (MEAS_DIM, MEAS_DIM) or not np.all(np.isfinite(R)):
            raise ValueError(f"R must be a finite {MEAS_DIM}x{MEAS_DIM} covariance, got {R!r}")
        Hk, Rk = self._model(R, correlated)
        if self.x is None or (z is not None and self._track_lost(z, Rk, Hk)):
            return self._initialise(z, R, Rk, Hk)
        x_prior, P_prior = predict(self.x, self.P, self.F, self.Q)
        if z is None:
            self.x, self.P, self._before = x_prior, P_prior, None
            return FilterStep(x_prior, P_prior, x_prior, P_prior, None, F=self._F_kept())
        x, P, innovation = update(x_prior, P_prior, z, Rk, Hk)
        kind = None
        if self.gate_chi2 > 0:
            fitted = self._other_hypothesis(z, Rk, Hk)
            normal_fits = innovation.mahalanobis**2 <= self.gate_chi2
            if fitted is not None and (not normal_fits or fitted[3] > _log_likelihood(innovation)):
                kind, x_prior, P_prior, _ = fitted
                x, P, innovation = update(x_prior, P_prior, z, Rk, Hk)
            elif not normal_fits:  # nothing explains it: an outlier, predict only
                self._gated.append(np.asarray(z, float).reshape(MEAS_DIM))
                self.x, self.P, self._before = x_prior, P_prior, None
                return FilterStep(x_prior, P_prior, x_prior.copy(), P_prior.copy(), innovation, gated=True, R=R,
                                  F=self._F_kept())
        self._gated = []
        self._applied += 1
        # a measurement can be retracted once the track before it knew its velocity (two measurements)
        self._before = (self.x, self.P) if kind != "retract" and self._applied >= 3 else None
        self._last = (np.asarray(z, float).reshape(MEAS_DIM), Rk, Hk)
        self.x, self.P = x, P
        return FilterStep(x_prior, P_prior, self.x.copy(), self.P.copy(), innovation, R=R,
                          maneuver=kind == "maneuver", retracted_previous=kind == "retract", F=self._F_kept())

    def _F_kept(self) -> np.ndarray | None:
        """The transition a step records for the smoother: None when it is the paper's (equation (6))."""
        return None if self.n == STATE_DIM else self.F

    def _other_hypothesis(self, z: np.ndarray, R: np.ndarray,
                          Hk: np.ndarray = H) -> tuple[str, np.ndarray, np.ndarray, float] | None:
        """A prediction ``z`` fits when the constant-velocity one does not, as ("retract" or "maneuver",
        x_prior, P_prior, its Mahalanobis distance), else None: the previous measurement was the bad one (predict from the state
        before it, twice, with Q; only when it contradicts that track and ``z``), or the car turned or
        braked (predict with the maneuver process noise, ``maneuver_accel_var_m2_s4``, when that exceeds
        Q). Where both fit, the one with the smaller Mahalanobis distance."""
        candidates = []
        if self._before is not None:
            x1, P1 = predict(*self._before, self.F, self.Q)
            x2, P2 = predict(x1, P1, self.F, self.Q)
            if self._previous_contradicted(x1, P1, x2, P2, z, R, Hk):
                candidates.append(("retract", x2, P2))
        if self.params.maneuver_accel_var_m2_s4 > self.params.accel_var_m2_s4:
            candidates.append(("maneuver", *predict(self.x, self.P, self.F, self.Q_maneuver)))
        fits = [(update(x, P, z, R, Hk)[2], kind, x, P) for kind, x, P in candidates]
        fits = [f for f in fits if f[0].mahalanobis ** 2 <= self.gate_chi2]
        if not fits:
            return None
        innovation, kind, x_prior, P_prior = max(fits, key=lambda f: _log_likelihood(f[0]))  # the likeliest
        return kind, x_prior, P_prior, _log_likelihood(innovation)

    def _previous_contradicted(self, x1: np.ndarray, P1: np.ndarray, x2: np.ndarray, P2: np.ndarray, z: np.ndarray,
                               R: np.ndarray, Hk: np.ndarray = H) -> bool:
        """Whether the previous measurement contradicts the track without it and ``z``: the state at its
        step, smoothed from the state before it (``x1``, ``P1``: its prediction) and this one (``x2``,
        ``P2``: the prediction two steps on, updated with ``z``), does not hold it within the gate. A
        measurement that merely moved the track (as the first of a turn) is kept."""
        x_now, P_now, _ = update(x2, P2, z, R, Hk)
        # one Rauch-Tung-Striebel step back: C = P1 F' P2^-1
        C = np.linalg.solve(P2, self.F @ P1).T
        x_s = x1 + C @ (x_now - x2)
        P_s = P1 + C @ (P_now - P2) @ C.T
        last_z, last_R, last_H = self._last
        y = last_z - last_H @ x_s
        S = last_H @ P_s @ last_H.T + last_R
        return float(y @ np.linalg.solve(S, y)) > self.gate_chi2

    def _track_lost(self, z: np.ndarray, R: np.ndarray, Hk: np.ndarray = H) -> bool:
        """True when this measurement would be gated too and the last ``reinit_after_gated`` - 1 were:
        the measurements agree with each other, not with the track."""
        if self.reinit_after_gated <= 0 or self.gate_chi2 <= 0 or len(self._gated) < self.reinit_after_gated - 1:
            return False
        x_prior, P_prior = predict(self.x, self.P, self.F, self.Q)
        _, _, innovation = update(x_prior, P_prior, z, R, Hk)
        return innovation.mahalanobis**2 > self.gate_chi2 and self._other_hypothesis(z, R, Hk) is None

    def _initialise(self, z: np.ndarray | None, R: np.ndarray, Rk: np.ndarray, Hk: np.ndarray) -> FilterStep:
        """Start (or restart) the track at ``z``; a restart takes its velocity from the last gated
        measurement and this one. ``R`` is the measurement's covariance, ``Rk`` and ``Hk`` how it is read."""
        if z is None:
            nan = np.full(self.n, np.nan)
            nan_p = np.full((self.n, self.n), np.nan)
            return FilterStep(nan, nan_p, nan, nan_p, None)
        z = np.asarray(z, float).reshape(MEAS_DIM)
        velocity = np.zeros(2)
        if self._gated and self.x is not None:
            velocity = (z - self._gated[-1]) / self.params.dt_s
        x_prior = np.concatenate([z, velocity, np.zeros(self.n - STATE_DIM)])
        P_prior = self.P0.copy()
        x, P, innovation = update(x_prior, P_prior, z, Rk, Hk)
        restarted = self.x is not None
        self._gated = []
        self._before = None
        self._applied = 1
        self.x, self.P = x, P
        self._last = (z, Rk, Hk)
        return FilterStep(x_prior, P_prior, self.x.copy(), self.P.copy(), innovation, R=R, restarted=restarted)


def run_filter(measurements_m: list[np.ndarray | None], params: FilterParams, *,
               covariances_m2: list[np.ndarray | None] | None = None, gate_chi2: float = 0.0,
               reinit_after_gated: int = 0, correlated: list[bool] | None = None, corr_fraction: float = 0.0,
               corr_time_s: float = 1.0) -> list[FilterStep]:
    """Filter a whole sequence of measurements (east_m, north_m) or None.

    ``covariances_m2``: per step a 2x2 R or None (the filter's R); ``correlated``: per step whether the
    measurement shares the measurement bias (default: all); ``gate_chi2``, ``corr_fraction``,
    ``corr_time_s``: see the module docstring.
    """
    kf = ConstantVelocityKalman(params, gate_chi2=gate_chi2, reinit_after_gated=reinit_after_gated,
                                corr_fraction=corr_fraction, corr_time_s=corr_time_s)
    covs = covariances_m2 if covariances_m2 is not None else [None] * len(measurements_m)
    shared = correlated if correlated is not None else [True] * len(measurements_m)
    if not len(covs) == len(shared) == len(measurements_m):
        raise ValueError("covariances_m2 and correlated must have one entry per measurement")
    return [kf.step(z, R, correlated=c) for z, R, c in zip(measurements_m, covs, shared)]


@dataclass(frozen=True)
class SmoothedStep(PositionOfState):
    x: np.ndarray  # (n,) smoothed state (n: 4, or 6 with the measurement bias)
    P: np.ndarray  # (n, n) its covariance


def rts_smooth(steps: list[FilterStep], dt_s: float) -> list[SmoothedStep]:
    """Rauch-Tung-Striebel smoothing of a finished filter run (constant velocity, step ``dt_s``).

    Uses each step's stored prediction (x_prior, P_prior = F P F' + Q, or the maneuver Q it was
    applied with), so it needs only F: the step's own (with the measurement bias), else equation (6)'s. Steps before the first measurement (NaN state) stay NaN.
    A restart cuts the run into segments, each smoothed on its own: the step before a restart
    is not smoothed towards the new track (its prior was P0 at the restart, not a prediction).
    A step whose measurement the next one retracted counts as its prediction alone.
    Backwards from the last step k = n-2 .. first:
        C_k = P_k F' (P_prior_{k+1})^-1
        x_s_k = x_k + C_k (x_s_{k+1} - x_prior_{k+1})
        P_s_k = P_k + C_k (P_s_{k+1} - P_prior_{k+1}) C_k'
    """
    F = transition_matrix(dt_s)
    # a step whose measurement the next step retracted is, for the smoother, its own prediction
    xs = [s.x_prior if k + 1 < len(steps) and steps[k + 1].retracted_previous else s.x for k, s in enumerate(steps)]
    Ps = [s.P_prior if k + 1 < len(steps) and steps[k + 1].retracted_previous else s.P for k, s in enumerate(steps)]
    out = [SmoothedStep(x.copy(), P.copy()) for x, P in zip(xs, Ps)]
    for k in range(len(steps) - 2, -1, -1):
        if not np.all(np.isfinite(xs[k])):
            continue  # before the track started
        nxt = steps[k + 1]
        if nxt.restarted:
            continue  # the last step of a segment: nothing after it belongs to its track
        Fk = F if nxt.F is None else nxt.F
        # C = P F' Pp^-1   (solve instead of inverting Pp; Pp is symmetric)
        C = np.linalg.solve(nxt.P_prior, Fk @ Ps[k]).T
        # x_s = x + C (x_s' - x_prior')
        x = xs[k] + C @ (out[k + 1].x - nxt.x_prior)
        # P_s = P + C (P_s' - P_prior') C'
        P = Ps[k] + C @ (out[k + 1].P - nxt.P_prior) @ C.T
        out[k] = SmoothedStep(x, 0.5 * (P + P.T))
    return out


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
