"""The simulated motorboat (sitl.vehicles.motorboat): top speed and turning radius as given, no sideways thrust,
drift."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sitl.vehicles.motorboat import MotorboatDynamics, MotorboatParams, params_for


def _boat(params: MotorboatParams, n: int = 1, heading: float = 0.0) -> MotorboatDynamics:
    boat = MotorboatDynamics(params, np.zeros((n, 2)), np.full(n, heading), np.random.default_rng(0))
    boat.torque_std[:] = 0.0
    boat.yaw_torque_nm[:] = 0.0
    return boat


def _run(boat: MotorboatDynamics, command, seconds: float, dt: float = 0.1, **kwargs) -> np.ndarray:
    track = []
    for _ in range(round(seconds / dt)):
        boat.step(np.tile(command, (len(boat), 1)), dt, **kwargs)
        track.append(boat.position_m.copy())
    return np.array(track)


@pytest.mark.parametrize(
    ("top_speed", "radius", "steering"),
    [
        (2.0, 3.0, "outboard"),
        (2.0, 3.0, "rudder"),
        (9.0, 25.0, "outboard"),
        (3.0, 2.25, "outboard"),
        (1.0, 8.0, "rudder"),
    ],
)
def test_top_speed_and_turning_radius_are_what_the_scenario_gives(top_speed, radius, steering) -> None:
    boat = _boat(params_for(top_speed, radius, steering))
    _run(boat, [1.0, 0.0], 60.0)
    assert np.hypot(*boat.velocity_mps[0]) == pytest.approx(top_speed, rel=0.01)
    track = _run(boat, [1.0, 1.0], 120.0)[-600:, 0]  # the last minute of a full-right turn
    centre = track.mean(axis=0)
    assert np.hypot(*(track - centre).T).mean() == pytest.approx(radius, rel=0.05)
    # Full right steering turns clockwise (yaw rate negative, heading from east counter-clockwise).
    assert boat.yaw_rate_radps[0] < 0


def test_straight_ahead_it_moves_only_along_its_keel() -> None:
    boat = _boat(params_for(2.0, 3.0), n=4, heading=0.0)
    boat.heading_rad[:] = [0.0, 0.7, -2.0, 3.0]
    _run(boat, [0.6, 0.0], 30.0)
    forward, sideways = boat.surge_sway().T
    assert (forward > 1.0).all()
    assert np.abs(sideways).max() < 1e-9


def test_a_rudder_needs_way_on_but_an_outboard_turns_from_rest() -> None:
    rudder, outboard = _boat(params_for(2.0, 3.0, "rudder")), _boat(params_for(2.0, 3.0, "outboard"))
    for boat in (rudder, outboard):
        _run(boat, [0.0, 1.0], 5.0)  # full steering, no throttle: nothing turns it
        assert abs(boat.heading_rad[0]) < 1e-9
    _run(outboard, [0.3, 1.0], 1.0)
    _run(rudder, [0.3, 1.0], 1.0)
    assert outboard.heading_rad[0] < rudder.heading_rad[0] < 0.0  # the outboard's thrust turns it at once


def test_an_idle_boat_drifts_with_the_water_and_a_little_with_the_wind() -> None:
    boat = _boat(params_for(2.0, 3.0), n=2)
    wind = np.array([[0.0, 0.0], [5.0, 0.0]])
    current = np.array([[0.0, 0.3], [0.0, 0.0]])
    _run(boat, [0.0, 0.0], 150.0, wind_mps=wind, current_mps=current)
    assert boat.velocity_mps[0] == pytest.approx([0.0, 0.3], abs=2e-3)  # still air holds it back a little
    # Wind: at least the 3 % surface drift, less than the wind itself.
    assert 0.15 < boat.velocity_mps[1, 0] < 1.0 and abs(boat.velocity_mps[1, 1]) < 1e-3


def test_reverse_is_weaker_a_weak_battery_slower_and_inactive_boats_stay_put() -> None:
    boat = _boat(params_for(2.0, 3.0), n=3)
    boat.active[2] = False
    for _ in range(600):
        boat.step(np.array([[-1.0, 0.0], [1.0, 0.0], [1.0, 0.0]]), 0.1, thrust_fraction=np.array([1.0, 0.4, 1.0]))
    astern, weak = -boat.velocity_mps[0, 0], boat.velocity_mps[1, 0]
    assert 0.5 < astern < 2.0 * math.sqrt(0.5) and 0.5 < weak < 2.0 * math.sqrt(0.4) + 0.05
    assert boat.position_m[2].tolist() == [0.0, 0.0] and boat.velocity_mps[2].tolist() == [0.0, 0.0]


def test_non_finite_commands_are_neutral_and_bad_parameters_are_refused() -> None:
    boat = _boat(params_for(2.0, 3.0))
    boat.step(np.array([[np.nan, np.inf]]), 0.1)
    assert np.isfinite(boat.position_m).all() and boat.velocity_mps[0].tolist() == [0.0, 0.0]
    for bad in ({"steering": "jet"}, {"top_speed_mps": 0.0}, {"turning_radius_m": 0.1}, {"max_steer_angle_deg": 90}):
        with pytest.raises(ValueError):
            MotorboatParams(**bad)
    with pytest.raises(ValueError, match=r"turning_radius_m >= 20.25 m"):
        params_for(9.0, 5.0)  # 16 m/s^2 sideways: no small hull turns like that
    with pytest.raises(ValueError, match="parameter sets"):
        MotorboatDynamics([MotorboatParams()], np.zeros((2, 2)), np.zeros(2), np.random.default_rng(0))
