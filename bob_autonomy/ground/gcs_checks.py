"""What the values of the MAVLink messages the ground-station component accepts may be, checked before use.

Every numeric field a handler of `bob_autonomy.ground.gcs` reads is checked here first; a message with a value that
is not finite or outside what its field allows is refused by the component (COMMAND_ACK MAV_RESULT_DENIED,
MISSION_ACK MAV_MISSION_INVALID_PARAMn, the PARAM_VALUE in force) and counted as `out_of_range`. Integer
fields are bounded by their wire type; the float fields are where NaN, infinities and absurd magnitudes come in.

Rules, after ArduPilot where it has one:

- COMMAND_LONG / COMMAND_INT: every parameter a command uses has a range (`COMMAND_RULES`); a parameter it
  does not use may be NaN, which MAVLink defines as "use the default" for float parameters (common.xml,
  MAV_CMD; QGroundControl sends DO_REPOSITION with yaw = NaN), or any finite value (ignored), never an
  infinity. A goal's latitude and longitude must lie in [-90, 90] and [-180, 180] (Rover/GCS_MAVLink_Rover.cpp,
  handle_command_int_do_reposition: check_latlng, else MAV_RESULT_DENIED) and its altitude must be a number
  within +-83,000 m (libraries/GCS_MAVLink/GCS_Common.cpp, location_from_command_t; LOCATION_ALT_MAX_M in
  libraries/AP_Common/Location.h), although a boat ignores it; COMMAND_INT must carry a goal in a global frame.
- MISSION_ITEM / MISSION_ITEM_INT: params 1 to 4 must not be infinite, nor NaN except param 4 (yaw) of a
  NAV_WAYPOINT; x and y are latitude and longitude as above; z must be a number within +-83,000 m
  (libraries/AP_Mission/AP_Mission.cpp: sanity_check_params and mavlink_int_to_mission_cmd, answered with
  MAV_MISSION_INVALID_PARAM1..4, PARAM5_X, PARAM6_Y, PARAM7). A fence vertex's param 1 (the polygon's vertex
  count) must be a whole number in [3, MAX_FENCE_VERTICES].
- PARAM_SET: the value must be finite and within the parameter's range (`bob_autonomy.ground.params.ParamSpec.check`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from bob_autonomy.ground.params import MAX_FENCE_VERTICES

__all__ = [
    "COMMAND_RULES",
    "GLOBAL_FRAMES",
    "GOAL_COMMANDS",
    "LOCATION_ALT_MAX_M",
    "FieldRule",
    "command_problem",
    "mission_item_problem",
]

LOCATION_ALT_MAX_M = 83_000.0  # ArduPilot libraries/AP_Common/Location.h: the altitude a Location can hold

GLOBAL_FRAMES = frozenset(
    {
        mavlink.MAV_FRAME_GLOBAL,
        mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT,
        mavlink.MAV_FRAME_GLOBAL_INT,
        mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
        mavlink.MAV_FRAME_GLOBAL_TERRAIN_ALT,
        mavlink.MAV_FRAME_GLOBAL_TERRAIN_ALT_INT,
    }
)
GOAL_COMMANDS = frozenset({mavlink.MAV_CMD_DO_REPOSITION, mavlink.MAV_CMD_NAV_WAYPOINT})


@dataclass(frozen=True)
class FieldRule:
    """What one numeric field may hold: a number in [lo, hi] (whole when `integer`); NaN only when
    `nan_is_default` (MAVLink's "use the default" for a parameter the command does not use)."""

    name: str
    lo: float = -math.inf
    hi: float = math.inf
    integer: bool = False
    nan_is_default: bool = False

    def problem(self, value: float) -> str | None:
        """None if `value` is allowed, else what is wrong with it (for a message naming the field)."""
        v = float(value)
        if math.isnan(v):
            return None if self.nan_is_default else "is not a number"
        if math.isinf(v):
            return "is not finite"
        if self.integer and v != math.floor(v):
            return "is not a whole number"
        if not self.lo <= v <= self.hi:
            return f"is outside [{self.lo:g}, {self.hi:g}]"
        return None


def _unused(name: str = "unused") -> FieldRule:
    return FieldRule(name, nan_is_default=True)


def _whole(name: str, lo: float, hi: float) -> FieldRule:
    return FieldRule(name, lo, hi, integer=True)


LATITUDE = FieldRule("latitude (deg)", -90.0, 90.0)
LONGITUDE = FieldRule("longitude (deg)", -180.0, 180.0)
ALTITUDE = FieldRule("altitude (m)", -LOCATION_ALT_MAX_M, LOCATION_ALT_MAX_M)
_GOAL = (_unused("speed"), _unused("flags"), _unused("radius"), _unused("yaw"), LATITUDE, LONGITUDE, ALTITUDE)


def _only(first: FieldRule, *more: FieldRule) -> tuple[FieldRule, ...]:
    rules = (first, *more)
    return rules + tuple(_unused() for _ in range(7 - len(rules)))


# The seven parameters of each command the component handles (params 5 and 6 of a goal are its latitude and
# longitude in degrees, COMMAND_INT's x and y divided by 1e7). Commands not listed are MAV_RESULT_UNSUPPORTED.
COMMAND_RULES: dict[int, tuple[FieldRule, ...]] = {
    mavlink.MAV_CMD_MISSION_START: _only(_unused("first item"), _unused("last item")),
    mavlink.MAV_CMD_DO_PAUSE_CONTINUE: _only(_whole("0 pause / 1 continue", 0, 1)),
    mavlink.MAV_CMD_COMPONENT_ARM_DISARM: _only(
        _whole("1 arm / 0 disarm", 0, 1), FieldRule("21196 forces", 0, 65535, integer=True, nan_is_default=True)
    ),
    mavlink.MAV_CMD_DO_SET_MODE: _only(_whole("base mode", 0, 255), _whole("custom mode", 0, 2**32 - 1)),
    mavlink.MAV_CMD_DO_REPOSITION: _GOAL,
    mavlink.MAV_CMD_NAV_WAYPOINT: _GOAL,
    mavlink.MAV_CMD_DO_FOLLOW: _only(_whole("leader system id", 0, 255)),
    mavlink.MAV_CMD_USER_1: _only(_whole("behaviour index", 0, 255)),
    mavlink.MAV_CMD_DO_FENCE_ENABLE: _only(_whole("enable", 0, 2)),
    mavlink.MAV_CMD_REQUEST_MESSAGE: _only(_whole("message id", 0, 2**24 - 1)),
    mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES: _only(_unused("version")),
}


def command_problem(
    command: int, params: Sequence[float], latlon: Sequence[float], frame: int | None = None
) -> str | None:
    """None if a command's parameters may be used, else what is wrong (naming the parameter).

    params: the seven parameters as received (COMMAND_INT: x and y as numbers); latlon: params 5 and 6 read
    as degrees (COMMAND_INT: x / 1e7, y / 1e7); frame: COMMAND_INT's frame (None for COMMAND_LONG)."""
    rules = COMMAND_RULES.get(command)
    if rules is None:
        return None
    values = list(params)
    if command in GOAL_COMMANDS:
        values[4:6] = latlon
        if frame is not None and frame not in GLOBAL_FRAMES:
            return f"frame {frame} is not a global frame"
    for k, (rule, value) in enumerate(zip(rules, values, strict=True), start=1):
        problem = rule.problem(value)
        if problem is not None:
            return f"param{k} ({rule.name}) = {float(value)!r} {problem}"
    return None


_INVALID_PARAM = (
    mavlink.MAV_MISSION_INVALID_PARAM1,
    mavlink.MAV_MISSION_INVALID_PARAM2,
    mavlink.MAV_MISSION_INVALID_PARAM3,
    mavlink.MAV_MISSION_INVALID_PARAM4,
)
_MISSION_Z = FieldRule("z, altitude (m)", -LOCATION_ALT_MAX_M, LOCATION_ALT_MAX_M)
_VERTEX_COUNT = _whole("vertex count", 3, MAX_FENCE_VERTICES)


def mission_item_problem(command: int, params: Sequence[float], lat: float, lon: float, z: float) -> (
    tuple[int, str] | None
):  # fmt: skip
    """None if a mission item's values may be used, else (MAV_MISSION_RESULT, what is wrong).

    params: param1..param4; lat, lon: degrees (MISSION_ITEM_INT: x / 1e7, y / 1e7); z: metres."""
    for k, value in enumerate(params[:4]):
        v = float(value)
        nan_ok = k == 3 and command == mavlink.MAV_CMD_NAV_WAYPOINT  # yaw: NaN = keep the heading
        if math.isinf(v) or (math.isnan(v) and not nan_ok):
            return _INVALID_PARAM[k], f"param{k + 1} = {v!r} is not finite"
    if command == mavlink.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION:
        problem = _VERTEX_COUNT.problem(params[0])
        if problem is not None:
            return mavlink.MAV_MISSION_INVALID_PARAM1, f"param1 ({_VERTEX_COUNT.name}) = {params[0]!r} {problem}"
    for result, rule, value in (
        (mavlink.MAV_MISSION_INVALID_PARAM5_X, LATITUDE, lat),
        (mavlink.MAV_MISSION_INVALID_PARAM6_Y, LONGITUDE, lon),
        (mavlink.MAV_MISSION_INVALID_PARAM7, _MISSION_Z, z),
    ):
        problem = rule.problem(value)
        if problem is not None:
            return result, f"{rule.name} = {float(value)!r} {problem}"
    return None
