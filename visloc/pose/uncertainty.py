"""What a refined measurement's covariance is made of, and how honest it is.

A refined measurement places the query in the frame of the database's geotags. Its error against
the query's true position has two parts, kept apart here:

* the **relative** part, what the pose gets wrong within the map: the PnP fit (pixel noise and
  the triangulated points' own uncertainty), the disagreement of the views it was posed against,
  and what the database's poses get wrong over the metres between the query and its nearest view
  (a residual bend of the structure, a heading or a scale a little off: an error that grows with
  that *lever*, and faster where every view lies on one side of the query, as a ruler read beyond
  its end). For the mean of views posed apart, the part of that error each view has of its own is in
  their spread; the lever term is what they share, and the gain is measured on such means. The filter
  fuses this part: it differs from one query to the next.
* the **absolute** part, the error the map's geotags share with any map of that receiver (the
  stated accuracy of the views' geotags: OXTS ``pos_accuracy``). No number of queries averages it
  away, so it is not fed to the filter: it is stated beside the estimate (``absolute_cov_m2``).

The lever's gain (metres of error per metre of lever) is a property of each database, and is
measured on it: the store poses its own images from their neighbours, each with the images
closer in time than the evaluation's exclusion window left out, as a query of that drive would
be (``visloc.pose.selfcheck``: posed as the path's measurements are, each the mean of views posed apart with
their spread in its covariance), and ``fit_lever_gain`` finds, per side, the gain whose ellipses hold
those poses as a Gaussian's would (80 % of them inside their 80 % ellipse). Nothing of a query's ground truth enters it. A store
without a self-check uses ``DEFAULT_LEVER_GAIN``, fitted once on the shared development drives.

Pure functions over numpy arrays.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from visloc.stats import CHI2_2DOF_95, chi2_2dof_quantile

SIDES = ("both", "one")  # views on both sides of the query, or on one side only
NOMINAL_LEVELS = (0.10, 0.20, 0.30, 0.40, 0.50, 0.60, 0.70, 0.80, 0.90, 0.95, 0.99)


@dataclass(frozen=True)
class LeverGain:
    """Metres of relative error per metre between a pose and its nearest view, per side.

    both_sides: the query has views before and after it; one_side: every view lies on one side.
    n_both, n_one: the self-check poses each was measured on (0: the default); source: where the
    numbers come from ("self-check of SOURCE/CAMERA" or "default")."""

    both_sides: float
    one_side: float
    n_both: int = 0
    n_one: int = 0
    source: str = "default"

    def of(self, side: str) -> float:
        return self.both_sides if side == "both" else self.one_side

    def as_dict(self) -> dict:
        return {"both_sides": self.both_sides, "one_side": self.one_side, "n_both": self.n_both,
                "n_one": self.n_one, "source": self.source}


# Fitted (``visloc.pose.selfcheck.lever_gain_from``) on the self-checks of the shared development drives pooled
# (2011_09_26_drive_0001 both cameras, 2011_09_26_drive_0005, 2011_10_03_drive_0027: 264 poses, each the mean of
# views posed apart; per drive they range from 0.002 to 0.031; ``benchmarks/self_check_agreement.py`` prints the
# pooled fit): used only by a store that has no self-check yet.
DEFAULT_LEVER_GAIN = LeverGain(both_sides=0.006, one_side=0.020)


def lever_covariance_m2(gain: float, lever_m: float) -> np.ndarray:
    """(2, 2) covariance of the database's error carried over a lever: (gain * lever)^2 per axis."""
    return (float(gain) * float(lever_m)) ** 2 * np.eye(2)


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

    if covered(0.0) >= probability:
        return 0.0
    if covered(max_gain) < probability:
        return max_gain
    low, high = 0.0, max_gain
    for _ in range(40):  # coverage grows with the gain: bisection to 1e-12
        mid = 0.5 * (low + high)
        low, high = (low, mid) if covered(mid) >= probability else (mid, high)
    return high


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
