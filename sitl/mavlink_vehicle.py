"""A simulated vehicle's autopilot as a MAVLink endpoint that behaves as ArduPilot Rover does.

What it does, and the ArduPilot source file behind each behaviour (docs/simulated-autopilot.md has the whole
table):
- Telemetry only at its stream rates (sitl/autopilot_streams.py): Rover's MAVn_* group defaults (1 Hz) until
  asked with SET_MESSAGE_INTERVAL or REQUEST_DATA_STREAM; REQUEST_MESSAGE sends one message now. Each message
  is made from the simulated sensors' latest reading of its kind; a stream faster than its sensor goes at the
  sensor's rate. `streams="sensor-rate"` keeps the old behaviour instead: every reading encoded as it comes,
  HEARTBEAT and SYS_STATUS at 1 Hz.
- Parameters (sitl/autopilot_params.py), missions (sitl/autopilot_mission.py), RC input, overrides and their
  expiry (sitl/autopilot_rc.py), arming checks, modes and failsafes (sitl/autopilot_safety.py).
- AUTOPILOT_VERSION as Rover advertises it (GCS_Common.cpp send_autopilot_version, capabilities from
  Rover/GCS_MAVLink_Rover.cpp and GCS_Common.cpp), HOME_POSITION set on the first GPS fix and moved with the
  vehicle while disarmed (Rover/commands.cpp update_home, once a second), MAV_CMD_DO_SET_HOME
  (GCS_Common.cpp handle_command_do_set_home).
- Commands are answered with COMMAND_ACK to COMMAND_LONG and COMMAND_INT alike (GCS_Common.cpp
  handle_command_long converts to COMMAND_INT). Messages are processed when addressed to this system (or 0) and
  component 1 (or 0) (libraries/GCS_MAVLink/MAVLink_routing.cpp check_and_forward).
- Hardening (#17): a field out of its range or not finite is refused (COMMAND_ACK MAV_RESULT_DENIED, the
  protocol's error, or no effect), counted in `counters.rejected`; an exception in a handler is counted in
  `counters.errors` and never escapes `receive`.

Transport-free: `receive(bytes)` returns the replies for the sender, `stream()` / `housekeeping()` the
telemetry and announcements for every listener; the lockstep simulator passes them in memory, the process
fleet over UDP.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_bridge.commands import GCS_SYSTEM_ID, ROVER_MODES
from firmware_bridge.decoder import TelemetryDecoder
from firmware_bridge.telemetry import TelemetryEncoder
from sitl import autopilot_safety as safety
from sitl.autopilot_mission import MissionStore
from sitl.autopilot_params import STREAM_PORT_PREFIX, ParameterStore, rover_parameter_table
from sitl.autopilot_rc import (
    PilotOutput,
    RcInput,
    norm_input_dz,
    omni_motor_outputs,
    pilot_demand,
    scale_angle,
    servo_pwm,
    skid_outputs,
    slew_limited,
)
from sitl.autopilot_streams import PRODUCED, SCHEDULABLE, StreamSchedule

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


class SimulatedVehicle:
    """The autopilot of one simulated buoy or eBot (see the module docstring).

    kind: "buoy" (command = body-frame thrust x forward, y left, N), "ebot" (wheel speeds left, right, m/s) or
    "motorboat" (throttle and steering outputs, each in [-1, 1]; FRAME_TYPE 0 with SERVO1 ground steering, SERVO3
    throttle).
    max_actuator: the full-scale actuator value, N of thrust or m/s of wheel speed (full RC deflection).
    failsafe_s: RC_OVERRIDE_TIME when given (ArduPilot's default 3 s otherwise). armed: armed at boot, without
    checks. mode: INITIAL_MODE when given. streams: "ardupilot" or "sensor-rate" (module docstring).
    rc_receiver: False for a vehicle with no RC receiver: radio failsafe (and HOLD) until overrides arrive.
    params: parameter values to start with (name -> value), e.g. {"PILOT_STEER_TYPE": 3}.
    """

    def __init__(
        self,
        system_id: int,
        kind: str,
        max_actuator: float,
        *,
        failsafe_s: float | None = None,
        armed: bool = False,
        mode: int | None = None,
        gcs_system_id: int = GCS_SYSTEM_ID,
        streams: str = "ardupilot",
        rc_receiver: bool = True,
        params: dict[str, float] | None = None,
    ) -> None:
        if kind not in KINDS:
            raise ValueError(f"unknown vehicle kind {kind!r}; choose one of {', '.join(KINDS)}")
        if failsafe_s is not None and not failsafe_s > 0:
            raise ValueError(f"failsafe_s must be positive, got {failsafe_s!r}")
        if streams not in STREAM_MODES:
            raise ValueError(f"streams must be one of {STREAM_MODES}, got {streams!r}")
        self.system_id, self.kind, self.max_actuator, self.streams = system_id, kind, float(max_actuator), streams
        self.telemetry = TelemetryEncoder(system_id)
        self.reader = TelemetryDecoder(clock=lambda: 0.0, agent=0)
        self.counters = VehicleCounters()
        overrides = dict(params or {})
        if failsafe_s is not None:
            overrides.setdefault("RC_OVERRIDE_TIME", float(failsafe_s))
        if mode is not None:
            overrides.setdefault("INITIAL_MODE", int(mode))
        table = rover_parameter_table(kind, system_id, gcs_system_id)
        self.params = ParameterStore(table, self.telemetry.pack, self.telemetry.mav, overrides)
        self._rc_cache: tuple[list[int], dict[str, tuple | None]] | None = None  # see _rc_setup
        self._rc_cache_version = -1
        initial = self.params.get_int("INITIAL_MODE")
        self.mode = initial if initial in SUPPORTED_MODES else ROVER_MODES["MANUAL"]
        self.armed = bool(armed)
        self.schedule = StreamSchedule(
            lambda g: self.params[STREAM_PORT_PREFIX + g], lambda g, hz: self.params.set(STREAM_PORT_PREFIX + g, hz)
        )
        self.rc = RcInput(receiver=rc_receiver)
        self.mission = MissionStore(self._home_item, self.telemetry.pack, self.telemetry.mav, self._text)
        self.failsafe = safety.FailsafeState()
        self.outbox = bytearray()  # announcements for every listener (STATUSTEXT, HOME_POSITION, mode HEARTBEAT)
        self.home: tuple[int, int, float] | None = None  # lat degE7, lon degE7, alt m
        self.home_locked = False
        self._gps = self._compass = self._imu = self._wheels = self._ranges = self._light = None
        self._last_fix_s = -math.inf
        self._sent_reading: dict[object, float] = {}
        self._command = np.zeros(2)  # what the last RC override asks for (N or m/s), before slew, arming and mode
        self._last_command_s = -math.inf
        self._out = PilotOutput()
        self._throttle = 0.0  # slew-limited throttle output
        self._t = -math.inf  # latest time seen
        self._actuator_t: float | None = None
        self._next_housekeeping_s = self._next_home_check_s = -math.inf
        self._next_prearm_s = 0.0
        self._gcs_seen_s: float | None = None
        self._driving_override = False
        self.in_failsafe = True  # no override in force (kept for callers that watch it)

    # -- parameters that act at once -----------------------------------------------------------------------

    @property
    def gcs_system_id(self) -> int:
        return self.params.get_int("MAV_GCS_SYSID")

    @property
    def failsafe_s(self) -> float:
        """RC_OVERRIDE_TIME, s: how long an RC override counts."""
        return float(self.params["RC_OVERRIDE_TIME"])

    def omni(self) -> bool:
        return self.params.get_int("FRAME_TYPE") != 0  # AP_MotorsUGV::is_omni (a known frame type has motors)

    def skid_steer(self) -> bool:
        """AP_MotorsUGV::have_skid_steering: throttle left and right assigned, or an omni frame."""
        functions = {self.params.get_int(f"SERVO{i}_FUNCTION") for i in range(1, 5)}
        return {73, 74} <= functions or self.omni()

    def has_fix(self) -> bool:
        return self._t - self._last_fix_s <= safety.GPS_TIMEOUT_S

    def radio_failsafe_on(self) -> bool:
        return bool(self.failsafe.bits & safety.FS_RADIO)

    def _text(self, severity: int, text: str) -> None:
        self.outbox += self.telemetry.statustext(severity, text)

    def _home_item(self) -> tuple[int, int, float] | None:
        return self.home

    # -- commands in ---------------------------------------------------------------------------------------

    def receive(self, data: bytes, t_s: float) -> bytes:
        """Take bytes from the autonomy or a GCS; returns the replies for that sender. Never raises."""
        replies = bytearray()
        for msg in self.reader.feed_messages(data):
            try:
                self._tick(t_s)
                replies += self._handle(msg, t_s)
            except Exception:  # one bad message must never stop the vehicle (#17)
                self.counters.errors += 1
        return bytes(replies)

    def _for_me(self, msg, system_field: str = "target_system", component_field: str | None = "target_component"):
        system = int(getattr(msg, system_field))
        component = 0 if component_field is None else int(getattr(msg, component_field))
        if system not in (0, self.system_id) or component not in (0, m.MAV_COMP_ID_AUTOPILOT1):
            self.counters.other_target += 1
            return False
        return True

    def _handle(self, msg, t_s: float) -> bytes:
        name = msg.get_type()
        src = msg.get_srcSystem()
        if self.params.get_int("MAV_OPTIONS") & 1 and src not in (self.gcs_system_id, self.system_id):
            self.counters.refused += 1  # MAV_OPTIONS bit 0: MAVLink only from MAV_GCS_SYSID (accept_packet)
            return b""
        sender = (src, msg.get_srcComponent())
        if name == "HEARTBEAT":
            if src == self.gcs_system_id:
                self._gcs_seen_s = t_s
            return b""
        if name == "RC_CHANNELS_OVERRIDE":
            if self._for_me(msg):
                self._override(msg, t_s)
            return b""
        if name == "MANUAL_CONTROL":
            if int(msg.target) == self.system_id:
                self._manual_control(msg, t_s)
            return b""
        if name in ("COMMAND_LONG", "COMMAND_INT"):
            if not self._for_me(msg):
                return b""
            result, extra = self._command_packet(msg, name == "COMMAND_INT")
            self.counters.acks += 1
            ack = self.telemetry.command_ack(int(msg.command), result, *sender)
            if int(msg.command) == m.MAV_CMD_GET_MESSAGE_INTERVAL:
                return extra + ack  # sent from inside the handler, before the ACK (GCS_Common.cpp)
            return ack + extra
        if name == "SET_MODE":
            if self._for_me(msg, component_field=None):
                self._set_mode_common(int(msg.base_mode), int(msg.custom_mode))
            return b""
        if name == "REQUEST_DATA_STREAM":
            if self._for_me(msg) and not self.schedule.request_data_stream(
                int(msg.req_stream_id), int(msg.req_message_rate), int(msg.start_stop)
            ):
                self.counters.rejected += 1
            return b""
        if name in ("PARAM_REQUEST_LIST", "PARAM_REQUEST_READ", "PARAM_SET"):
            return self._param_message(msg, name)
        if name in MISSION_MESSAGES:
            if not self._for_me(msg):
                return b""
            before = self.mission.errors
            reply = self.mission.handle(msg, sender, t_s)
            self.counters.rejected += self.mission.errors - before
            return reply
        return b""

    def _param_message(self, msg, name: str) -> bytes:
        if not self._for_me(msg):
            return b""
        if name == "PARAM_REQUEST_LIST":
            self._banner()
            return self.params.request_list()
        if name == "PARAM_REQUEST_READ":
            return self.params.request_read(msg)
        before = self.params.refused
        reply = self.params.handle_set(msg)
        self.counters.rejected += self.params.refused - before
        self.outbox += reply  # ArduPilot sends the new value to every link (GCS::send_parameter_value)
        return b""

    def _banner(self) -> None:
        """GCS_Common.cpp send_banner: the firmware string (sent on PARAM_REQUEST_LIST and DO_SEND_BANNER)."""
        self._text(m.MAV_SEVERITY_INFO, f"{FIRMWARE_STRING} ({GIT_HASH.decode()})")

    # -- RC input ------------------------------------------------------------------------------------------

    def _override(self, msg, t_s: float) -> None:
        if msg.get_srcSystem() != self.gcs_system_id:
            self.counters.refused += 1  # GCS_Common.cpp handle_rc_channels_override: only from our GCS
            return
        raw = [int(getattr(msg, name, 0)) for name in OVERRIDE_FIELDS]
        if any(not (800 <= v <= 2200 or v in (0, 65534, 65535)) for v in raw):
            self.counters.rejected += 1  # stricter than ArduPilot, which clamps any value into RCx_MIN..MAX
            return
        self.rc.apply_override(raw, t_s)
        self._gcs_seen_s = t_s
        self._after_override(t_s)

    def _manual_control(self, msg, t_s: float) -> None:
        """Rover's MANUAL_CONTROL: y -> steering, z -> throttle channel, over RCx_MIN..MAX (GCS_MAVLink_Rover.cpp
        handle_manual_control_axes, GCS_Common.cpp manual_override); INT16_MAX releases the channel."""
        if msg.get_srcSystem() != self.gcs_system_id:
            self.counters.refused += 1
            return
        if any(not (-1000 <= int(a) <= 1000 or int(a) == 32767) for a in (msg.y, msg.z)):
            self.counters.rejected += 1  # ArduPilot would wrap such a value into a full deflection
            return
        for axis, param in ((msg.y, "RCMAP_ROLL"), (msg.z, "RCMAP_THROTTLE")):
            ch = self.params.get_int(param)
            if not 1 <= ch <= 8:
                continue
            value = 0
            if int(axis) != 32767:
                low, high = self.params.get_int(f"RC{ch}_MIN"), self.params.get_int(f"RC{ch}_MAX")
                value = int(low + (high - low) * (int(axis) + 1000) / 2000)
            raw = [65535] * 8 + [0] * 10
            raw[ch - 1] = value
            self.rc.apply_override(raw, t_s)
        self._gcs_seen_s = t_s
        self._after_override(t_s)

    def _after_override(self, t_s: float) -> None:
        self.rc.update(t_s, self.failsafe_s, self._trims())
        demand = self._demand(PilotOutput(*self._read_pilot()))
        self._command = demand
        self._last_command_s = t_s
        if self.armed and self.mode in DRIVING_MODES:
            self.counters.commands += 1
            self._driving_override = True
        else:
            self.counters.idle += 1

    def _rc_setup(self) -> tuple[list[int], dict[str, tuple | None]]:
        """RC1..8_TRIM and, per role, (channel, MIN, TRIM, MAX, DZ, REVERSED) or None for an invalid map; read
        again from the parameters only when one has changed."""
        if self._rc_cache_version != self.params.version or self._rc_cache is None:
            p = self.params
            trims = [p.get_int(f"RC{ch}_TRIM") for ch in range(1, 9)]
            roles: dict[str, tuple | None] = {}
            for role, name in (("steer", "RCMAP_ROLL"), ("throttle", "RCMAP_THROTTLE"), ("lateral", "RCMAP_YAW")):
                ch = p.get_int(name)
                roles[role] = None if not 1 <= ch <= 8 else (
                    ch, p.get_int(f"RC{ch}_MIN"), p.get_int(f"RC{ch}_TRIM"), p.get_int(f"RC{ch}_MAX"),
                    p.get_int(f"RC{ch}_DZ"), bool(p.get_int(f"RC{ch}_REVERSED")),
                )  # fmt: skip
            self._rc_cache, self._rc_cache_version = (trims, roles), p.version
        return self._rc_cache

    def _trims(self) -> list[int]:
        return self._rc_setup()[0]

    def _channel(self, role: str, paddle: bool = False) -> float:
        setup = self._rc_setup()[1][role]
        if setup is None:
            return 0.0  # RC_Channels: a dummy channel for an invalid map
        ch, *calib = setup
        pwm = self.rc.radio_in[ch - 1]
        if pwm == 0:
            return 0.0
        return norm_input_dz(pwm, *calib) if paddle else scale_angle(pwm, *calib)

    def _read_pilot(self) -> tuple[float, float, float]:
        steering, throttle = pilot_demand(self._channel, self.params.get_int("PILOT_STEER_TYPE"), self.skid_steer())
        lateral = self._channel("lateral") if self.omni() else 0.0
        return steering, throttle, lateral

    def _demand(self, out: PilotOutput) -> np.ndarray:
        """The actuator vector (N thrust x, y body; m/s wheels left, right; or a motorboat's throttle and ground
        steering outputs, each in [-1, 1], steering > 0 to starboard) for motor demands `out`."""
        if self.kind == MOTORBOAT:
            return np.array([out.throttle, out.steering])
        if self.kind == BUOY:
            return np.array([out.throttle * self.max_actuator, -out.lateral * self.max_actuator])
        left, right = skid_outputs(out)
        return np.array([left * self.max_actuator, right * self.max_actuator])

    # -- commands ------------------------------------------------------------------------------------------

    def _command_packet(self, msg, is_int: bool) -> tuple[int, bytes]:
        """(MAV_RESULT, messages to send after the ACK) for a COMMAND_LONG or COMMAND_INT."""
        cmd = int(msg.command)
        p = [float(msg.param1), float(msg.param2), float(msg.param3), float(msg.param4)]
        if cmd == m.MAV_CMD_COMPONENT_ARM_DISARM:
            return self._arm_disarm(p[0], p[1]), b""
        if cmd == m.MAV_CMD_DO_SET_MODE:
            if not (_finite(p[0], p[1]) and 0 <= p[0] < 256 and 0 <= p[1] < 2**32):
                return self._reject(m.MAV_RESULT_DENIED), b""
            return self._set_mode_common(int(p[0]), int(p[1])), b""
        if cmd == m.MAV_CMD_SET_MESSAGE_INTERVAL:
            result, text = self.schedule.set_message_interval(p[0], p[1], p[2])
            if text:
                self._text(m.MAV_SEVERITY_INFO, text)
            return self._counted(result), b""
        if cmd == m.MAV_CMD_GET_MESSAGE_INTERVAL:
            result, interval = self.schedule.get_message_interval(p[0])
            reply = b"" if interval is None else self.telemetry.message_interval(int(p[0]), interval)
            return self._counted(result), reply
        if cmd == m.MAV_CMD_REQUEST_MESSAGE:
            return self._request_message(p[0], p[1])
        if cmd == m.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES:
            if p[0] != 1.0:
                return self._reject(m.MAV_RESULT_FAILED), b""
            return m.MAV_RESULT_ACCEPTED, self._one_message(m.MAVLINK_MSG_ID_AUTOPILOT_VERSION)
        if cmd == m.MAV_CMD_GET_HOME_POSITION:
            if self.home is None:
                return m.MAV_RESULT_FAILED, b""
            return m.MAV_RESULT_ACCEPTED, self._one_message(m.MAVLINK_MSG_ID_HOME_POSITION)
        if cmd == m.MAV_CMD_DO_SET_HOME:
            return self._set_home_command(msg, p, is_int), b""
        if cmd == m.MAV_CMD_RUN_PREARM_CHECKS:
            if self.armed:
                return m.MAV_RESULT_TEMPORARILY_REJECTED, b""
            self._report_failures("PreArm", safety.arming_failures(self))
            return m.MAV_RESULT_ACCEPTED, b""
        if cmd == m.MAV_CMD_DO_SEND_BANNER:
            self._banner()
            return m.MAV_RESULT_ACCEPTED, b""
        if cmd in (m.MAV_CMD_NAV_RETURN_TO_LAUNCH, m.MAV_CMD_MISSION_START):
            return m.MAV_RESULT_FAILED, b""  # RTL and AUTO are not simulated (Rover/GCS_MAVLink_Rover.cpp)
        return m.MAV_RESULT_UNSUPPORTED, b""

    def _reject(self, result: int) -> int:
        self.counters.rejected += 1
        return result

    def _counted(self, result: int) -> int:
        return self._reject(result) if result == m.MAV_RESULT_DENIED else result

    def _request_message(self, param1: float, param2: float) -> tuple[int, bytes]:
        """GCS_Common.cpp handle_command_request_message: the message once, after the ACK."""
        if not (_finite(param1) and 0 <= param1 < 2**32):
            return self._reject(m.MAV_RESULT_DENIED), b""
        message_id = int(param1)
        if message_id == m.MAVLINK_MSG_ID_MESSAGE_INTERVAL:
            result, interval = self.schedule.get_message_interval(param2)
            reply = b"" if interval is None else self.telemetry.message_interval(int(param2), interval)
            return self._counted(result), reply
        if message_id not in SCHEDULABLE:
            return m.MAV_RESULT_FAILED, b""
        return m.MAV_RESULT_ACCEPTED, self._one_message(message_id)

    def _arm_disarm(self, param1: float, param2: float) -> int:
        """GCS_Common.cpp handle_command_component_arm_disarm with AP_Arming::arm / Rover's checks."""
        if param1 == 1.0:
            if self.armed:
                return m.MAV_RESULT_ACCEPTED
            failures = [] if param2 in safety.FORCE_ARM else safety.arming_failures(self)
            if failures:
                self._report_failures("Arm", failures)
                return m.MAV_RESULT_FAILED
            self.armed = True
            self._text(m.MAV_SEVERITY_INFO, "Throttle armed")
            return m.MAV_RESULT_ACCEPTED
        if param1 == 0.0:
            if self.armed:
                self._disarm()
            return m.MAV_RESULT_ACCEPTED
        return self._reject(m.MAV_RESULT_UNSUPPORTED) if not _finite(param1) else m.MAV_RESULT_UNSUPPORTED

    def _disarm(self) -> None:
        self.armed = False
        self._text(m.MAV_SEVERITY_INFO, "Throttle disarmed")

    def _report_failures(self, prefix: str, failures: Sequence[str]) -> None:
        for reason in failures:
            self._text(m.MAV_SEVERITY_CRITICAL, f"{prefix}: {reason}")

    def _set_mode_common(self, base_mode: int, custom_mode: int) -> int:
        """GCS_Common.cpp _set_mode_common: only custom modes; Rover::set_mode."""
        if not base_mode & m.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            return self._reject(m.MAV_RESULT_DENIED)
        return m.MAV_RESULT_ACCEPTED if self.set_mode(custom_mode) else m.MAV_RESULT_FAILED

    def set_mode(self, mode: int) -> bool:
        """Enter Rover mode number `mode` if the simulator can (autopilot_safety docstring); says why not."""
        if mode == self.mode:
            return True
        if mode not in safety.ROVER_MODE_NUMBERS:
            self._text(m.MAV_SEVERITY_WARNING, f"No such mode {mode}")
            return False
        needs_fix = mode in safety.NEEDS_POSITION or safety.needs_velocity(mode, self.skid_steer())
        if mode == safety.AUTO and not self.mission.items:
            self._text(m.MAV_SEVERITY_NOTICE, "No Mission. Can't set AUTO.")  # Rover/mode_auto.cpp _enter
        if mode not in SUPPORTED_MODES or (self.armed and needs_fix and not self.has_fix()):
            self._text(m.MAV_SEVERITY_WARNING, "Flight mode change failed")
            return False
        self.mode = mode
        self.outbox += self._heartbeat()  # Rover::set_mode sends a HEARTBEAT at once
        return True

    def _set_home_command(self, msg, p: list[float], is_int: bool) -> int:
        """GCS_Common.cpp handle_command_do_set_home (COMMAND_LONG: lat/lon degrees in param5/6). Stricter than
        ArduPilot, which takes a NaN latitude or longitude for 0: a non-finite one is DENIED unless param1 = 1."""
        if is_int:
            x, y, z, frame = int(msg.x), int(msg.y), float(msg.z), int(msg.frame)
        else:
            lat, lon = float(msg.param5), float(msg.param6)
            if p[0] != 1.0 and not (_finite(lat, lon) and abs(lat) <= 1e3 and abs(lon) <= 1e3):
                return self._reject(m.MAV_RESULT_DENIED)
            x, y = (round(lat * 1e7), round(lon * 1e7)) if _finite(lat, lon) else (0, 0)
            z, frame = float(msg.param7), m.MAV_FRAME_GLOBAL
        if p[0] == 1.0 or (x == 0 and y == 0):
            if self._gps is None or not self.has_fix():
                return m.MAV_RESULT_FAILED
            _, lat, lon, _ = self._gps
            self._set_home(round(lat * 1e7), round(lon * 1e7), 0.0, lock=True)
            return m.MAV_RESULT_ACCEPTED
        if p[0] != 0.0:
            return self._reject(m.MAV_RESULT_FAILED)
        frames = {m.MAV_FRAME_GLOBAL, m.MAV_FRAME_GLOBAL_INT, m.MAV_FRAME_GLOBAL_RELATIVE_ALT,
                  m.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT}  # fmt: skip
        if not math.isfinite(z) or abs(z) > 83000 or frame not in frames:
            return self._reject(m.MAV_RESULT_DENIED)
        if abs(x) > 900_000_000 or abs(y) > 1_800_000_000:
            return self._reject(m.MAV_RESULT_FAILED)  # AP_AHRS::set_home refuses an invalid location
        self._set_home(x, y, z, lock=True)
        return m.MAV_RESULT_ACCEPTED

    def _set_home(self, lat_e7: int, lon_e7: int, alt_m: float, *, lock: bool) -> None:
        self.home = (int(lat_e7), int(lon_e7), float(alt_m))
        if lock:
            self.home_locked = True
            self._text(m.MAV_SEVERITY_INFO, f"Set HOME to {lat_e7 * 1e-7:.6f} {lon_e7 * 1e-7:.6f} at {alt_m:.2f}m")
        self.outbox += self.telemetry.home_position(self._t, *self.home)  # AP_AHRS::set_home sends it

    # -- the autopilot's own clock: failsafes, home, reminders -------------------------------------------------

    def _tick(self, t_s: float) -> None:
        if t_s < self._t:
            return
        self._t = t_s
        timeout = self.failsafe_s
        self.rc.update(t_s, timeout, self._trims())
        if self._driving_override and not self.rc.any_override(t_s, timeout):
            self._driving_override = False
            if self.armed and self.mode in DRIVING_MODES and np.any(self._command):
                self.counters.failsafes += 1  # the override expired while driving: the vehicle stops
        self.in_failsafe = not self.rc.any_override(t_s, timeout)
        self._failsafes(t_s)
        if t_s >= self._next_home_check_s:
            self._next_home_check_s = t_s + 1.0
            self._update_home()
        if not self.armed and t_s >= self._next_prearm_s:
            self._next_prearm_s = t_s + safety.PREARM_DISPLAY_PERIOD_S
            self._report_failures("PreArm", safety.arming_failures(self))
        self.outbox += self.mission.tick(t_s)

    def _failsafes(self, t_s: float) -> None:
        p = self.params
        radio = False
        if p.get_int("FS_THR_ENABLE"):
            ch = p.get_int("RCMAP_THROTTLE")
            pwm = self.rc.radio_in[ch - 1] if 1 <= ch <= 8 else 0
            radio = pwm < p.get_int("FS_THR_VALUE") or t_s - self.rc.last_valid_s > safety.RADIO_TIMEOUT_S
        gcs = False
        if p.get_int("FS_GCS_ENABLE") and self._gcs_seen_s is not None:
            gcs = t_s - self._gcs_seen_s >= p["FS_GCS_TIMEOUT"]
        may = self.mode not in (safety.HOLD, safety.RTL) or bool(p.get_int("FS_OPTIONS") & 1)
        # As Rover calls failsafe_trigger: the radio check every loop when FS_THR_ENABLE, the GCS check when
        # FS_GCS_ENABLE and the GCS has been heard. Whichever call first finds FS_TIMEOUT passed names the
        # failsafe, so a lost GCS is announced "Radio Failsafe" when the radio check is on (Rover/failsafe.cpp).
        checks = [(safety.FS_RADIO, "Radio", radio)] if p.get_int("FS_THR_ENABLE") else []
        if p.get_int("FS_GCS_ENABLE") and self._gcs_seen_s is not None:
            checks.append((safety.FS_GCS, "GCS", gcs))
        for kind, name, on in checks:
            text = self.failsafe.update(kind, name, on, t_s, p["FS_TIMEOUT"], may)
            if text is None:
                continue
            if not text.startswith("!"):
                self._text(m.MAV_SEVERITY_INFO, text)
                continue
            self._text(m.MAV_SEVERITY_WARNING, text[1:])
            self.rc.clear_overrides()
            self.counters.failsafes += 1
            action = safety.failsafe_mode(p.get_int("FS_ACTION"), self.has_fix())
            if action == -1:
                if self.armed:
                    self._disarm()
            elif action is not None:
                self.set_mode(action) or self.set_mode(safety.HOLD)

    def _update_home(self) -> None:
        """Rover::update_home: while disarmed and home not locked, home follows the position (0.5 m steps)."""
        if self.armed or self.home_locked or self._gps is None or not self.has_fix():
            return
        _, lat, lon, _ = self._gps
        if self.home is not None:
            dn = (lat - self.home[0] * 1e-7) * 111_320.0
            de = (lon - self.home[1] * 1e-7) * 111_320.0 * math.cos(math.radians(lat))
            if math.hypot(dn, de) < HOME_MOVE_M:
                return
        self._set_home(round(lat * 1e7), round(lon * 1e7), 0.0, lock=False)

    # -- what the motors do ----------------------------------------------------------------------------------

    def actuator(self, t_s: float) -> np.ndarray:
        """The thrust (N, body frame) or wheel speeds (m/s) applied now: pilot input (RC) in MANUAL, ACRO and
        STEERING while armed and out of radio failsafe, zero otherwise; throttle slew-limited (MOT_SLEWRATE)."""
        self._tick(t_s)
        dt = 0.0 if self._actuator_t is None else max(0.0, t_s - self._actuator_t)
        self._actuator_t = t_s
        steering = throttle = lateral = 0.0
        if self.armed and self.mode in DRIVING_MODES and not self.radio_failsafe_on():
            steering, throttle, lateral = self._read_pilot()
        limited = slew_limited(throttle, self._throttle, self.params["MOT_SLEWRATE"], dt)
        if (throttle < 0) != (limited < 0) and self.params.get_int("PILOT_STEER_TYPE") in (0, 2):
            steering = -steering  # Rover/mode.cpp: throttle still on the other side of zero
        self._throttle = limited
        self._out = PilotOutput(steering, limited, lateral)
        return self._demand(self._out)

    def servo_outputs(self) -> list[int]:
        """SERVO1..8 PWM as the outputs stand (trim while disarmed; AP_MotorsUGV setup_safety_output)."""
        functions = [self.params.get_int(f"SERVO{i}_FUNCTION") for i in range(1, 5)]
        out = self._out if self.armed else PilotOutput()
        values = {26: out.steering, 70: out.throttle}
        values[73], values[74] = skid_outputs(out)
        for k, v in enumerate(omni_motor_outputs(self.params.get_int("FRAME_TYPE"), out)):
            values[33 + k] = v
        return [servo_pwm(values[f]) if f in values else 0 for f in functions] + [0] * 4

    # -- telemetry out ---------------------------------------------------------------------------------------

    def observe(self, kind: str, t_s: float, *values) -> None:
        """Take the latest reading of one sensor: "gps" (lat, lon deg, velocity (east, north) or None), "compass"
        (heading rad), "imu" (accel body (x, y) m/s^2, yaw rate rad/s), "wheels" (distances (l, r) m), "ranges"
        (distances m, max range m), "light" (left, right)."""
        setattr(self, f"_{kind}", (t_s, *values))
        if kind == "gps":
            self._last_fix_s = t_s
            self._t = max(self._t, t_s)
            if self.home is None:
                self._update_home()

    def heading(self) -> float | None:
        """The latest compass heading, rad from east counter-clockwise (None before the first reading)."""
        return None if self._compass is None else float(self._compass[1])

    def _fresh(self, key, reading) -> bool:
        return reading is not None and reading[0] > self._sent_reading.get(key, -math.inf)

    def _message(self, message_id: int) -> bytes:
        """One message from the current state and the latest readings (b"" when there is nothing to say)."""
        enc, t = self.telemetry, self._t
        if message_id == m.MAVLINK_MSG_ID_HEARTBEAT:
            return self._heartbeat()
        if message_id == m.MAVLINK_MSG_ID_SYS_STATUS:
            return enc.sys_status(12.6, 100.0)
        if message_id == m.MAVLINK_MSG_ID_BATTERY_STATUS:
            return enc.battery_status(12.6, 100.0)
        if message_id == m.MAVLINK_MSG_ID_AUTOPILOT_VERSION:
            return enc.autopilot_version(CAPABILITIES, FLIGHT_SW_VERSION, GIT_HASH, 0x5B0B0000 + self.system_id)
        if message_id == m.MAVLINK_MSG_ID_HOME_POSITION:
            return b"" if self.home is None else enc.home_position(t, *self.home)
        if message_id == m.MAVLINK_MSG_ID_RC_CHANNELS:
            return enc.rc_channels(t, self.rc.radio_in, 16 if self.rc.receiver else 0)
        if message_id == m.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW:
            return enc.servo_output_raw(t, self.servo_outputs())
        if message_id == m.MAVLINK_MSG_ID_SYSTEM_TIME:
            return enc.system_time(t)
        heading = None if self._compass is None else self._compass[1]
        if message_id in (m.MAVLINK_MSG_ID_GPS_RAW_INT, m.MAVLINK_MSG_ID_GLOBAL_POSITION_INT) and self._gps:
            _, lat, lon, velocity = self._gps
            if message_id == m.MAVLINK_MSG_ID_GPS_RAW_INT:
                return enc.gps_raw_int(t, lat, lon, velocity)
            return enc.global_position_int(t, lat, lon, velocity, heading)
        if message_id == m.MAVLINK_MSG_ID_VFR_HUD and (self._gps or self._compass):
            velocity = self._gps[3] if self._gps else None
            speed = math.hypot(*velocity) if velocity is not None else 0.0
            return enc.vfr_hud(speed, heading, 100.0 * self._throttle)
        if message_id == m.MAVLINK_MSG_ID_ATTITUDE and self._compass:
            return enc.attitude(t, self._compass[1])
        if message_id in (m.MAVLINK_MSG_ID_RAW_IMU, m.MAVLINK_MSG_ID_SCALED_IMU) and self._imu:
            _, accel, gyro = self._imu
            return (enc.raw_imu if message_id == m.MAVLINK_MSG_ID_RAW_IMU else enc.scaled_imu)(t, accel, gyro)
        if message_id == m.MAVLINK_MSG_ID_WHEEL_DISTANCE and self._wheels and self._encoders():
            return enc.wheel_distance(t, self._wheels[1], self._encoders())
        if message_id == m.MAVLINK_MSG_ID_DISTANCE_SENSOR and self._ranges:
            _, distances, max_range = self._ranges
            return b"".join(enc.distance_sensor(t, k, float(d), max_range) for k, d in enumerate(distances))
        return b""

    def _encoders(self) -> int:
        """WHEEL_DISTANCE's count: the wheel encoders configured (WENC_TYPE, WENC2_TYPE; Rover/GCS_MAVLink_Rover.cpp
        send_wheel_encoder_distance sends nothing without one)."""
        if self.params.get_int("WENC2_TYPE"):
            return 2
        return 1 if self.params.get_int("WENC_TYPE") else 0

    def _one_message(self, message_id: int) -> bytes:
        return self._message(message_id) if message_id in PRODUCED else b""

    def _heartbeat(self) -> bytes:
        """Rover's HEARTBEAT (Rover/GCS_MAVLink_Rover.cpp base_mode, vehicle_system_status, GCS_Rover frame_type)."""
        flags = 0
        if self.mode in safety.PILOT_MODES:
            flags |= m.MAV_MODE_FLAG_MANUAL_INPUT_ENABLED
        if self.mode in safety.AUTOPILOT_MODES:
            flags |= m.MAV_MODE_FLAG_GUIDED_ENABLED
        state = m.MAV_STATE_ACTIVE
        if self.failsafe.triggered:
            state = m.MAV_STATE_CRITICAL
        elif self.mode == safety.HOLD:
            state = m.MAV_STATE_STANDBY
        boat = self.params.get_int("FRAME_CLASS") == 2
        mav_type = m.MAV_TYPE_SURFACE_BOAT if boat else m.MAV_TYPE_GROUND_ROVER
        return self.telemetry.heartbeat(mav_type, self.armed, self.mode, base_flags=flags, state=state)

    _READING_OF: ClassVar[dict[int, str]] = {
        m.MAVLINK_MSG_ID_GPS_RAW_INT: "_gps", m.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: "_gps",
        m.MAVLINK_MSG_ID_VFR_HUD: "_gps", m.MAVLINK_MSG_ID_ATTITUDE: "_compass", m.MAVLINK_MSG_ID_RAW_IMU: "_imu",
        m.MAVLINK_MSG_ID_SCALED_IMU: "_imu", m.MAVLINK_MSG_ID_WHEEL_DISTANCE: "_wheels",
        m.MAVLINK_MSG_ID_DISTANCE_SENSOR: "_ranges",
    }  # fmt: skip

    def stream(self, t_s: float) -> bytes:
        """Everything due at t_s for every listener: announcements, then each scheduled message whose interval has
        come and whose reading is newer than its last copy ("ardupilot" streams)."""
        self._tick(t_s)
        out = bytearray(self.outbox)
        self.outbox.clear()
        if self.streams != "ardupilot":
            return bytes(out)
        for message_id in self.schedule.due_among(PRODUCED_IN_ORDER, t_s):
            reading_name = self._READING_OF.get(message_id)
            reading = None if reading_name is None else getattr(self, reading_name)
            if reading_name is not None and not self._fresh(message_id, reading):
                continue
            try:
                data = self._message(message_id)
            except Exception:  # a message that cannot be built is skipped and counted, never raised into a fleet
                self.counters.errors += 1
                data = b""
            if data:
                out += data
                self.schedule.sent(message_id, t_s)
                if reading is not None:
                    self._sent_reading[message_id] = reading[0]
        if self._fresh("light", self._light):
            self._sent_reading["light"] = self._light[0]
            out += self.telemetry.light(t_s, *self._light[1:])  # as a script sends it: every reading
        return bytes(out)

    def housekeeping(self, t_s: float, voltage_v: float = 12.6, remaining_pct: float = 100.0) -> bytes:
        """ "sensor-rate" streams: HEARTBEAT and SYS_STATUS once a second and the announcements; "ardupilot": the
        same as `stream`."""
        if self.streams == "ardupilot":
            return self.stream(t_s)
        out = bytearray(self.stream(t_s))
        if t_s >= self._next_housekeeping_s:
            self._next_housekeeping_s = t_s + HOUSEKEEPING_PERIOD_S
            out += self._heartbeat() + self.telemetry.sys_status(voltage_v, remaining_pct)
        return bytes(out)


# The sensor readings' way into the vehicles (re-exported: callers import them from here).
from sitl.vehicle_telemetry import encode_readings, encode_senses  # noqa: E402

__all__ = ["BUOY", "EBOT", "MOTORBOAT", "SimulatedVehicle", "VehicleCounters", "encode_readings", "encode_senses"]
