"""The simulated autopilot's parameters and the MAVLink parameter protocol, as ArduPilot Rover serves them.

Names, defaults and documented ranges are ArduPilot Rover's (upstream master at
commit 90700977c553, the tree issue #18 built; the file behind each is in its
`ParamSpec.source`). Current names, not the documentation's older ones:
MAV_SYSID and MAV_GCS_SYSID replaced SYSID_THISMAV and SYSID_MYGCS
(Rover/Parameters.cpp `gcs_conversion_info`, libraries/GCS_MAVLink/GCS.cpp), and
the per-port stream rates SRn_* are MAVn_* (n = port + 1: MAV1_* for SERIAL0,
libraries/GCS_MAVLink/GCS.cpp `AP_SUBGROUPVARPTR(_chan[0], "1", ...)`).

The protocol (libraries/GCS_MAVLink/GCS_Param.cpp):
- PARAM_REQUEST_LIST: every parameter as PARAM_VALUE with its index and the count.
- PARAM_REQUEST_READ: by index when param_index != -1, else by name; an unknown
  name or index gets no answer at all.
- PARAM_SET: an unknown name, NaN or infinity is ignored without a reply
  (`handle_param_set`). Integer parameters are stored as ArduPilot stores them
  (value + 0.01 toward the sign, truncated, clamped to the type: AP_Param.cpp
  `set_float`), and the new value is echoed as PARAM_VALUE with index -1
  (AP_Param.cpp `save` -> `send_parameter`, GCS_Param.cpp `send_parameter_value`).
  Stricter than ArduPilot, which stores any finite value: a value outside the
  documented @Range is refused and the unchanged value echoed, so a test that
  relies on an out-of-range setting fails here before it misleads on a boat.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass

from pymavlink.dialects.v20 import ardupilotmega as mavlink

INT8, INT16, INT32, REAL32 = (
    mavlink.MAV_PARAM_TYPE_INT8,
    mavlink.MAV_PARAM_TYPE_INT16,
    mavlink.MAV_PARAM_TYPE_INT32,
    mavlink.MAV_PARAM_TYPE_REAL32,
)
_TYPE_LIMITS = {INT8: (-128, 127), INT16: (-32768, 32767), INT32: (-(2**31), 2**31 - 1)}

# Frame settings of each simulated kind (Rover/Parameters.cpp FRAME_CLASS 0..3, FRAME_TYPE 0..4;
# libraries/AR_Motors/AP_MotorsUGV.h frame_type; libraries/SRV_Channel/SRV_Channel.h function numbers).
FRAME_ROVER, FRAME_BOAT = 1, 2
FRAME_TYPE_UNDEFINED, FRAME_TYPE_OMNIX = 0, 2
SERVO_GROUND_STEERING, SERVO_THROTTLE, SERVO_THROTTLE_LEFT, SERVO_THROTTLE_RIGHT = 26, 70, 73, 74
SERVO_MOTOR1 = 33  # motor1..motor4 = 33..36
SERVO_GPIO = -1
SERVO_OUTPUTS = 32  # SERVO1..32 (NUM_SERVO_CHANNELS on SITL and boards over 1 MB: SRV_Channel_config.h)
KIND_FRAMES = {
    # A BoB buoy: a boat with vectored thrust, i.e. an omni frame (OmniX: 4 motors), so lateral (RCMAP_YAW) moves it
    # sideways (AP_MotorsUGV::setup_omni, is_omni).
    # SPEED_MAX: what full thrust really gives (1 m/s, BODY_SPECS and sitl/vehicles/dynamics.py), as an owner would set
    # it; without it the autonomy would take CRUISE_SPEED / CRUISE_THROTTLE (4 m/s with Rover's defaults).
    "buoy": {"FRAME_CLASS": FRAME_BOAT, "FRAME_TYPE": FRAME_TYPE_OMNIX, "SERVO1_FUNCTION": SERVO_MOTOR1,
             "SERVO2_FUNCTION": SERVO_MOTOR1 + 1, "SERVO3_FUNCTION": SERVO_MOTOR1 + 2,
             "SERVO4_FUNCTION": SERVO_MOTOR1 + 3, "SPEED_MAX": 1.0},
    # The eBot: a skid-steer rover (throttle left / right on SERVO1 / SERVO3), two wheel encoders.
    "ebot": {"FRAME_CLASS": FRAME_ROVER, "FRAME_TYPE": FRAME_TYPE_UNDEFINED, "SERVO1_FUNCTION": SERVO_THROTTLE_LEFT,
             "SERVO3_FUNCTION": SERVO_THROTTLE_RIGHT, "WENC_TYPE": 10, "WENC2_TYPE": 10, "SPEED_MAX": 0.2},
    # A motorboat: steering + throttle, no lateral (Rover/Parameters.cpp set_default_function CH_1, CH_3;
    # Tools/autotest/default_params/motorboat.parm: FRAME_CLASS 2); dynamics in sitl/vehicles/motorboat.py.
    "motorboat": {"FRAME_CLASS": FRAME_BOAT, "FRAME_TYPE": FRAME_TYPE_UNDEFINED,
                  "SERVO1_FUNCTION": SERVO_GROUND_STEERING, "SERVO3_FUNCTION": SERVO_THROTTLE},
}  # fmt: skip

STREAM_PARAMS = ("RAW_SENS", "EXT_STAT", "RC_CHAN", "RAW_CTRL", "POSITION", "EXTRA1", "EXTRA2", "EXTRA3", "PARAMS")
# Rover's stream defaults, Hz (libraries/GCS_MAVLink/GCS_MAVLink_Parameters.cpp AP_MAV_DEFAULT_STREAM_RATE_* for
# APM_BUILD_Rover: 1 Hz each, PARAMS 10).
ROVER_STREAM_DEFAULTS_HZ = dict.fromkeys(STREAM_PARAMS, 1) | {"PARAMS": 10}
STREAM_PORT_PREFIX = "MAV1_"  # SERIAL0's MAVLink channel 0 (libraries/GCS_MAVLink/GCS.cpp)
RC_CHANNELS = 8  # RC1..RC8 (RC_CHANNELS_OVERRIDE's first eight; RCMAP_* may point at any of them)


@dataclass(frozen=True)
class ParamSpec:
    """One parameter: name (<= 16 chars), default, MAV_PARAM_TYPE, documented range, ArduPilot file."""

    name: str
    default: float
    mav_type: int
    low: float
    high: float
    source: str


def _rc_specs(dead_zone_channels: Iterable[int]) -> list[ParamSpec]:
    src = "libraries/RC_Channel/RC_Channel.cpp"
    specs = []
    for ch in range(1, RC_CHANNELS + 1):
        # Rover gives its steering, throttle and lateral inputs a 30 us dead zone (Rover/radio.cpp init_rc_in).
        dz = 30 if ch in dead_zone_channels else 0
        specs += [
            ParamSpec(f"RC{ch}_MIN", 1100, INT16, 800, 2200, src),
            ParamSpec(f"RC{ch}_TRIM", 1500, INT16, 800, 2200, src),
            ParamSpec(f"RC{ch}_MAX", 1900, INT16, 800, 2200, src),
            ParamSpec(f"RC{ch}_REVERSED", 0, INT8, 0, 1, src),
            ParamSpec(f"RC{ch}_DZ", dz, INT16, 0, 200, src),
        ]
    return specs


def rover_parameter_table(kind: str, system_id: int, gcs_system_id: int = 255) -> list[ParamSpec]:
    """The simulated Rover's parameters in PARAM_REQUEST_LIST order, with the defaults of `kind`'s frame."""
    if kind not in KIND_FRAMES:
        raise ValueError(f"unknown vehicle kind {kind!r}; choose one of {sorted(KIND_FRAMES)}")
    rover, gcs = "Rover/Parameters.cpp", "libraries/GCS_MAVLink/GCS.cpp"
    arming, rcmap = "libraries/AP_Arming/AP_Arming.cpp", "libraries/AP_RCMapper/AP_RCMapper.cpp"
    specs = [
        ParamSpec("FRAME_CLASS", 1, INT8, 0, 3, rover),
        ParamSpec("FRAME_TYPE", 0, INT8, 0, 4, rover),
        ParamSpec("INITIAL_MODE", 0, INT8, 0, 16, rover),
        ParamSpec("PILOT_STEER_TYPE", 0, INT8, 0, 3, rover),
        ParamSpec("MANUAL_STR_EXPO", 0.0, REAL32, -0.5, 0.95, rover),
        ParamSpec("CRUISE_SPEED", 2.0, REAL32, 0, 100, rover),
        ParamSpec("CRUISE_THROTTLE", 50, INT8, 0, 100, rover),
        ParamSpec("FS_ACTION", 2, INT8, 0, 6, rover),
        ParamSpec("FS_TIMEOUT", 1.5, REAL32, 1, 100, rover),
        ParamSpec("FS_THR_ENABLE", 1, INT8, 0, 2, rover),
        ParamSpec("FS_THR_VALUE", 910, INT16, 910, 1100, rover),
        ParamSpec("FS_GCS_ENABLE", 0, INT8, 0, 2, rover),
        ParamSpec("FS_GCS_TIMEOUT", 5.0, REAL32, 2, 120, rover),
        ParamSpec("FS_OPTIONS", 0, INT32, 0, 1, rover),
        ParamSpec("MAV_SYSID", system_id, INT16, 1, 255, gcs),
        ParamSpec("MAV_GCS_SYSID", gcs_system_id, INT16, 1, 255, gcs),
        ParamSpec("MAV_OPTIONS", 0, INT16, 0, 1, gcs),
        ParamSpec("ARMING_CHECK", 1, INT32, 0, 2**21 - 1, arming),
        ParamSpec("ARMING_NEED_LOC", 0, INT8, 0, 1, arming),
        ParamSpec("RC_OVERRIDE_TIME", 3.0, REAL32, -1, 120, "libraries/RC_Channel/RC_Channels_VarInfo.h"),
        ParamSpec("RCMAP_ROLL", 1, INT8, 1, 16, rcmap),
        ParamSpec("RCMAP_PITCH", 2, INT8, 1, 16, rcmap),
        ParamSpec("RCMAP_THROTTLE", 3, INT8, 1, 16, rcmap),
        ParamSpec("RCMAP_YAW", 4, INT8, 1, 16, rcmap),
        ParamSpec("MOT_SLEWRATE", 100, INT16, 0, 1000, "libraries/AR_Motors/AP_MotorsUGV.cpp"),
        # the GPS lag the autopilot compensates (0: its GPS type's default); a vessel places fixes with it
        ParamSpec("GPS1_DELAY_MS", 0, INT16, 0, 250, "libraries/AP_GPS/AP_GPS_Params.cpp"),
        # where the GPS antenna and the IMU are on the hull (m, FRD); the simulated GPS is at the IMU
        *(ParamSpec(f"GPS1_POS_{a}", 0.0, REAL32, -5, 5, "libraries/AP_GPS/AP_GPS_Params.cpp") for a in "XYZ"),
        *(
            ParamSpec(f"INS_POS1_{a}", 0.0, REAL32, -5, 5, "libraries/AP_InertialSensor/AP_InertialSensor.cpp")
            for a in "XYZ"
        ),
        ParamSpec("MOT_THR_MAX", 100, INT8, 30, 100, "libraries/AR_Motors/AP_MotorsUGV.cpp"),
        ParamSpec("WENC_TYPE", 0, INT8, 0, 10, "libraries/AP_WheelEncoder/AP_WheelEncoder.cpp"),
        ParamSpec("WENC2_TYPE", 0, INT8, 0, 10, "libraries/AP_WheelEncoder/AP_WheelEncoder.cpp"),
        # What a motorboat's controller plans with: top speed (0: from CRUISE_SPEED / CRUISE_THROTTLE) and the
        # turning radius (Rover/Parameters.cpp ParametersG2 speed_max, turn_radius).
        ParamSpec("SPEED_MAX", 0.0, REAL32, 0, 30, rover),
        ParamSpec("TURN_RADIUS", 0.9, REAL32, 0, 10, rover),
    ]
    servo = "Rover/Parameters.cpp (set_default_function), libraries/SRV_Channel/SRV_Channel_aux.cpp"
    # Outputs 17-32 default to GPIO (-1: disabled; SRV_Channels.cpp constructor), the others to none (0).
    functions = {1: SERVO_GROUND_STEERING, 3: SERVO_THROTTLE}
    defaults = {i: functions.get(i, 0 if i <= 16 else SERVO_GPIO) for i in range(1, SERVO_OUTPUTS + 1)}
    specs += [ParamSpec(f"SERVO{i}_FUNCTION", f, INT16, -1, 200, servo) for i, f in defaults.items()]
    specs += _rc_specs((1, 3, 4))
    rates, hz = "libraries/GCS_MAVLink/GCS_MAVLink_Parameters.cpp", ROVER_STREAM_DEFAULTS_HZ
    specs += [ParamSpec(STREAM_PORT_PREFIX + g, hz[g], INT16, 0, 50, rates) for g in STREAM_PARAMS]
    overrides = KIND_FRAMES[kind]
    return [ParamSpec(s.name, overrides.get(s.name, s.default), s.mav_type, s.low, s.high, s.source) for s in specs]


def parameter_default(kind: str, name: str) -> float:
    """The default of parameter `name` on a simulated autopilot of `kind` (KeyError for a name it does not have)."""
    for spec in rover_parameter_table(kind, 1):
        if spec.name == name:
            return float(spec.default)
    raise KeyError(f"the simulated {kind} autopilot has no parameter {name!r}")


def stored_value(value: float, mav_type: int) -> float:
    """`value` as ArduPilot stores it in a parameter of `mav_type` (AP_Param.cpp set_float: integers get 0.01 added
    toward the value's sign, are truncated and clamped to the type's range)."""
    if mav_type == REAL32:
        return float(value)
    low, high = _TYPE_LIMITS[mav_type]
    nudged = value + (0.01 if value >= 0 else -0.01)
    return float(int(min(high, max(low, nudged))))


def _param_name(raw) -> str:
    text = raw.decode("ascii", "replace") if isinstance(raw, bytes | bytearray) else str(raw)
    return text.split("\x00", 1)[0]


class ParameterStore:
    """The parameter values of one vehicle and the replies of the parameter protocol.

    pack: turns a pymavlink message into frame bytes (the vehicle's encoder). on_change(name, value) is told of
    every value that changed, so the vehicle can apply it.
    """

    def __init__(self, specs: list[ParamSpec], pack: Callable, mav, overrides: dict[str, float] | None = None) -> None:
        self.specs = list(specs)
        self.index = {s.name: i for i, s in enumerate(self.specs)}
        self.values = {s.name: stored_value(s.default, s.mav_type) for s in self.specs}
        self.pack, self.mav = pack, mav
        self.on_change: Callable[[str, float], None] | None = None
        self.refused = 0  # PARAM_SETs refused (unknown name, non-finite or out of range)
        self.version = 0  # counts changes, so that values derived from parameters can be cached
        for name, value in (overrides or {}).items():
            if not self.set(name, value):
                raise ValueError(f"cannot set parameter {name} to {value!r}: {self.problem(name, value)}")

    def __getitem__(self, name: str) -> float:
        return self.values[name]

    def __len__(self) -> int:
        return len(self.specs)

    def get_int(self, name: str) -> int:
        return int(self.values[name])

    def problem(self, name: str, value: float) -> str | None:
        """Why `value` cannot be stored in `name`, or None."""
        if name not in self.index:
            return f"no parameter {name!r}"
        if not math.isfinite(value):
            return "the value must be finite"
        spec = self.specs[self.index[name]]
        if not spec.low <= stored_value(value, spec.mav_type) <= spec.high:
            return f"{name} takes {spec.low:g}..{spec.high:g} ({spec.source}), got {value!r}"
        return None

    def set(self, name: str, value: float) -> bool:
        """Store a value (ArduPilot's integer rounding); False, and nothing changed, when `problem` says no."""
        if self.problem(name, value) is not None:
            return False
        spec = self.specs[self.index[name]]
        new = stored_value(value, spec.mav_type)
        changed = new != self.values[name]
        self.values[name] = new
        self.version += changed
        if changed and self.on_change is not None:
            self.on_change(name, new)
        return True

    # -- the protocol ------------------------------------------------------------------------------------

    def param_value(self, name: str, index: int) -> bytes:
        """PARAM_VALUE of `name` with `index` (-1: not in answer to an indexed request, sent as 65535)."""
        spec = self.specs[self.index[name]]
        message = self.mav.param_value_encode(
            name.encode("ascii"), float(self.values[name]), spec.mav_type, len(self.specs), index & 0xFFFF
        )
        return self.pack(message)

    def request_list(self) -> bytes:
        """Every parameter with its index (PARAM_REQUEST_LIST; GCS_Param.cpp queued_param_send)."""
        return b"".join(self.param_value(s.name, i) for i, s in enumerate(self.specs))

    def request_read(self, msg) -> bytes:
        """PARAM_REQUEST_READ: by index unless it is -1, else by name; nothing when unknown (param_io_timer)."""
        index = int(msg.param_index)
        if index != -1:
            if not 0 <= index < len(self.specs):
                return b""
            return self.param_value(self.specs[index].name, index)
        name = _param_name(msg.param_id)
        return self.param_value(name, -1) if name in self.index else b""

    def handle_set(self, msg) -> bytes:
        """PARAM_SET: store and echo; unknown or non-finite: no reply; out of range: echo the unchanged value."""
        name = _param_name(msg.param_id)
        value = float(msg.param_value)
        if name not in self.index or not math.isfinite(value):
            self.refused += 1
            return b""
        if not self.set(name, value):
            self.refused += 1
        return self.param_value(name, -1)
