"""What the autonomy knows of its ArduPilot autopilot, and how it talks to it.

Transport-free: `AutopilotSession.handle(msg)` takes every MAVLink message the
autopilot (the vehicle's system, component 1) sends; its methods return bytes
to send. `bob_autonomy.onboard.autopilot_start` drives the start-up over a real link.

Facts from ArduPilot's source behind each choice:
- RC overrides are taken only from the system id in MAV_GCS_SYSID (SYSID_MYGCS
  before 4.7), whatever their target (libraries/GCS_MAVLink/GCS_Common.cpp
  `handle_rc_channels_override`), and lapse after RC_OVERRIDE_TIME s; 0 disables
  them, -1 never lets them lapse (libraries/RC_Channel/RC_Channels_VarInfo.h).
- Steering is RCMAP_ROLL's channel, throttle RCMAP_THROTTLE's, lateral
  RCMAP_YAW's (Rover/radio.cpp `set_control_channels`); lateral moves only omni
  frames, FRAME_TYPE 1-4 (libraries/AR_Motors/AP_MotorsUGV.h `is_omni`).
- With PILOT_STEER_TYPE 0 (default) or 2 the steering input is negated while
  the throttle is negative (Rover/mode.cpp `get_pilot_input`); 1 (two paddles)
  reads the channels as paddles. "Negative" is the integer the autopilot reads
  (whole percent, truncated: RC_Channel::control_in), so -0.6 % is not. A frame
  with a steering output (not skid-steer, not omni) negates it once more
  (AP_MotorsUGV::output_regular), so its rudder follows the stick in MANUAL.
- Top speed: SPEED_MAX, or when 0 CRUISE_SPEED / CRUISE_THROTTLE % (Rover/Parameters.cpp).
- Turning radius: TURN_RADIUS, m (Rover/Parameters.cpp, 0.9 m by default), what a motorboat's controller plans with.
- Frames and kinds: a buoy (thrust in any direction: throttle + lateral) needs an omni frame; a motorboat
  (steering + throttle) drives any frame, omni ones included (they take steering and throttle too); an eBot is
  driven as a skid-steer rover (docs/ardupilot.md, "Frames: omni, motorboat, skid-steer").
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from functools import cached_property

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_bridge.autopilot_requests import (
    NO_INTERVAL,
    STREAM_OF_MESSAGE,
    param_request_read,
    request_data_stream,
    request_message,
    set_message_interval,
)
from firmware_bridge.commands import ROVER_MODES, Encoder, rc_override
from firmware_bridge.decoder import MAX_GPS_LAG_S
from firmware_bridge.rc_channels import DEFAULT_DEAD_ZONE_US, RcChannelRange, RcMap, ResolutionCarry, before_expo

BUOY, EBOT, MOTORBOAT = "buoy", "ebot", "motorboat"
OMNI_FRAME_TYPES = {1: "omni3", 2: "omniX", 3: "omniPlus", 4: "omni3mecanum"}
FRAME_CLASSES = {0: "undefined", 1: "rover", 2: "boat", 3: "balancebot"}
FORCE_ARM_MAGIC = 21196.0  # MAV_CMD_COMPONENT_ARM_DISARM param2 that skips the checks (GCS_Common.cpp)

SERVO_OUTPUTS = 32  # NUM_SERVO_CHANNELS of a board with over 1 MB of flash, SITL's too (SRV_Channel_config.h)
CORE_PARAMS = (
    "FRAME_CLASS",
    "FRAME_TYPE",
    "RCMAP_ROLL",
    "RCMAP_THROTTLE",
    "RCMAP_YAW",
    "MAV_GCS_SYSID",
    "SYSID_MYGCS",
    "RC_OVERRIDE_TIME",
    "FS_ACTION",
    "FS_TIMEOUT",
    "FS_GCS_ENABLE",
    "FS_THR_ENABLE",
    "PILOT_STEER_TYPE",
    "CRUISE_SPEED",
    "CRUISE_THROTTLE",
    "SPEED_MAX",
    "MOT_VEC_ANGLEMAX",
    "WENC_TYPE",
    "TURN_RADIUS",
    "MANUAL_OPTIONS",
    "MANUAL_STR_EXPO",
    "MOT_THR_MAX",
    "MOT_SLEWRATE",
    "GPS1_DELAY_MS",
    "GPS_DELAY_MS",  # GPS1_DELAY_MS before ArduPilot 4.6
    *(f"GPS1_POS_{axis}" for axis in "XYZ"),
    *(f"GPS_POS1_{axis}" for axis in "XYZ"),  # GPS1_POS_* before ArduPilot 4.6
    *(f"INS_POS1_{axis}" for axis in "XYZ"),
    *(f"SERVO{n}_FUNCTION" for n in range(1, SERVO_OUTPUTS + 1)),
)
_CORE_PARAM_SET = frozenset(CORE_PARAMS)
# Names of CORE_PARAMS that only older firmware has (the newer name is read too): ArduPilot ignores a request for
# a name it does not know, so these go unanswered by a current one.
LEGACY_PARAMS = frozenset({"SYSID_MYGCS", "GPS_DELAY_MS", "GPS_POS1_X", "GPS_POS1_Y", "GPS_POS1_Z"})
MAX_ANTENNA_OFFSET_M = 10.0  # an antenna offset larger than this is taken for a bad parameter and not used
DEFAULT_THROTTLE_SLEW_PER_S = 1.0  # MOT_SLEWRATE's default, 100 %/s (libraries/AR_Motors/AP_MotorsUGV.cpp)
SKID_STEER_FUNCTIONS = (73, 74)  # SERVOn_FUNCTION throttle left / right (libraries/SRV_Channel/SRV_Channel.h)
MANUAL_SPEED_SCALING = 1  # MANUAL_OPTIONS bit 0: steering scaled down with speed (Rover/Parameters.cpp)
RC_FIELDS = ("MIN", "TRIM", "MAX", "DZ", "REVERSED")

# Messages the estimators need and the rates asked for (Hz), with the slowest rate still usable. ArduPilot
# refuses intervals under 0.8 of its main loop period (GCS_Common.cpp `cap_message_interval`; Rover's loop runs
# at 50 Hz), so nothing here is asked faster than 25 Hz.
_HOUSEKEEPING = {
    mavlink.MAVLINK_MSG_ID_SYS_STATUS: (1.0, 0.2),
    mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: (2.0, 0.0),
    mavlink.MAVLINK_MSG_ID_RC_CHANNELS: (4.0, 0.0),
}
# Buoys and motorboats are estimated alike: GPS, compass (the autopilot's attitude) and IMU.
_AFLOAT = {
    mavlink.MAVLINK_MSG_ID_GPS_RAW_INT: (10.0, 2.0),
    mavlink.MAVLINK_MSG_ID_ATTITUDE: (20.0, 5.0),
    mavlink.MAVLINK_MSG_ID_SCALED_IMU: (25.0, 5.0),
    **_HOUSEKEEPING,
}
STREAMS_HZ = {
    BUOY: _AFLOAT,
    MOTORBOAT: _AFLOAT,
    EBOT: {
        mavlink.MAVLINK_MSG_ID_GPS_RAW_INT: (10.0, 0.0),
        mavlink.MAVLINK_MSG_ID_ATTITUDE: (20.0, 5.0),
        mavlink.MAVLINK_MSG_ID_WHEEL_DISTANCE: (20.0, 0.0),
        mavlink.MAVLINK_MSG_ID_DISTANCE_SENSOR: (20.0, 0.0),
        **_HOUSEKEEPING,
    },
}


# An RC_CHANNELS shows the overrides the autopilot had when it sent it. Over a link that delivers seconds late (a
# slow telemetry radio, or an autopilot sharing an overloaded computer) that is an override we sent that long
# ago: with ArduPilot's own SITL behind a link holding its bytes 2 s, the echo of our overrides came 2.2 s after
# we sent them, and a 1.5 s look-back called a vehicle that took every override one that ignored them
# (tests/ardupilot/test_real_lagging_link.py). Overrides up to this much older still count as echoed, s.
OVERRIDE_ECHO_LAG_S = 5.0

RECOVERED_FACTOR = 1.25  # a slow stream counts as recovered at this multiple of its slowest usable rate

# Every Rover mode by number (Rover/mode.h `Mode::Number`), for messages: those we set and the others it may be in.
ROVER_MODE_NAMES = {number: name for name, number in ROVER_MODES.items()} | {
    6: "FOLLOW", 7: "SIMPLE", 8: "DOCK", 9: "CIRCLE", 12: "SMART_RTL", 16: "INITIALISING"
}  # fmt: skip

# The autopilot's clock since boot (time_boot_ms of ATTITUDE, GLOBAL_POSITION_INT, SYSTEM_TIME, ...) only goes
# forward while it runs; going back by more than this (s) means it restarted: a brownout, a watchdog, a reboot
# command. Less is let pass (messages of two streams may arrive slightly out of order).
REBOOT_BACKSTEP_S = 2.0


def message_name(message_id: int) -> str:
    entry = mavlink.mavlink_map.get(message_id)
    return entry.msgname if entry is not None else f"message {message_id}"


def _int(values: dict[str, float], name: str, default: int) -> int:
    v = values.get(name)
    return round(v) if v is not None and math.isfinite(v) else default


@dataclass(frozen=True)
class AutopilotProfile:
    """The autopilot configuration the autonomy adapts to (read from its parameters; defaults = ArduPilot's)."""

    values: dict[str, float] = field(default_factory=dict)

    def get(self, name: str) -> float | None:
        return self.values.get(name)

    @property
    def known(self) -> bool:
        """True when the frame parameters were read (an autopilot without the parameter protocol is not)."""
        return "FRAME_CLASS" in self.values and "FRAME_TYPE" in self.values

    @property
    def frame_class(self) -> int:
        return _int(self.values, "FRAME_CLASS", 1)

    @property
    def frame_type(self) -> int:
        return _int(self.values, "FRAME_TYPE", 0)

    @property
    def lateral_capable(self) -> bool:
        return self.frame_type in OMNI_FRAME_TYPES

    @property
    def frame_name(self) -> str:
        kind = OMNI_FRAME_TYPES.get(self.frame_type, "steering + throttle")
        frame_class = FRAME_CLASSES.get(self.frame_class, "?")
        return f"FRAME_CLASS={self.frame_class} ({frame_class}), FRAME_TYPE={self.frame_type} ({kind})"

    @property
    def gcs_system_id(self) -> int:
        """The system id RC overrides must come from: MAV_GCS_SYSID (SYSID_MYGCS on older firmware), else 255."""
        for name in ("MAV_GCS_SYSID", "SYSID_MYGCS"):
            if name in self.values:
                return _int(self.values, name, 255)
        return 255

    @property
    def override_timeout_s(self) -> float:
        v = self.values.get("RC_OVERRIDE_TIME")
        return 3.0 if v is None or not math.isfinite(v) else float(v)

    @cached_property
    def skid_steering(self) -> bool:
        """Throttle left and throttle right (SERVOn_FUNCTION 73 and 74) both on some output, any of the 32
        (AP_MotorsUGV::have_skid_steering: SRV_Channels::function_assigned of both)."""
        functions = {_int(self.values, f"SERVO{n}_FUNCTION", 0) for n in range(1, SERVO_OUTPUTS + 1)}
        return set(SKID_STEER_FUNCTIONS) <= functions

    @cached_property
    def steering_expo(self) -> float:
        """MANUAL_STR_EXPO: in MANUAL, ArduPilot shapes the steering stick x into (1 - e) x / (1 - e |x|)
        (Rover/mode_manual.cpp, AP_Math input_expo; none at e >= 0.95), so a steering command must be sent
        through the inverse (`firmware_bridge.rc_channels.before_expo`) to come out as meant."""
        expo = self.values.get("MANUAL_STR_EXPO", 0.0)
        return float(expo) if expo is not None and math.isfinite(expo) else 0.0

    @cached_property
    def steering_flips_in_reverse(self) -> bool:
        """Whether, in MANUAL, what the steering stick does is turned the other way while the autopilot reads the
        throttle as negative. Rover/mode.cpp get_pilot_input flips the stick for PILOT_STEER_TYPE 0 and 2; a frame
        with a steering output (neither skid-steer nor omni: a motorboat's rudder or drive) flips it back in
        AP_MotorsUGV::output_regular ("reverse steering direction when backing up"), so there the rudder follows
        the stick with 0 and 2 and is flipped with 3. ArduPilot's SITL motorboat put its rudder on the other side
        astern when we assumed the first flip alone (tests/ardupilot/test_real_rc_resolution.py)."""
        steer_type = _int(self.values, "PILOT_STEER_TYPE", 0)
        if steer_type == 1:  # two paddles: not driven by this process
            return False
        regular = not self.lateral_capable and not self.skid_steering
        return (steer_type in (0, 2)) != regular

    @property
    def top_speed_mps(self) -> float | None:
        """The speed at full throttle the autopilot is configured for, m/s (None when it says nothing)."""
        speed_max = self.values.get("SPEED_MAX", 0.0)
        if speed_max is not None and math.isfinite(speed_max) and speed_max > 0:
            return float(speed_max)
        cruise, throttle = self.values.get("CRUISE_SPEED"), self.values.get("CRUISE_THROTTLE")
        if cruise is None or throttle is None or not (math.isfinite(cruise) and math.isfinite(throttle)):
            return None
        if cruise <= 0 or throttle <= 0:
            return None
        return float(cruise) * 100.0 / float(throttle)

    @property
    def throttle_ceiling(self) -> float:
        """MOT_THR_MAX as a fraction: the autopilot clips the throttle demand to +-this (AP_MotorsUGV::set_throttle;
        sanity_check_parameters keeps it within 30-100 %), so a boat's controller plans with no more."""
        value = self.values.get("MOT_THR_MAX")
        if value is None or not math.isfinite(value):
            return 1.0
        return min(max(float(int(value)), 30.0), 100.0) / 100.0

    @property
    def throttle_slew_per_s(self) -> float:
        """MOT_SLEWRATE / 100: the fastest change of the throttle output the autopilot lets through, full-scale
        units per s (AP_MotorsUGV::slew_limit_throttle, in MANUAL too; 0: none). Its default (100 %/s, 2 s from full
        ahead to full astern) when not read: a boat's controller plans its braking with it."""
        value = self.values.get("MOT_SLEWRATE")
        if value is None or not math.isfinite(value):
            return DEFAULT_THROTTLE_SLEW_PER_S
        return max(float(int(value)), 0.0) / 100.0

    @property
    def gps_lag_s(self) -> float | None:
        """GPS1_DELAY_MS (GPS_DELAY_MS before ArduPilot 4.6) in s: the lag from a GPS measurement to the autopilot
        reading it, which its EKF compensates (libraries/AP_GPS/AP_GPS.cpp get_lag). None when not read or 0 (the
        autopilot then uses its detected GPS type's default, 0.08-0.22 s, which it does not report)."""
        for name in ("GPS1_DELAY_MS", "GPS_DELAY_MS"):
            value = self.values.get(name)
            if value is not None and math.isfinite(value) and value > 0:
                return min(float(value), 1000.0 * MAX_GPS_LAG_S) / 1000.0
        return None

    @property
    def gps_antenna_m(self) -> tuple[float, float, float] | None:
        """Where the GPS antenna is from the IMU, m, x forward, y right, z down: GPS1_POS_X/Y/Z (GPS_POS1_* before
        ArduPilot 4.6) less INS_POS1_X/Y/Z, as ArduPilot's EKF3 takes it (AP_NavEKF3_PosVelFusion.cpp
        CorrectGPSForAntennaOffset). None when not read or all zero."""
        for prefix in ("GPS1_POS_", "GPS_POS1_"):
            antenna = [self.values.get(prefix + axis) for axis in "XYZ"]
            if all(v is not None for v in antenna):
                break
        else:
            return None
        imu = [self.values.get(f"INS_POS1_{axis}", 0.0) for axis in "XYZ"]
        offset = tuple(float(a) - float(b) for a, b in zip(antenna, imu, strict=True))
        if not all(math.isfinite(v) and abs(v) <= MAX_ANTENNA_OFFSET_M for v in offset) or not any(offset):
            return None
        return offset

    @property
    def turn_radius_m(self) -> float | None:
        """TURN_RADIUS, m: the turning radius the autopilot is configured with (None when not read or not > 0)."""
        value = self.values.get("TURN_RADIUS")
        return float(value) if value is not None and math.isfinite(value) and value > 0 else None

    @property
    def rc_map(self) -> RcMap:
        steering = _int(self.values, "RCMAP_ROLL", 1)
        throttle = _int(self.values, "RCMAP_THROTTLE", 3)
        lateral = _int(self.values, "RCMAP_YAW", 4)
        ranges = []
        for channel in sorted({steering, throttle, lateral}):
            p = f"RC{channel}_"
            ranges.append(
                (
                    channel,
                    RcChannelRange(
                        min_us=_int(self.values, p + "MIN", 1100),
                        trim_us=_int(self.values, p + "TRIM", 1500),
                        max_us=_int(self.values, p + "MAX", 1900),
                        dead_zone_us=_int(self.values, p + "DZ", DEFAULT_DEAD_ZONE_US),
                        reversed=bool(_int(self.values, p + "REVERSED", 0)),
                    ),
                )
            )
        return RcMap(steering, throttle, lateral, tuple(ranges))

    def problems(self, kind: str) -> list[str]:
        """What makes this autopilot impossible to drive as `kind`, each with what to change."""
        found = []
        if kind == BUOY and self.known and not self.lateral_capable:
            found.append(
                f"a buoy needs thrust in any direction, but this autopilot is {self.frame_name}: it cannot move "
                "sideways and the lateral channel would be ignored. Run it as a motorboat (--kind motorboat: "
                "steering + throttle, it turns towards where it goes), or set FRAME_TYPE to the omni frame the "
                "vessel really has"
            )
        timeout = self.override_timeout_s
        if timeout == 0:
            found.append("RC_OVERRIDE_TIME is 0, so the autopilot ignores RC overrides; set it to 1-3 s")
        if _int(self.values, "PILOT_STEER_TYPE", 0) == 1:
            found.append("PILOT_STEER_TYPE is 1 (two paddles); set it to 0 (default) or 3 for RC overrides")
        why = self.rc_map.problem()
        if why is not None:
            found.append(f"RC map: {why}; fix the RCMAP_* / RCn_* parameters")
        return found

    def warnings(self, control_period_s: float) -> list[str]:
        """What is drivable but unsafe or surprising, each with what to change."""
        found = []
        timeout = self.override_timeout_s
        if _int(self.values, "MANUAL_OPTIONS", 0) & MANUAL_SPEED_SCALING:
            found.append(
                "MANUAL_OPTIONS has bit 0 (steering speed scaling) set: in MANUAL the autopilot scales the steering "
                "down with its ground speed and flips it on its own speed's sign, not on the throttle's, so the "
                "steering this process asks for is not the steering applied; clear bit 0 of MANUAL_OPTIONS"
            )
        if timeout < 0:
            found.append(
                "RC_OVERRIDE_TIME is -1: overrides never lapse, so if this computer dies the last command runs on; "
                "set it to 1-3 s"
            )
        elif 0 < timeout < 3 * control_period_s:
            found.append(f"RC_OVERRIDE_TIME {timeout:g} s is under three control periods; overrides may lapse")
        far = [self.values.get(f"{p}{a}") for p in ("GPS1_POS_", "GPS_POS1_", "INS_POS1_") for a in "XYZ"]
        if any(v is not None and not abs(v) <= MAX_ANTENNA_OFFSET_M / 2 for v in far):
            found.append(
                f"GPS1_POS_X/Y/Z or INS_POS1_X/Y/Z is over {MAX_ANTENNA_OFFSET_M / 2:g} m or not a number: an antenna "
                f"offset over {MAX_ANTENNA_OFFSET_M:g} m is not used; set them in metres from the hull's reference "
                "point (x forward, y right, z down)"
            )
        if _int(self.values, "FS_GCS_ENABLE", 0) == 0 and self.known:
            found.append(
                f"FS_GCS_ENABLE is 0: if this computer dies the vehicle stops only when RC overrides lapse after "
                f"{timeout:g} s; set FS_GCS_ENABLE=1 and FS_ACTION=2 (Hold) for a failsafe on lost heartbeats"
            )
        return found


@dataclass
class RateMeter:
    """Arrival rates of messages over a sliding window of `window_s` (clock seconds)."""

    window_s: float = 5.0
    arrivals: dict[int, deque] = field(default_factory=dict)

    def note(self, message_id: int, t_s: float) -> None:
        q = self.arrivals.setdefault(message_id, deque())
        q.append(t_s)
        while q and q[0] <= t_s - self.window_s:
            q.popleft()

    def rate_hz(self, message_id: int, now_s: float) -> float:
        q = self.arrivals.get(message_id)
        if not q:
            return 0.0
        while q and q[0] <= now_s - self.window_s:
            q.popleft()
        return len(q) / self.window_s


class AutopilotSession:
    """The autonomy's conversation with one ArduPilot autopilot (system `target_system`, component 1).

    kind: BUOY, MOTORBOAT or EBOT (what the estimators need and how commands map). encoder: our source ids (its
    system id is made the autopilot's MAV_GCS_SYSID once that is known, so that overrides are taken). clock: s.
    """

    def __init__(
        self,
        target_system: int,
        kind: str,
        encoder: Encoder,
        clock: Callable[[], float],
        *,
        estimator: str = "ekf",
    ) -> None:
        if kind not in STREAMS_HZ:
            raise ValueError(f"unknown vehicle kind {kind!r}; choose {', '.join(STREAMS_HZ)}")
        self.target_system, self.kind, self.encoder, self.clock = target_system, kind, encoder, clock
        self.streams = dict(STREAMS_HZ[kind])
        if estimator != "ekf":
            self.streams.pop(mavlink.MAVLINK_MSG_ID_SCALED_IMU, None)
        self.profile = AutopilotProfile()
        self.carry = ResolutionCarry()  # throttle and lateral finer than whole percent, spread over overrides
        self.params: dict[str, float] = {}
        self.acks: deque = deque(maxlen=64)  # (t, command, result) of the COMMAND_ACKs addressed to us
        self.acks_for_others = 0  # COMMAND_ACKs addressed to another sender on the link (a router passes them on)
        self.param_changes: list[tuple[str, float, float]] = []  # (name, before, after) once the profile is learned
        self.texts: deque = deque(maxlen=32)  # (t, severity, text)
        self.other_autopilots: set[int] = set()  # system ids of other autopilots heard on this link (start-up errors)
        self.rates = RateMeter()
        self.custom_mode: int | None = None
        self.armed: bool | None = None
        self.fix_type = 0
        self.last_param_t = -math.inf  # when the last PARAM_VALUE came
        self.prearm_ok: bool | None = None
        self.heading_rad = math.nan  # the autopilot's own attitude: heading (from east, CCW) and its rate (rad/s)
        self.yaw_rate_radps = math.nan
        self.attitude_t = -math.inf  # SYS_STATUS's pre-arm check bit, where the autopilot reports it
        self.satellites = 0
        self.home: tuple[float, float] | None = None
        self.version: object | None = None
        self.rc_in: dict[int, int] = {}
        self.rc_in_t: float | None = None
        self.boot_s: float | None = None  # the autopilot's newest clock since boot (s)
        self.reboots = 0  # times that clock went back (REBOOT_BACKSTEP_S)
        self.last_reboot: tuple[float, float] | None = None  # (clock before, clock after) at the newest reboot, s
        self._slow_warned: set[int] = set()
        self._streams_requested_at: float | None = None
        self.intervals_accepted = False  # this autopilot accepted a SET_MESSAGE_INTERVAL: it schedules by message id
        self.frames_lost = 0  # the autopilot's frames missed on the link, from gaps in their sequence numbers
        self._last_seq: int | None = None
        self._slow_asked_at: dict[int, float] = {}  # when each slow message was last asked for again (clock s)
        self.sent: deque = deque(maxlen=128)  # (t, {channel: PWM}) of the overrides we sent (6.5 s at 20 Hz)

    # -- what the autopilot says ---------------------------------------------------------------------

    def is_autopilot(self, msg) -> bool:
        return msg.get_srcSystem() == self.target_system and msg.get_srcComponent() == mavlink.MAV_COMP_ID_AUTOPILOT1

    def handle(self, msg) -> None:
        """Take one decoded message; only the autopilot's own (system, component 1) count."""
        if not self.is_autopilot(msg):
            if (
                msg.get_type() == "HEARTBEAT"
                and msg.get_srcComponent() == mavlink.MAV_COMP_ID_AUTOPILOT1
                and msg.autopilot != mavlink.MAV_AUTOPILOT_INVALID
            ):
                self.other_autopilots.add(int(msg.get_srcSystem()))
            return
        now = float(self.clock())
        self.rates.note(msg.get_msgId(), now)
        self._count_sequence(msg.get_seq())
        name = msg.get_type()
        try:
            boot_ms = getattr(msg, "time_boot_ms", None)
            if boot_ms is not None:
                self._note_boot_time(boot_ms / 1000.0)
            if name == "HEARTBEAT":
                self.custom_mode = int(msg.custom_mode)
                self.armed = bool(msg.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
            elif name == "PARAM_VALUE":
                value = float(msg.param_value)
                self.last_param_t = now
                if math.isfinite(value):
                    pid = msg.param_id.decode() if isinstance(msg.param_id, bytes) else msg.param_id
                    self._take_param(pid.rstrip("\x00"), value)
            elif name == "COMMAND_ACK":
                self._take_ack(msg, now)
            elif name == "STATUSTEXT":
                text = msg.text.decode(errors="replace") if isinstance(msg.text, bytes) else str(msg.text)
                self.texts.append((now, int(msg.severity), text.rstrip("\x00")))
            elif name == "ATTITUDE":
                yaw, rate = float(msg.yaw), float(msg.yawspeed)
                if math.isfinite(yaw) and math.isfinite(rate):
                    # ours: heading from east, counter-clockwise; MAVLink: yaw from north, clockwise
                    self.heading_rad, self.yaw_rate_radps, self.attitude_t = math.pi / 2 - yaw, -rate, now
            elif name == "SYS_STATUS":
                bit = mavlink.MAV_SYS_STATUS_PREARM_CHECK
                if msg.onboard_control_sensors_present & bit and msg.onboard_control_sensors_enabled & bit:
                    self.prearm_ok = bool(msg.onboard_control_sensors_health & bit)
            elif name == "GPS_RAW_INT":
                self.fix_type, self.satellites = int(msg.fix_type), int(msg.satellites_visible)
            elif name == "HOME_POSITION":
                self.home = (msg.latitude * 1e-7, msg.longitude * 1e-7)
            elif name == "AUTOPILOT_VERSION":
                self.version = msg
            elif name == "RC_CHANNELS":
                self.rc_in = {c: int(getattr(msg, f"chan{c}_raw")) for c in range(1, 9)}
                self.rc_in_t = now
        except (AttributeError, TypeError, ValueError, UnicodeError):
            pass  # a message we cannot read is the decoder's business; it never stops the session

    def _take_param(self, name: str, value: float) -> None:
        """A PARAM_VALUE. ArduPilot sends a parameter's new value to every link when anyone sets it
        (GCS::send_parameter_value), so a ground station's change of one the profile was learned from is heard:
        the profile is learned again (RC map and calibration, steering expo, GCS id act at the next override)."""
        before = self.params.get(name)
        self.params[name] = value
        if before is not None and value != before and name in self.profile.values and self._profile_reads(name):
            self.param_changes.append((name, before, value))
            self.learn()

    def _profile_reads(self, name: str) -> bool:
        """Whether the profile is learned from parameter `name` (CORE_PARAMS, the mapped RC channels' calibration).
        ArduPilot also sends the values it sets itself to every link, STAT_RUNTIME and STAT_FLTTIME every 30 s
        (AP_Stats): those are not a ground station's change."""
        return name in _CORE_PARAM_SET or name in self.rc_param_names()

    def _take_ack(self, msg, now: float) -> None:
        if not self._addressed_to_us(msg):
            self.acks_for_others += 1
            return
        self.acks.append((now, int(msg.command), int(msg.result)))
        if msg.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL and msg.result == mavlink.MAV_RESULT_ACCEPTED:
            self.intervals_accepted = True

    def _addressed_to_us(self, msg) -> bool:
        """Whether a COMMAND_ACK answers us. ArduPilot addresses it to the command's sender (target_system,
        target_component; GCS_Common.cpp handle_command_long), and a router (MAVProxy, mavlink-router) passes
        those meant for a ground station to us too. We send as the autopilot's own system until `learn`, then as
        its GCS id, always as our component; an ack with both targets 0 (MAVLink 1, older firmware) is taken."""
        system, component = int(getattr(msg, "target_system", 0)), int(getattr(msg, "target_component", 0))
        if system == 0 and component == 0:
            return True
        mav = self.encoder.mav
        return component == mav.srcComponent and system in (mav.srcSystem, self.target_system)

    def _note_boot_time(self, boot_s: float) -> None:
        if self.boot_s is not None and boot_s < self.boot_s - REBOOT_BACKSTEP_S:
            self.reboots += 1
            self.last_reboot = (self.boot_s, boot_s)
            self.prearm_ok = None  # what it said before the restart no longer holds
            self._streams_requested_at = None
        self.boot_s = boot_s

    def take_ack(self, command: int, since_s: float) -> int | None:
        """The result of the newest COMMAND_ACK for `command` heard since `since_s`, if any."""
        for t, cmd, result in reversed(self.acks):
            if cmd == command and t >= since_s:
                return result
        return None

    def acks_since(self, command: int, since_s: float) -> list[int]:
        """The results of every COMMAND_ACK for `command` heard since `since_s`, oldest first."""
        return [result for t, cmd, result in self.acks if cmd == command and t >= since_s]

    def texts_since(self, since_s: float, prefixes: Iterable[str] = ("PreArm", "Arm")) -> list[str]:
        """The autopilot's STATUSTEXTs since `since_s` that start with one of `prefixes` (its arming reasons)."""
        wanted = tuple(prefixes)
        seen: list[str] = []
        for t, _severity, text in self.texts:
            if t >= since_s and text.startswith(wanted) and text not in seen:
                seen.append(text)
        return seen

    # -- requests --------------------------------------------------------------------------------------

    def stream_requests(self) -> list[bytes]:
        """SET_MESSAGE_INTERVAL for every message the estimators and the watch need (REQUEST_DATA_STREAM of its
        group for a message ArduPilot cannot schedule by id)."""
        self._streams_requested_at = float(self.clock())
        frames = []
        for message, (hz, _) in self.streams.items():
            if message in NO_INTERVAL:
                stream = STREAM_OF_MESSAGE[message]
                frames.append(request_data_stream(self.encoder, self.target_system, stream, math.ceil(hz)))
            else:
                frames.append(set_message_interval(self.encoder, self.target_system, message, hz))
        return frames

    @property
    def interval_requests(self) -> int:
        """How many of `stream_requests` are SET_MESSAGE_INTERVAL (each answered by a COMMAND_ACK)."""
        return sum(1 for m in self.streams if m not in NO_INTERVAL)

    def stream_fallback_requests(self) -> list[bytes]:
        """REQUEST_DATA_STREAM for the groups holding those messages (firmware without SET_MESSAGE_INTERVAL)."""
        rates: dict[int, float] = {}
        for message, (hz, _) in self.streams.items():
            stream = STREAM_OF_MESSAGE.get(message)
            if stream is not None:
                rates[stream] = max(rates.get(stream, 0.0), hz)
        return [request_data_stream(self.encoder, self.target_system, s, math.ceil(hz)) for s, hz in rates.items()]

    def _count_sequence(self, seq: int) -> None:
        """Count the autopilot's frames lost on the way: each MAVLink frame carries a sequence number that its
        sender increments per link (mod 256), so a gap of k means k frames spoiled or dropped, as MAVProxy counts
        a link's loss. A frame from behind the newest (a step back of under 128) came late, not lost: it takes
        back the loss its gap was counted as (a UDP link may reorder; so does our simulated autopilot, whose
        queued replies can follow a newer frame)."""
        if self._last_seq is None:
            self._last_seq = seq
            return
        gap = (seq - self._last_seq - 1) % 256
        if gap < 128:
            self.frames_lost += gap
            self._last_seq = seq
        elif self.frames_lost > 0:
            self.frames_lost -= 1

    def lagging_messages(self, now_s: float, window_s: float) -> list[int]:
        """Requested messages as good as absent over the last `window_s`: under a quarter of the asked rate and
        under 2 Hz (their request was lost, refused or ignored, not merely limited by a slower sensor)."""
        lagging = []
        for message, (hz, _) in self.streams.items():
            q = self.rates.arrivals.get(message, ())
            got = sum(1 for t in q if t > now_s - window_s) / window_s
            if got < min(0.25 * hz, 2.0):
                lagging.append(message)
        return lagging

    def requests_again(self, messages: Iterable[int]) -> list[bytes]:
        """Ask for `messages` again: each by its id (SET_MESSAGE_INTERVAL) from an autopilot that has accepted
        that command and schedules the message by id; the rest by their stream groups (REQUEST_DATA_STREAM, each
        group at the highest rate wanted of it). Never a group for a message that has an interval: ArduPilot sets
        every message of a requested group to the group's rate (GCS_Param.cpp handle_request_data_stream,
        GCS_Common.cpp initialise_message_intervals_for_stream), and the groups of GPS_RAW_INT, ATTITUDE and
        SCALED_IMU at 10-25 Hz overfill a 57,600 baud line so far that every stream starves (found with ArduPilot's
        SITL on a noisy serial line, where a lost SET_MESSAGE_INTERVAL had been answered with its group)."""
        frames, rates = [], {}
        for message in messages:
            hz = self.streams[message][0]
            if self.intervals_accepted and message not in NO_INTERVAL:
                frames.append(set_message_interval(self.encoder, self.target_system, message, hz))
            elif message in STREAM_OF_MESSAGE:
                stream = STREAM_OF_MESSAGE[message]
                rates[stream] = max(rates.get(stream, 0.0), hz)
        groups = [request_data_stream(self.encoder, self.target_system, s, math.ceil(hz)) for s, hz in rates.items()]
        return frames + groups

    def lagging_stream_requests(self, now_s: float, window_s: float) -> list[bytes]:
        """`requests_again` for the `lagging_messages` of the last `window_s`."""
        return self.requests_again(self.lagging_messages(now_s, window_s))

    def slow_stream_requests(self, now_s: float, grace_s: float = 5.0, every_s: float = 5.0) -> list[bytes]:
        """While driving: SET_MESSAGE_INTERVAL again for each message the estimators need that arrives slower
        than usable, `grace_s` after the streams were requested, at most once per `every_s` per message (its
        request lost on a noisy line, or the autopilot's streams reset). Only from an autopilot that schedules by
        id: never a stream group while driving (`requests_again`)."""
        if not self.intervals_accepted or self._streams_requested_at is None:
            return []
        if now_s - self._streams_requested_at < grace_s:
            return []
        frames = []
        for message, (wanted, slowest) in self.streams.items():
            if slowest <= 0 or message in NO_INTERVAL or self.rates.rate_hz(message, now_s) >= slowest:
                continue
            if now_s - self._slow_asked_at.get(message, -math.inf) >= every_s:
                self._slow_asked_at[message] = now_s
                frames.append(set_message_interval(self.encoder, self.target_system, message, wanted))
        return frames

    def info_requests(self) -> list[bytes]:
        return [
            request_message(self.encoder, self.target_system, mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION),
            request_message(self.encoder, self.target_system, mavlink.MAVLINK_MSG_ID_HOME_POSITION),
        ]

    def param_requests(self, names: Iterable[str]) -> list[bytes]:
        return [param_request_read(self.encoder, self.target_system, n) for n in names if n not in self.params]

    def rc_param_names(self) -> list[str]:
        """RCn_* calibration parameters of the channels the RCMAP parameters read so far name."""
        profile = AutopilotProfile(dict(self.params))
        m = profile.rc_map
        return [f"RC{c}_{f}" for c in sorted({m.steering, m.throttle, m.lateral}) for f in RC_FIELDS]

    def learn(self) -> AutopilotProfile:
        """Adopt the parameters read so far; our encoder sends as the autopilot's GCS system id from now on."""
        self.profile = AutopilotProfile(dict(self.params))
        self.encoder.mav.srcSystem = self.profile.gcs_system_id
        return self.profile

    # -- commands --------------------------------------------------------------------------------------

    def override(self, steering: float, throttle: float, lateral: float | None = None) -> bytes:
        """RC_CHANNELS_OVERRIDE for normalised steering (positive = turn right), throttle (positive = forward) and
        lateral (positive = right), each in [-1, 1] (non-finite -> neutral), through the autopilot's RC map and
        calibration, throttle and lateral in the whole percent the autopilot reads (finer commands spread over
        successive overrides: `ResolutionCarry`); the steering goes through the inverse of the autopilot's
        MANUAL_STR_EXPO and its sign is flipped where the autopilot will read the throttle as negative and flip it
        back."""
        steer = float(steering) if math.isfinite(steering) else 0.0
        thr = self.carry("throttle", float(throttle) if math.isfinite(throttle) else 0.0)
        lat = None if lateral is None or not math.isfinite(lateral) else float(lateral)
        if not self.profile.lateral_capable and self.profile.known:
            lat = None
        if lat is not None:
            lat = self.carry("lateral", lat)
        steer = before_expo(steer, self.profile.steering_expo)
        flip = self.profile.steering_flips_in_reverse
        channels = self.profile.rc_map.channels_for(steer, thr, lat, flip_in_reverse=flip)
        self.sent.append((float(self.clock()), channels))
        return rc_override(channels, self.target_system, mavlink.MAV_COMP_ID_AUTOPILOT1, encoder=self.encoder)

    def release(self) -> bytes:
        """RC_CHANNELS_OVERRIDE handing channels 1-8 back to the RC receiver (0 = release)."""
        channels = dict.fromkeys(range(1, 9), 0)
        return rc_override(channels, self.target_system, mavlink.MAV_COMP_ID_AUTOPILOT1, encoder=self.encoder)

    def arm(self, arm: bool = True, *, force: bool = False) -> bytes:
        p2 = FORCE_ARM_MAGIC if force else 0.0
        message = self.encoder.mav.command_long_encode(
            self.target_system,
            mavlink.MAV_COMP_ID_AUTOPILOT1,
            mavlink.MAV_CMD_COMPONENT_ARM_DISARM,
            0,
            1.0 if arm else 0.0,
            p2,
            0,
            0,
            0,
            0,
            0,
        )
        return self.encoder.pack(message)

    def set_mode(self, mode: str) -> bytes:
        message = self.encoder.mav.command_long_encode(
            self.target_system,
            mavlink.MAV_COMP_ID_AUTOPILOT1,
            mavlink.MAV_CMD_DO_SET_MODE,
            0,
            float(mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED),
            float(ROVER_MODES[mode]),
            0,
            0,
            0,
            0,
            0,
        )
        return self.encoder.pack(message)

    # -- watching ----------------------------------------------------------------------------------------

    def ready(self) -> str | None:
        """None when the autopilot can be armed for us (3D GPS fix and, where SYS_STATUS reports it, its pre-arm
        checks passing: libraries/GCS_MAVLink/GCS.cpp sets MAV_SYS_STATUS_PREARM_CHECK); else what it waits for."""
        if self.custom_mode is None:
            return "no HEARTBEAT from the autopilot yet"
        if self.fix_type < 3:
            return f"waiting for a 3D GPS fix (fix type {self.fix_type}, {self.satellites} satellites)"
        if self.prearm_ok is False:
            recent = [text for _t, _s, text in list(self.texts)[-8:] if text.startswith(("PreArm", "Arm"))]
            return "its pre-arm checks are not passing yet" + (f" ({recent[-1]})" if recent else "")
        return None

    def slow_streams(self, now_s: float, grace_s: float = 5.0) -> list[str]:
        """New warnings for messages the estimators need that arrive slower than usable, `grace_s` after the
        streams were requested: each said once until it has recovered to 1.25 times the slowest usable rate (so a
        rate hovering at the limit is reported once, not every few seconds)."""
        if self._streams_requested_at is None or now_s - self._streams_requested_at < grace_s:
            return []
        found = []
        for message, (wanted, slowest) in self.streams.items():
            if slowest <= 0:
                continue
            rate = self.rates.rate_hz(message, now_s)
            if rate < slowest and message not in self._slow_warned:
                self._slow_warned.add(message)
                found.append(
                    f"{message_name(message)} arrives at {rate:.1f} Hz (asked {wanted:g} Hz, the estimator needs at "
                    f"least {slowest:g} Hz): check the autopilot's SRn_* rates and the link's bandwidth"
                )
            elif rate >= RECOVERED_FACTOR * slowest:
                self._slow_warned.discard(message)
        return found

    def stream_rates(self, now_s: float) -> dict[str, float]:
        """Measured rate (Hz) of each requested message."""
        return {message_name(m): round(self.rates.rate_hz(m, now_s), 2) for m in self.streams}

    def mode_name(self) -> str:
        return ROVER_MODE_NAMES.get(self.custom_mode, f"mode {self.custom_mode}")

    def ignoring_overrides(self, now_s: float, window_s: float = 1.5, lag_s: float = OVERRIDE_ECHO_LAG_S) -> bool:
        """True when the autopilot's latest RC_CHANNELS (younger than `window_s`) matches none of the overrides we
        sent in the last `window_s` + `lag_s` (within 10 us on every channel we set): it is not taking our
        overrides (a wrong MAV_GCS_SYSID, RC_OVERRIDE_TIME = 0, or a link that drops our frames). `lag_s`: how
        much older the override an RC_CHANNELS shows may be, on a link that delivers late."""
        if self.rc_in_t is None or now_s - self.rc_in_t > window_s:
            return False
        recent = [channels for t, channels in self.sent if now_s - t <= window_s + lag_s]
        if not recent:
            return False
        return not any(all(abs(self.rc_in.get(c, pwm) - pwm) <= 10 for c, pwm in ch.items()) for ch in recent)
