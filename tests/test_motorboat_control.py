"""The motorboat controllers (bob_autonomy.motorboat_control) against the simulated motorboat (sitl.motorboat)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bob_autonomy.motorboat_control import HOLD_SPEED_MPS, MotorboatController, MotorboatModel, MotorboatMpc
from sitl.motorboat import MotorboatDynamics, params_for

TOP_SPEED, RADIUS = 2.0, 3.0
MODEL = MotorboatModel.for_top_speed(TOP_SPEED, RADIUS)


def _drive(controller, goal, current=(0.0, 0.0), seconds: float = 90.0, dt: float = 0.2, heading: float = 0.0):
    """Drive the simulated boat from the origin towards `goal` (wish: 0.2 /s of the distance, at most 1 m/s, the
    drift known); returns the track (steps, 2) m and the commands."""
    params = params_for(TOP_SPEED, RADIUS)
    boat = MotorboatDynamics(params, np.zeros((1, 2)), np.array([heading]), np.random.default_rng(3))
    current_arr = np.array([current])
    track, commands = [], []
    for _ in range(round(seconds / dt)):
        offset = np.asarray(goal) - boat.position_m[0]
        distance = float(np.hypot(*offset))
        wish = offset / max(distance, 1e-9) * min(1.0, 0.2 * distance)
        state = (wish, boat.velocity_mps[0], current_arr[0], boat.heading_rad[0], boat.yaw_rate_radps[0])
        cmd = controller.solve(*state) if isinstance(controller, MotorboatMpc) else controller.command(*state)
        commands.append(cmd)
        boat.step(np.array([[cmd.throttle, cmd.steering]]), dt, current_mps=current_arr)
        track.append(boat.position_m[0].copy())
    return np.array(track), commands


@pytest.mark.parametrize("goal", [(50.0, 0.0), (0.0, 50.0), (-50.0, 0.0), (0.0, -50.0)])
def test_the_mpc_reaches_goals_in_four_directions_and_holds_near_them_against_a_current(goal) -> None:
    mpc = MotorboatMpc(MODEL, time_budget_s=math.inf)  # simulated time: a loaded machine must not change the run
    track, commands = _drive(mpc, goal, current=(0.15, -0.1))
    distance = np.hypot(*(track - goal).T)
    arrived = np.flatnonzero(distance < 5.0)
    assert arrived.size and arrived[0] * 0.2 < 70.0  # 50 m at up to 1 m/s, a turn-around included
    # Held: a boat that cannot stop in place either points into the current and holds (within 1 m), or overshoots
    # and turns around on a circle of its turning radius R (up to 2 R away, plus what the current carries it
    # during the turn): within 2.5 R of the goal for the last 15 s.
    assert distance[-75:].max() < 2.5 * RADIUS
    assert mpc.fallbacks == 0 and all(c.ok for c in commands)
    assert all(-1.0 <= c.throttle <= 1.0 and -1.0 <= c.steering <= 1.0 for c in commands)


def test_the_simple_controller_also_gets_there() -> None:
    track, _ = _drive(MotorboatController(MODEL), (-50.0, 0.0), seconds=120.0)
    assert np.hypot(*(track[-50:] - (-50.0, 0.0)).T).max() < 2.5 * RADIUS


def test_a_wish_to_the_left_steers_left_and_a_wish_behind_turns_at_steerage_speed() -> None:
    mpc = MotorboatMpc(MODEL)
    left = mpc.solve(np.array([0.0, 1.0]), np.array([1.0, 0.0]), np.zeros(2), 0.0)
    assert left.steering < -0.5 and left.heading_error_rad == pytest.approx(math.pi / 2)
    mpc.reset()
    behind = mpc.solve(np.array([-1.5, 0.0]), np.zeros(2), np.zeros(2), 0.0)  # faster than REVERSE_SPEED_MPS
    assert behind.throttle > 0.0 and abs(behind.steering) > 0.5
    assert behind.speed_ref_mps == pytest.approx(0.25 * MODEL.top_speed_mps)  # turns, never stops to think


def test_a_slow_wish_behind_is_met_astern_and_astern_can_be_forbidden() -> None:
    mpc = MotorboatMpc(MODEL)
    back = mpc.solve(np.array([-0.3, 0.05]), np.zeros(2), np.zeros(2), 0.0)  # 0.3 m/s, 170 deg off the bow
    assert back.speed_ref_mps < 0.0 and back.throttle < 0.0
    # Astern the stern points along the wish: 10 deg to the left of the stern is e0 = -10 deg (turn the bow right)
    assert back.heading_error_rad == pytest.approx(-math.radians(9.46), abs=1e-3)
    for _ in range(5):
        back = mpc.solve(np.array([-0.3, 0.05]), np.array([-0.3, 0.0]), np.zeros(2), 0.0)
    assert back.steering < 0.0  # astern, the steering is reversed: left steering swings the bow right
    # Fast or forbidden: it turns around instead.
    assert MotorboatMpc(MODEL).solve(np.array([-1.5, 0.05]), np.zeros(2), np.zeros(2), 0.0).throttle > 0.0
    forward_only = MotorboatMpc(MODEL, min_throttle=0.0)
    assert forward_only.solve(np.array([-0.3, 0.05]), np.zeros(2), np.zeros(2), 0.0).throttle >= 0.0
    assert MODEL.throttle_of(-0.25) == pytest.approx(-0.5) and MODEL.fraction_of(-0.5) == pytest.approx(-0.25)


def test_the_drift_is_a_known_disturbance_pointing_into_it_holds_ground() -> None:
    mpc = MotorboatMpc(MODEL)
    # Wished still over ground in a 0.3 m/s current setting west: point east (into it) at 0.3 m/s through the water.
    for _ in range(20):  # still over ground, so 0.3 m/s through the water; the throttle settles
        cmd = mpc.solve(np.zeros(2), np.zeros(2), np.array([-0.3, 0.0]), 0.0)
    assert cmd.heading_error_rad == pytest.approx(0.0) and cmd.speed_ref_mps == pytest.approx(0.3)
    assert cmd.throttle == pytest.approx(MODEL.drag_n(0.3) / MODEL.max_thrust_n, rel=0.05)


def test_a_small_wish_holds_with_hysteresis_and_a_weak_battery_limits_the_throttle() -> None:
    mpc = MotorboatMpc(MODEL)
    hold = HOLD_SPEED_MPS
    assert mpc.solve(np.array([0.8 * hold, 0.0]), np.zeros(2), np.zeros(2), 0.0).status == "hold"
    assert mpc.solve(np.array([1.2 * hold, 0.0]), np.zeros(2), np.zeros(2), 0.0).status == "hold"  # 1.5x to leave
    assert mpc.solve(np.array([1.6 * hold, 0.0]), np.zeros(2), np.zeros(2), 0.0).status == "optimal"
    cmd = mpc.solve(np.array([2.0, 0.0]), np.zeros(2), np.zeros(2), 0.0, max_throttle=0.4)
    assert 0.0 < cmd.throttle <= 0.4


def test_a_failed_or_late_solve_falls_back_counted_and_bad_inputs_never_escape() -> None:
    mpc = MotorboatMpc(MODEL, time_budget_s=0.0)  # every solve is late
    cmd = mpc.solve(np.array([0.0, 1.0]), np.array([0.5, 0.0]), np.zeros(2), 0.0, 0.0)
    assert cmd.fallback and not cmd.ok and mpc.fallbacks == 1 and "time budget" in cmd.status
    assert cmd.steering < 0.0 and 0.0 < cmd.throttle <= 1.0
    mpc = MotorboatMpc(MODEL)
    for bad in (np.nan, np.inf, -np.inf):
        cmd = mpc.solve(np.array([bad, 1.0]), np.array([bad, bad]), np.array([0.0, bad]), bad, bad, bad)
        assert math.isfinite(cmd.throttle) and math.isfinite(cmd.steering)
        assert -1.0 <= cmd.steering <= 1.0 and 0.0 <= cmd.throttle <= 1.0


def test_the_model_rescales_to_a_top_speed_and_refuses_nonsense() -> None:
    for speed in (0.5, 2.0, 9.0):
        assert MotorboatModel.for_top_speed(speed, 10.0).top_speed_mps == pytest.approx(speed, rel=1e-9)
    for bad in (0.0, math.nan, 100.0):
        with pytest.raises(ValueError, match="top speed"):
            MotorboatModel.for_top_speed(bad)
    with pytest.raises(ValueError):
        MotorboatModel(turning_radius_m=0.0)
