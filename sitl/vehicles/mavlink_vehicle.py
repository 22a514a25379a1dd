"""A simulated vehicle's autopilot as a MAVLink endpoint that behaves as ArduPilot Rover does.

What it does, and the ArduPilot source file behind each behaviour (docs/simulated-autopilot.md has the whole
table):
- Telemetry only at its stream rates (sitl/vehicles/autopilot_streams.py): Rover's MAVn_* group defaults (1 Hz) until
  asked with SET_MESSAGE_INTERVAL or REQUEST_DATA_STREAM; REQUEST_MESSAGE sends one message now. Each message
  is made from the simulated sensors' latest reading of its kind; a stream faster than its sensor goes at the
  sensor's rate. `streams="sensor-rate"` keeps the old behaviour instead: every reading encoded as it comes,
  HEARTBEAT and SYS_STATUS at 1 Hz.
- Parameters (sitl/vehicles/autopilot_params.py), missions (sitl/vehicles/autopilot_mission.py), RC input, overrides
  and their
  expiry (sitl/vehicles/autopilot_rc.py), arming checks, modes and failsafes (sitl/vehicles/autopilot_safety.py).
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

import numpy as np

from firmware_bridge.commands import GCS_SYSTEM_ID, ROVER_MODES
from firmware_bridge.decoder import TelemetryDecoder
from firmware_bridge.telemetry import TelemetryEncoder
from sitl.vehicles import autopilot_safety as safety
from sitl.vehicles.autopilot_mission import MissionStore
from sitl.vehicles.autopilot_params import SERVO_OUTPUTS, STREAM_PORT_PREFIX, ParameterStore, rover_parameter_table
from sitl.vehicles.autopilot_rc import (
    OMNI_FACTORS,
    PilotOutput,
    RcInput,
    omni_motor_outputs,
    servo_pwm,
    skid_outputs,
    slew_limited,
)
from sitl.vehicles.autopilot_safety import FailsafeParams
from sitl.vehicles.autopilot_streams import StreamSchedule
from sitl.vehicles.vehicle_commands import VehicleCommands
from sitl.vehicles.vehicle_defs import (  # noqa: F401 - re-exported: callers import these from here
    BUOY,
    CAPABILITIES,
    DRIVING_MODES,
    EBOT,
    FIRMWARE_STRING,
    FLIGHT_SW_VERSION,
    GIT_HASH,
    HOME_MOVE_M,
    HOUSEKEEPING_PERIOD_S,
    KINDS,
    MISSION_MESSAGES,
    MOTORBOAT,
    OVERRIDE_FIELDS,
    PRODUCED_IN_ORDER,
    STREAM_MODES,
    SUPPORTED_MODES,
    VehicleCounters,
    _finite,
    m,
)
from sitl.vehicles.vehicle_rc_input import RcInputHandling
from sitl.vehicles.vehicle_streams import TelemetryStreams


class SimulatedVehicle(RcInputHandling, VehicleCommands, TelemetryStreams):
    """The autopilot of one simulated buoy or eBot (see the module docstring).

    kind: "buoy" (command = body-frame thrust x forward, y left, N), "ebot" (wheel speeds left, right, m/s) or
    "motorboat" (throttle and steering outputs, each in [-1, 1]; FRAME_TYPE 0 with SERVO1 ground steering, SERVO3
    throttle).
    max_actuator: the full-scale actuator value, N of thrust or m/s of wheel speed (full RC deflection).
    failsafe_s: RC_OVERRIDE_TIME when given (ArduPilot's default 3 s otherwise). armed: armed at boot, without
    checks. mode: INITIAL_MODE when given. streams: "ardupilot" or "sensor-rate" (module docstring).
    rc_receiver: False for a vehicle with no RC receiver: radio failsafe (and HOLD) until overrides arrive.
    params: parameter values to start with (name -> value), e.g. {"PILOT_STEER_TYPE": 3}.
    boot_s: when it booted on the times it is given, s: its messages carry the time since (0 before).
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
        boot_s: float = 0.0,
    ) -> None:
        if kind not in KINDS:
            raise ValueError(f"unknown vehicle kind {kind!r}; choose one of {', '.join(KINDS)}")
        if failsafe_s is not None and not failsafe_s > 0:
            raise ValueError(f"failsafe_s must be positive, got {failsafe_s!r}")
        if streams not in STREAM_MODES:
            raise ValueError(f"streams must be one of {STREAM_MODES}, got {streams!r}")
        self.system_id, self.kind, self.max_actuator, self.streams = system_id, kind, float(max_actuator), streams
        self.telemetry = TelemetryEncoder(system_id, boot_s=boot_s)
        self.reader = TelemetryDecoder(clock=lambda: 0.0, agent=0)
        self.counters = VehicleCounters()
        overrides = dict(params or {})
        if failsafe_s is not None:
            overrides.setdefault("RC_OVERRIDE_TIME", float(failsafe_s))
        if mode is not None:
            overrides.setdefault("INITIAL_MODE", int(mode))
        table = rover_parameter_table(kind, system_id, gcs_system_id)
        self.params = ParameterStore(table, self.telemetry.pack, self.telemetry.mav, overrides)
        self._rc_cache: tuple[list[int], dict[str, tuple | None], dict] | None = None  # see _rc_setup
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
        self._gps_accuracy: tuple[float | None, float | None] = (None, None)  # the receiver's reported h, speed
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
        self._frame_version = self._failsafe_version = -1  # parameter-derived caches, stale at first
        self._servo_cache: tuple[tuple, list[int]] | None = None  # see servo_outputs
        self._pilot_cache: tuple[tuple, tuple[float, float, float]] | None = None  # see _read_pilot
        self._prearm_cache: tuple[tuple, bool] | None = None  # see _sensor_bits

    # -- parameters that act at once -----------------------------------------------------------------------

    @property
    def gcs_system_id(self) -> int:
        return self.params.get_int("MAV_GCS_SYSID")

    @property
    def failsafe_s(self) -> float:
        """RC_OVERRIDE_TIME, s: how long an RC override counts."""
        return float(self.params["RC_OVERRIDE_TIME"])

    def omni(self) -> bool:
        return self._frame()[0]

    def skid_steer(self) -> bool:
        """AP_MotorsUGV::have_skid_steering: throttle left and right assigned, or an omni frame."""
        return self._frame()[1]

    def _frame(self) -> tuple[bool, bool, int, list[int]]:
        """(omni, skid steering, FRAME_TYPE, SERVO1..8_FUNCTION) from the parameters, read again only when a
        parameter changed (these are asked several times per vehicle and step)."""
        if self._frame_version != self.params.version:
            p = self.params
            frame_type = p.get_int("FRAME_TYPE")
            omni = frame_type != 0  # AP_MotorsUGV::is_omni (a known frame type has motors)
            functions = [p.get_int(f"SERVO{i}_FUNCTION") for i in range(1, SERVO_OUTPUTS + 1)]
            skid = {73, 74} <= set(functions) or omni
            self._frame_cache, self._frame_version = (omni, skid, frame_type, functions[:8]), p.version
        return self._frame_cache

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

    def receive_override(self, source_system: int, fields: Sequence[int], t_s: float) -> None:
        """What `receive` does with bytes that were one RC_CHANNELS_OVERRIDE, its frame already checked and its
        fields read in declaration order (target system, target component, channels 1-18): for a fleet that
        reads all its vehicles' overrides at once (`firmware_bridge.override_batch`). Never raises."""
        try:
            self._tick(t_s)
            if self._accepts(source_system) and self._targets_me(int(fields[0]), int(fields[1])):
                self._override(source_system, list(map(int, fields[2:20])), t_s)
        except Exception:  # one bad message must never stop the vehicle (#17)
            self.counters.errors += 1

    def _for_me(self, msg, system_field: str = "target_system", component_field: str | None = "target_component"):
        system = int(getattr(msg, system_field))
        component = 0 if component_field is None else int(getattr(msg, component_field))
        return self._targets_me(system, component)

    def _targets_me(self, system: int, component: int) -> bool:
        if system not in (0, self.system_id) or component not in (0, m.MAV_COMP_ID_AUTOPILOT1):
            self.counters.other_target += 1
            return False
        return True

    def _accepts(self, src: int) -> bool:
        """MAV_OPTIONS bit 0: MAVLink only from MAV_GCS_SYSID (GCS_Common.cpp accept_packet); refusals counted."""
        if self.params.get_int("MAV_OPTIONS") & 1 and src not in (self.gcs_system_id, self.system_id):
            self.counters.refused += 1
            return False
        return True

    def _handle(self, msg, t_s: float) -> bytes:
        name = msg.get_type()
        src = msg.get_srcSystem()
        if not self._accepts(src):
            return b""
        sender = (src, msg.get_srcComponent())
        if name == "HEARTBEAT":
            if src == self.gcs_system_id:
                self._gcs_seen_s = t_s
            return b""
        if name == "RC_CHANNELS_OVERRIDE":
            if self._for_me(msg):
                self._override(src, [int(getattr(msg, field, 0)) for field in OVERRIDE_FIELDS], t_s)
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

    # -- the autopilot's own clock: failsafes, home, reminders -------------------------------------------------

    def _tick(self, t_s: float) -> None:
        if t_s < self._t:
            return
        self._t = t_s
        live = self.rc.update(t_s, self.failsafe_s, self._trims())
        if self._driving_override and not live:
            self._driving_override = False
            if self.armed and self.mode in DRIVING_MODES and np.any(self._command):
                self.counters.failsafes += 1  # the override expired while driving: the vehicle stops
        self.in_failsafe = not live
        self._failsafes(t_s)
        if t_s >= self._next_home_check_s:
            self._next_home_check_s = t_s + 1.0
            self._update_home()
        if not self.armed and t_s >= self._next_prearm_s:
            self._next_prearm_s = t_s + safety.PREARM_DISPLAY_PERIOD_S
            self._report_failures("PreArm", safety.arming_failures(self))
        if self.mission.receiving:  # MissionStore.tick has nothing to do otherwise
            self.outbox += self.mission.tick(t_s)

    def _failsafe_params(self) -> FailsafeParams:
        """The failsafe parameters, read again only when a parameter changed (checked at every tick)."""
        if self._failsafe_version != self.params.version:
            p = self.params
            self._failsafe_cache = FailsafeParams(
                p.get_int("FS_THR_ENABLE"), p.get_int("RCMAP_THROTTLE"), p.get_int("FS_THR_VALUE"),
                p.get_int("FS_GCS_ENABLE"), p["FS_GCS_TIMEOUT"], p.get_int("FS_OPTIONS"), p["FS_TIMEOUT"],
            )  # fmt: skip
            self._failsafe_version = p.version
        return self._failsafe_cache

    def _failsafes(self, t_s: float) -> None:
        p = self.params
        f = self._failsafe_params()
        radio = False
        if f.thr_enable:
            ch = f.rcmap_throttle
            pwm = self.rc.radio_in[ch - 1] if 1 <= ch <= 8 else 0
            radio = pwm < f.thr_value or t_s - self.rc.last_valid_s > safety.RADIO_TIMEOUT_S
        gcs = False
        if f.gcs_enable and self._gcs_seen_s is not None:
            gcs = t_s - self._gcs_seen_s >= f.gcs_timeout_s
        state = self.failsafe
        if not (radio or gcs or state.bits or state.triggered):
            return  # FailsafeState.update would change nothing and say nothing (the usual case)
        may = self.mode not in (safety.HOLD, safety.RTL) or bool(f.options & 1)
        # As Rover calls failsafe_trigger: the radio check every loop when FS_THR_ENABLE, the GCS check when
        # FS_GCS_ENABLE and the GCS has been heard. Whichever call first finds FS_TIMEOUT passed names the
        # failsafe, so a lost GCS is announced "Radio Failsafe" when the radio check is on (Rover/failsafe.cpp).
        checks = [(safety.FS_RADIO, "Radio", radio)] if f.thr_enable else []
        if f.gcs_enable and self._gcs_seen_s is not None:
            checks.append((safety.FS_GCS, "GCS", gcs))
        for kind, name, on in checks:
            text = state.update(kind, name, on, t_s, f.timeout_s, may)
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
        STEERING while armed and out of radio failsafe, zero otherwise; throttle within MOT_THR_MAX and slew-limited
        (MOT_SLEWRATE)."""
        self._tick(t_s)
        dt = 0.0 if self._actuator_t is None else max(0.0, t_s - self._actuator_t)
        self._actuator_t = t_s
        steering = throttle = lateral = 0.0
        if self.armed and self.mode in DRIVING_MODES and not self.radio_failsafe_on():
            steering, throttle, lateral = self._read_pilot()
        ceiling = self.params["MOT_THR_MAX"] / 100.0  # AP_MotorsUGV::set_throttle clips the demand to +-MOT_THR_MAX
        throttle = min(ceiling, max(-ceiling, throttle))
        limited = slew_limited(throttle, self._throttle, self.params["MOT_SLEWRATE"], dt)
        if (throttle < 0) != (limited < 0) and self.params.get_int("PILOT_STEER_TYPE") in (0, 2):
            steering = -steering  # Rover/mode.cpp: throttle still on the other side of zero
        self._throttle = limited
        self._out = PilotOutput(steering, limited, lateral)
        return self._demand(self._out)

    def servo_outputs(self) -> list[int]:
        """SERVO1..8 PWM as the outputs stand (trim while disarmed; AP_MotorsUGV setup_safety_output). Kept while
        the outputs, the arming and the parameters stay as they were (SERVO_OUTPUT_RAW goes out every second)."""
        out = self._out if self.armed else PilotOutput()
        key = (self.params.version, out.steering, out.throttle, out.lateral)
        if self._servo_cache is None or self._servo_cache[0] != key:
            self._servo_cache = (key, self._servo_pwms(out))
        return list(self._servo_cache[1])

    def _servo_pwms(self, out: PilotOutput) -> list[int]:
        """Each output's PWM by its SERVOn_FUNCTION; only the outputs the functions ask for are worked out."""
        _, _, frame_type, functions = self._frame()
        values: dict[int, float] = {}
        if 26 in functions:
            values[26] = self._steering_output(out)
        values[70] = out.throttle
        if 73 in functions or 74 in functions:
            values[73], values[74] = skid_outputs(out)
        if frame_type in OMNI_FACTORS:
            for k, v in enumerate(omni_motor_outputs(frame_type, out)):
                values[33 + k] = v
        return [servo_pwm(values[f]) if f in values else 0 for f in functions]


# The sensor readings' way into the vehicles (re-exported: callers import them from here).
from sitl.vehicles.vehicle_telemetry import encode_readings, encode_senses, prepend_streams  # noqa: E402

__all__ = [
    "BUOY",
    "EBOT",
    "MOTORBOAT",
    "SimulatedVehicle",
    "VehicleCounters",
    "encode_readings",
    "encode_senses",
    "prepend_streams",
]
