"""bob_autonomy/estimation/simple_estimator.py: alpha-beta GPS tracking, compass smoothing, eBot dead reckoning.

Expected values are worked out by hand in the comments (frames: x east, y north in m,
heading in rad from east, counter-clockwise).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from bob_autonomy.estimation.simple_estimator import AlphaBetaBuoyEstimator, OdometryEstimator, wrap

FIX_PERIOD_S = 0.2  # 5 Hz GPS


def fixes(n: int) -> np.ndarray:
    return np.arange(n, dtype=np.intp)


# ---------------------------------------------------------------- wrap


def test_wrap_range_and_values() -> None:
    angles = np.array([0.0, math.pi, -math.pi, 3 * math.pi / 2, -3 * math.pi / 2, 7.0])
    wrapped = wrap(angles)
    # [-pi, pi): pi and -pi both map to -pi; 3pi/2 -> -pi/2; -3pi/2 -> pi/2; 7 -> 7 - 2pi.
    np.testing.assert_allclose(wrapped, [0.0, -math.pi, -math.pi, -math.pi / 2, math.pi / 2, 7.0 - 2 * math.pi])


# ---------------------------------------------------------------- alpha-beta GPS tracking


def test_first_fix_initializes_position_and_estimate_is_nan_before() -> None:
    est = AlphaBetaBuoyEstimator(3)
    assert np.isnan(est.estimate(0.0).position).all()
    est.update_gps(np.array([1]), np.array([5.0]), np.array([[12.0, -7.0]]))
    e = est.estimate(5.0)
    np.testing.assert_array_equal(e.position[1], [12.0, -7.0])  # taken as is, no blending
    np.testing.assert_array_equal(e.velocity[1], [0.0, 0.0])
    assert np.isnan(e.position[[0, 2]]).all()  # the others have no fix yet
    assert est.t_fix[1] == 5.0
    assert est.rejected == 0


def test_second_fix_alpha_beta_update_by_hand() -> None:
    est = AlphaBetaBuoyEstimator(1, alpha=0.35, beta=0.06)
    a = fixes(1)
    est.update_gps(a, np.array([0.0]), np.array([[0.0, 0.0]]))
    est.update_gps(a, np.array([1.0]), np.array([[1.0, -2.0]]))
    # predicted = (0, 0) + (0, 0) * 1 = (0, 0); residual = (1, -2)
    # position = 0 + 0.35 * (1, -2) = (0.35, -0.7); velocity = 0.06 * (1, -2) / 1 s = (0.06, -0.12)
    np.testing.assert_allclose(est.position[0], [0.35, -0.7])
    np.testing.assert_allclose(est.velocity[0], [0.06, -0.12])
    # estimate(3) extrapolates by velocity * (3 - 1): (0.35 + 0.12, -0.7 - 0.24) = (0.47, -0.94)
    e = est.estimate(3.0)
    np.testing.assert_allclose(e.position[0], [0.47, -0.94])
    np.testing.assert_allclose(e.velocity[0], [0.06, -0.12])
    # estimate() does not change the state
    np.testing.assert_allclose(est.position[0], [0.35, -0.7])


def test_stationary_target_noisy_fixes_converge() -> None:
    rng = np.random.default_rng(11)
    n, noise_m, truth = 200, 2.0, np.array([30.0, -40.0])
    est = AlphaBetaBuoyEstimator(n)
    errors = []
    for k in range(200):
        t = np.full(n, k * FIX_PERIOD_S)
        est.update_gps(fixes(n), t, truth + noise_m * rng.standard_normal((n, 2)))
        if k >= 100:
            errors.append(est.estimate(t[0]).position - truth)
    err = np.array(errors)  # (100, n, 2)
    # Steady-state alpha-beta position noise ratio (alpha 0.35, beta 0.06):
    #   (2a^2 + 2b - 3ab) / (a (4 - 2a - b)) = (0.245 + 0.12 - 0.063) / (0.35 * 3.24) = 0.302 / 1.134 = 0.266
    # -> error std ~ sqrt(0.266) * 2 m = 1.03 m per axis, about half the fix noise.
    assert err.std() < 0.6 * noise_m
    # unbiased: the mean error over 200 agents and 100 fixes is near zero
    assert np.all(np.abs(err.mean(axis=(0, 1))) < 0.15)
    assert np.isfinite(err).all()


def test_constant_velocity_target_tracked() -> None:
    velocity = np.array([0.3, -0.2])
    start = np.array([5.0, 10.0])
    est = AlphaBetaBuoyEstimator(1)
    for k in range(100):
        t = k * FIX_PERIOD_S
        est.update_gps(fixes(1), np.array([t]), (start + velocity * t)[None])
    # Error dynamics z^2 - (2 - a - b) z + (1 - a) = z^2 - 1.59 z + 0.65: complex roots of modulus
    # sqrt(0.65) = 0.806, so after ~99 updates the 0.3 m/s start error is down to ~0.3 * 0.806^99 ~ 1e-10.
    np.testing.assert_allclose(est.velocity[0], velocity, atol=0.05)
    np.testing.assert_allclose(est.velocity[0], velocity, atol=1e-4)
    t_last = 99 * FIX_PERIOD_S
    np.testing.assert_allclose(est.estimate(t_last).position[0], start + velocity * t_last, atol=1e-3)
    # 1.5 s after the last fix the estimate is extrapolated along the velocity
    np.testing.assert_allclose(est.estimate(t_last + 1.5).position[0], start + velocity * (t_last + 1.5), atol=1e-3)


def test_receiver_velocity_blended_halfway_by_hand() -> None:
    est = AlphaBetaBuoyEstimator(1, alpha=0.35, beta=0.06)
    a = fixes(1)
    est.update_gps(a, np.array([0.0]), np.array([[0.0, 0.0]]), np.array([[0.4, 0.0]]))
    est.update_gps(a, np.array([1.0]), np.array([[1.0, -2.0]]), np.array([[0.5, 0.0]]))
    # alpha as above: position (0.35, -0.7); with the receiver's velocity the position residual no longer
    # feeds the velocity, which moves halfway from (0, 0) to the receiver's (0.5, 0): (0.25, 0).
    np.testing.assert_allclose(est.position[0], [0.35, -0.7])
    np.testing.assert_allclose(est.velocity[0], [0.25, 0.0])
    # a NaN receiver velocity rejects the fix (counted), the state stays finite
    est.update_gps(a, np.array([2.0]), np.array([[2.0, 0.0]]), np.array([[np.nan, 0.0]]))
    assert est.rejected == 1
    assert np.isfinite(est.estimate(2.0).position).all() and np.isfinite(est.velocity).all()


def test_receiver_velocity_makes_velocity_estimate_no_worse_than_the_receiver() -> None:
    rng = np.random.default_rng(5)
    n, velocity_noise = 200, 0.1
    est = AlphaBetaBuoyEstimator(n)
    errors = []
    for k in range(300):
        t = np.full(n, k * FIX_PERIOD_S)
        est.update_gps(fixes(n), t, 2.0 * rng.standard_normal((n, 2)), velocity_noise * rng.standard_normal((n, 2)))
        if k >= 100:
            errors.append(est.velocity.copy())
    # the target is still: the velocity estimate's error should be no noisier than one receiver reading
    assert np.std(errors) <= velocity_noise


def test_late_fix_rejected_and_counted() -> None:
    est = AlphaBetaBuoyEstimator(2)
    est.update_gps(fixes(2), np.array([1.0, 1.0]), np.array([[0.0, 0.0], [10.0, 10.0]]))
    est.update_gps(fixes(2), np.array([2.0, 2.0]), np.array([[1.0, 0.0], [10.0, 10.0]]))
    position, velocity, t_fix = est.position.copy(), est.velocity.copy(), est.t_fix.copy()
    # agent 0: a fix measured at 1.5 s arrives after the one of 2 s -> rejected; agent 1: fresh fix at 2.2 s
    est.update_gps(fixes(2), np.array([1.5, 2.2]), np.array([[100.0, 100.0], [10.0, 10.0]]))
    assert est.rejected == 1
    np.testing.assert_array_equal(est.position[0], position[0])
    np.testing.assert_array_equal(est.velocity[0], velocity[0])
    assert est.t_fix[0] == t_fix[0] == 2.0
    assert est.t_fix[1] == 2.2  # the other agent's fix in the same batch was used


def test_nan_fix_and_compass_rejected_and_counted() -> None:
    est = AlphaBetaBuoyEstimator(3)
    est.update_gps(fixes(3), np.zeros(3), np.array([[1.0, 2.0], [3.0, 4.0], [5.0, 6.0]]))
    est.update_compass(fixes(3), np.array([0.1, 0.2, 0.3]))
    # NaN x for agent 0, NaN y for agent 1, NaN time for agent 2: all three rejected
    est.update_gps(fixes(3), np.array([1.0, 1.0, np.nan]), np.array([[np.nan, 2.0], [3.0, np.nan], [5.0, 6.0]]))
    assert est.rejected == 3
    est.update_compass(np.array([0, 2]), np.array([np.nan, np.inf]))
    assert est.rejected == 5
    e = est.estimate(3.0)
    assert np.isfinite(e.position).all() and np.isfinite(e.velocity).all() and np.isfinite(e.heading).all()
    np.testing.assert_array_equal(e.position, [[1.0, 2.0], [3.0, 4.0], [5.0, 6.0]])
    np.testing.assert_allclose(e.heading, [0.1, 0.2, 0.3])
    # a NaN first fix does not initialize anything (and is counted)
    fresh = AlphaBetaBuoyEstimator(1)
    fresh.update_gps(fixes(1), np.array([0.0]), np.array([[np.nan, np.nan]]))
    assert fresh.rejected == 1 and np.isnan(fresh.t_fix[0])
    fresh.update_gps(fixes(1), np.array([0.5]), np.array([[7.0, 8.0]]))
    np.testing.assert_array_equal(fresh.position[0], [7.0, 8.0])


def test_compass_first_reading_then_smoothing() -> None:
    est = AlphaBetaBuoyEstimator(1, heading_gain=0.5)
    est.update_compass(fixes(1), np.array([1.0]))
    assert est.heading[0] == pytest.approx(1.0)  # first reading taken as is
    est.update_compass(fixes(1), np.array([2.0]))
    assert est.heading[0] == pytest.approx(1.5)  # 1 + 0.5 * (2 - 1)


def test_compass_smoothing_across_the_wrap() -> None:
    est = AlphaBetaBuoyEstimator(1, heading_gain=0.5)
    est.update_compass(fixes(1), np.radians([179.0]))
    est.update_compass(fixes(1), np.radians([-179.0]))
    # innovation = wrap(-179 - 179) = wrap(-358 deg) = +2 deg; 179 + 0.5 * 2 = 180 deg (== -180 deg)
    # Through 0 would have given 179 + 0.5 * (-358) = 0 deg.
    heading = est.heading[0]
    assert abs(wrap(np.array([heading - math.pi]))[0]) < 1e-9
    assert -math.pi <= heading < math.pi
    est.update_compass(fixes(1), np.radians([-179.0]))
    # from 180 deg: innovation +1 deg -> 180.5 deg = -179.5 deg
    assert math.degrees(est.heading[0]) == pytest.approx(-179.5)


# ---------------------------------------------------------------- odometry


def odometry(compass_gain: float = 0.0) -> OdometryEstimator:
    # metres_per_tick 1 mm, wheel base 0.1 m, start at (1, 2) heading 0.5 rad
    return OdometryEstimator(np.array([[1.0, 2.0]]), np.array([0.5]), 0.1, 0.001, compass_gain=compass_gain)


def encoders(est: OdometryEstimator, t: float, left: int, right: int) -> None:
    est.update_encoders(fixes(1), np.array([t]), np.array([[left, right]], dtype=np.int64))


def test_odometry_first_reading_only_initializes() -> None:
    est = odometry()
    encoders(est, 0.0, 5000, 7000)  # cumulative counts since power-up: not a motion
    np.testing.assert_array_equal(est.position[0], [1.0, 2.0])
    assert est.heading[0] == 0.5
    np.testing.assert_array_equal(est.velocity[0], [0.0, 0.0])


def test_odometry_equal_ticks_move_straight_along_heading() -> None:
    est = odometry()
    encoders(est, 0.0, 100, 100)
    encoders(est, 2.0, 300, 300)
    # 200 ticks * 1 mm = 0.2 m along 0.5 rad: (1 + 0.2 cos 0.5, 2 + 0.2 sin 0.5)
    step = 0.2 * np.array([math.cos(0.5), math.sin(0.5)])
    np.testing.assert_allclose(est.position[0], np.array([1.0, 2.0]) + step)
    assert est.heading[0] == pytest.approx(0.5)
    np.testing.assert_allclose(est.velocity[0], step / 2.0)  # over 2 s
    np.testing.assert_allclose(est.estimate(2.0).position[0], np.array([1.0, 2.0]) + step)


def test_odometry_opposite_ticks_turn_in_place() -> None:
    est = odometry()
    encoders(est, 0.0, 100, 100)
    encoders(est, 1.0, 50, 150)
    # left -0.05 m, right +0.05 m: forward 0, turn (0.05 - (-0.05)) / 0.1 = 1 rad to the left
    np.testing.assert_allclose(est.position[0], [1.0, 2.0], atol=1e-12)
    assert est.heading[0] == pytest.approx(1.5)
    encoders(est, 2.0, 150, 50)  # left +0.1 m, right -0.1 m: turn (-0.1 - 0.1) / 0.1 = -2 rad
    assert est.heading[0] == pytest.approx(-0.5)


def test_odometry_compass_gain_pulls_heading() -> None:
    est = odometry(compass_gain=0.05)
    est.update_compass(fixes(1), np.array([1.5]))
    assert est.heading[0] == pytest.approx(0.5 + 0.05 * 1.0)  # innovation 1.5 - 0.5 = 1
    est.update_compass(fixes(1), np.array([np.nan]))
    assert est.rejected == 1 and est.heading[0] == pytest.approx(0.55)
    # across the wrap: heading 3.1, reading -3.1 -> innovation wrap(-6.2) = 2 pi - 6.2 = +0.0832
    wrapped = OdometryEstimator(np.zeros((1, 2)), np.array([3.1]), 0.1, 0.001, compass_gain=0.05)
    wrapped.update_compass(fixes(1), np.array([-3.1]))
    assert wrapped.heading[0] == pytest.approx(3.1 + 0.05 * (2 * math.pi - 6.2))
    # gain 0 ignores the compass
    ignore = odometry(compass_gain=0.0)
    ignore.update_compass(fixes(1), np.array([2.0]))
    assert ignore.heading[0] == 0.5


def test_odometry_negative_cumulative_ticks_still_integrate() -> None:
    # Regression: a negative cumulative count (left wheel backwards) once read as "no reading yet".
    est = odometry()
    encoders(est, 0.0, 0, 0)
    encoders(est, 0.1, -10, 10)  # turn 0.02 / 0.1 = 0.2 rad
    encoders(est, 0.2, -20, 20)  # another 0.2 rad
    encoders(est, 0.3, -30, 30)  # another 0.2 rad
    assert est.heading[0] == pytest.approx(0.5 + 3 * 0.2)
