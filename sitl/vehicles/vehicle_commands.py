"""Commands to a simulated vehicle (sitl.vehicles.mavlink_vehicle): COMMAND_LONG and COMMAND_INT answered with
COMMAND_ACK as Rover answers them: arming and its checks, modes, REQUEST_MESSAGE, set home
(GCS_Common.cpp handle_command_long and friends)."""

from __future__ import annotations

import math
from collections.abc import Sequence

from sitl.vehicles import autopilot_safety as safety
from sitl.vehicles.autopilot_streams import SCHEDULABLE
from sitl.vehicles.vehicle_defs import (
    SUPPORTED_MODES,
    _finite,
    m,
)


class VehicleCommands:
    """The command handlers, mixed into SimulatedVehicle (which holds the state they use)."""

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
