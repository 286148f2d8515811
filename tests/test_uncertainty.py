"""The covariance model's pieces: the lever gain fit, the calibration figures, the heading spread."""

import numpy as np
import pytest

from visloc.geometry.bundle import heading_spread_rad
from visloc.pose.selfcheck import MIN_POSES_PER_SIDE, SelfCheckPose, lever_gain_from
from visloc.stats import CHI2_2DOF_95, chi2_2dof_quantile
from visloc.pose.uncertainty import (DEFAULT_LEVER_GAIN, NOMINAL_LEVELS, calibration, common_lever_covariance_m2,
                                fit_lever_gain, nees)


def test_the_chi_square_quantiles_of_two_degrees_of_freedom():
    assert chi2_2dof_quantile(0.95) == pytest.approx(CHI2_2DOF_95, abs=1e-3)
    assert chi2_2dof_quantile(0.5) == pytest.approx(1.386, abs=1e-3)
    rng = np.random.default_rng(0)
    e = rng.normal(size=(200_000, 2))
    assert np.mean(np.sum(e**2, axis=1) <= chi2_2dof_quantile(0.8)) == pytest.approx(0.8, abs=0.005)


def test_the_lever_gain_is_recovered_from_errors_that_grow_with_the_lever():
    rng = np.random.default_rng(1)
    n, true_gain = 400, 0.02
    lever = rng.uniform(2.0, 12.0, n)
    base = np.tile(np.diag([0.01**2, 0.02**2]), (n, 1, 1))
    sigma = np.sqrt(np.diagonal(base, axis1=1, axis2=2) + (true_gain * lever[:, None]) ** 2)
    errors = rng.normal(size=(n, 2)) * sigma
    gain = fit_lever_gain(errors, base, lever)
    assert gain == pytest.approx(true_gain, rel=0.15)
    # at that gain the errors fill their ellipses as a Gaussian's do
    values = [nees(e, c + (gain * d) ** 2 * np.eye(2)) for e, c, d in zip(errors, base, lever)]
    cal = calibration(values)
    assert cal.nees_mean == pytest.approx(2.0, rel=0.2) and cal.inside_95 == pytest.approx(0.95, abs=0.03)
    # base covariances that already hold the errors need no lever term
    assert fit_lever_gain(errors * 1e-3, base, lever) == 0.0
    # errors no gain up to the limit explains give the limit
    assert fit_lever_gain(np.full((5, 2), 1e6), base[:5], lever[:5], max_gain=1.0) == 1.0
    with pytest.raises(ValueError):
        fit_lever_gain(np.zeros((0, 2)), np.zeros((0, 2, 2)), np.zeros(0))


def test_a_few_gross_errors_do_not_decide_the_gain():
    rng = np.random.default_rng(2)
    lever = rng.uniform(4.0, 10.0, 200)
    base = np.tile(np.eye(2) * 1e-4, (200, 1, 1))
    errors = rng.normal(size=(200, 2)) * (0.01 * lever[:, None])
    clean = fit_lever_gain(errors, base, lever)
    errors[:6] = 5.0  # 3 % of the poses 5 m off
    assert fit_lever_gain(errors, base, lever) == pytest.approx(clean, rel=0.2)


def test_calibration_figures_of_honest_and_dishonest_covariances():
    rng = np.random.default_rng(3)
    honest = np.sum(rng.normal(size=(50_000, 2)) ** 2, axis=1)
    cal = calibration(honest)
    assert cal.n == 50_000 and cal.nees_mean == pytest.approx(2.0, abs=0.05)
    assert cal.nees_median == pytest.approx(1.386, abs=0.05) and cal.inside_95 == pytest.approx(0.95, abs=0.005)
    np.testing.assert_allclose(cal.coverage, NOMINAL_LEVELS, atol=0.01)
    too_small = calibration(honest * 9.0)  # ellipses three times too small
    assert too_small.nees_mean == pytest.approx(18.0, rel=0.05) and too_small.inside_95 < 0.6
    assert all(c < p for c, p in zip(too_small.coverage, NOMINAL_LEVELS))
    empty = calibration([None])
    assert empty.n == 0 and empty.nees_mean is None and empty.coverage == ()
    assert set(cal.as_dict()["coverage"]) == {f"{p:g}" for p in NOMINAL_LEVELS}


def _poses(side, n, gain, rng, lever=8.0):
    return [SelfCheckPose(k, rng.normal(size=2) * gain * lever, np.eye(2) * 1e-6, lever, side) for k in range(n)]


def test_the_self_check_gain_per_side_and_what_a_side_without_poses_keeps():
    rng = np.random.default_rng(4)
    both, one = _poses("both", 150, 0.01, rng), _poses("one", 150, 0.04, rng)
    gain = lever_gain_from(both + one)
    assert gain.both_sides == pytest.approx(0.01, rel=0.2) and gain.one_side == pytest.approx(0.04, rel=0.2)
    assert (gain.n_both, gain.n_one) == (150, 150) and gain.source == "self-check"
    # one-sided poses that happen to fit a smaller gain: never below the both-sides gain
    luckier = lever_gain_from(_poses("both", 150, 0.03, rng) + _poses("one", 150, 0.01, rng))
    assert luckier.one_side == luckier.both_sides == pytest.approx(0.03, rel=0.2)
    # too few one-sided poses: that side keeps the default, but never below the other side's gain
    few = lever_gain_from(_poses("both", 150, 0.1, rng) + _poses("one", MIN_POSES_PER_SIDE - 1, 0.0, rng))
    assert few.one_side == pytest.approx(few.both_sides) and few.one_side > DEFAULT_LEVER_GAIN.one_side
    # only one-sided poses: both sides take their gain
    only_one = lever_gain_from(_poses("one", 50, 0.03, rng))
    assert only_one.both_sides == only_one.one_side
    # no pose at all (every image failed): the defaults
    failed = [SelfCheckPose(k, None, None, None, None, "PnP RANSAC found no pose") for k in range(20)]
    nothing = lever_gain_from(failed)
    assert (nothing.both_sides, nothing.one_side) == (DEFAULT_LEVER_GAIN.both_sides, DEFAULT_LEVER_GAIN.one_side)


def test_the_heading_spread_sees_an_ins_heading_that_strays_from_the_course():
    t = np.arange(120) * 0.1
    # a car turning at 10 deg/s, 8 m/s: course and heading agree on an arc
    yaw = np.radians(10.0) * t
    radius = 8.0 / np.radians(10.0)
    en = radius * np.stack([np.sin(yaw), 1.0 - np.cos(yaw)], axis=1)
    assert np.degrees(heading_spread_rad(en, yaw)) < 0.05
    # a constant mounting offset is no spread
    assert np.degrees(heading_spread_rad(en, yaw + np.radians(1.5))) < 0.05
    # a heading that wanders by a degree
    wander = np.radians(1.0) * np.sin(t)
    assert np.degrees(heading_spread_rad(en, yaw + wander)) == pytest.approx(np.degrees(np.std(wander)), rel=0.2)
    # too few images far enough apart to tell
    assert heading_spread_rad(en[:3], yaw[:3]) is None


def test_views_posed_apart_share_only_part_of_the_lever_error():
    """Views posed apart: each pose's error is a part common to the views plus one of its own, and the gain was
    measured on single poses. Their mean's covariance, the spread's covariance of the mean plus the common part
    of the lever term, holds the mean's errors nearly as a Gaussian's would (a little large: the clipping at zero
    of a spread estimated from four poses errs on the side of caution); adding the whole lever term would not."""
    rng = np.random.default_rng(5)
    sigma_common_m, sigma_own_m, n = 0.03, 0.05, 4
    lever_m2 = (sigma_common_m**2 + sigma_own_m**2) * np.eye(2)  # what the self-check's single poses carry
    shared, whole = [], []
    for _ in range(4000):
        poses = rng.normal(scale=sigma_common_m, size=2) + rng.normal(scale=sigma_own_m, size=(n, 2))
        mean = poses.mean(axis=0)
        d = poses - mean
        views_m2 = d.T @ d / (n * (n - 1))
        shared.append(nees(mean, views_m2 + common_lever_covariance_m2(lever_m2, views_m2, n)))
        whole.append(nees(mean, views_m2 + lever_m2))
    assert 1.5 < np.mean(shared) < 2.2 and 0.94 < np.mean(np.array(shared) <= CHI2_2DOF_95) < 0.98
    assert np.mean(whole) < 0.9  # the whole lever term: ellipses far too large
    # where the views disagree more than the gain says, their spread alone stands for it; never negative
    wide = common_lever_covariance_m2(0.01 * np.eye(2), np.diag([0.01, 0.0001]), 4)
    np.testing.assert_allclose(wide, np.diag([0.0, 0.0096]), atol=1e-12)
    assert np.all(np.linalg.eigvalsh(wide) >= -1e-15)
