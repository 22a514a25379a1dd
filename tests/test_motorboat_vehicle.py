"""The simulated autopilot of a motorboat (sitl.vehicles.mavlink_vehicle, kind "motorboat"): ArduPilot's motorboat
frame,
steering + throttle from RC overrides, lateral ignored, and bob-autonomy's motorboat kind on it."""

from __future__ import annotations

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from bob_autonomy.onboard.autopilot import BUOY, MOTORBOAT, AutopilotProfile, AutopilotSession
from firmware_bridge.commands import Encoder, rc_override
from sitl.vehicles.mavlink_vehicle import SimulatedVehicle


def _settled(vehicle: SimulatedVehicle, channels: dict[int, int], seconds: float = 2.0) -> np.ndarray:
    """Send the override (from the GCS id 255) and let the throttle slew settle; returns the actuator."""
    applied = np.zeros(2)
    for t in np.arange(0.0, seconds, 0.1):
        vehicle.receive(rc_override(channels, vehicle.system_id, 1), float(t))
        applied = vehicle.actuator(float(t))
    return applied


def test_the_motorboat_frame_is_ardupilots() -> None:
    v = SimulatedVehicle(3, "motorboat", 1.0, streams="sensor-rate")
    p = v.params
    assert (p["FRAME_CLASS"], p["FRAME_TYPE"], p["SERVO1_FUNCTION"], p["SERVO3_FUNCTION"]) == (2, 0, 26, 70)
    assert not v.omni() and not v.skid_steer()
    assert p["TURN_RADIUS"] == pytest.approx(0.9) and p["SPEED_MAX"] == 0.0  # Rover's defaults
    messages = mavlink.MAVLink(None).parse_buffer(v.housekeeping(0.0))
    assert [m.type for m in messages if m.get_type() == "HEARTBEAT"] == [mavlink.MAV_TYPE_SURFACE_BOAT]
    assert AutopilotProfile(dict(p.values)).problems(MOTORBOAT) == []
    assert "cannot move sideways" in AutopilotProfile(dict(p.values)).problems(BUOY)[0]


@pytest.mark.parametrize(
    ("steering", "throttle", "expected"),
    [(0.5, 0.6, (0.6, 0.5)), (-1.0, 1.0, (1.0, -1.0)), (0.0, 0.0, (0.0, 0.0)), (0.7, -0.4, (-0.4, 0.7))],
)
def test_bob_autonomy_overrides_reach_the_motorboat_as_throttle_and_steering(steering, throttle, expected) -> None:
    vehicle = SimulatedVehicle(1, "motorboat", 1.0, armed=True)
    session = AutopilotSession(1, MOTORBOAT, Encoder(), lambda: 0.0)
    session.profile = AutopilotProfile(dict(vehicle.params.values))
    session.encoder.mav.srcSystem = 255
    frame = session.override(steering, throttle, 0.9)  # lateral on a motorboat frame: left at TRIM
    decoded = mavlink.MAVLink(None).parse_buffer(frame)[0]
    assert decoded.chan4_raw == 1500
    channels = {c: getattr(decoded, f"chan{c}_raw") for c in (1, 3, 4)}
    applied = _settled(vehicle, channels)
    assert applied == pytest.approx(expected, abs=0.01)  # the reverse steering flip is undone by the autopilot


def test_lateral_never_moves_a_motorboat_and_overrides_lapse() -> None:
    vehicle = SimulatedVehicle(1, "motorboat", 1.0, armed=True, failsafe_s=1.0)
    assert _settled(vehicle, {1: 1500, 3: 1500, 4: 1900}) == pytest.approx((0.0, 0.0))
    vehicle.receive(rc_override({1: 1900, 3: 1900}, 1, 1), 10.0)
    assert vehicle.actuator(10.5)[1] == pytest.approx(1.0)
    assert vehicle.actuator(12.0).tolist() == [0.0, 0.0]  # RC_OVERRIDE_TIME passed: neutral
