"""Requests a companion computer sends its autopilot: message rates, parameters, single messages.

ArduPilot streams on a companion port only at its SRn_* rates (often 1 Hz or
off), so a client asks for what it needs: MAV_CMD_SET_MESSAGE_INTERVAL per
message (libraries/GCS_MAVLink/GCS_Common.cpp `handle_command_set_message_interval`),
REQUEST_DATA_STREAM per stream group for older firmware (`handle_request_data_stream`),
MAV_CMD_REQUEST_MESSAGE for one message now, PARAM_REQUEST_READ by name
(libraries/GCS_MAVLink/GCS_Param.cpp). Each function returns one packed frame.
"""

from __future__ import annotations

import math

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_bridge.commands import Encoder

AUTOPILOT_COMPONENT = mavlink.MAV_COMP_ID_AUTOPILOT1

# REQUEST_DATA_STREAM's groups holding each message (ArduPilot's stream map,
# libraries/GCS_MAVLink/GCS_MAVLink_Parameters.cpp STREAM_*_msgs): the fallback for firmware without
# SET_MESSAGE_INTERVAL, and for messages it will not schedule by id (WHEEL_DISTANCE has no interval of its own).
# SCALED_IMU is in no group: RAW_SENSORS brings RAW_IMU instead, which the decoder reads the same way.
STREAM_OF_MESSAGE = {
    mavlink.MAVLINK_MSG_ID_RAW_IMU: mavlink.MAV_DATA_STREAM_RAW_SENSORS,
    mavlink.MAVLINK_MSG_ID_SCALED_IMU: mavlink.MAV_DATA_STREAM_RAW_SENSORS,
    mavlink.MAVLINK_MSG_ID_SYS_STATUS: mavlink.MAV_DATA_STREAM_EXTENDED_STATUS,
    mavlink.MAVLINK_MSG_ID_GPS_RAW_INT: mavlink.MAV_DATA_STREAM_EXTENDED_STATUS,
    mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: mavlink.MAV_DATA_STREAM_POSITION,
    mavlink.MAVLINK_MSG_ID_ATTITUDE: mavlink.MAV_DATA_STREAM_EXTRA1,
    mavlink.MAVLINK_MSG_ID_RC_CHANNELS: mavlink.MAV_DATA_STREAM_RC_CHANNELS,
    mavlink.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW: mavlink.MAV_DATA_STREAM_RC_CHANNELS,
    mavlink.MAVLINK_MSG_ID_WHEEL_DISTANCE: mavlink.MAV_DATA_STREAM_EXTRA1,
    mavlink.MAVLINK_MSG_ID_DISTANCE_SENSOR: mavlink.MAV_DATA_STREAM_EXTRA3,
    mavlink.MAVLINK_MSG_ID_BATTERY_STATUS: mavlink.MAV_DATA_STREAM_EXTRA3,
}


# Messages ArduPilot has no ap_message id for, so SET_MESSAGE_INTERVAL is denied ("No ap_message for mavlink id",
# libraries/GCS_MAVLink/GCS_Common.cpp `mavlink_id_to_ap_message_id`): only their stream group schedules them.
NO_INTERVAL = {mavlink.MAVLINK_MSG_ID_WHEEL_DISTANCE}


def _command_long(encoder: Encoder, target_system: int, command: int, *params: float) -> bytes:
    values = [float(p) for p in params] + [0.0] * (7 - len(params))
    if not all(math.isfinite(v) for v in values):
        raise ValueError(f"command {command} parameters must be finite, got {values}")
    message = encoder.mav.command_long_encode(target_system, AUTOPILOT_COMPONENT, command, 0, *values)
    return encoder.pack(message)


def set_message_interval(encoder: Encoder, target_system: int, message_id: int, rate_hz: float) -> bytes:
    """MAV_CMD_SET_MESSAGE_INTERVAL: `message_id` every 1 / rate_hz s (rate 0: stop it; negative: the default)."""
    # -1 disables the message, 0 restores the autopilot's default interval
    interval_us = 1e6 / rate_hz if rate_hz > 0 else (-1.0 if rate_hz == 0 else 0.0)
    return _command_long(encoder, target_system, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, message_id, interval_us)


def request_data_stream(encoder: Encoder, target_system: int, stream_id: int, rate_hz: int) -> bytes:
    """REQUEST_DATA_STREAM (deprecated, but the only way into older firmware): a whole group at rate_hz."""
    rate = max(0, min(65535, round(float(rate_hz))))
    message = encoder.mav.request_data_stream_encode(target_system, AUTOPILOT_COMPONENT, stream_id, rate, int(rate > 0))
    return encoder.pack(message)


def request_message(encoder: Encoder, target_system: int, message_id: int) -> bytes:
    """MAV_CMD_REQUEST_MESSAGE: send `message_id` once now (AUTOPILOT_VERSION, HOME_POSITION, ...)."""
    return _command_long(encoder, target_system, mavlink.MAV_CMD_REQUEST_MESSAGE, message_id)


def param_request_read(encoder: Encoder, target_system: int, name: str) -> bytes:
    """PARAM_REQUEST_READ of one parameter by name (index -1); the autopilot answers with PARAM_VALUE."""
    if not 0 < len(name) <= 16 or not name.isascii():
        raise ValueError(f"a parameter name is 1-16 ASCII characters, got {name!r}")
    message = encoder.mav.param_request_read_encode(target_system, AUTOPILOT_COMPONENT, name.encode(), -1)
    return encoder.pack(message)


def param_set(encoder: Encoder, target_system: int, name: str, value: float) -> bytes:
    """PARAM_SET of one float parameter by name; the autopilot echoes PARAM_VALUE."""
    if not math.isfinite(value):
        raise ValueError(f"parameter {name} must be set to a finite value, got {value!r}")
    message = encoder.mav.param_set_encode(
        target_system, AUTOPILOT_COMPONENT, name.encode(), float(value), mavlink.MAV_PARAM_TYPE_REAL32
    )
    return encoder.pack(message)
