"""scripts/filter_replay.py: the refined filter replayed on an evaluation's records reproduces it, and the other
filters are compared on the same measurements."""

from __future__ import annotations

import dataclasses
import sys

import numpy as np
import pytest

from helpers import REPO

sys.path.insert(0, str(REPO / "scripts"))
import filter_replay  # noqa: E402

from visloc.geo import LocalFrame  # noqa: E402
from visloc.params import FilterParams, RefinedParams  # noqa: E402
from visloc.tracking.kalman import run_filter  # noqa: E402


def evaluation(n_series: int = 6, fallback_last: bool = False) -> dict:
    """Series of six steps along a straight road at 10 m/s, measurements 5 cm off at random with an honest R."""
    rng = np.random.default_rng(1)
    frame = LocalFrame(49.0, 8.4)
    fp, rp = FilterParams(), RefinedParams()
    series = []
    for k in range(n_series):
        truth = np.array([[10.0 * (k + i), 0.5 * k] for i in range(6)])
        R = 0.05**2 * np.eye(2)
        z = truth + rng.normal(0.0, 0.05, truth.shape)
        covs = [R] * 6
        if fallback_last and k == n_series - 1:
            z[-1] += [7.0, 0.0]
            covs = [R] * 5 + [11.12**2 * np.eye(2)]
        steps = run_filter(list(z), fp, covariances_m2=covs, gate_chi2=rp.gate_chi2,
                           reinit_after_gated=rp.reinit_after_gated, correlated=[c[0, 0] <= 1 for c in covs],
                           corr_fraction=rp.error_correlation, corr_time_s=rp.error_correlation_time_s)
        records = []
        for i in range(6):
            t_lat, t_lon = frame.to_geo(truth[i])
            m_lat, m_lon = frame.to_geo(z[i])
            records.append({"truth_lat_deg": float(t_lat), "truth_lon_deg": float(t_lon),
                            "measurement_lat_deg": float(m_lat), "measurement_lon_deg": float(m_lon),
                            "measurement_cov_m2": covs[i].tolist(),
                            "measurement_source": "geotag" if covs[i][0, 0] > 1 else "geometry",
                            "estimate_error_m": float(np.linalg.norm(steps[i].x[:2] - truth[i]))})
        series.append(records)
    return {"params": {"filter": dataclasses.asdict(fp), "refined": dataclasses.asdict(rp)}, "series": series}


def test_the_refined_filter_replayed_reproduces_the_recorded_estimates():
    r = filter_replay.replay(evaluation())
    assert r["n_series"] == 6 and r["n_series_ending_on_a_fallback"] == 0
    filters = {f["name"]: f for f in r["filters"]}
    assert filters["as run"]["final_estimate_mean_m"] == pytest.approx(r["recorded_final_estimate_mean_m"], abs=1e-6)
    assert set(filters) >= {"as run", "Q x 16"}
    assert all(f["innovation_d2_mean"] > 0 for f in r["filters"])


def test_a_series_ending_on_a_fallback_is_counted_and_kept_apart():
    r = filter_replay.replay(evaluation(fallback_last=True))
    assert r["n_series_ending_on_a_fallback"] == 1
    # the fallback 7 m off with its 11 m sigma barely moves the estimate: the filter beats that final measurement
    assert r["filters"][0]["name"] == "as run" and r["filters"][0]["minus_measurement_mm"] < -500
    assert abs(r["as_run_minus_measurement_mm_geometry_finals"]) < 50


def test_no_evaluations_is_a_clear_error(tmp_path, capsys):
    assert filter_replay.main([str(tmp_path)]) == 2
    assert str(tmp_path) in capsys.readouterr().err


def test_a_file_that_is_not_an_evaluation_is_named(tmp_path, capsys):
    (tmp_path / "broken_refined.json").write_text('{"series": []}')
    assert filter_replay.main([str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "broken_refined.json" in err and len(err.strip().splitlines()) == 1
