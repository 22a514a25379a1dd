"""What the parts of a simulated vehicle (sitl.vehicles.mavlink_vehicle) share: the vehicle kinds, the firmware it
claims to be (Rover 4.7.0-dev at 90700977), its capabilities and modes, and its counters."""

from __future__ import annotations

import math
from dataclasses import dataclass

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sitl.vehicles import autopilot_safety as safety
from sitl.vehicles.autopilot_streams import PRODUCED

m = mavlink
BUOY, EBOT, MOTORBOAT = "buoy", "ebot", "motorboat"
KINDS = (BUOY, EBOT, MOTORBOAT)
DRIVING_MODES = safety.PILOT_MODES
SUPPORTED_MODES = safety.SIMULATED_MODES
HOUSEKEEPING_PERIOD_S = 1.0  # HEARTBEAT and SYS_STATUS in "sensor-rate" streams
STREAM_MODES = ("ardupilot", "sensor-rate")
# AUTOPILOT_VERSION: ArduRover V4.7.0-dev at 90700977 (Rover/version.h FIRMWARE_VERSION 4,7,0,DEV).
FLIGHT_SW_VERSION = (4 << 24) | (7 << 16) | (0 << 8) | m.FIRMWARE_VERSION_TYPE_DEV
FIRMWARE_STRING, GIT_HASH = "ArduRover V4.7.0-dev", b"90700977"
CAPABILITIES = (
    m.MAV_PROTOCOL_CAPABILITY_MISSION_FLOAT
    | m.MAV_PROTOCOL_CAPABILITY_MISSION_INT
    | m.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
    | m.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
    | m.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_GLOBAL_INT
    | m.MAV_PROTOCOL_CAPABILITY_SET_ATTITUDE_TARGET
    | m.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT
    | m.MAV_PROTOCOL_CAPABILITY_COMPASS_CALIBRATION
    | m.MAV_PROTOCOL_CAPABILITY_MAVLINK2
)  # fmt: skip  (no MISSION_FENCE / MISSION_RALLY / FTP: the simulator has none of them)
OVERRIDE_FIELDS = tuple(f"chan{i}_raw" for i in range(1, 19))  # RC_CHANNELS_OVERRIDE's channels
PRODUCED_IN_ORDER = tuple(sorted(PRODUCED))  # the order `stream` sends a step's messages in
HOME_MOVE_M = 0.5  # Rover/defines.h DISTANCE_HOME_MINCHANGE
MISSION_MESSAGES = {"MISSION_COUNT", "MISSION_ITEM_INT", "MISSION_ITEM", "MISSION_REQUEST_LIST",
                    "MISSION_REQUEST_INT", "MISSION_REQUEST", "MISSION_CLEAR_ALL"}  # fmt: skip


@dataclass
class VehicleCounters:
    """What a simulated vehicle has seen: RC overrides applied (armed, driving mode), taken as RC input while
    disarmed or not driving (`idle`: ArduPilot keeps them, e.g. they clear a radio failsafe) and refused (not from
    MAV_GCS_SYSID, or MAV_OPTIONS), failsafe stops (override expiries while driving and failsafe actions), commands
    acknowledged, messages for other systems, messages refused for a bad field (`rejected`), handler errors."""

    commands: int = 0
    idle: int = 0
    refused: int = 0
    failsafes: int = 0
    acks: int = 0
    other_target: int = 0
    rejected: int = 0
    errors: int = 0


def _finite(*values: float) -> bool:
    return all(math.isfinite(float(v)) for v in values)
