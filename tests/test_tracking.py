"""The constant-velocity Kalman filter: a hand-worked case and filterpy as a reference."""

import numpy as np
import pytest

from visloc.params import FilterParams
from visloc.stats import CHI2_2DOF_999
from visloc.stats import error_correlation_by_lag, fit_error_correlation
from visloc.tracking.kalman import ConstantVelocityKalman, process_noise, rts_smooth, run_filter, transition_matrix


def test_transition_and_process_noise_match_equation_6_and_the_white_acceleration_model():
    F = transition_matrix(2.0)
    assert F.tolist() == [[1, 0, 2, 0], [0, 1, 0, 2], [0, 0, 1, 0], [0, 0, 0, 1]]
    Q = process_noise(2.0, 3.0)
    # G = [dt^2/2, dt] = [2, 2]: per axis 3 * (1 s / 2 s) * [[4, 4], [4, 4]]
    assert Q[0, 0] == Q[0, 2] == Q[2, 2] == Q[1, 1] == Q[1, 3] == Q[3, 3] == pytest.approx(6.0)
    assert Q[0, 1] == Q[0, 3] == 0.0
    # at the paper's 1 s interval, exactly sigma_a^2 G G^T: [[1/4, 1/2], [1/2, 1]] per axis
    assert process_noise(1.0, 3.0)[np.ix_([0, 2], [0, 2])].tolist() == [[0.75, 1.5], [1.5, 3.0]]


@pytest.mark.parametrize("hz", [2, 10, 30])
def test_the_velocity_may_change_as_much_in_a_second_at_any_rate(hz):
    """Predicting a second ahead in steps of 1/hz s grows the velocity's variance by as much as one step of 1 s
    (the same car, however often it is measured), and the position's by nearly as much (a finer piecewise-constant
    acceleration: sigma_a^2 T^3 / 3 in the limit, against T^3 / 4 in one step)."""
    accel_var = 2.0
    one = transition_matrix(1.0) @ np.eye(4) @ transition_matrix(1.0).T + process_noise(1.0, accel_var)
    F, Q = transition_matrix(1.0 / hz), process_noise(1.0 / hz, accel_var)
    P = np.eye(4)
    for _ in range(hz):
        P = F @ P @ F.T + Q
    assert P[2, 2] == pytest.approx(one[2, 2]) and P[3, 3] == pytest.approx(one[3, 3])
    grown_one, grown_fast = one[0, 0] - 2.0, P[0, 0] - 2.0  # beyond what the unit velocity variance moves it
    assert grown_one <= grown_fast <= grown_one * 4 / 3 + 1e-12


def test_hand_worked_two_steps():
    kf = ConstantVelocityKalman(FilterParams(dt_s=1.0, meas_var_m2=100.0, accel_var_m2_s4=0.0, init_var=1000.0))
    first = kf.step(np.array([10.0, 20.0]))
    # The first measurement initialises the position and is applied once: estimate = z,
    # position variance (1/1000 + 1/100)^-1 = 90.909, velocity untouched.
    np.testing.assert_allclose(first.x, [10, 20, 0, 0])
    np.testing.assert_allclose(np.diag(first.P), [1000 / 11, 1000 / 11, 1000, 1000])
    second = kf.step(np.array([20.0, 20.0]))
    # predict: Pxx = 90.909 + 1000, Pxv = 1000; innovation 10 m east, S = 1190.909
    # K = [1090.909, 1000] / 1190.909 = [0.916031, 0.839695]
    np.testing.assert_allclose(second.x_prior, [10, 20, 0, 0])
    np.testing.assert_allclose(second.x, [10 + 10 * 0.9160305, 20, 10 * 0.8396947, 0], rtol=1e-6)
    assert second.innovation.y.tolist() == [10.0, 0.0]
    assert second.innovation.mahalanobis == pytest.approx(10 / np.sqrt(1190.909), rel=1e-5)


def test_missing_measurement_only_predicts():
    params = FilterParams(dt_s=1.0, meas_var_m2=4.0, accel_var_m2_s4=0.5, init_var=100.0)
    steps = run_filter([np.array([0.0, 0.0]), np.array([5.0, 1.0]), None], params)
    assert steps[2].innovation is None
    np.testing.assert_allclose(steps[2].x, transition_matrix(1.0) @ steps[1].x)
    assert np.trace(steps[2].P) > np.trace(steps[1].P)


def test_no_measurement_before_the_first_gives_an_empty_step():
    steps = run_filter([None, np.array([1.0, 2.0])], FilterParams())
    assert np.isnan(steps[0].x).all()
    np.testing.assert_allclose(steps[1].x[:2], [1, 2])


def test_covariance_stays_symmetric_positive_definite():
    rng = np.random.default_rng(3)
    zs = [rng.normal(size=2) * 50 for _ in range(200)]
    for s in run_filter(zs, FilterParams(meas_var_m2=1e-6, accel_var_m2_s4=1e-3, init_var=1e6)):
        np.testing.assert_allclose(s.P, s.P.T, atol=1e-9 * np.abs(s.P).max())
        assert np.linalg.eigvalsh(s.P).min() > 0


@pytest.mark.parametrize("params", [
    FilterParams(),  # the paper preset
    FilterParams(dt_s=0.1, meas_var_m2=0.25, accel_var_m2_s4=4.0, init_var=10.0),
    FilterParams(dt_s=2.0, meas_var_m2=400.0, accel_var_m2_s4=0.0, init_var=1e5),
])
def test_agrees_with_filterpy(params):
    from filterpy.kalman import KalmanFilter

    rng = np.random.default_rng(42)
    truth = np.cumsum(np.full((12, 2), [9.0, -3.0]), axis=0)
    zs = [t + rng.normal(scale=8.0, size=2) for t in truth]
    zs[5] = None
    ours = run_filter(zs, params)

    ref = KalmanFilter(dim_x=4, dim_z=2)
    ref.F = transition_matrix(params.dt_s)
    ref.H = np.array([[1.0, 0, 0, 0], [0, 1.0, 0, 0]])
    ref.Q = process_noise(params.dt_s, params.accel_var_m2_s4)
    ref.R = params.meas_var_m2 * np.eye(2)
    ref.P = params.init_var * np.eye(4)
    ref.x = np.array([[zs[0][0]], [zs[0][1]], [0.0], [0.0]])  # same initialisation as ours
    for k, z in enumerate(zs):
        if k > 0:
            ref.predict()
        # filterpy 2.0 does not reshape a 1-D z: pass a column vector
        ref.update(None if z is None else np.asarray(z).reshape(2, 1))
        np.testing.assert_allclose(ours[k].x, ref.x.ravel(), rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(ours[k].P, ref.P, rtol=1e-8, atol=1e-8)


def test_a_step_may_bring_its_own_measurement_covariance():
    params = FilterParams(dt_s=1.0, meas_var_m2=100.0, accel_var_m2_s4=1.0, init_var=1000.0)
    zs = [np.array([0.0, 0.0]), np.array([10.0, 1.0]), np.array([20.5, 2.0])]
    R_small = np.diag([0.01, 0.04])
    steps = run_filter(zs, params, covariances_m2=[None, None, R_small])
    # by hand: the update of step 3 with R_small, from the same prior
    prior_x, prior_P = steps[2].x_prior, steps[2].P_prior
    H = np.eye(2, 4)
    S = H @ prior_P @ H.T + R_small
    K = prior_P @ H.T @ np.linalg.inv(S)
    np.testing.assert_allclose(steps[2].x, prior_x + K @ (zs[2] - H @ prior_x), rtol=1e-10)
    np.testing.assert_allclose(steps[2].R, R_small)
    np.testing.assert_allclose(steps[1].R, 100.0 * np.eye(2))
    # a precise measurement pins the position: within a few centimetres of it
    assert np.linalg.norm(steps[2].x[:2] - zs[2]) < 0.05
    with pytest.raises(ValueError, match="R must be a finite 2x2"):
        ConstantVelocityKalman(params).step(zs[0], R=np.eye(3))


def test_the_gate_rejects_an_outlier_and_only_predicts():
    params = FilterParams(dt_s=1.0, meas_var_m2=0.01, accel_var_m2_s4=0.1, init_var=1000.0)
    track = [np.array([10.0 * k, 0.0]) for k in range(5)]
    outlier = np.array([50.0, 30.0])  # 30 m off the track (expected: 50, 0)
    gated = run_filter([*track, outlier, np.array([60.0, 0.0])], params, gate_chi2=CHI2_2DOF_999)
    assert [s.gated for s in gated] == [False] * 5 + [True, False]
    np.testing.assert_allclose(gated[5].x, gated[5].x_prior)  # predicted only
    np.testing.assert_allclose(gated[5].P, gated[5].P_prior)
    assert gated[5].innovation.mahalanobis ** 2 > CHI2_2DOF_999  # kept for diagnostics
    assert np.linalg.norm(gated[6].x[:2] - [60.0, 0.0]) < 0.2  # the track goes on undisturbed
    ungated = run_filter([*track, outlier], params)  # gate off (the paper's filter): the outlier is applied
    assert not ungated[5].gated and ungated[5].x[1] > 25.0  # pulled most of the 30 m towards it


def test_the_first_measurement_is_never_gated():
    steps = run_filter([np.array([1e6, 1e6])], FilterParams(init_var=1.0), gate_chi2=1e-9)
    assert not steps[0].gated
    np.testing.assert_allclose(steps[0].x[:2], [1e6, 1e6])


@pytest.mark.parametrize("with_gap", [False, True])
def test_rts_smoother_agrees_with_filterpy(with_gap):
    from filterpy.kalman import rts_smoother

    from visloc.tracking.kalman import rts_smooth

    params = FilterParams(dt_s=1.0, meas_var_m2=25.0, accel_var_m2_s4=0.5, init_var=1000.0)
    rng = np.random.default_rng(9)
    truth = np.cumsum(np.full((10, 2), [8.0, 2.0]), axis=0)
    zs = [t + rng.normal(scale=5.0, size=2) for t in truth]
    covs = [None if k % 3 else np.diag([1.0, 4.0]) for k in range(10)]  # mixed per-step R
    if with_gap:
        zs[4] = None
    steps = run_filter(zs, params, covariances_m2=covs)
    ours = rts_smooth(steps, params.dt_s)
    F, Q = transition_matrix(params.dt_s), process_noise(params.dt_s, params.accel_var_m2_s4)
    xs, Ps, _, _ = rts_smoother(np.array([s.x for s in steps]), np.array([s.P for s in steps]),
                                Fs=[F] * len(steps), Qs=[Q] * len(steps))
    for k in range(len(steps)):
        np.testing.assert_allclose(ours[k].x, xs[k], rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(ours[k].P, Ps[k], rtol=1e-8, atol=1e-8)
    # the last step is the filter's own; earlier ones are at least as certain as filtered
    np.testing.assert_allclose(ours[-1].x, steps[-1].x)
    assert all(np.trace(o.P) <= np.trace(s.P) + 1e-9 for o, s in zip(ours, steps))


def test_rts_smoother_by_hand_for_two_steps():
    from visloc.tracking.kalman import rts_smooth

    params = FilterParams(dt_s=1.0, meas_var_m2=100.0, accel_var_m2_s4=0.0, init_var=1000.0)
    steps = run_filter([np.array([10.0, 20.0]), np.array([20.0, 20.0])], params)
    s = rts_smooth(steps, 1.0)
    # C = P0 F' Pp1^-1, x_s0 = x0 + C (x1 - x_prior1), with the numbers of test_hand_worked_two_steps
    C = steps[0].P @ transition_matrix(1.0).T @ np.linalg.inv(steps[1].P_prior)
    np.testing.assert_allclose(s[0].x, steps[0].x + C @ (steps[1].x - steps[1].x_prior))
    # no process noise: the smoothed first position is the second estimate moved back by its velocity
    np.testing.assert_allclose(s[0].x[:2], steps[1].x[:2] - steps[1].x[2:], atol=1e-9)


def _drive(n, speed_m_s=5.0, start_m=0.0):
    return [np.array([start_m + speed_m_s * k, 0.0]) for k in range(n)]


def test_measurements_that_persistently_disagree_with_the_track_restart_it():
    """A jump the track cannot follow: the first jumped measurement is gated, the second restarts the
    track there with the velocity the two agree on, and the track follows the measurements again."""
    truth = _drive(4) + _drive(4, start_m=40.0)
    R = 0.01 * np.eye(2)
    steps = run_filter(truth, FilterParams(), covariances_m2=[R] * len(truth), gate_chi2=CHI2_2DOF_999, reinit_after_gated=2)
    assert [s.gated for s in steps] == [False] * 4 + [True, False, False, False]
    assert [s.restarted for s in steps] == [False] * 5 + [True, False, False]
    assert np.linalg.norm(steps[-1].position_m - truth[-1]) < 0.1
    np.testing.assert_allclose(steps[5].x[2:], [5.0, 0.0], atol=1e-6)
    # without restarts the same track locks every later measurement out
    locked = run_filter(truth, FilterParams(), covariances_m2=[R] * len(truth), gate_chi2=CHI2_2DOF_999)
    assert all(s.gated for s in locked[4:]) and np.linalg.norm(locked[-1].position_m - truth[-1]) > 10


def test_a_single_outlier_neither_enters_nor_restarts_the_track():
    truth = _drive(8)
    measured = [z.copy() for z in truth]
    measured[4] = measured[4] + np.array([0.0, 15.0])
    R = 0.01 * np.eye(2)
    steps = run_filter(measured, FilterParams(), covariances_m2=[R] * len(measured), gate_chi2=CHI2_2DOF_999,
                       reinit_after_gated=2)
    assert [s.gated for s in steps] == [False] * 4 + [True] + [False] * 3
    assert not any(s.restarted for s in steps)
    assert max(np.linalg.norm(s.position_m - t) for s, t in zip(steps, truth)) < 0.3


def test_a_first_measurement_that_was_an_outlier_is_replaced_once_the_next_ones_agree():
    truth = _drive(6)
    measured = [z.copy() for z in truth]
    measured[0] = measured[0] + np.array([12.0, -9.0])
    R = 0.01 * np.eye(2)
    steps = run_filter(measured, FilterParams(), covariances_m2=[R] * len(measured), gate_chi2=CHI2_2DOF_999,
                       reinit_after_gated=2)
    # the second measurement still fits (the first one says nothing of the velocity); the two after
    # it do not, and the second of those restarts the track
    assert [s.restarted for s in steps] == [False, False, False, True, False, False]
    assert np.linalg.norm(steps[-1].position_m - truth[-1]) < 0.1


def _turn(n=10, speed_m_s=6.0, yaw_rate_deg_s=40.0, dt_s=1.0):
    """Positions of a car driving straight for 3 s, then turning at ``yaw_rate_deg_s`` (a 90-degree corner)."""
    heading, p, out = 0.0, np.zeros(2), []
    for k in range(n):
        out.append(p.copy())
        if k >= 2:
            heading += np.radians(yaw_rate_deg_s) * dt_s
        p = p + speed_m_s * dt_s * np.array([np.cos(heading), np.sin(heading)])
    return out


@pytest.mark.parametrize("kind", ["turn", "stop"])
def test_a_turn_or_a_stop_is_followed_not_gated(kind):
    """Precise measurements of a car that turns a corner or brakes to a stop: the constant-velocity
    prediction is metres off, the measurements fit the maneuver prediction and are applied, so the
    estimate stays with them; without the maneuver test the same gate drops them and the estimate
    falls behind the car."""
    if kind == "turn":
        truth = _turn()
    else:  # 10 m/s, brakes at 4 m/s^2 from the third second, then stands
        speeds = [10.0, 10.0, 10.0, 6.0, 2.0, 0.0, 0.0, 0.0, 0.0]
        truth = [np.array([x, 0.0]) for x in np.concatenate([[0.0], np.cumsum(speeds[:-1])])]
    rng = np.random.default_rng(3)
    R = 0.1**2 * np.eye(2)
    measured = [t + rng.normal(scale=0.1, size=2) for t in truth]
    steps = run_filter(measured, FilterParams(), covariances_m2=[R] * len(truth), gate_chi2=CHI2_2DOF_999,
                       reinit_after_gated=2)
    assert not any(s.gated for s in steps) and any(s.maneuver for s in steps)
    errors = [np.linalg.norm(s.position_m - t) for s, t in zip(steps, truth)]
    measurement_errors = [np.linalg.norm(z - t) for z, t in zip(measured, truth)]
    assert np.mean(errors) <= 1.5 * np.mean(measurement_errors) and max(errors) < 0.5
    stiff = run_filter(measured, FilterParams(maneuver_accel_var_m2_s4=0.0), covariances_m2=[R] * len(truth),
                       gate_chi2=CHI2_2DOF_999, reinit_after_gated=2)
    assert any(s.gated for s in stiff) and max(np.linalg.norm(s.position_m - t) for s, t in zip(stiff, truth)) > 1.0


def test_a_bad_measurement_that_got_in_does_not_lock_the_good_ones_out():
    """A measurement 2.5 m off that claims centimetres gets in (nothing contradicts it yet); the good
    ones after it differ from the prediction by its error and are not gated: the track is back on
    the car within two steps, and the last estimate is no worse than the last measurement."""
    truth = _drive(8)
    measured = [z.copy() for z in truth]
    measured[3] = measured[3] + np.array([0.0, 2.5])
    R = 0.05**2 * np.eye(2)
    steps = run_filter(measured, FilterParams(), covariances_m2=[R] * len(measured), gate_chi2=CHI2_2DOF_999,
                       reinit_after_gated=2)
    assert not steps[3].gated  # it got in
    assert steps[4].retracted_previous  # the next one contradicted it and took it out
    assert not any(s.gated for s in steps[4:])
    assert all(np.linalg.norm(s.position_m - t) < 0.3 for s, t in zip(steps[5:], truth[5:]))
    assert np.linalg.norm(steps[-1].position_m - truth[-1]) <= np.linalg.norm(measured[-1] - truth[-1]) + 0.05
    # the smoother counts the retracted step as its prediction: the whole smoothed track is on the car
    from visloc.tracking.kalman import rts_smooth

    smoothed = rts_smooth(steps, 1.0)
    assert max(np.linalg.norm(s.position_m - t) for s, t in zip(smoothed, truth)) < 0.1


def test_the_smoother_runs_on_each_segment_between_restarts_on_its_own():
    from visloc.tracking.kalman import rts_smooth

    truth = _drive(4) + _drive(4, start_m=40.0)
    R = 0.01 * np.eye(2)
    params = FilterParams()
    steps = run_filter(truth, params, covariances_m2=[R] * len(truth), gate_chi2=CHI2_2DOF_999, reinit_after_gated=2)
    restart = next(k for k, s in enumerate(steps) if s.restarted)
    smoothed = rts_smooth(steps, params.dt_s)
    # each segment smoothed alone gives the same numbers
    before = rts_smooth(steps[:restart], params.dt_s)
    after = rts_smooth(steps[restart:], params.dt_s)
    for ours, alone in zip(smoothed, before + after):
        np.testing.assert_allclose(ours.x, alone.x, atol=1e-12)
        np.testing.assert_allclose(ours.P, alone.P, atol=1e-12)
    # the last step of the first segment is its own filtered step, not pulled towards the new track
    np.testing.assert_allclose(smoothed[restart - 1].x, steps[restart - 1].x)


def test_a_late_measurement_fused_in_its_place_equals_having_had_it_in_time():
    """The point follower's replay: restore the filter from before a step, fuse the late measurement there and
    the later ones again; the filter ends as one that had the late measurement in time."""
    from visloc.features.sift import Query
    from visloc.pose.measurement import Measurement
    from visloc.retrieval.retrievers import Retrieval
    from visloc.tracking.localizer import Localizer

    params = FilterParams(dt_s=0.1)
    q, r = Query(np.zeros((0, 128), np.uint8), 0.0), Retrieval(np.zeros(0, np.int64), np.zeros(0, np.int64), None)
    meas = [Measurement(np.array([k * 1.0, 0.5 * k]), np.eye(2) * 0.04, "geometry") for k in range(6)]
    late = Measurement(np.array([2.3, 0.9]), np.eye(2) * 0.01, "geometry")

    def localizer() -> Localizer:
        from types import SimpleNamespace
        return Localizer(SimpleNamespace(reset=lambda: None), None, params)  # type: ignore[arg-type]  # filter only

    in_time = localizer()
    for k, m in enumerate(meas):
        in_time.fuse(q, r, late if k == 2 else m)
    replayed = localizer()
    before = []
    for m in meas:
        before.append(replayed.snapshot())
        replayed.fuse(q, r, m)
    replayed.restore(before[2])
    for k in range(2, 6):
        replayed.fuse(q, r, late if k == 2 else meas[k])
    np.testing.assert_allclose(replayed._kalman.x, in_time._kalman.x)
    np.testing.assert_allclose(replayed._kalman.P, in_time._kalman.P)


def test_frames_posed_on_the_same_points_count_the_map_error_once():
    from visloc.pose.measurement import Measurement
    from visloc.pose.trackedcov import shared_map_error

    terms = {"pnp": np.eye(2) * 0.01, "views": np.eye(2) * 0.02, "lever": np.eye(2) * 0.03}
    m = Measurement(np.zeros(2), np.eye(2) * 0.06, "geometry", cov_terms_m2=terms)
    assert shared_map_error(m, 1) is m
    third = shared_map_error(m, 3)
    np.testing.assert_allclose(third.cov_m2, np.eye(2) * (0.01 + 3 * 0.05))  # PnP's pixel noise stays once
    np.testing.assert_allclose(third.cov_terms_m2["lever"], np.eye(2) * 0.09)


def test_a_frames_map_error_repeats_only_while_its_views_stay():
    """Frames on the same points count their map error once per frame in a row on the same views: a frame that the
    linking moved on to another view's structure carries that view's error."""
    from visloc.pose.trackedcov import ViewRuns

    runs = ViewRuns()
    assert runs.frames((4, 5), 1) == 1
    assert runs.frames((4, 5), 2) == 2
    assert runs.frames((5, 6), 3) == 2  # view 5: its third frame in a row; view 6: its first
    assert runs.frames((7,), 4) == 1  # moved on to a view of its own: counted afresh
    assert runs.frames((7,), 1) == 1  # fresh points: never more than the frames posed on them
    assert runs.frames((), 3) == 3  # no view named: the frames on the points


def _posed_apart(east_north_m, views_m, lever_m, side="both"):
    """A geometry measurement at the mean of ``views_m`` (one view's positions), its "views" term the covariance of
    that mean from their spread, as ``pose_from_views`` states it; ``side``: "both" when its views lie on both
    sides of it, else "one"."""
    from visloc.pose.measurement import Measurement
    from visloc.pose.viewpose import _mean_covariance

    views = _mean_covariance(list(views_m)) if len(views_m) > 1 else np.zeros((2, 2))
    terms = {"pnp": np.eye(2) * 1e-4, "views": views, "lever": np.eye(2) * 1e-4}
    return Measurement(np.asarray(east_north_m, float), sum(terms.values()), "geometry", lever_m=lever_m,
                       cov_terms_m2=terms, views_posed_apart=len(views_m), side=side)


def test_a_followed_frame_states_the_scatter_of_its_views_that_the_runs_poses_show():
    from visloc.pose.trackedcov import ViewScatter
    from visloc.pose.measurement import Measurement

    # one view's pose strays 1 cm per metre of lever, per axis; the run's poses average three views posed apart
    rng = np.random.default_rng(7)
    per_m = 0.01
    scatter = ViewScatter()
    lone = Measurement(np.zeros(2), np.eye(2) * 2e-4, "geometry", lever_m=8.0,
                       cov_terms_m2={"pnp": np.eye(2) * 1e-4, "views": np.zeros((2, 2)), "lever": np.eye(2) * 1e-4},
                       views_posed_apart=1)
    assert scatter.stated(lone) is lone  # nothing to learn from yet: as posed
    for _ in range(200):
        lever_m = rng.uniform(4.0, 15.0)
        scatter.add(_posed_apart(np.zeros(2), rng.normal(0.0, per_m * lever_m, (3, 2)), lever_m))
    # pooled over the last poses, n times each mean's covariance is one view's: about (1 cm)^2 per m^2 of lever
    assert np.trace(scatter.per_m2()) / 2 == pytest.approx(per_m**2, rel=0.25)
    stated = scatter.stated(lone)
    assert np.trace(stated.cov_terms_m2["views"]) / 2 == pytest.approx((per_m * 8.0) ** 2, rel=0.25)
    np.testing.assert_allclose(stated.cov_m2, sum(stated.cov_terms_m2.values()))

    def nees(m):
        return float(m.east_north_m @ np.linalg.solve(m.cov_m2, m.east_north_m))

    # poses on one view, and means of two views posed apart, at their levers: with the pooled scatter their
    # ellipses hold them (NEES near 2, a 2-D chi-square's mean, and within 1-4); two views' own spread alone (one
    # degree of freedom) often says they agree when both stray, and their ellipses then claim far too much
    one_view, two_views, two_as_posed = [], [], []
    for _ in range(2000):
        lever_m = rng.uniform(4.0, 15.0)
        one_view.append(nees(scatter.stated(
            _posed_apart(rng.normal(0.0, per_m * lever_m, 2), [np.zeros(2)], lever_m))))
        views_m = rng.normal(0.0, per_m * lever_m, (2, 2))
        two = _posed_apart(views_m.mean(axis=0), views_m, lever_m)
        two_views.append(nees(scatter.stated(two)))
        two_as_posed.append(nees(two))
    assert np.mean(one_view) == pytest.approx(2.0, rel=0.3)
    assert 1.0 < np.mean(two_views) < 4.0  # one more degree of freedom than the spread: still a little heavy-tailed
    # inside the 95 % ellipse: 89 % of them; as posed, 38 % (two points spread along a line: the spread alone
    # states nothing across it)
    assert np.mean(np.array(two_views) < 5.991) > 0.85
    assert np.mean(np.array(two_as_posed) < 5.991) < 0.5
    # a geotag has no views: as it is
    geotag = Measurement(np.zeros(2), None, "geotag")
    assert scatter.stated(geotag) is geotag


def test_a_followed_frames_views_count_once_per_side_they_lie_on():
    from visloc.pose.trackedcov import ViewScatter

    rng = np.random.default_rng(11)
    scatter = ViewScatter()
    for _ in range(50):
        scatter.add(_posed_apart(np.zeros(2), rng.normal(0.0, 0.08, (3, 2)), 8.0))
    views_m = rng.normal(0.0, 0.08, (4, 2))

    def views_term(side, views=views_m):
        return scatter.stated(_posed_apart(views.mean(axis=0), views, 8.0, side)).cov_terms_m2["views"]

    # four views, two ahead and two behind: the mean of one view on each side, not of four independent views
    one_view = ((4 - 1) * _posed_apart(np.zeros(2), views_m, 8.0).cov_terms_m2["views"] * 4
                + scatter.per_m2() * 8.0**2) / 4
    np.testing.assert_allclose(views_term("both"), one_view / 2)
    # all on one side: they share that side's error, and their mean states one view's covariance
    np.testing.assert_allclose(views_term("one"), one_view)
    # one view: its own, on whichever side it lies
    lone = views_m[:1]
    np.testing.assert_allclose(views_term("one", lone), views_term("both", lone))
    np.testing.assert_allclose(views_term("one", lone), scatter.per_m2() * 8.0**2)


def test_a_track_chooses_only_its_first_measurement_with_its_first_rule():
    from types import SimpleNamespace

    from visloc.features.sift import Query
    from visloc.pose.measurement import Measurement
    from visloc.retrieval.retrievers import Retrieval
    from visloc.tracking.localizer import Localizer

    retrieval = Retrieval(np.arange(3), np.array([5, 4, 3]), 0)
    retriever = SimpleNamespace(reset=lambda: None, retrieve=lambda query, prediction=None: retrieval)
    measurer = SimpleNamespace(measure=lambda query, r: Measurement(np.array([9.0, 9.0]), None, "geotag",
                                                                    fallback_reason="no pose"))
    seen = []

    def first(m, r):
        seen.append(r)
        return Measurement(np.zeros(2), None, "geotag", fallback_reason="first fix")

    loc = Localizer(retriever, measurer, FilterParams(dt_s=0.1))
    q = Query(np.zeros((0, 128), np.uint8), 0.0)
    a = loc.step(q, first=first)
    b = loc.step(q, first=first)
    assert seen == [retrieval]  # asked once, while the filter held no track
    assert a.measurement.fallback_reason == "first fix" and b.measurement.fallback_reason == "no pose"


def _correlated_drive(rng, n_steps: int, dt_s: float, fraction: float, time_s: float, sigma_m: float):
    """A car at 8 m/s east and measurements of it whose errors share ``fraction`` of their variance as a
    Gauss-Markov process of correlation time ``time_s`` (the rest white): (truth, measurements)."""
    phi = np.exp(-dt_s / time_s)
    truth = np.stack([8.0 * dt_s * np.arange(n_steps), np.zeros(n_steps)], axis=1)
    shared = np.zeros((n_steps, 2))
    shared[0] = rng.normal(size=2)
    for k in range(1, n_steps):
        shared[k] = phi * shared[k - 1] + np.sqrt(1 - phi**2) * rng.normal(size=2)
    error = sigma_m * (np.sqrt(fraction) * shared + np.sqrt(1 - fraction) * rng.normal(size=(n_steps, 2)))
    return truth, truth + error


def _estimate_nees(steps, truth) -> np.ndarray:
    return np.array([(s.x[:2] - t) @ np.linalg.solve(s.P[:2, :2], s.x[:2] - t) for s, t in zip(steps, truth)])


def test_measurements_sharing_their_errors_at_ten_hertz_keep_the_estimate_honest_only_when_modelled():
    """Ten measurements a second whose errors share 55 % of their variance over 0.76 s: a filter that takes
    them as independent claims far too small an ellipse; with the shared part modelled its NEES is near 2 and
    about 95 % of estimates lie inside their 95 % ellipse, and it is as accurate."""
    rng = np.random.default_rng(7)
    # the car holds its speed: a filter that expects little acceleration (0.1 m^2/s^4 over a second)
    fp = FilterParams(dt_s=0.1, meas_var_m2=1.0, accel_var_m2_s4=0.1, init_var=1000.0)
    sigma_m = 0.2
    R = sigma_m**2 * np.eye(2)
    nees = {0.0: [], 0.55: []}
    errors = {0.0: [], 0.55: []}
    for _ in range(40):
        truth, z = _correlated_drive(rng, 150, 0.1, 0.55, 0.76, sigma_m)
        for c in nees:
            steps = run_filter(list(z), fp, covariances_m2=[R] * len(z), corr_fraction=c, corr_time_s=0.76)
            nees[c].append(_estimate_nees(steps, truth)[20:])
            errors[c].append(np.linalg.norm(np.array([s.x[:2] for s in steps]) - truth, axis=1)[20:])
    independent, modelled = np.concatenate(nees[0.0]), np.concatenate(nees[0.55])
    assert independent.mean() > 4.0 and np.mean(independent <= 5.991) < 0.85
    assert 1.6 < modelled.mean() < 2.5 and 0.92 < np.mean(modelled <= 5.991) < 0.98
    assert np.mean(np.concatenate(errors[0.55])) <= 1.02 * np.mean(np.concatenate(errors[0.0]))


def test_the_shared_error_changes_nothing_at_one_hertz_and_a_geotag_fallback_is_read_without_it():
    """A measurement alone keeps its covariance R whatever is shared; at 1 Hz with a 0.76 s correlation time the
    filter barely differs from one that takes measurements as independent; a measurement marked not
    correlated (a geotag fallback) is applied with its whole R and leaves the shared part as it was."""
    fp = FilterParams(dt_s=1.0, meas_var_m2=1.0, accel_var_m2_s4=1.0, init_var=1000.0)
    R = np.array([[0.04, 0.01], [0.01, 0.09]])
    first = ConstantVelocityKalman(fp, corr_fraction=0.55, corr_time_s=0.76).step(np.array([3.0, 4.0]), R)
    np.testing.assert_allclose(first.x[:2], [3.0, 4.0], atol=1e-3)
    np.testing.assert_allclose(first.P[:2, :2], np.linalg.inv(np.linalg.inv(R) + np.eye(2) / 1000), rtol=1e-3)
    zs = [np.array([10.0 * k, 0.1 * (-1) ** k]) for k in range(8)]
    plain = run_filter(zs, fp, covariances_m2=[R] * 8)
    shared = run_filter(zs, fp, covariances_m2=[R] * 8, corr_fraction=0.55, corr_time_s=0.76)
    for a, b in zip(plain, shared):
        np.testing.assert_allclose(b.x[:2], a.x[:2], atol=0.01)
        np.testing.assert_allclose(b.P[:2, :2], a.P[:2, :2], rtol=0.15)
    kf = ConstantVelocityKalman(FilterParams(dt_s=0.1, meas_var_m2=1.0, accel_var_m2_s4=1.0, init_var=1000.0),
                                corr_fraction=0.55, corr_time_s=0.76)
    for k in range(5):
        kf.step(np.array([0.8 * k, 0.0]), R)
    bias_before = kf.x[4:].copy()
    step = kf.step(np.array([4.0, 0.0]), 25.0 * np.eye(2), correlated=False)
    np.testing.assert_allclose(step.innovation.S - step.P_prior[:2, :2], 25.0 * np.eye(2))
    np.testing.assert_allclose(step.x[4:], kf.F[4:, 4:] @ bias_before, atol=0.05)


def test_the_smoother_runs_over_the_state_with_the_shared_error():
    """The Rauch-Tung-Striebel smoother uses each step's own transition: over measurements of a straight drive
    its positions are at least as close as the filter's, and its covariances are no larger."""
    rng = np.random.default_rng(3)
    fp = FilterParams(dt_s=0.1, meas_var_m2=1.0, accel_var_m2_s4=1.0, init_var=1000.0)
    truth, z = _correlated_drive(rng, 80, 0.1, 0.55, 0.76, 0.2)
    steps = run_filter(list(z), fp, covariances_m2=[0.04 * np.eye(2)] * 80, corr_fraction=0.55, corr_time_s=0.76)
    smoothed = rts_smooth(steps, 0.1)
    assert all(s.x.shape == (6,) for s in smoothed)
    err_f = np.mean([np.linalg.norm(s.x[:2] - t) for s, t in zip(steps, truth)])
    err_s = np.mean([np.linalg.norm(s.x[:2] - t) for s, t in zip(smoothed, truth)])
    assert err_s <= err_f
    assert all(np.trace(s.P[:2, :2]) <= np.trace(f.P[:2, :2]) + 1e-9 for s, f in zip(smoothed, steps))


def test_measured_correlations_give_back_the_shared_fraction_and_time():
    """``error_correlation_by_lag`` and ``fit_error_correlation`` on simulated errors of known shared fraction and
    correlation time find them again."""
    rng = np.random.default_rng(11)
    times, whitened = [], []
    for run in range(30):
        _, z = _correlated_drive(rng, 200, 0.1, 0.5, 0.8, 1.0)
        truth = np.stack([0.8 * np.arange(200), np.zeros(200)], axis=1)
        times.append(100.0 * run + 0.1 * np.arange(200))
        whitened.append(z - truth)
    lags, rho, pairs = error_correlation_by_lag(np.concatenate(times), np.concatenate(whitened), max_lag_s=3.0)
    assert lags[0] == pytest.approx(0.1) and pairs[0] == 30 * 199
    fraction, time_s = fit_error_correlation(lags, rho, pairs)
    assert fraction == pytest.approx(0.5, abs=0.05) and time_s == pytest.approx(0.8, rel=0.2)
