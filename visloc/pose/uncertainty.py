"""What a refined measurement's covariance is made of, and how honest it is.

A refined measurement places the query in the frame of the database's geotags. Its error against
the query's true position has two parts, kept apart here:

* the **relative** part, what the pose gets wrong within the map: the PnP fit (pixel noise and
  the triangulated points' own uncertainty), the disagreement of the views it was posed against,
  and what the database's poses get wrong over the metres between the query and its nearest view
  (a residual bend of the structure, a heading or a scale a little off: an error that grows with
  that *lever*, and faster where every view lies on one side of the query, as a ruler read beyond
  its end; along the road, where a scale a little off moves it, at another rate than across it,
  where a heading does). For the mean of views posed apart, the part of that error each view has of its own is in
  their spread; the lever term is what they share, and the gain is measured on such means. The filter
  fuses this part: it differs from one query to the next.
* the **absolute** part, the error the map's geotags share with any map of that receiver (the
  stated accuracy of the views' geotags: OXTS ``pos_accuracy``). No number of queries averages it
  away, so it is not fed to the filter: it is stated beside the estimate (``absolute_cov_m2``).

The lever's gain (metres of error per metre of lever) is a property of each database, and is
measured on it: the store poses its own images from their neighbours, each with the images
closer in time than the evaluation's exclusion window left out, as a query of that drive would
be (``visloc.pose.selfcheck``: posed as the path's measurements are, each the mean of views posed apart with
their spread in its covariance), and ``fit_lever_gains`` finds, per side, the gains along and across the heading whose
ellipses hold those poses as a Gaussian's would (80 % of them inside their 80 % ellipse). Nothing of a query's ground truth enters it. A store
without a self-check uses ``DEFAULT_LEVER_GAIN``, fitted once on the shared development drives.

Pure functions over numpy arrays.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from visloc.stats import CHI2_2DOF_95, chi2_1dof_quantile, chi2_2dof_quantile

SIDES = ("both", "one")  # views on both sides of the query, or on one side only
NOMINAL_LEVELS = (0.10, 0.20, 0.30, 0.40, 0.50, 0.60, 0.70, 0.80, 0.90, 0.95, 0.99)


@dataclass(frozen=True)
class LeverGain:
    """Metres of relative error per metre between a pose and its nearest view, per side, along the vehicle's
    heading and across it.

    both_sides: the query has views before and after it; one_side: every view lies on one side; each along
    the heading, and across it ``both_sides_across``, ``one_side_across`` (None: the same as along). A
    database's error over a lever need not be round: along the road it is the scale of its structure (how
    far apart its geotags put its images), across it the heading of its poses, and one can be several times
    the other (``fit_lever_gains``). n_both, n_one: the self-check poses each was measured on (0: the
    default); source: where the numbers come from ("self-check of SOURCE/CAMERA" or "default")."""

    both_sides: float
    one_side: float
    n_both: int = 0
    n_one: int = 0
    source: str = "default"
    both_sides_across: float | None = None
    one_side_across: float | None = None

    def of(self, side: str) -> float:
        """The gain along the heading."""
        return self.both_sides if side == "both" else self.one_side

    def across_of(self, side: str) -> float:
        """The gain across the heading."""
        across = self.both_sides_across if side == "both" else self.one_side_across
        return self.of(side) if across is None else across

    def covariance_m2(self, side: str, lever_m: float, heading_deg: float | None) -> np.ndarray:
        """(2, 2) the lever term of a pose with views on ``side``, ``lever_m`` from its nearest view, the
        vehicle heading ``heading_deg`` (compass; None: round, the larger gain both ways)."""
        return lever_covariance_m2(self.of(side), lever_m, across_gain=self.across_of(side),
                                   heading_deg=heading_deg)

    def as_dict(self) -> dict:
        return {"both_sides": self.both_sides, "one_side": self.one_side,
                "both_sides_across": self.across_of("both"), "one_side_across": self.across_of("one"),
                "n_both": self.n_both, "n_one": self.n_one, "source": self.source}


# Fitted (``visloc.pose.selfcheck.lever_gain_from``) on the self-checks of the shared development drives pooled
# (2011_09_26_drive_0001 both cameras, 2011_09_26_drive_0005, 2011_10_03_drive_0027: 264 poses, each the mean of
# views posed apart; per drive they range from 0.002 to 0.031; ``benchmarks/self_check_agreement.py`` prints the
# pooled fit): used only by a store that has no self-check yet.
DEFAULT_LEVER_GAIN = LeverGain(both_sides=0.006, one_side=0.020)


def along_across(heading_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """Unit vectors (east, north) along a compass heading (0 = north, clockwise) and across it (to the left)."""
    h = np.radians(float(heading_deg))
    return np.array([np.sin(h), np.cos(h)]), np.array([-np.cos(h), np.sin(h)])


def lever_covariance_m2(gain: float, lever_m: float, *, across_gain: float | None = None,
                        heading_deg: float | None = None) -> np.ndarray:
    """(2, 2) covariance of the database's error carried over a lever: (gain * lever)^2 along the heading
    ``heading_deg`` and (across_gain * lever)^2 across it; round (per axis) when either is None, with the
    larger gain where both gains are given but no heading."""
    if across_gain is None:
        return (float(gain) * float(lever_m)) ** 2 * np.eye(2)
    if heading_deg is None or not np.isfinite(heading_deg):
        return (max(float(gain), float(across_gain)) * float(lever_m)) ** 2 * np.eye(2)
    u, v = along_across(heading_deg)
    d2 = float(lever_m) ** 2
    return d2 * (float(gain) ** 2 * np.outer(u, u) + float(across_gain) ** 2 * np.outer(v, v))


def unstated_geotags(geotag_sigma_m: np.ndarray | None) -> np.ndarray:
    """(N,) bool: the geotags that state no accuracy of their own in a database whose other geotags do (an OXTS
    record with no position solution, which KITTI filled in by extrapolating; an empty ``accuracy_m`` cell). Those
    are not the receiver's fixes, so their error is not the map's shared one: it is their own. A database that
    states no accuracy anywhere has none such (its geotags are all alike)."""
    if geotag_sigma_m is None:
        return np.zeros(0, bool)
    stated = np.isfinite(np.asarray(geotag_sigma_m, float))
    return ~stated if stated.any() else np.zeros(len(stated), bool)


def unstated_geotag_covariance_m2(views: dict[int, Sequence[int]], unstated: np.ndarray, sigma_m: float) -> np.ndarray:
    """(2, 2) what a measurement posed on ``views`` (view -> the images its structure was triangulated with) takes
    from geotags that state no accuracy (``unstated_geotags``), each taken as ``sigma_m`` per axis: a view's
    structure lies where the mean of its images' geotags puts it, so it carries the share f of those that are
    unstated times their error, (f sigma)^2; such geotags err alike (an extrapolation), so the views' shares are
    averaged as variances, not divided by their number."""
    if not len(unstated) or not views:
        return np.zeros((2, 2))
    shares = [float(np.mean(unstated[[int(view), *(int(j) for j in images)]])) for view, images in views.items()]
    return float(np.mean([(f * sigma_m) ** 2 for f in shares])) * np.eye(2)


def nees(error_m: np.ndarray, cov_m2: np.ndarray) -> float:
    """e' C^-1 e of a 2-D error: chi-square with 2 degrees of freedom when C is honest (mean 2)."""
    e = np.asarray(error_m, float).reshape(2)
    return float(e @ np.linalg.solve(np.asarray(cov_m2, float), e))


def fit_lever_gain(errors_m: np.ndarray, base_cov_m2: np.ndarray, lever_m: np.ndarray, *,
                   probability: float = 0.8, max_gain: float = 1.0) -> float:
    """The smallest gain g >= 0 that puts a share ``probability`` of the errors inside their
    ``probability`` ellipse, e' (C + (g d)^2 I)^-1 e <= -2 ln(1 - p): the gain whose covariances
    match the errors at that level (``max_gain`` if none does; 0 if the base covariances already
    hold them). ``errors_m`` (N, 2), ``base_cov_m2`` (N, 2, 2), ``lever_m`` (N,).

    Matching one level rather than the mean of e' C^-1 e keeps a few gross errors from deciding
    every ellipse; 0.8 is far enough out to see the body's spread, and still held by a few dozen
    poses, where 0.95 would rest on two or three."""
    e = np.asarray(errors_m, float).reshape(-1, 2)
    C = np.asarray(base_cov_m2, float).reshape(-1, 2, 2)
    d = np.asarray(lever_m, float).reshape(-1)
    if len(e) == 0:
        raise ValueError("fit_lever_gain needs at least one error")
    radius2 = chi2_2dof_quantile(probability)

    def covered(g: float) -> float:
        S = C + ((g * d) ** 2)[:, None, None] * np.eye(2)
        m = np.einsum("ni,ni->n", e, np.linalg.solve(S, e[:, :, None])[..., 0])
        return float(np.mean(m <= radius2))

    return _fit_scale(covered, max_gain, probability)


def _fit_scale(covered, max_scale: float, probability: float) -> float:
    """The smallest s in [0, max_scale] with covered(s) >= probability (coverage grows with s)."""
    if covered(0.0) >= probability:
        return 0.0
    if covered(max_scale) < probability:
        return max_scale
    low, high = 0.0, max_scale
    for _ in range(40):  # bisection to 1e-12 of max_scale
        mid = 0.5 * (low + high)
        low, high = (low, mid) if covered(mid) >= probability else (mid, high)
    return high


def fit_lever_gains(errors_m: np.ndarray, base_cov_m2: np.ndarray, lever_m: np.ndarray, heading_deg: np.ndarray, *,
                    probability: float = 0.8, max_gain: float = 1.0) -> tuple[float, float]:
    """The lever gains (along, across the heading) whose covariances match the errors: their ratio from each
    direction alone (the smallest gain that puts a share ``probability`` of the errors' components inside
    their two-sided ``probability`` interval, as ``fit_lever_gain`` does in 2-D), their size from both at
    once (the share ``probability`` inside the ``probability`` ellipse). ``heading_deg`` (N,) the vehicle's
    compass heading at each error; the other arrays as ``fit_lever_gain``'s."""
    e = np.asarray(errors_m, float).reshape(-1, 2)
    C = np.asarray(base_cov_m2, float).reshape(-1, 2, 2)
    d = np.asarray(lever_m, float).reshape(-1)
    if len(e) == 0:
        raise ValueError("fit_lever_gains needs at least one error")
    axes = [along_across(h) for h in np.asarray(heading_deg, float).reshape(-1)]
    z2 = chi2_1dof_quantile(probability)
    gains = []
    for which in (0, 1):
        w = np.array([a[which] for a in axes])
        component = np.einsum("ni,ni->n", e, w)
        variance = np.einsum("ni,nij,nj->n", w, C, w)
        gains.append(_fit_scale(lambda g: float(np.mean(component ** 2 <= z2 * (variance + (g * d) ** 2))),
                                max_gain, probability))
    if max(gains) == 0.0:
        return 0.0, 0.0
    along, across = gains[0] / max(gains), gains[1] / max(gains)
    radius2 = chi2_2dof_quantile(probability)
    U = np.array([a[0] for a in axes])
    V = np.array([a[1] for a in axes])
    shape = (d ** 2)[:, None, None] * (along ** 2 * np.einsum("ni,nj->nij", U, U)
                                       + across ** 2 * np.einsum("ni,nj->nij", V, V))

    def covered(s: float) -> float:
        S = C + s ** 2 * shape
        return float(np.mean(np.einsum("ni,ni->n", e, np.linalg.solve(S, e[:, :, None])[..., 0]) <= radius2))

    scale = _fit_scale(covered, max_gain, probability)
    return float(scale * along), float(scale * across)


@dataclass(frozen=True)
class Calibration:
    """How honest a set of covariances is against errors measured with them.

    n: errors; nees_mean: mean of e' C^-1 e (2 if honest); nees_median (1.39 if honest);
    inside_95: the share inside the 95 % ellipse (0.95 if honest); coverage: observed share inside
    each nominal ellipse of ``NOMINAL_LEVELS`` (the calibration curve; the nominal level if honest)."""

    n: int
    nees_mean: float | None
    nees_median: float | None
    inside_95: float | None
    coverage: tuple[float, ...]

    def as_dict(self) -> dict:
        return {"n": self.n, "nees_mean": self.nees_mean, "nees_median": self.nees_median,
                "inside_95": self.inside_95,
                "coverage": {f"{p:g}": c for p, c in zip(NOMINAL_LEVELS, self.coverage)}}


def calibration(nees_values: Sequence[float]) -> Calibration:
    """The calibration figures of NEES values (e' C^-1 e of 2-D errors)."""
    v = np.asarray([x for x in nees_values if x is not None], float)
    if v.size == 0:
        return Calibration(0, None, None, None, tuple())
    cover = tuple(float(np.mean(v <= chi2_2dof_quantile(p))) for p in NOMINAL_LEVELS)
    return Calibration(int(v.size), float(v.mean()), float(np.median(v)), float(np.mean(v <= CHI2_2DOF_95)), cover)
