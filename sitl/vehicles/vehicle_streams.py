"""Telemetry of a simulated vehicle (sitl.vehicles.mavlink_vehicle): the latest sensor readings, each message built from
them, and the streams that send them at their rates, as Rover does (GCS_Common.cpp, Rover/GCS_MAVLink_Rover.cpp)."""

from __future__ import annotations

import math

from sitl.vehicles import autopilot_safety as safety
from sitl.vehicles.autopilot_streams import PRODUCED, next_due
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
        """Take the latest reading of one sensor: "gps" (lat, lon deg, velocity (east, north) or None; then
        optionally the receiver's reported horizontal and speed accuracies, m and m/s, None for none), "compass"
        (heading rad; on a tilted hull also roll, pitch rad and body rates (p, q, r) rad/s FRD), "imu" (accel body
        (x, y) m/s^2, yaw rate rad/s; on a tilted hull also z m/s^2 and the (x, y) rates), "wheels" (distances
        (l, r) m), "ranges" (distances m, max range m), "light" (left, right)."""
        if kind == "gps":
            self._gps_accuracy = tuple(values[3:5]) if len(values) > 3 else (None, None)
            values = values[:3]
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
        build = _BUILDERS.get(message_id)
        return b"" if build is None else build(self)

    # One builder per message (looked up by id in _BUILDERS: a chain of comparisons cost up to 6 us per message).

    def _build_heartbeat(self) -> bytes:
        return self._heartbeat()

    def _build_sys_status(self) -> bytes:
        return self.telemetry.sys_status(12.6, 100.0, self._sensor_bits())

    def _sensor_bits(self) -> tuple[int, int, int]:
        """SYS_STATUS's (present, enabled, health) as a Rover SITL reports them (safety.SENSORS_*): GPS and AHRS
        healthy with a fix, the RC receiver out of radio failsafe, the pre-arm check while nothing stops arming,
        logging enabled while armed."""
        fix, radio_failsafe = self.has_fix(), self.radio_failsafe_on()
        enabled = safety.SENSORS_ENABLED | (m.MAV_SYS_STATUS_AHRS if fix else 0)
        enabled |= m.MAV_SYS_STATUS_LOGGING if self.armed else 0
        health = safety.SENSORS_HEALTHY
        health |= (m.MAV_SYS_STATUS_SENSOR_GPS | m.MAV_SYS_STATUS_AHRS) if fix else 0
        health |= 0 if radio_failsafe else m.MAV_SYS_STATUS_SENSOR_RC_RECEIVER
        # arming_failures reads only these (about 18 us; each vehicle sends SYS_STATUS every second)
        key = (self.params.version, self.mode, fix, self.home is None, radio_failsafe)
        if self._prearm_cache is None or self._prearm_cache[0] != key:
            self._prearm_cache = (key, not safety.arming_failures(self))
        health |= m.MAV_SYS_STATUS_PREARM_CHECK if self._prearm_cache[1] else 0
        return safety.SENSORS_PRESENT, enabled, health

    def _build_battery_status(self) -> bytes:
        return self.telemetry.battery_status(12.6, 100.0)

    def _build_autopilot_version(self) -> bytes:
        return self.telemetry.autopilot_version(CAPABILITIES, FLIGHT_SW_VERSION, GIT_HASH, 0x5B0B0000 + self.system_id)

    def _build_home_position(self) -> bytes:
        return b"" if self.home is None else self.telemetry.home_position(self._t, *self.home)

    def _build_rc_channels(self) -> bytes:
        return self.telemetry.rc_channels(self._t, self.rc.radio_in, 16 if self.rc.receiver else 0)

    def _build_servo_output_raw(self) -> bytes:
        return self.telemetry.servo_output_raw(self._t, self.servo_outputs())

    def _build_system_time(self) -> bytes:
        return self.telemetry.system_time(self._t)

    def _build_gps_raw_int(self) -> bytes:
        """As ArduPilot sends it (libraries/AP_GPS/AP_GPS.cpp send_mavlink_gps_raw): at its interval whatever the
        GPS's rate, stamped with the time of the fix it holds, so a fix goes out again until a newer one comes;
        when no fix has come for GPS_TIMEOUT_MS (4 s) the GPS state is cleared (AP_GPS::update_instance): NO_GPS,
        no position, unknown HDOP and accuracies, still the last fix's time. Nothing before the first fix. The
        receiver's accuracies (h_acc, vel_acc) as it reported them, as ArduPilot passes them on."""
        if not self._gps:
            return b""
        t_fix, lat, lon, velocity = self._gps
        if self.has_fix():
            h_acc, vel_acc = self._gps_accuracy
            return self.telemetry.gps_raw_int(t_fix, lat, lon, velocity, h_acc_m=h_acc, vel_acc_mps=vel_acc)
        cleared = m.GPS_FIX_TYPE_NO_GPS  # and speed and course 0, as the cleared state has them
        return self.telemetry.gps_raw_int(t_fix, 0.0, 0.0, (0.0, 0.0), fix_type=cleared, satellites=0, hdop=None)

    def _build_global_position_int(self) -> bytes:
        if not self._gps:
            return b""
        _, lat, lon, velocity = self._gps
        heading = None if self._compass is None else self._compass[1]
        return self.telemetry.global_position_int(self._t, lat, lon, velocity, heading)

    def _build_vfr_hud(self) -> bytes:
        if not (self._gps or self._compass):
            return b""
        velocity = self._gps[3] if self._gps else None
        speed = math.hypot(*velocity) if velocity is not None else 0.0
        heading = None if self._compass is None else self._compass[1]
        return self.telemetry.vfr_hud(speed, heading, 100.0 * self._throttle)

    def _build_attitude(self) -> bytes:
        """ATTITUDE from the latest compass reading: level, or the tilted hull's roll, pitch and rates."""
        if not self._compass:
            return b""
        if len(self._compass) == 2:  # a level hull
            return self.telemetry.attitude(self._t, self._compass[1])
        _, heading, roll, pitch, (p, q, r) = self._compass
        return self.telemetry.attitude(
            self._t, heading, -r, roll_rad=roll, pitch_rad=pitch, roll_pitch_rates_radps=(p, q)
        )

    def _imu_fields(self) -> tuple[tuple, dict]:
        """The latest IMU reading as the telemetry encoder takes it: (accel, gyro) and, on a tilted hull, the z
        specific force and the x, y rates."""
        if len(self._imu) == 3:
            return self._imu[1:], {}
        _, accel, gyro, z, gyro_xy = self._imu
        return (accel, gyro), {"accel_z_mps2": z, "gyro_xy_radps": gyro_xy}

    def _build_raw_imu(self) -> bytes:
        if not self._imu:
            return b""
        if len(self._imu) == 3:  # a level hull: no extra fields
            return self.telemetry.raw_imu(self._t, self._imu[1], self._imu[2])
        args, extra = self._imu_fields()
        return self.telemetry.raw_imu(self._t, *args, **extra)

    def _build_scaled_imu(self) -> bytes:
        if not self._imu:
            return b""
        if len(self._imu) == 3:  # a level hull: no extra fields
            return self.telemetry.scaled_imu(self._t, self._imu[1], self._imu[2])
        args, extra = self._imu_fields()
        return self.telemetry.scaled_imu(self._t, *args, **extra)

    def _build_wheel_distance(self) -> bytes:
        if not self._wheels or not self._encoders():
            return b""
        return self.telemetry.wheel_distance(self._t, self._wheels[1], self._encoders())

    def _build_distance_sensor(self) -> bytes:
        if not self._ranges:
            return b""
        enc, t = self.telemetry, self._t
        _, distances, max_range = self._ranges
        return b"".join(enc.distance_sensor(t, k, float(d), max_range) for k, d in enumerate(distances))

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

    def stream(self, t_s: float) -> bytes:
        """Everything due at t_s for every listener: announcements, then each scheduled message whose interval has
        come and whose reading is newer than its last copy ("ardupilot" streams; GPS_RAW_INT whenever due)."""
        self._tick(t_s)
        out = bytearray(self.outbox)
        self.outbox.clear()
        if self.streams != "ardupilot":
            return bytes(out)
        sent_reading, made_of, due_s = self._sent_reading, _MADE_OF, self.schedule.next_due_s
        limit = t_s + 1e-9
        # `StreamSchedule.due` and `sent` inlined (about 8.5 messages per vehicle and lockstep step)
        for message_id, period in self.schedule.scheduled(PRODUCED_IN_ORDER):
            due = due_s.get(message_id, -math.inf)
            if limit < due:
                continue
            reading_name, build = made_of[message_id]
            reading = None
            if reading_name is not None:
                reading = getattr(self, reading_name)
                if reading is None or not reading[0] > sent_reading.get(message_id, -math.inf):
                    continue  # nothing newer than the last copy (`_fresh`)
            try:
                data = build(self)
            except Exception:  # a message that cannot be built is skipped and counted, never raised into a fleet
                self.counters.errors += 1
                data = b""
            if data:
                out += data
                due_s[message_id] = next_due(due, period, t_s)  # as StreamSchedule.sent
                if reading is not None:
                    sent_reading[message_id] = reading[0]
        if self._fresh("light", self._light):
            sent_reading["light"] = self._light[0]
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
            out += self._heartbeat() + self.telemetry.sys_status(voltage_v, remaining_pct, self._sensor_bits())
        return bytes(out)


# The reading each message is made from (sent only when that reading is newer than the message's last copy).
# GPS_RAW_INT is not among them: ArduPilot repeats a fix with its own time (`_build_gps_raw_int`).
_READING_OF: dict[int, str] = {
    m.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: "_gps",
    m.MAVLINK_MSG_ID_VFR_HUD: "_gps", m.MAVLINK_MSG_ID_ATTITUDE: "_compass", m.MAVLINK_MSG_ID_RAW_IMU: "_imu",
    m.MAVLINK_MSG_ID_SCALED_IMU: "_imu", m.MAVLINK_MSG_ID_WHEEL_DISTANCE: "_wheels",
    m.MAVLINK_MSG_ID_DISTANCE_SENSOR: "_ranges",
}  # fmt: skip
_BUILDERS = {message_id: getattr(TelemetryStreams, f"_build_{m.mavlink_map[message_id].msgname.lower()}")
             for message_id in PRODUCED}  # fmt: skip
# Per message: the reading it is made from (or None) and its builder.
_MADE_OF = {message_id: (_READING_OF.get(message_id), build) for message_id, build in _BUILDERS.items()}
