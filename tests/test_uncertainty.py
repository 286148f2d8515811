"""The covariance model's pieces: the lever gain fit, the calibration figures, the heading spread."""

from dataclasses import replace

import numpy as np
import pytest

from visloc.geometry.bundle import heading_spread_rad
from visloc.pose.selfcheck import MIN_POSES_PER_SIDE, SelfCheckPose, lever_gain_from, pose_record, record_pose
from visloc.stats import CHI2_2DOF_95, chi2_2dof_quantile
from visloc.pose.uncertainty import (DEFAULT_LEVER_GAIN, NOMINAL_LEVELS, LeverGain, along_across, calibration,
                                fit_lever_gain, fit_lever_gains, lever_covariance_m2, nees)


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


def _road_errors(rng, n: int, along_gain: float, across_gain: float):
    """Errors of poses on a winding road: ``along_gain`` per metre of lever along each pose's heading,
    ``across_gain`` across it, over a small base covariance."""
    lever = rng.uniform(2.0, 12.0, n)
    heading = rng.uniform(0.0, 360.0, n)
    base = np.tile(np.eye(2) * 1e-6, (n, 1, 1))
    axes = [along_across(h) for h in heading]
    errors = np.array([d * (along_gain * rng.normal() * u + across_gain * rng.normal() * v)
                       for d, (u, v) in zip(lever, axes)])
    return errors, base, lever, heading


def test_the_gains_along_and_across_the_road_are_told_apart():
    rng = np.random.default_rng(5)
    errors, base, lever, heading = _road_errors(rng, 600, 0.03, 0.006)
    along, across = fit_lever_gains(errors, base, lever, heading)
    assert along == pytest.approx(0.03, rel=0.15) and across == pytest.approx(0.006, rel=0.2)
    # the covariance they state is long along the heading, and honest
    cov = [lever_covariance_m2(along, d, across_gain=across, heading_deg=h) for d, h in zip(lever, heading)]
    u, v = along_across(90.0)  # due east: along is east, across is north
    np.testing.assert_allclose(u, [1.0, 0.0], atol=1e-12) and np.testing.assert_allclose(v, [0.0, 1.0], atol=1e-12)
    east = lever_covariance_m2(along, 10.0, across_gain=across, heading_deg=90.0)
    assert east[0, 0] == pytest.approx((10 * along) ** 2) and east[1, 1] == pytest.approx((10 * across) ** 2)
    cal = calibration([nees(e, b + c) for e, b, c in zip(errors, base, cov)])
    assert cal.nees_mean == pytest.approx(2.0, rel=0.2) and cal.inside_95 == pytest.approx(0.95, abs=0.03)
    # one round gain for the same errors: too large across, too small along; the shaped one is tighter
    round_gain = fit_lever_gain(errors, base, lever)
    assert across < round_gain < along
    # errors the base covariances hold need no lever term either way
    assert fit_lever_gains(errors * 1e-4, base, lever, heading) == (0.0, 0.0)
    # no heading: round, at the larger gain
    np.testing.assert_allclose(lever_covariance_m2(0.02, 5.0, across_gain=0.01, heading_deg=None),
                               (0.1) ** 2 * np.eye(2))


def test_the_self_check_fits_along_and_across_where_its_poses_state_a_heading():
    rng = np.random.default_rng(6)
    errors, base, lever, heading = _road_errors(rng, 300, 0.02, 0.005)
    poses = [SelfCheckPose(k, e, b, d, "both", heading_deg=h)
             for k, (e, b, d, h) in enumerate(zip(errors, base, lever, heading))]
    gain = lever_gain_from(poses)
    assert gain.of("both") == pytest.approx(0.02, rel=0.2) and gain.across_of("both") == pytest.approx(0.005, rel=0.25)
    # no one-sided poses: that side keeps the default, never below the both-sides gains either way
    assert gain.of("one") >= max(gain.of("both"), DEFAULT_LEVER_GAIN.one_side)
    assert gain.across_of("one") >= gain.across_of("both")
    # a pose without a heading: one round gain for its side
    unheaded = lever_gain_from([SelfCheckPose(p.index, p.error_m, p.base_cov_m2, p.lever_m, p.side) for p in poses])
    assert unheaded.of("both") == unheaded.across_of("both")
    # a gain made without a shape is round
    assert LeverGain(0.01, 0.03).across_of("one") == 0.03 and LeverGain(0.01, 0.03).as_dict()["both_sides_across"] == 0.01


def test_a_self_check_pose_is_fitted_beyond_the_covariance_its_measurement_states():
    """A self-check pose keeps the covariance its measurement states without the lever and the geotags' terms: on
    the exact path, a few views' spread made round."""
    from visloc.pose.measurement import Measurement
    from visloc.pose.selfcheck import _pose_of

    terms = {"pnp": np.eye(2) * 1e-4, "views": np.diag([4e-4, 0.0]), "views_round": np.diag([0.0, 4e-4]),
             "lever": np.eye(2) * 1e-2, "geotags": np.eye(2) * 1e-2}
    m = Measurement(np.array([1.0, 2.0]), sum(terms.values()), "geometry", lever_m=5.0, side="both",
                    cov_terms_m2=terms)
    m = replace(m, views_posed_apart=3)
    pose = _pose_of(1, m, np.array([[0.0, 0.0], [1.0, 1.0]]))
    np.testing.assert_allclose(pose.base_cov_m2, np.eye(2) * 5e-4)
    np.testing.assert_allclose(pose.error_m, [0.0, 1.0])
    # as the store keeps it and reads it back: the views it is the mean of too
    again = record_pose(pose_record(pose, 7, "{}"), 1, heading_deg=90.0)
    assert again.views_posed_apart == 3 and again.heading_deg == 90.0
    np.testing.assert_allclose(again.base_cov_m2, pose.base_cov_m2)


def test_the_gain_is_fitted_on_poses_whose_spread_is_shaped_where_a_side_has_enough():
    """Poses on few views carry a round spread that already holds their error: fitted among the others, the more a
    self-check has of them, the lower the gain a query on more views gets."""
    rng = np.random.default_rng(8)
    many = [replace(p, views_posed_apart=6) for p in _poses("both", 100, 0.02, rng)]
    few = [SelfCheckPose(1000 + k, rng.normal(size=2) * 0.02, np.eye(2), 8.0, "both", views_posed_apart=2)
           for k in range(300)]
    pooled, shaped = lever_gain_from(many + few), lever_gain_from(many + few, min_views=4)
    assert shaped.both_sides == pytest.approx(0.02, rel=0.2) and pooled.both_sides < 0.5 * shaped.both_sides
    assert shaped.n_both == pooled.n_both == 400  # the counts are the side's poses, whichever were fitted
    # too few poses on enough views: every pose of the side is fitted
    assert lever_gain_from(many[:MIN_POSES_PER_SIDE - 1] + few, min_views=4).both_sides == pytest.approx(
        lever_gain_from(many[:MIN_POSES_PER_SIDE - 1] + few).both_sides)
    # a pose that does not say (a row of an older store) is not among those on enough views
    unsaid = [replace(p, views_posed_apart=None) for p in many]
    assert lever_gain_from(unsaid + few, min_views=4).both_sides == pytest.approx(pooled.both_sides)


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


def test_a_gain_measured_on_means_of_views_posed_apart_holds_such_means():
    """Each view's error is a part common to the views plus one of its own, both growing with the lever. The mean of
    n views posed apart carries the common part and the mean of the own parts, which their spread estimates. A gain
    fitted on such means, their spread in the base covariance (the self-check poses as the queries are posed), is the
    common part's, and stated whole beside the spread it holds other such means as a Gaussian's would. A gain fitted
    on single poses (a cheaper self-check) holds both parts, and stated for a mean its ellipses are far too large."""
    rng = np.random.default_rng(5)
    n_poses, n_views, common_gain, own_gain = 3000, 6, 0.02, 0.03
    lever = rng.uniform(3.0, 12.0, n_poses)

    def poses():
        common = rng.normal(size=(n_poses, 2)) * (common_gain * lever[:, None])
        views = common[:, None, :] + rng.normal(size=(n_poses, n_views, 2)) * (own_gain * lever[:, None, None])
        means = views.mean(axis=1)
        spread = views - means[:, None, :]
        return views, means, np.einsum("nvi,nvj->nij", spread, spread) / (n_views * (n_views - 1))

    views, means, views_m2 = poses()
    apart = fit_lever_gain(means, views_m2, lever)
    assert apart == pytest.approx(common_gain, rel=0.2)
    single = fit_lever_gain(views[:, 0], np.broadcast_to(1e-8 * np.eye(2), (n_poses, 2, 2)), lever)
    assert single == pytest.approx(np.hypot(common_gain, own_gain), rel=0.15)
    # the self-check's fit per side is this fit
    checked = [SelfCheckPose(k, e, c, d, "both") for k, (e, c, d) in enumerate(zip(means, views_m2, lever))]
    assert lever_gain_from(checked).both_sides == pytest.approx(apart)

    _, q_means, q_views_m2 = poses()  # queries: other means of the same kind

    def honesty(gain: float):
        return calibration([nees(e, v + lever_covariance_m2(gain, d)) for e, v, d in zip(q_means, q_views_m2, lever)])

    held = honesty(apart)
    assert 1.5 < held.nees_mean < 3.0 and 0.9 < held.inside_95 < 0.99, held
    assert honesty(single).nees_mean < 1.0  # the views' own part counted twice: ellipses too large
