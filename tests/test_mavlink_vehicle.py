"""The simulated autopilot and the telemetry encoder, against real MAVLink bytes and firmware_bridge's decoder."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_bridge import commands
from firmware_bridge.commands import Encoder
from firmware_bridge.decoder import TelemetryDecoder
from firmware_bridge.readings import CompassReading, GpsFix, ImuReading
from firmware_bridge.telemetry import TelemetryEncoder, yaw_from_heading
from sitl.vehicles.mavlink_vehicle import SimulatedVehicle


def _decode(data: bytes):
    decoder = TelemetryDecoder(clock=lambda: 5.0)
    readings = decoder.feed(data)
    assert decoder.counters.decoded >= 1 and decoder.counters.bad_crc == 0
    return readings


@pytest.mark.parametrize("heading", [0.0, 0.7, math.pi / 2, -2.5, math.pi])
def test_telemetry_round_trips_through_the_decoder(heading: float) -> None:
    enc = TelemetryEncoder(3)
    gps, att, imu = _decode(
        enc.gps_raw_int(1.0, 1.3405123, 103.9560456, (0.3, -0.4))
        + enc.attitude(1.0, heading, 0.25)
        + enc.scaled_imu(1.0, (0.5, -0.2), 0.1)
    )
    assert isinstance(gps, GpsFix) and isinstance(att, CompassReading) and isinstance(imu, ImuReading)
    assert gps.lat_deg[0] == pytest.approx(1.3405123, abs=1e-7) and gps.lon_deg[0] == pytest.approx(
        103.9560456, abs=1e-7
    )
    np.testing.assert_allclose(gps.velocity_mps[0], (0.3, -0.4), atol=0.01)
    assert math.remainder(att.heading_rad[0] - heading, 2 * math.pi) == pytest.approx(0.0, abs=1e-6)
    np.testing.assert_allclose(imu.accel_body_mps2[0], (0.5, -0.2), atol=0.01)  # 1 mG steps
    assert imu.gyro_z_radps[0] == pytest.approx(0.1, abs=1e-3)


def test_yaw_convention() -> None:
    assert yaw_from_heading(math.pi / 2) == pytest.approx(0.0)  # north
    assert yaw_from_heading(0.0) == pytest.approx(math.pi / 2)  # east
    assert yaw_from_heading(math.pi) == pytest.approx(-math.pi / 2)  # west


# A command reaches ArduPilot as the nearest whole percent (RC_Channel::control_in), sent as the first PWM read as
# that: within half a percent and one PWM step (1/370 of the range past the dead zone) of what was meant.
RESOLUTION = 0.005 + 1 / 370


@pytest.mark.parametrize("thrust", [(45.0, 0.0), (-10.0, 20.0), (0.0, -45.0), (3.3, 4.4)])
def test_rc_thrust_round_trip_within_the_autopilots_resolution(thrust) -> None:
    msg = mavlink.MAVLink(None).decode(bytearray(commands.rc_override_for_thrust(thrust, 45.0)))
    np.testing.assert_allclose(commands.thrust_from_rc(msg, 45.0), thrust, atol=45.0 * RESOLUTION)


@pytest.mark.parametrize("wheels", [(0.2, 0.2), (-0.1, 0.15), (0.2, -0.2), (0.0, 0.05)])
def test_rc_wheels_round_trip_within_the_autopilots_resolution(wheels) -> None:
    msg = mavlink.MAVLink(None).decode(bytearray(commands.rc_override_for_wheels(*wheels, 0.2)))
    np.testing.assert_allclose(commands.wheels_from_rc(msg, 0.2), wheels, atol=2 * 0.2 * RESOLUTION)


# No throttle slew, so that a command applies at once (MOT_SLEWRATE is tested in tests/test_autopilot_rc.py);
# firmware_bridge.commands encodes RC as ArduPilot's default calibration reads it (30 us dead zone).
LINEAR = {"MOT_SLEWRATE": 0}


def _vehicle(**kw) -> SimulatedVehicle:
    return SimulatedVehicle(2, "buoy", 45.0, failsafe_s=1.0, params=LINEAR, **kw)


def _acks(data: bytes) -> list:
    return [m for m in TelemetryDecoder().feed_messages(data) if m.get_type() == "COMMAND_ACK"]


def test_disarmed_vehicle_refuses_to_drive_until_armed_with_an_ack() -> None:
    v = _vehicle()
    v.receive(commands.rc_override_for_thrust((45.0, 0.0), 45.0, target_system=2), 0.0)
    assert v.counters.idle == 1 and v.counters.refused == 0 and not v.actuator(0.0).any()
    (ack,) = _acks(v.receive(commands.command_long_arm(True, target_system=2), 0.1))
    assert ack.command == mavlink.MAV_CMD_COMPONENT_ARM_DISARM and ack.result == mavlink.MAV_RESULT_ACCEPTED
    v.receive(commands.rc_override_for_thrust((45.0, 0.0), 45.0, target_system=2), 0.2)
    np.testing.assert_allclose(v.actuator(0.3), (45.0, 0.0), atol=45.0 / 400)


def test_commands_for_others_or_from_a_stranger_are_not_obeyed() -> None:
    v = _vehicle(armed=True)
    v.receive(commands.rc_override_for_thrust((45.0, 0.0), 45.0, target_system=3), 0.0)
    stranger = Encoder(source_system=77)
    v.receive(commands.rc_override_for_thrust((45.0, 0.0), 45.0, target_system=2, encoder=stranger), 0.0)
    assert v.counters.other_target == 1 and v.counters.refused == 1 and not v.actuator(0.1).any()


def test_hold_mode_stops_and_unsimulated_modes_are_refused() -> None:
    v = _vehicle(armed=True)
    v.receive(commands.rc_override_for_thrust((20.0, 0.0), 45.0, target_system=2), 0.0)
    (ack,) = _acks(v.receive(commands.set_mode("HOLD", target_system=2), 0.1))
    assert ack.result == mavlink.MAV_RESULT_ACCEPTED and not v.actuator(0.2).any()
    # AUTO exists in Rover but is not simulated: refused as Rover refuses a mode it cannot enter.
    (ack,) = _acks(v.receive(commands.set_mode("AUTO", target_system=2), 0.3))
    assert ack.result == mavlink.MAV_RESULT_FAILED and v.mode == 4


def test_failsafe_stops_the_thruster_when_commands_stop() -> None:
    v = _vehicle(armed=True)
    v.receive(commands.rc_override_for_thrust((30.0, 0.0), 45.0, target_system=2), 10.0)
    np.testing.assert_allclose(v.actuator(10.9), (30.0, 0.0), atol=45.0 * RESOLUTION)
    assert not v.actuator(11.1).any() and v.counters.failsafes == 1
    assert not v.actuator(15.0).any() and v.counters.failsafes == 1  # one lapse, counted once
    v.receive(commands.rc_override_for_thrust((10.0, 0.0), 45.0, target_system=2), 16.0)
    np.testing.assert_allclose(v.actuator(16.1), (10.0, 0.0), atol=45.0 * RESOLUTION)


def test_garbage_is_counted_never_raised() -> None:
    v = _vehicle(armed=True)
    rng = np.random.default_rng(4)
    good = commands.rc_override_for_thrust((9.0, 0.0), 45.0, target_system=2)
    for _ in range(200):
        noise = rng.integers(0, 256, rng.integers(1, 80)).astype(np.uint8).tobytes()
        v.receive(noise + good[: rng.integers(0, len(good))], 0.0)
    v.receive(good, 0.0)
    np.testing.assert_allclose(v.actuator(0.0), (9.0, 0.0), atol=45.0 / 400)
    assert v.reader.counters.skipped_bytes > 0


def test_housekeeping_once_a_second() -> None:
    v = _vehicle(streams="sensor-rate")
    assert v.housekeeping(0.0) and not v.housekeeping(0.5) and v.housekeeping(1.0)
    kinds = [m.get_type() for m in TelemetryDecoder().feed_messages(v.housekeeping(2.0))]
    assert kinds == ["HEARTBEAT", "SYS_STATUS"]
