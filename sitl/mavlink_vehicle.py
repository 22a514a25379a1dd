"""A simulated vehicle's autopilot as a MAVLink endpoint: telemetry out, commands in, failsafe.

It behaves like a stock ArduPilot Rover as far as the autonomy can tell: it
sends HEARTBEAT and SYS_STATUS at 1 Hz and GPS_RAW_INT, ATTITUDE, SCALED_IMU
and WHEEL_DISTANCE at the rates of the simulated sensors; it applies
RC_CHANNELS_OVERRIDE (and MANUAL_CONTROL for wheels) from its GCS system id
only while armed and in a driving mode; it answers arm/disarm and set-mode
COMMAND_LONGs with a COMMAND_ACK. When no command has arrived for `failsafe_s`
it stops its thrusters or wheels (counted), rather than keep the last command.
Malformed bytes are counted by its reader and skipped.

Transport-free: `receive(bytes)` and the telemetry methods return bytes; the
lockstep simulator passes them in memory, the process fleet over UDP.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_bridge.commands import (
    GCS_SYSTEM_ID,
    ROVER_MODES,
    thrust_from_rc,
    wheels_from_manual_control,
    wheels_from_rc,
)
from firmware_bridge.decoder import TelemetryDecoder
from firmware_bridge.readings import SensorReadings
from firmware_bridge.telemetry import TelemetryEncoder

BUOY, EBOT = "buoy", "ebot"
MAV_TYPES = {BUOY: mavlink.MAV_TYPE_SURFACE_BOAT, EBOT: mavlink.MAV_TYPE_GROUND_ROVER}
DRIVING_MODES = {ROVER_MODES["MANUAL"], ROVER_MODES["ACRO"], ROVER_MODES["STEERING"]}
SUPPORTED_MODES = DRIVING_MODES | {ROVER_MODES["HOLD"]}
HOUSEKEEPING_PERIOD_S = 1.0  # HEARTBEAT and SYS_STATUS


@dataclass
class VehicleCounters:
    """What a simulated vehicle has seen: commands applied, refused (disarmed, not driving, wrong sender),
    failsafe stops, commands acknowledged, messages for other systems."""

    commands: int = 0
    refused: int = 0
    failsafes: int = 0
    acks: int = 0
    other_target: int = 0


class SimulatedVehicle:
    """The autopilot of one simulated buoy or eBot.

    kind: "buoy" (command = body-frame thrust x forward, y left, N) or "ebot" (wheel speeds left, right, m/s).
    max_actuator: the full-scale actuator value, N of thrust or m/s of wheel speed (RC 1900 us).
    """

    def __init__(
        self,
        system_id: int,
        kind: str,
        max_actuator: float,
        *,
        failsafe_s: float = 1.0,
        armed: bool = False,
        mode: int = ROVER_MODES["MANUAL"],
        gcs_system_id: int = GCS_SYSTEM_ID,
    ) -> None:
        if kind not in MAV_TYPES:
            raise ValueError(f"unknown vehicle kind {kind!r}; choose buoy or ebot")
        if not failsafe_s > 0:
            raise ValueError(f"failsafe_s must be positive, got {failsafe_s!r}")
        self.system_id, self.kind, self.max_actuator = system_id, kind, float(max_actuator)
        self.failsafe_s, self.armed, self.mode, self.gcs_system_id = float(failsafe_s), armed, mode, gcs_system_id
        self.telemetry = TelemetryEncoder(system_id)
        self.reader = TelemetryDecoder(clock=lambda: 0.0, agent=0)
        self.counters = VehicleCounters()
        self._command = np.zeros(2)
        self._last_command_s = -math.inf
        self._next_housekeeping_s = -math.inf
        self.in_failsafe = True  # nothing commanded yet

    # -- commands in ---------------------------------------------------------------------------------

    def receive(self, data: bytes, t_s: float) -> bytes:
        """Take bytes from the autonomy or a GCS; returns the replies (COMMAND_ACKs) to send back."""
        replies = bytearray()
        for msg in self.reader.feed_messages(data):
            name = msg.get_type()
            if name == "RC_CHANNELS_OVERRIDE":
                self._drive(
                    msg,
                    t_s,
                    lambda m: (
                        thrust_from_rc(m, self.max_actuator)
                        if self.kind == BUOY
                        else wheels_from_rc(m, self.max_actuator)
                    ),
                )
            elif name == "MANUAL_CONTROL" and self.kind == EBOT:
                self._drive(msg, t_s, lambda m: wheels_from_manual_control(m, self.max_actuator))
            elif name == "COMMAND_LONG":
                replies += self._command_long(msg)
        return bytes(replies)

    def _for_me(self, msg) -> bool:
        if msg.target_system != self.system_id:
            self.counters.other_target += 1
            return False
        return True

    def _drive(self, msg, t_s: float, actuator) -> None:
        if not self._for_me(msg):
            return
        if msg.get_srcSystem() != self.gcs_system_id or not self.armed or self.mode not in DRIVING_MODES:
            self.counters.refused += 1
            return
        self._command = np.array(actuator(msg), dtype=float)
        self._last_command_s = t_s
        self.counters.commands += 1

    def _command_long(self, msg) -> bytes:
        if not self._for_me(msg):
            return b""
        if msg.command == mavlink.MAV_CMD_COMPONENT_ARM_DISARM:
            self.armed = msg.param1 > 0.5
            result = mavlink.MAV_RESULT_ACCEPTED
        elif msg.command == mavlink.MAV_CMD_DO_SET_MODE:
            mode = int(msg.param2)
            result = mavlink.MAV_RESULT_ACCEPTED if mode in SUPPORTED_MODES else mavlink.MAV_RESULT_UNSUPPORTED
            if mode in SUPPORTED_MODES:
                self.mode = mode
        else:
            result = mavlink.MAV_RESULT_UNSUPPORTED
        self.counters.acks += 1
        return self.telemetry.command_ack(msg.command, result, msg.get_srcSystem(), msg.get_srcComponent())

    def actuator(self, t_s: float) -> np.ndarray:
        """The thrust (N, body frame) or wheel speeds (m/s) applied now: zero when disarmed, holding, or when no
        command came for `failsafe_s` (each lapse into failsafe counted once)."""
        stale = t_s - self._last_command_s > self.failsafe_s
        if stale and not self.in_failsafe and math.isfinite(self._last_command_s):
            self.counters.failsafes += 1
        self.in_failsafe = stale
        if stale or not self.armed or self.mode not in DRIVING_MODES:
            return np.zeros(2)
        return self._command.copy()

    # -- telemetry out -------------------------------------------------------------------------------

    def housekeeping(self, t_s: float, voltage_v: float = 12.6, remaining_pct: float = 100.0) -> bytes:
        """HEARTBEAT and SYS_STATUS when a second has passed since the last ones, else nothing."""
        if t_s < self._next_housekeeping_s:
            return b""
        self._next_housekeeping_s = t_s + HOUSEKEEPING_PERIOD_S
        heartbeat = self.telemetry.heartbeat(MAV_TYPES[self.kind], self.armed, self.mode)
        return heartbeat + self.telemetry.sys_status(voltage_v, remaining_pct)


def encode_readings(
    readings: SensorReadings,
    t_s: float,
    vehicles: Sequence[SimulatedVehicle],
    frames: list[bytearray],
    rows: Sequence[int] | None = None,
    *,
    metres_per_tick: float = 1.0,
    fused_position: bool = False,
) -> None:
    """Append to frames[row] the telemetry of each reading: SCALED_IMU, GPS_RAW_INT (and GLOBAL_POSITION_INT when
    `fused_position`, for ground stations), ATTITUDE, WHEEL_DISTANCE (ticks * metres_per_tick). A reading's agent
    k is vehicle rows[k] (rows None: k itself)."""

    def vehicle_rows(agents):
        return [(i, int(k) if rows is None else int(rows[k])) for i, k in enumerate(agents)]

    if readings.imu is not None:
        m = readings.imu
        for i, row in vehicle_rows(m.agents):
            frames[row] += vehicles[row].telemetry.scaled_imu(t_s, m.accel_body_mps2[i], m.gyro_z_radps[i])
    if readings.gps is not None:
        g = readings.gps
        for i, row in vehicle_rows(g.agents):
            velocity = None if g.velocity_mps is None else g.velocity_mps[i]
            telemetry = vehicles[row].telemetry
            frames[row] += telemetry.gps_raw_int(t_s, g.lat_deg[i], g.lon_deg[i], velocity)
            if fused_position:
                frames[row] += telemetry.global_position_int(t_s, g.lat_deg[i], g.lon_deg[i], velocity)
    if readings.compass is not None:
        c = readings.compass
        for i, row in vehicle_rows(c.agents):
            frames[row] += vehicles[row].telemetry.attitude(t_s, c.heading_rad[i])
    if readings.encoders is not None:
        e = readings.encoders
        for i, row in vehicle_rows(e.agents):
            frames[row] += vehicles[row].telemetry.wheel_distance(t_s, e.ticks[i] * metres_per_tick)


def encode_senses(
    t_s: float,
    vehicles: Sequence[SimulatedVehicle],
    frames: list[bytearray],
    rows: Sequence[int],
    ranges_m: np.ndarray,
    light: np.ndarray,
    max_range_m: float,
) -> None:
    """Append to frames[rows[k]] eBot k's range finders as DISTANCE_SENSOR (id = sonar index) and its two light
    readings as NAMED_VALUE_FLOAT: ranges_m (k, sonars) m, NaN = no echo; light (k, 2) W/m^2."""
    for k, row in enumerate(rows):
        telemetry = vehicles[row].telemetry
        for sonar, distance in enumerate(ranges_m[k]):
            frames[row] += telemetry.distance_sensor(t_s, sonar, float(distance), max_range_m)
        frames[row] += telemetry.light(t_s, float(light[k, 0]), float(light[k, 1]))
