"""Summary statistics and chi-square thresholds: one definition each, for every stage, run, track,
suite and results page.

``summary_of(values, names)`` is how a series of figures is summarised everywhere: entries that are None
(a step without a measurement, say) are left out, and a series with nothing left gives None for each
figure, so a summary never fails on an empty run and never mixes a missing value into a mean.
"""

from __future__ import annotations

from collections.abc import Iterable

# numpy is imported where it is used: the command line reads these thresholds through the parameters'
# declarations, and answers --help without loading numpy

# the squared Mahalanobis radius of a 2-D Gaussian's 95 % ellipse: e' C^-1 e <= 5.991
CHI2_2DOF_95 = 5.991
# ... and of its 99.9 % ellipse, -2 ln(0.001) = 13.8155 to two decimals: the filter's gate and the test
# of two positions that disagree
CHI2_2DOF_999 = 13.82

FIGURES = ("mean", "median", "min", "max", "p50", "p90", "p95")  # what ``summary_of`` can compute
ERROR_FIGURES = ("median", "mean", "p90", "max")  # how an error series is summarised
LATENCY_FIGURES = ("p50", "p95", "max")  # how a series of timings is summarised


def chi2_2dof_quantile(probability: float) -> float:
    """The squared Mahalanobis radius holding ``probability`` of a 2-D Gaussian: -2 ln(1 - p)."""
    import numpy as np

    return float(-2.0 * np.log1p(-probability))


def summary_of(values: Iterable[float | None], names: Iterable[str] = ERROR_FIGURES, *, count: bool = False) -> dict:
    """Each figure of ``names`` (of ``FIGURES``) over ``values`` without its None entries, as floats
    (None for every figure when nothing is left); with ``count``, also their number as "n"."""
    import numpy as np

    compute = {"mean": np.mean, "median": np.median, "min": np.min, "max": np.max,
               "p50": lambda a: np.percentile(a, 50), "p90": lambda a: np.percentile(a, 90),
               "p95": lambda a: np.percentile(a, 95)}
    v = np.asarray([x for x in values if x is not None], float)
    out: dict = {n: (float(compute[n](v)) if v.size else None) for n in names}
    if count:
        out["n"] = int(v.size)
    return out
