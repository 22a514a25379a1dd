"""bob_autonomy/control/velocity_control.py: buoy thrust (feed-forward + P, body frame, clipped) and eBot wheel speeds.

Nominal buoy model: mass 35 kg, drag 5 N/(m/s) + 40 N/(m/s)^2, max thrust 45 N, gain 1.5 /s
(so the proportional correction is 35 * 1.5 = 52.5 N per m/s of velocity error).
eBot: wheel base 0.1 m, wheels at most 0.2 m/s, 4 rad/s of yaw rate per rad of heading error.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from bob_autonomy.control.velocity_control import (
    BuoyModel,
    BuoyVelocityController,
    DiffDriveController,
    clip_norm,
    rotate_to_body,
)

MAX_THRUST_N = 45.0


def thrust(desired, velocity, heading, max_thrust=MAX_THRUST_N) -> np.ndarray:
    desired = np.atleast_2d(np.asarray(desired, dtype=float))
    n = desired.shape[0]
    return BuoyVelocityController().thrust(
        desired,
        np.atleast_2d(np.asarray(velocity, dtype=float)).reshape(n, 2),
        np.broadcast_to(np.asarray(heading, dtype=float), (n,)),
        np.broadcast_to(np.asarray(max_thrust, dtype=float), (n,)),
    )


# ---------------------------------------------------------------- helpers


def test_rotate_to_body_by_hand() -> None:
    world = np.array([[1.0, 0.0], [1.0, 0.0], [0.0, 1.0], [3.0, 4.0]])
    heading = np.array([0.0, math.pi / 2, math.pi / 2, math.pi])
    # heading 0: body = world. heading 90 deg (facing north): east is to the right -> (0, -1); north is ahead
    # -> (1, 0). heading 180 deg: everything reversed -> (-3, -4).
    np.testing.assert_allclose(
        rotate_to_body(world, heading), [[1.0, 0.0], [0.0, -1.0], [1.0, 0.0], [-3.0, -4.0]], atol=1e-12
    )


def test_clip_norm_by_hand() -> None:
    v = np.array([[3.0, 4.0], [3.0, 4.0], [0.0, 0.0]])
    # norm 5: limit 10 keeps it, limit 2.5 halves it; a zero row stays zero
    np.testing.assert_allclose(clip_norm(v, np.array([10.0, 2.5, 1.0])), [[3.0, 4.0], [1.5, 2.0], [0.0, 0.0]])
    np.testing.assert_allclose(clip_norm(v, 1.0), [[0.6, 0.8], [0.6, 0.8], [0.0, 0.0]])


# ---------------------------------------------------------------- buoy


def test_zero_wish_at_rest_gives_zero_thrust() -> None:
    np.testing.assert_array_equal(thrust([[0.0, 0.0]], [[0.0, 0.0]], [0.7]), [[0.0, 0.0]])


def test_full_speed_wish_at_rest_is_clipped_along_body_x() -> None:
    # feed-forward (5 + 40 * 1) * 1 = 45 N, correction 35 * 1.5 * (1 - 0) = 52.5 N -> 97.5 N east,
    # clipped to 45 N; heading 0: body x.
    np.testing.assert_allclose(thrust([[1.0, 0.0]], [[0.0, 0.0]], [0.0]), [[45.0, 0.0]], atol=1e-12)


def test_heading_90_puts_east_thrust_on_body_minus_y() -> None:
    # the same 45 N east, seen from a buoy facing north: rotate_to_body((45, 0), pi/2) =
    # (cos * 45 + sin * 0, -sin * 45 + cos * 0) = (0, -45)
    np.testing.assert_allclose(thrust([[1.0, 0.0]], [[0.0, 0.0]], [math.pi / 2]), [[0.0, -45.0]], atol=1e-9)


def test_unsaturated_feed_forward_plus_correction_by_hand() -> None:
    # desired (0.2, 0), velocity (0.1, 0.1): speed 0.2 -> feed-forward (5 + 40 * 0.2) * (0.2, 0) = (2.6, 0);
    # correction 52.5 * (0.1, -0.1) = (5.25, -5.25) -> world (7.85, -5.25), norm 9.44 < 45.
    np.testing.assert_allclose(thrust([[0.2, 0.0]], [[0.1, 0.1]], [0.0]), [[7.85, -5.25]])
    # facing north: body = (-5.25, -7.85)
    np.testing.assert_allclose(thrust([[0.2, 0.0]], [[0.1, 0.1]], [math.pi / 2]), [[-5.25, -7.85]], atol=1e-12)
    # at the wished velocity only the drag is fed forward: (5 + 40 * 0.5) * 0.5 = 12.5 N along (0, 1) (north)
    np.testing.assert_allclose(thrust([[0.0, 0.5]], [[0.0, 0.5]], [0.0]), [[0.0, 12.5]], atol=1e-12)


def test_per_agent_max_thrust_clips_each_row() -> None:
    limits = np.array([45.0, 18.0, 0.5, 0.0])
    out = thrust(np.tile([1.0, 0.0], (4, 1)), np.zeros((4, 2)), np.zeros(4), limits)
    np.testing.assert_allclose(out, [[45.0, 0.0], [18.0, 0.0], [0.5, 0.0], [0.0, 0.0]], atol=1e-12)
    # a row under its limit is not touched by another row's limit: (2.6, 0) with limits 45 and 1
    out = thrust([[0.2, 0.0], [0.2, 0.0]], [[0.2, 0.0], [0.2, 0.0]], [0.0, 0.0], [45.0, 1.0])
    np.testing.assert_allclose(out, [[2.6, 0.0], [1.0, 0.0]], atol=1e-12)


def test_custom_model_and_gain() -> None:
    model = BuoyModel(mass_kg=10.0, linear_drag_n_per_mps=2.0, quadratic_drag_n_per_mps2=0.0, max_thrust_n=100.0)
    ctrl = BuoyVelocityController(model, gain_per_s=1.0)
    # (2 + 0) * 0.5 + 10 * 1 * (0.5 - 0) = 6 N
    out = ctrl.thrust(np.array([[0.5, 0.0]]), np.zeros((1, 2)), np.zeros(1), np.array([100.0]))
    np.testing.assert_allclose(out, [[6.0, 0.0]])


def test_nan_inputs_give_finite_thrust() -> None:
    # a NaN wish means none; a NaN velocity or heading estimate is taken as 0
    out = thrust([[np.nan, np.nan], [1.0, 0.0]], [[0.0, 0.0], [np.nan, np.nan]], [0.0, np.nan])
    assert np.isfinite(out).all()
    np.testing.assert_allclose(out, [[0.0, 0.0], [45.0, 0.0]], atol=1e-12)


def test_thrust_never_exceeds_limit_random_batch() -> None:
    rng = np.random.default_rng(2024)
    n = 5000
    desired = rng.uniform(-3.0, 3.0, (n, 2))
    velocity = rng.uniform(-3.0, 3.0, (n, 2))
    heading = rng.uniform(-4.0, 4.0, n)
    limit = rng.uniform(0.0, 45.0, n)
    out = BuoyVelocityController().thrust(desired, velocity, heading, limit)
    assert out.shape == (n, 2) and np.isfinite(out).all()
    assert np.all(np.hypot(out[:, 0], out[:, 1]) <= limit * (1.0 + 1e-12) + 1e-12)
    # the rotation keeps the magnitude: unclipped rows equal |feed-forward + correction|
    speed = np.hypot(desired[:, 0], desired[:, 1])[:, None]
    world = (5.0 + 40.0 * speed) * desired + 52.5 * (desired - velocity)
    expected = np.minimum(np.hypot(world[:, 0], world[:, 1]), limit)
    np.testing.assert_allclose(np.hypot(out[:, 0], out[:, 1]), expected, rtol=1e-9, atol=1e-9)


# ---------------------------------------------------------------- eBot


def wheels(desired, desired_heading, heading) -> np.ndarray:
    desired = np.atleast_2d(np.asarray(desired, dtype=float))
    return DiffDriveController().wheels(
        desired, np.asarray(desired_heading, dtype=float).reshape(-1), np.asarray(heading, dtype=float).reshape(-1)
    )


@pytest.mark.parametrize(("speed", "expected"), [(0.1, 0.1), (0.2, 0.2), (0.5, 0.2)])
def test_diff_drive_along_heading_equal_wheels(speed: float, expected: float) -> None:
    heading = 0.8
    desired = speed * np.array([[math.cos(heading), math.sin(heading)]])
    np.testing.assert_allclose(wheels(desired, [np.nan], [heading]), [[expected, expected]], atol=1e-12)


def test_diff_drive_heading_error_90_turns_in_place() -> None:
    # heading 0, wish north at 0.1 m/s: error pi/2 -> forward 0.1 * max(cos(pi/2), 0) = 0;
    # omega 4 * pi/2 = 6.28 rad/s -> wheels -+ 6.28 * 0.05 = -+0.314 m/s, scaled to the 0.2 limit.
    out = wheels([[0.0, 0.1]], [np.nan], [0.0])
    magnitude = min(0.2, 4.0 * (math.pi / 2) * 0.05)
    np.testing.assert_allclose(out, [[-magnitude, magnitude]], atol=1e-12)
    assert out[0, 0] + out[0, 1] == pytest.approx(0.0, abs=1e-12)  # no forward speed
    # a wished heading 90 deg to the right (no velocity) turns the other way
    np.testing.assert_allclose(wheels([[0.0, 0.0]], [-math.pi / 2], [0.0]), [[magnitude, -magnitude]], atol=1e-12)


def test_diff_drive_small_heading_error_unsaturated() -> None:
    # error 0.1 rad, wish 0.05 m/s: forward 0.05 cos(0.1) = 0.049750; omega 0.4 -> +-0.02 m/s
    out = wheels([[0.05 * math.cos(0.1), 0.05 * math.sin(0.1)]], [np.nan], [0.0])
    forward = 0.05 * math.cos(0.1)
    np.testing.assert_allclose(out, [[forward - 0.02, forward + 0.02]], atol=1e-12)


def test_diff_drive_nan_heading_faces_velocity_and_given_heading_wins() -> None:
    # NaN wished heading: face along the velocity (north) -> turn left (right wheel faster)
    out = wheels([[0.0, 0.1]], [np.nan], [0.0])
    assert out[0, 1] > out[0, 0]
    # the same velocity with a wished heading of 0 (already held): no turn
    out = wheels([[0.1, 0.0]], [0.0], [0.0])
    np.testing.assert_allclose(out, [[0.1, 0.1]], atol=1e-12)
    # no velocity and no heading wish: stand still
    np.testing.assert_array_equal(wheels([[0.0, 0.0]], [np.nan], [1.0]), [[0.0, 0.0]])
    # a NaN velocity wish is no wish
    np.testing.assert_array_equal(wheels([[np.nan, np.nan]], [np.nan], [1.0]), [[0.0, 0.0]])


def test_diff_drive_heading_error_across_wrap() -> None:
    # heading 179 deg, wished -179 deg: error +2 deg (turn left a little), not -358 deg
    out = wheels([[0.0, 0.0]], [math.radians(-179.0)], [math.radians(179.0)])
    omega = 4.0 * math.radians(2.0)
    np.testing.assert_allclose(out, [[-omega * 0.05, omega * 0.05]], atol=1e-12)


def test_diff_drive_never_exceeds_wheel_limit_random_batch() -> None:
    rng = np.random.default_rng(7)
    n = 5000
    desired = rng.uniform(-1.0, 1.0, (n, 2))
    desired_heading = np.where(rng.random(n) < 0.5, np.nan, rng.uniform(-4.0, 4.0, n))
    heading = rng.uniform(-math.pi, math.pi, n)
    out = DiffDriveController().wheels(desired, desired_heading, heading)
    assert out.shape == (n, 2) and np.isfinite(out).all()
    assert np.abs(out).max() <= 0.2 + 1e-12
    # the forward part never goes backwards: (left + right) / 2 >= 0
    assert np.all(out.sum(axis=1) >= -1e-12)
