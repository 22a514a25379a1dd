"""Arming checks, modes and failsafes of the simulated autopilot, as ArduPilot Rover applies them.

Modes (Rover/mode.h `Mode::Number`; Rover/system.cpp `set_mode`): the simulator honours MANUAL, ACRO,
STEERING (pilot input drives the motors, treated alike: no rate or speed controller is simulated), HOLD (motors
stopped), LOITER and GUIDED (accepted and reported; no navigation is simulated, so the motors stop as in HOLD).
Entering a mode that needs a position (LOITER, GUIDED) or a velocity (STEERING; ACRO unless skid-steer/omni,
Rover/mode_acro.cpp) fails while armed without a GPS fix: "Flight mode change failed", MAV_RESULT_FAILED
(Rover/mode.cpp `Mode::enter`; disarmed, any mode is allowed). Other existing Rover modes (AUTO, RTL, SMART_RTL,
FOLLOW, SIMPLE, DOCK, CIRCLE) are not simulated and fail the same way; unknown numbers: "No such mode N"
(libraries/AP_Vehicle/AP_Vehicle.cpp `notify_no_such_mode`).

Arming (libraries/AP_Arming/AP_Arming.cpp, Rover/AP_Arming_Rover.cpp): with ARMING_CHECK != 0 the checks below
run, each failure a STATUSTEXT "Arm: <reason>" (severity CRITICAL; "PreArm: <reason>" when run by
MAV_CMD_RUN_PREARM_CHECKS or the 30 s reminder while disarmed) and MAV_RESULT_FAILED:
- GPS (ARMING_CHECK bit 0 or 3), only when ARMING_NEED_LOC = 1 or the mode needs a position or a velocity
  (AP_Arming_Rover::gps_checks): "GPS 1: Bad fix" without a 3D fix, "AHRS: waiting for home" before home is set.
- RC (bit 0 or 6): "Radio failsafe on" (AP_Arming::manual_transmitter_checks); "Steer radio min too high" /
  "Throttle radio max too low" when RCx_MIN > 1300 / RCx_MAX < 1700 on those channels
  (AP_Arming_Rover::rc_calibration_checks); "RCn_MIN is greater than RCn_TRIM", "RCn_MAX is less than RCn_TRIM".
- Mode: RTL and SMART_RTL are "Mode not armable" (Rover/mode.h allows_arming).
Param2 = 2989 or 21196 forces arming past them (GCS.h magic_force_arm_value); already armed: ACCEPTED.
Armed / disarmed: "Throttle armed" / "Throttle disarmed" (INFO).

Failsafes (Rover/failsafe.cpp `failsafe_trigger`, Rover/radio.cpp `radio_failsafe_check`, Rover/Rover.cpp
`gcs_failsafe_check`): the radio failsafe (FS_THR_ENABLE != 0) is on while the throttle input is below
FS_THR_VALUE or no new RC input (receiver or override) came for 0.5 s; the GCS failsafe (FS_GCS_ENABLE != 0)
when nothing was heard from MAV_GCS_SYSID (HEARTBEAT, RC_CHANNELS_OVERRIDE, MANUAL_CONTROL) for FS_GCS_TIMEOUT s,
once it has been heard. While the radio failsafe is on, pilot input is zero. After FS_TIMEOUT s of a failsafe,
unless the mode is HOLD (or RTL) and FS_OPTIONS bit 0 is clear: "<Radio|GCS> Failsafe" (WARNING), RC overrides
cleared, FS_ACTION applied: 0 nothing, 1 RTL, 2 Hold, 3 SmartRTL or RTL, 4 SmartRTL or Hold, 5 Terminate
(disarm), 6 Loiter or Hold. RTL and SmartRTL are not simulated, so 1, 3 and 4 end in HOLD, as ArduPilot falls
through to Hold when it cannot enter them; 6 enters LOITER when the position is known. "<..> Failsafe Cleared"
(INFO) when the last failsafe condition ends. The HEARTBEAT reports MAV_STATE_CRITICAL while triggered.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

from pymavlink.dialects.v20 import ardupilotmega as mavlink

MANUAL, ACRO, STEERING, HOLD, LOITER, FOLLOW, SIMPLE, DOCK, CIRCLE, AUTO, RTL, SMART_RTL, GUIDED, INITIALISING = (
    0, 1, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 15, 16)  # fmt: skip
ROVER_MODE_NUMBERS = {MANUAL, ACRO, STEERING, HOLD, LOITER, FOLLOW, SIMPLE, DOCK, CIRCLE, AUTO, RTL, SMART_RTL,
                      GUIDED, INITIALISING}  # fmt: skip
SIMULATED_MODES = {MANUAL, ACRO, STEERING, HOLD, LOITER, GUIDED}
PILOT_MODES = {MANUAL, ACRO, STEERING}  # has_manual_input: the motors follow the RC input
AUTOPILOT_MODES = {LOITER, FOLLOW, DOCK, CIRCLE, AUTO, RTL, SMART_RTL, GUIDED}  # is_autopilot_mode
NEEDS_POSITION = {LOITER, FOLLOW, DOCK, CIRCLE, AUTO, RTL, SMART_RTL, GUIDED, SIMPLE}
NOT_ARMABLE = {RTL, SMART_RTL, INITIALISING}
FORCE_ARM = (2989.0, 21196.0)  # libraries/GCS_MAVLink/GCS.h magic_force_arm_value, magic_force_arm_disarm_value
CHECK_ALL, CHECK_GPS, CHECK_RC = 1, 1 << 3, 1 << 6
RC_CALIB_MIN_LIMIT_PWM, RC_CALIB_MAX_LIMIT_PWM = 1300, 1700  # libraries/RC_Channel/RC_Channel.h
RADIO_TIMEOUT_S = 0.5  # Rover/radio.cpp: no valid RC input for 500 ms
GPS_TIMEOUT_S = 4.0  # libraries/AP_GPS/AP_GPS.cpp GPS_TIMEOUT_MS: no fix after this long without one
PREARM_DISPLAY_PERIOD_S = 30.0  # libraries/AP_Arming/AP_Arming.cpp PREARM_DISPLAY_PERIOD
FS_RADIO, FS_GCS = 1, 4  # Rover/defines.h FAILSAFE_EVENT_THROTTLE, FAILSAFE_EVENT_GCS


class FailsafeParams(NamedTuple):
    """The parameters the failsafe checks read at every tick (FS_THR_ENABLE, RCMAP_THROTTLE, FS_THR_VALUE us,
    FS_GCS_ENABLE, FS_GCS_TIMEOUT s, FS_OPTIONS, FS_TIMEOUT s), cached by the vehicle until one changes."""

    thr_enable: int
    rcmap_throttle: int
    thr_value: int
    gcs_enable: int
    gcs_timeout_s: float
    options: int
    timeout_s: float


def needs_velocity(mode: int, skid_steer: bool) -> bool:
    """Rover's requires_velocity: STEERING always, ACRO unless skid-steer or omni (Rover/mode_acro.cpp)."""
    return mode == STEERING or (mode == ACRO and not skid_steer) or mode in NEEDS_POSITION


def check_enabled(checks: int, bit: int) -> bool:
    """AP_Arming::check_enabled: bit 0 (ALL) enables every check."""
    return bool(checks & CHECK_ALL) or bool(checks & bit)


# SYS_STATUS onboard_control_sensors of a Rover SITL (rover-omni3mecanum, disarmed, 2026-11-27: present 0x1331dc2f,
# enabled 0x1221802f once its EKF runs and 0x1321802f armed, health 0x1331812f with a fix and the pre-arm checks
# passing; libraries/GCS_MAVLink/GCS.cpp update_sensor_status_flags). Enabled and health below leave out the bits
# the vehicle's state sets (vehicle_streams._sensor_bits): GPS and AHRS health, AHRS enabled (with a fix), the
# RC receiver's health (out of radio failsafe), the pre-arm check's health, logging enabled (armed). ArduPilot
# reports LASER_POSITION healthy though absent; so does this.
_S = mavlink
_SENSORS = (_S.MAV_SYS_STATUS_SENSOR_3D_GYRO | _S.MAV_SYS_STATUS_SENSOR_3D_ACCEL | _S.MAV_SYS_STATUS_SENSOR_3D_MAG
            | _S.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE)  # fmt: skip
SENSORS_PRESENT = (
    _SENSORS | _S.MAV_SYS_STATUS_SENSOR_GPS | _S.MAV_SYS_STATUS_SENSOR_ANGULAR_RATE_CONTROL
    | _S.MAV_SYS_STATUS_SENSOR_ATTITUDE_STABILIZATION | _S.MAV_SYS_STATUS_SENSOR_YAW_POSITION
    | _S.MAV_SYS_STATUS_SENSOR_XY_POSITION_CONTROL | _S.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS
    | _S.MAV_SYS_STATUS_SENSOR_RC_RECEIVER | _S.MAV_SYS_STATUS_GEOFENCE | _S.MAV_SYS_STATUS_AHRS
    | _S.MAV_SYS_STATUS_LOGGING | _S.MAV_SYS_STATUS_SENSOR_BATTERY | _S.MAV_SYS_STATUS_PREARM_CHECK
)  # fmt: skip
SENSORS_ENABLED = (
    _SENSORS | _S.MAV_SYS_STATUS_SENSOR_GPS | _S.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS
    | _S.MAV_SYS_STATUS_SENSOR_RC_RECEIVER | _S.MAV_SYS_STATUS_SENSOR_BATTERY | _S.MAV_SYS_STATUS_PREARM_CHECK
)  # fmt: skip
SENSORS_HEALTHY = (
    _SENSORS | _S.MAV_SYS_STATUS_SENSOR_LASER_POSITION | _S.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS
    | _S.MAV_SYS_STATUS_GEOFENCE | _S.MAV_SYS_STATUS_LOGGING | _S.MAV_SYS_STATUS_SENSOR_BATTERY
)  # fmt: skip


def arming_failures(v) -> list[str]:
    """Reasons (without the "Arm: " / "PreArm: " prefix) why vehicle `v` may not arm now; empty when it may."""
    p = v.params
    checks = p.get_int("ARMING_CHECK")
    if checks == 0:
        return []
    reasons: list[str] = []
    skid = v.skid_steer()
    if check_enabled(checks, CHECK_GPS) and (p.get_int("ARMING_NEED_LOC") == 1 or needs_velocity(v.mode, skid)):
        if not v.has_fix():
            reasons.append("GPS 1: Bad fix")
        elif v.home is None:
            reasons.append("AHRS: waiting for home")
    if check_enabled(checks, CHECK_RC):
        if v.radio_failsafe_on():
            reasons.append("Radio failsafe on")
        else:
            for name, ch in (("Steer", p.get_int("RCMAP_ROLL")), ("Throttle", p.get_int("RCMAP_THROTTLE"))):
                if not 1 <= ch <= 8:
                    continue
                if p.get_int(f"RC{ch}_MIN") > RC_CALIB_MIN_LIMIT_PWM:
                    reasons.append(f"{name} radio min too high")
                    break
                if p.get_int(f"RC{ch}_MAX") < RC_CALIB_MAX_LIMIT_PWM:
                    reasons.append(f"{name} radio max too low")
                    break
            else:
                for ch in range(1, 9):
                    trim = p.get_int(f"RC{ch}_TRIM")
                    if p.get_int(f"RC{ch}_MIN") > trim:
                        reasons.append(f"RC{ch}_MIN is greater than RC{ch}_TRIM")
                    if p.get_int(f"RC{ch}_MAX") < trim:
                        reasons.append(f"RC{ch}_MAX is less than RC{ch}_TRIM")
    if v.mode in NOT_ARMABLE:
        reasons.append("Mode not armable")
    return reasons


@dataclass
class FailsafeState:
    """Rover's failsafe bits and what has been triggered (Rover.h `failsafe`)."""

    bits: int = 0
    triggered: int = 0
    start_s: float = -math.inf

    def update(self, kind: int, name: str, on: bool, t_s: float, timeout_s: float, may_trigger: bool) -> str | None:
        """Rover::failsafe_trigger for one event; returns the STATUSTEXT to send when something changed, prefixed
        "!" when the failsafe action must be taken now."""
        old = self.bits
        self.bits = (self.bits | kind) if on else (self.bits & ~kind)
        if old == 0 and self.bits != 0:
            self.start_s = t_s
        text = None
        if self.triggered != 0 and self.bits == 0:
            text = f"{name} Failsafe Cleared"
        self.triggered &= self.bits
        if self.triggered == 0 and self.bits != 0 and t_s - self.start_s > timeout_s and may_trigger:
            self.triggered = self.bits
            return f"!{name} Failsafe"
        return text


def failsafe_mode(action: int, position_ok: bool) -> int | None:
    """The mode FS_ACTION leads to in the simulator (None: no change; -1: disarm)."""
    if action == 0:
        return None
    if action == 5:
        return -1
    if action == 6 and position_ok:
        return LOITER
    return HOLD


def mavlink_severity(name: str) -> int:
    return getattr(mavlink, f"MAV_SEVERITY_{name}")
