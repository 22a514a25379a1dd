"""Command encoding: the bytes decode back (with pymavlink) to the fields ArduPilot Rover reads."""

from __future__ import annotations

import math

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_bridge import commands
from firmware_bridge.commands import Encoder


def decode_one(data: bytes):
    parser = mavlink.MAVLink(None)
    messages = parser.parse_buffer(data)
    assert messages is not None and len(messages) == 1
    assert data[0] == mavlink.PROTOCOL_MARKER_V2  # MAVLink 2
    return messages[0]


def channels(message) -> list[int]:
    return [getattr(message, f"chan{i}_raw") for i in range(1, 19)]


@pytest.mark.parametrize(
    ("thrust", "throttle", "lateral"),
    [
        ((10.0, 0.0), 1900, 1500),  # full forward
        ((0.0, 0.0), 1500, 1500),  # zero
        ((-10.0, 0.0), 1100, 1500),  # full reverse
        ((25.0, -40.0), 1900, 1900),  # clipped; y to the right -> lateral high
        # half forward, half to the left: past Rover's 30 us dead zone, 1530 + 0.5 * 370 (ArduPilot's scaling)
        ((5.0, 5.0), 1715, 1285),
        ((math.nan, 0.0), 1500, 1500),  # non-finite -> neutral
    ],
)
def test_rc_override_for_thrust(thrust, throttle, lateral):
    message = decode_one(commands.rc_override_for_thrust(thrust, 10.0, target_system=3, target_component=1))
    assert message.get_type() == "RC_CHANNELS_OVERRIDE"
    assert (message.target_system, message.target_component) == (3, 1)
    raw = channels(message)
    assert raw[commands.CHANNEL_THROTTLE - 1] == throttle
    assert raw[commands.CHANNEL_LATERAL - 1] == lateral
    assert raw[commands.CHANNEL_STEERING - 1] == 1500
    untouched = [raw[i - 1] for i in range(1, 9) if i not in (1, 3, 4)]
    assert untouched == [65535] * 5 and raw[8:] == [0] * 10


def test_rc_override_yaw_command_ccw_positive_is_steering_left():
    message = decode_one(commands.rc_override_for_thrust((0.0, 0.0), 10.0, yaw_command=0.5))
    assert channels(message)[0] == 1285  # 1470 - 0.5 * 370
    with pytest.raises(ValueError):
        commands.rc_override_for_thrust((1.0, 0.0), 0.0)


@pytest.mark.parametrize(
    ("left", "right", "throttle", "steering"),
    [
        (2.0, 2.0, 1900, 1500),
        (0.0, 0.0, 1500, 1500),
        (2.0, -2.0, 1500, 1900),  # spin clockwise (turn right)
        (-1.0, 1.0, 1500, 1285),  # 1470 - 0.5 * 370
        (1.0, 0.0, 1623, 1623),  # 1530 + 0.25 * 370, rounded away from the dead zone
        (9.0, 9.0, 1900, 1500),  # clipped
    ],
)
def test_rc_override_for_wheels(left, right, throttle, steering):
    raw = channels(decode_one(commands.rc_override_for_wheels(left, right, 2.0)))
    assert raw[2] == throttle and raw[0] == steering


def test_manual_control_axes():
    message = decode_one(commands.manual_control(0.5, -2.0, target_system=1))
    assert message.get_type() == "MANUAL_CONTROL"
    assert (message.target, message.z, message.y, message.x, message.r) == (1, 500, -1000, 32767, 32767)


def test_heartbeat_from_onboard_computer():
    message = decode_one(commands.heartbeat())
    assert message.get_type() == "HEARTBEAT"
    assert message.type == mavlink.MAV_TYPE_ONBOARD_CONTROLLER
    assert message.autopilot == mavlink.MAV_AUTOPILOT_INVALID
    assert message.get_srcComponent() == mavlink.MAV_COMP_ID_ONBOARD_COMPUTER == 191
    assert message.get_srcSystem() == 255


@pytest.mark.parametrize(("arm", "param1"), [(True, 1.0), (False, 0.0)])
def test_arm_disarm_command_long(arm, param1):
    message = decode_one(commands.command_long_arm(arm, target_system=2, target_component=1))
    assert message.get_type() == "COMMAND_LONG"
    assert message.command == mavlink.MAV_CMD_COMPONENT_ARM_DISARM == 400
    assert (message.target_system, message.target_component, message.param1, message.param2) == (2, 1, param1, 0.0)
    forced = decode_one(commands.command_long_arm(False, force=True))
    assert forced.param2 == 21196.0


def test_set_mode():
    message = decode_one(commands.set_mode("guided"))
    assert message.command == mavlink.MAV_CMD_DO_SET_MODE
    assert message.param1 == mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED and message.param2 == 15.0
    assert decode_one(commands.set_mode(4)).param2 == 4.0
    with pytest.raises(ValueError, match="unknown Rover mode"):
        commands.set_mode("FLY")


def test_encoder_sequence_and_source_ids():
    encoder = Encoder(source_system=42, source_component=191)
    first = decode_one(commands.heartbeat(encoder=encoder))
    second = decode_one(commands.heartbeat(encoder=encoder))
    assert first.get_srcSystem() == 42
    assert (second.get_seq() - first.get_seq()) % 256 == 1
