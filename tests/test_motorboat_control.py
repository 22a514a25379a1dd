"""The motorboat controllers (bob_autonomy.control.motorboat_control) against the simulated motorboat
(sitl.vehicles.motorboat)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bob_autonomy.control.motorboat_control import (
    HOLD_DWELL_S,
    HOLD_SPEED_MPS,
    TURN_SPEED_FRACTION,
    MotorboatController,
    MotorboatModel,
    MotorboatMpc,
)
from sitl.vehicles.motorboat import MotorboatDynamics, params_for

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
    assert behind.speed_ref_mps == pytest.approx(TURN_SPEED_FRACTION * MODEL.top_speed_mps)  # turns, never stops


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
    # Wished still over ground in a 0.4 m/s current setting west: point east (into it) at 0.4 m/s through the water
    # (a current under 1.5 HOLD_SPEED_MPS is drifted with: the boat holds, it only goes back when its wish grows).
    current = 0.4
    assert current > 1.5 * HOLD_SPEED_MPS
    for _ in range(20):  # still over ground, so 0.4 m/s through the water; the throttle settles
        cmd = mpc.solve(np.zeros(2), np.zeros(2), np.array([-current, 0.0]), 0.0)
    assert cmd.heading_error_rad == pytest.approx(0.0) and cmd.speed_ref_mps == pytest.approx(current)
    assert cmd.throttle == pytest.approx(MODEL.drag_n(current) / MODEL.max_thrust_n, rel=0.05)


@pytest.mark.parametrize("controller", [MotorboatMpc(MODEL), MotorboatController(MODEL)], ids=["mpc", "simple"])
def test_a_boat_told_to_hold_while_making_way_brakes_astern_then_drifts(controller) -> None:
    solve = controller.solve if isinstance(controller, MotorboatMpc) else controller.command
    moving = solve(np.zeros(2), np.array([0.8, 0.0]), np.zeros(2), 0.0)  # 0.8 m/s ahead, wish: nothing
    assert moving.speed_ref_mps == 0.0 and moving.throttle < -0.5 and moving.steering == 0.0
    backing = solve(np.zeros(2), np.array([-0.5, 0.0]), np.zeros(2), 0.0)  # drifting astern through the water
    assert backing.throttle > 0.0
    # Way off, or the drift carries it at the wished speed (no speed through the water): throttle 0, it drifts.
    assert solve(np.zeros(2), np.array([0.1, 0.0]), np.zeros(2), 0.0).throttle == 0.0
    assert solve(np.zeros(2), np.array([0.3, 0.0]), np.array([0.3, 0.0]), 0.0).throttle == 0.0


def _stopping_distance_m(controller) -> float:
    """Metres the simulated boat travels from steady 0.8 m/s (east) until slower than 0.1 m/s, told to hold."""
    boat = MotorboatDynamics(params_for(TOP_SPEED, RADIUS), np.zeros((1, 2)), np.zeros(1), np.random.default_rng(3))
    for _ in range(100):  # 20 s at a throttle giving about 0.8 m/s
        boat.step(np.array([[0.25, 0.0]]), 0.2)
    assert 0.6 < boat.velocity_mps[0, 0] < 1.0
    start = boat.position_m[0].copy()
    while np.hypot(*boat.velocity_mps[0]) > 0.1:
        if controller is None:
            throttle = 0.0
        else:
            state = (np.zeros(2), boat.velocity_mps[0], np.zeros(2), boat.heading_rad[0], boat.yaw_rate_radps[0])
            control = controller.solve if isinstance(controller, MotorboatMpc) else controller.command
            throttle = control(*state).throttle
        boat.step(np.array([[throttle, 0.0]]), 0.2)
    return float(np.hypot(*(boat.position_m[0] - start)))


def test_braking_stops_a_boat_in_under_half_the_distance_it_coasts() -> None:
    coasting = _stopping_distance_m(None)
    for controller in (MotorboatMpc(MODEL), MotorboatController(MODEL)):
        assert _stopping_distance_m(controller) < 0.5 * coasting


def test_a_small_wish_holds_with_hysteresis_and_a_weak_battery_limits_the_throttle() -> None:
    mpc = MotorboatMpc(MODEL)
    hold = HOLD_SPEED_MPS
    assert mpc.solve(np.array([0.8 * hold, 0.0]), np.zeros(2), np.zeros(2), 0.0).status == "hold"
    assert mpc.solve(np.array([1.2 * hold, 0.0]), np.zeros(2), np.zeros(2), 0.0).status == "hold"  # 1.5x to leave
    assert mpc.solve(np.array([1.6 * hold, 0.0]), np.zeros(2), np.zeros(2), 0.0).status == "optimal"
    cmd = mpc.solve(np.array([2.0, 0.0]), np.zeros(2), np.zeros(2), 0.0, max_throttle=0.4)
    assert 0.0 < cmd.throttle <= 0.4


@pytest.mark.parametrize("kind", ["mpc", "simple"])
def test_a_steady_wish_between_the_hold_speed_and_its_hysteresis_gets_a_holding_boat_under_way(kind) -> None:
    # A leader driven at 0.3 m/s against a 0.03 m/s drift wishes 0.27 m/s through the water: under 1.5 x the hold
    # speed, so once held (stopped by collision avoidance) it stayed held for good. Held for HOLD_DWELL_S, it goes.
    def statuses(times, wish=1.35 * HOLD_SPEED_MPS):
        controller = MotorboatMpc(MODEL) if kind == "mpc" else MotorboatController(MODEL)
        solve = controller.solve if kind == "mpc" else controller.command
        return [solve(np.array([w, 0.0]), np.zeros(2), np.zeros(2), 0.0, t_s=t).status
                for t, w in zip(times, np.broadcast_to(wish, len(times)), strict=True)]  # fmt: skip

    steps = np.arange(0.0, HOLD_DWELL_S + 1.0, 0.5)
    held = [status == "hold" for status in statuses(steps)]
    assert all(held[: int(HOLD_DWELL_S / 0.5)]) and not any(held[int(HOLD_DWELL_S / 0.5) :])
    # a dip under the hold speed starts the dwell again; without the time there is no dwell (the 1.5x hysteresis)
    dipped = statuses(steps, np.where(steps == 2.0, 0.5 * HOLD_SPEED_MPS, 1.35 * HOLD_SPEED_MPS))
    assert dipped[-1] == "hold"
    assert statuses([None] * 20)[-1] == "hold"


def test_a_failed_or_late_solve_falls_back_counted_and_bad_inputs_never_escape() -> None:
    mpc = MotorboatMpc(MODEL, time_budget_s=0.0)  # every solve is late
    cmd = mpc.solve(np.array([0.0, 1.0]), np.array([0.1, 0.0]), np.zeros(2), 0.0, 0.0)
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


SLEW_PER_S = 1.0  # ArduPilot's MOT_SLEWRATE default, 100 %/s: 2 s from full ahead to full astern
SLEWED = MotorboatModel.for_top_speed(TOP_SPEED, RADIUS, throttle_slew_per_s=SLEW_PER_S)


def _through_a_slewing_autopilot(model: MotorboatModel, dt: float = 0.5):
    """Drive the simulated boat for 20 s ahead (a wish of 1.5 m/s), then 15 s with a slow wish astern, through an
    autopilot that moves its throttle output at most SLEW_PER_S per s towards each command (AP_MotorsUGV). Returns
    (command throttle, output before it) per step and the plans."""
    mpc = MotorboatMpc(model, step_s=dt, time_budget_s=math.inf)
    boat = MotorboatDynamics(params_for(TOP_SPEED, RADIUS), np.zeros((1, 2)), np.zeros(1), np.random.default_rng(3))
    output, steps, plans = 0.0, [], []
    for k in range(round(35.0 / dt)):
        wish = np.array([1.5, 0.0]) if k * dt < 20.0 else np.array([-0.6, 0.0])
        cmd = mpc.solve(wish, boat.velocity_mps[0], np.zeros(2), boat.heading_rad[0], boat.yaw_rate_radps[0])
        steps.append((cmd.throttle, output))
        plans.append(mpc.last_plan)
        output = min(max(cmd.throttle, output - SLEW_PER_S * dt), output + SLEW_PER_S * dt)
        boat.step(np.array([[output, cmd.steering]]), dt)
    return np.array(steps), plans, boat


def test_a_boat_that_knows_the_throttle_slew_asks_only_for_what_the_autopilot_can_reach() -> None:
    steps, plans, boat = _through_a_slewing_autopilot(SLEWED)
    reach = SLEW_PER_S * 0.5
    assert np.abs(steps[:, 0] - steps[:, 1]).max() <= reach + 1e-12  # the output is what was asked, every step
    for plan in filter(lambda p: p is not None, plans):  # and so is every step planned (thrust fractions)
        assert np.abs(np.diff(plan[:, 0])).max() <= reach + 1e-6
    assert steps[:, 0].max() == pytest.approx(1.0) and steps[-1, 0] < -0.2  # full ahead, then astern
    assert boat.velocity_mps[0, 0] < 0.0
    # A controller that does not know the slew asks for jumps the autopilot spreads over seconds.
    blind, _, _ = _through_a_slewing_autopilot(MODEL)
    assert np.abs(blind[:, 0] - blind[:, 1]).max() > 2 * reach


def test_the_first_planned_thrust_is_what_the_slew_reaches_from_the_output_now() -> None:
    mpc = MotorboatMpc(SLEWED, step_s=0.5, call_period_s=0.1)
    assert mpc.first_thrust_bounds((-0.5, 1.0)) == (-0.25, 0.5)  # from 0: throttle -0.5..0.5, astern at half thrust
    mpc._follow(1.0)  # five calls of 0.1 s take the output from 0 to full ahead
    assert mpc._output == pytest.approx(0.1)
    for _ in range(9):
        mpc._follow(1.0)
    assert mpc._output == pytest.approx(1.0)
    assert mpc.first_thrust_bounds((-0.5, 1.0)) == pytest.approx((0.5, 1.0))
    assert mpc.first_thrust_bounds((-0.5, 0.3)) == pytest.approx((0.5, 0.5))  # out of reach: the nearest it gets
    for _ in range(30):
        mpc._follow(-1.0)
    assert mpc.first_thrust_bounds((0.0, 1.0)) == pytest.approx((-0.25, -0.25))
    assert MotorboatMpc(MODEL).first_thrust_bounds((-0.5, 0.3)) == (-0.5, 0.3)  # no slew: the bounds as they are
    for bad in (-0.1, math.nan, math.inf):
        with pytest.raises(ValueError, match="throttle_slew_per_s"):
            MotorboatModel(throttle_slew_per_s=bad)
    with pytest.raises(ValueError, match="call_period_s"):
        MotorboatMpc(SLEWED, call_period_s=0.0)
