"""Summary statistics and chi-square thresholds: one definition each, for every stage, run, track,
suite and results page.

``summary_of(values, names)`` is how a series of figures is summarised everywhere: entries that are None
(a step without a measurement, say) are left out, and a series with nothing left gives None for each
figure, so a summary never fails on an empty run and never mixes a missing value into a mean.

``error_correlation_by_lag`` and ``fit_error_correlation`` measure how much of their errors measurements
made close in time share (the refined modes' filter models that part: ``visloc.tracking.kalman``).
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import numpy as np

# numpy is imported where it is used: the command line reads these thresholds through the parameters'
# declarations, and answers --help without loading numpy

# the squared Mahalanobis radius of a 2-D Gaussian's 95 % ellipse: e' C^-1 e <= 5.991
CHI2_2DOF_95 = 5.991
# ... and of its 99.9 % ellipse, -2 ln(0.001) = 13.8155 to two decimals: the filter's gate and the test
# of two positions that disagree
CHI2_2DOF_999 = 13.82

FIGURES = ("mean", "median", "min", "max", "p50", "p80", "p90", "p95")  # what ``summary_of`` can compute
ERROR_FIGURES = ("median", "mean", "p90", "max")  # how an error series is summarised
LATENCY_FIGURES = ("p50", "p95", "max")  # how a series of timings is summarised


def chi2_2dof_quantile(probability: float) -> float:
    """The squared Mahalanobis radius holding ``probability`` of a 2-D Gaussian: -2 ln(1 - p)."""
    import numpy as np

    return float(-2.0 * np.log1p(-probability))


def chi2_1dof_quantile(probability: float) -> float:
    """The squared radius holding ``probability`` of a 1-D Gaussian, in standard deviations: z^2 with
    z the two-sided quantile, Phi^-1((1 + p) / 2)."""
    from statistics import NormalDist

    return float(NormalDist().inv_cdf(0.5 + 0.5 * probability) ** 2)


def summary_of(values: Iterable[float | None], names: Iterable[str] = ERROR_FIGURES, *, count: bool = False) -> dict:
    """Each figure of ``names`` (of ``FIGURES``) over ``values`` without its None entries, as floats
    (None for every figure when nothing is left); with ``count``, also their number as "n"."""
    import numpy as np

    compute = {"mean": np.mean, "median": np.median, "min": np.min, "max": np.max,
               "p50": lambda a: np.percentile(a, 50), "p90": lambda a: np.percentile(a, 90),
               "p80": lambda a: np.percentile(a, 80), "p95": lambda a: np.percentile(a, 95)}
    v = np.asarray([x for x in values if x is not None], float)
    out: dict = {n: (float(compute[n](v)) if v.size else None) for n in names}
    if count:
        out["n"] = int(v.size)
    return out


def error_correlation_by_lag(times_s: np.ndarray, whitened: np.ndarray, *, bin_s: float = 0.1, max_lag_s: float = 4.0,
                             outlier_d2: float = 25.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """How much of their errors measurements share, by the time between them.

    ``whitened``: (n, 2) each measurement's error in its own units (L^-1 e, L L' its covariance), NaN where a
    step has none; ``times_s``: (n,) when each was made. Every pair at most ``max_lag_s`` apart, binned by
    their time apart in bins of ``bin_s``: (each bin's mean lag s, correlation sum(a.b) / sqrt(sum(a.a)
    sum(b.b)), pairs). A whitened error beyond sqrt(``outlier_d2``) is an outlier and left out: one would
    decide the correlation of its bins alone. Bins without a pair are left out."""
    import numpy as np

    t = np.asarray(times_s, float)
    w = np.asarray(whitened, float)
    ok = np.all(np.isfinite(w), axis=1) & (np.einsum("ij,ij->i", w, w) <= outlier_d2)
    n_bins = int(round(max_lag_s / bin_s))
    ab, aa, bb, lag_sum, count = (np.zeros(n_bins + 1) for _ in range(5))
    idx = np.flatnonzero(ok)
    for pos, i in enumerate(idx):
        later = idx[pos + 1:]
        dt = t[later] - t[i]
        later, dt = later[dt <= max_lag_s + 0.5 * bin_s], dt[dt <= max_lag_s + 0.5 * bin_s]
        b = np.rint(dt / bin_s).astype(int)
        keep = (b >= 1) & (b <= n_bins)
        later, dt, b = later[keep], dt[keep], b[keep]
        np.add.at(ab, b, w[later] @ w[i])
        np.add.at(aa, b, np.full(b.size, w[i] @ w[i]))
        np.add.at(bb, b, np.einsum("ij,ij->i", w[later], w[later]))
        np.add.at(lag_sum, b, dt)
        np.add.at(count, b, 1)
    has = count > 0
    rho = np.divide(ab[has], np.sqrt(aa[has] * bb[has]), out=np.zeros(int(has.sum())), where=aa[has] * bb[has] > 0)
    return lag_sum[has] / count[has], rho, count[has].astype(int)


def fit_error_correlation(lags_s: np.ndarray, rho: np.ndarray, pairs: np.ndarray) -> tuple[float, float]:
    """The shared fraction c and correlation time tau (s) of rho(dt) = c exp(-dt / tau) that fit the measured
    correlations best (least squares weighted by each lag's pairs; c on a 0.01 grid in [0, 0.99], tau on a
    log grid from 0.05 to 30 s)."""
    import numpy as np

    lags, r, wt = (np.asarray(a, float) for a in (lags_s, rho, pairs))
    c = np.arange(0.0, 0.991, 0.01)[:, None, None]
    tau = np.geomspace(0.05, 30.0, 200)[None, :, None]
    loss = np.sum(wt * (r - c * np.exp(-lags / tau)) ** 2, axis=2)
    i, j = np.unravel_index(int(np.argmin(loss)), loss.shape)
    return float(c[i, 0, 0]), float(tau[0, j, 0])
