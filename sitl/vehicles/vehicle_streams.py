"""Telemetry of a simulated vehicle (sitl.vehicles.mavlink_vehicle): the latest sensor readings, each message built from
them, and the streams that send them at their rates, as Rover does (GCS_Common.cpp, Rover/GCS_MAVLink_Rover.cpp)."""

from __future__ import annotations

import math
from typing import ClassVar

from sitl.vehicles import autopilot_safety as safety
from sitl.vehicles.autopilot_streams import PRODUCED
from sitl.vehicles.vehicle_defs import (
    CAPABILITIES,
    FLIGHT_SW_VERSION,
    GIT_HASH,
    HOUSEKEEPING_PERIOD_S,
    PRODUCED_IN_ORDER,
    m,
)


class TelemetryStreams:
    """Telemetry out, mixed into SimulatedVehicle (which holds the state it uses)."""

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

    def stream(self, t_s: float, *, tick: bool = True) -> bytes:
        """Everything due at t_s for every listener: announcements, then each scheduled message whose interval has
        come and whose reading is newer than its last copy ("ardupilot" streams). tick=False: the autopilot's clock
        already ran to t_s (`housekeeping(t_s)` just now, nothing received since: running it again changes
        nothing, and each run costs about 3 % of the lockstep MAVLink time)."""
        if tick:
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
