"""Encode a vehicle's telemetry as MAVLink 2 bytes: the autopilot's side of `firmware_bridge.decoder`.

Simulated vehicles and bridges to firmwares that do not speak MAVLink (the eBot)
use these to look like an ArduPilot vehicle. Every function is the exact inverse
of the decoder's conversion (frames and signs in docs/mavlink-mapping.md), up to
the message's integer units: lat/lon 1e-7 deg, speed 1 cm/s, course 0.01 deg,
acceleration 1 mG, rates 1 mrad/s.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_bridge.commands import Encoder
from firmware_bridge.decoder import STANDARD_GRAVITY_MPS2, UINT16_MAX

INT16_MAX = 32767


def yaw_from_heading(heading_rad: float) -> float:
    """MAVLink yaw (rad from north, clockwise) in (-pi, pi] from our heading (from east, counter-clockwise)."""
    yaw = math.pi / 2.0 - float(heading_rad)
    return math.pi - (math.pi - yaw) % (2.0 * math.pi)


def _usec(t_s: float) -> int:
    """A vehicle time stamp in microseconds (uint64; times before boot, t_s < 0, are sent as 0)."""
    return max(0, int(t_s * 1e6))


def _ms(t_s: float) -> int:
    """A vehicle time stamp in milliseconds since boot (uint32, wrapping)."""
    return max(0, int(t_s * 1000)) & 0xFFFFFFFF


def _cm_s(v_mps: float) -> int:
    return int(max(-32767, min(32767, round(v_mps * 100.0))))


def _uint16s(values: Sequence[int], count: int) -> list[int]:
    """`count` values as uint16 fields: the first `count` of `values` as integers clamped to 0..UINT16_MAX, zeros
    after them (the clamping only done when some value needs it: these go out several times a second)."""
    out = list(map(int, values[:count] if isinstance(values, list) else list(values)[:count]))
    if out and (min(out) < 0 or max(out) > UINT16_MAX):
        out = [max(0, min(UINT16_MAX, v)) for v in out]
    return out + [0] * (count - len(out))


def _int16(value: float) -> int:
    """value rounded (halves to even) and clamped to +-INT16_MAX."""
    v = round(value)
    return -INT16_MAX if v < -INT16_MAX else INT16_MAX if v > INT16_MAX else int(v)


def _imu_fields(
    accel_body_mps2: Sequence[float], gyro_z_radps: float, accel_z_mps2: float | None, gyro_xy_radps: Sequence[float]
) -> list[int]:
    """SCALED_IMU's and RAW_IMU's accelerometer (mG), gyro (mrad/s) and magnetometer (0) fields, FRD, from our
    x forward, y left, z up; a z specific force of None is 1 g exactly (-1000 mG)."""
    to_mg = 1000.0 / STANDARD_GRAVITY_MPS2
    ax, ay, gz = _int16(accel_body_mps2[0] * to_mg), _int16(-accel_body_mps2[1] * to_mg), _int16(-gyro_z_radps * 1000.0)
    if accel_z_mps2 is None and gyro_xy_radps == (0.0, 0.0):  # a level hull (the simulator's, every message)
        return [ax, ay, -1000, 0, 0, gz, 0, 0, 0]
    z = -1000 if accel_z_mps2 is None else _int16(-accel_z_mps2 * to_mg)
    return [ax, ay, z, _int16(gyro_xy_radps[0] * 1000.0), _int16(-gyro_xy_radps[1] * 1000.0), gz, 0, 0, 0]


class TelemetryEncoder:
    """One vehicle's telemetry frames, sent as (system_id, component 1: the autopilot). Times t_s are on the
    caller's clock, s; the frames carry the vehicle's time since boot, t_s - boot_s (`_usec`, `_ms`; the decoder
    stamps readings at reception; it uses the vehicle's times to tell a repeated GPS fix, and a restart, from new
    ones)."""

    def __init__(
        self, system_id: int, component_id: int = mavlink.MAV_COMP_ID_AUTOPILOT1, *, boot_s: float = 0.0
    ) -> None:
        self.boot_s = float(boot_s)
        self.encoder = Encoder(system_id, component_id)
        self.mav = self.encoder.mav
        self._text_id = 0  # the id of the last chunked STATUSTEXT

    def pack(self, message) -> bytes:
        """Any pymavlink message as one frame from this vehicle (protocol replies: PARAM_VALUE, MISSION_*)."""
        return self.encoder.pack(message)

    def heartbeat(
        self, mav_type: int, armed: bool, custom_mode: int = 0, *, base_flags: int = 0, state: int | None = None
    ) -> bytes:
        """HEARTBEAT of an ArduPilot vehicle: custom mode enabled, the armed flag, extra MAV_MODE_FLAGs (`base_flags`),
        system status `state` (default: ACTIVE when armed, else STANDBY)."""
        base_mode = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | int(base_flags)
        if armed:
            base_mode |= mavlink.MAV_MODE_FLAG_SAFETY_ARMED
        if state is None:
            state = mavlink.MAV_STATE_ACTIVE if armed else mavlink.MAV_STATE_STANDBY
        return self.encoder.frame(
            mavlink.MAVLink_heartbeat_message,
            mav_type,
            mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
            base_mode & 0xFF,
            int(custom_mode),
            state,
        )

    def gps_raw_int(
        self,
        t_s: float,
        lat_deg: float,
        lon_deg: float,
        velocity_mps: Sequence[float] | None = None,
        *,
        fix_type: int = mavlink.GPS_FIX_TYPE_3D_FIX,
        satellites: int = 12,
        hdop: float | None = 0.9,
        h_acc_m: float | None = None,
        vel_acc_mps: float | None = None,
    ) -> bytes:
        """GPS_RAW_INT: position (deg), ground velocity (east, north) m/s as speed and course over ground; hdop
        None: unknown (UINT16_MAX); h_acc_m, vel_acc_mps: the receiver's one-sigma horizontal (m) and speed (m/s)
        accuracies in the MAVLink 2 extension fields h_acc (mm) and vel_acc (mm/s), as ArduPilot sends them (both
        None: the extensions left out; one None: that one 0, unknown)."""
        extensions = ()
        if h_acc_m is not None or vel_acc_mps is not None:
            h_acc = 0 if h_acc_m is None else min(2**32 - 1, max(0, round(h_acc_m * 1000.0)))
            vel_acc = 0 if vel_acc_mps is None else min(2**32 - 1, max(0, round(vel_acc_mps * 1000.0)))
            extensions = (0, h_acc, 0, vel_acc)  # alt_ellipsoid, h_acc, v_acc, vel_acc
        vel, cog = UINT16_MAX, UINT16_MAX
        if velocity_mps is not None and all(map(math.isfinite, velocity_mps)):
            east, north = float(velocity_mps[0]), float(velocity_mps[1])
            vel = min(UINT16_MAX - 1, round(math.hypot(east, north) * 100.0))
            cog = round(math.degrees(math.atan2(east, north)) * 100.0) % 36000
        return self.encoder.frame(
            mavlink.MAVLink_gps_raw_int_message,
            _usec(t_s - self.boot_s),
            fix_type,
            round(lat_deg * 1e7),
            round(lon_deg * 1e7),
            0,
            UINT16_MAX if hdop is None else min(UINT16_MAX - 1, round(hdop * 100)),
            UINT16_MAX,
            vel,
            cog,
            satellites,
            *extensions,
        )

    def global_position_int(
        self,
        t_s: float,
        lat_deg: float,
        lon_deg: float,
        velocity_mps: Sequence[float] | None = None,
        heading_rad: float | None = None,
    ) -> bytes:
        """GLOBAL_POSITION_INT (what ground stations show as the position): lat/lon degE7, altitude 0, ground
        velocity north/east cm/s (0 when unknown), heading cdeg 0..35999 from our heading (from east, CCW), as
        ArduPilot sends its AHRS yaw (GCS_Common.cpp send_global_position_int); UINT16_MAX when unknown."""
        east, north = 0.0, 0.0
        if velocity_mps is not None and all(map(math.isfinite, velocity_mps)):
            east, north = float(velocity_mps[0]), float(velocity_mps[1])
        hdg = UINT16_MAX
        if heading_rad is not None and math.isfinite(heading_rad):
            hdg = round(math.degrees(yaw_from_heading(heading_rad)) * 100.0) % 36000
        return self.encoder.frame(
            mavlink.MAVLink_global_position_int_message,
            _ms(t_s - self.boot_s),
            round(lat_deg * 1e7),
            round(lon_deg * 1e7),
            0,
            0,
            _cm_s(north),
            _cm_s(east),
            0,
            hdg,
        )

    def distance_sensor(
        self, t_s: float, sensor_id: int, distance_m: float, max_m: float, min_m: float = 0.02
    ) -> bytes:
        """DISTANCE_SENSOR of range finder `sensor_id` (cm); no echo (NaN) is sent as max + 1 cm, as ArduPilot
        reports out of range. Orientation is MAV_SENSOR_ROTATION_CUSTOM: the sensor's bearing is the receiver's
        configuration (docs/mavlink-mapping.md)."""
        max_cm = round(max_m * 100.0)
        current = max_cm + 1 if not math.isfinite(distance_m) else min(max_cm + 1, round(distance_m * 100.0))
        return self.encoder.frame(mavlink.MAVLink_distance_sensor_message,
            _ms(t_s - self.boot_s), round(min_m * 100.0), max_cm, current, mavlink.MAV_DISTANCE_SENSOR_ULTRASOUND,
            int(sensor_id), mavlink.MAV_SENSOR_ROTATION_CUSTOM, 255,
        )  # fmt: skip

    def light(self, t_s: float, left: float, right: float) -> bytes:
        """The two light readings as NAMED_VALUE_FLOAT "light_l" and "light_r" (W/m^2)."""
        ms = _ms(t_s - self.boot_s)
        named = mavlink.MAVLink_named_value_float_message
        return self.encoder.frame(named, ms, b"light_l", float(left)) + self.encoder.frame(
            named, ms, b"light_r", float(right)
        )

    def attitude(
        self,
        t_s: float,
        heading_rad: float,
        yaw_rate_radps: float = 0.0,
        *,
        roll_rad: float = 0.0,
        pitch_rad: float = 0.0,
        roll_pitch_rates_radps: Sequence[float] = (0.0, 0.0),
    ) -> bytes:
        """ATTITUDE: yaw from our heading, yawspeed clockwise-positive (rad/s); level unless given roll (right side
        down), pitch (nose up) and the body rates about x forward and y right (rollspeed, pitchspeed), rad, rad/s."""
        return self.encoder.frame(
            mavlink.MAVLink_attitude_message,
            _ms(t_s - self.boot_s),
            float(roll_rad),
            float(pitch_rad),
            yaw_from_heading(heading_rad),
            float(roll_pitch_rates_radps[0]),
            float(roll_pitch_rates_radps[1]),
            -float(yaw_rate_radps),
        )

    def scaled_imu(
        self,
        t_s: float,
        accel_body_mps2: Sequence[float],
        gyro_z_radps: float,
        *,
        accel_z_mps2: float | None = None,
        gyro_xy_radps: Sequence[float] = (0.0, 0.0),
    ) -> bytes:
        """SCALED_IMU (mG, mrad/s, FRD body frame) from our IMU (x forward, y left, z up; yaw rate CCW): a level
        hull's unless given the z specific force (None: 1 g) and the rates about x and y."""
        return self.encoder.frame(
            mavlink.MAVLink_scaled_imu_message, _ms(t_s - self.boot_s), *_imu_fields(accel_body_mps2, gyro_z_radps,
                                                                              accel_z_mps2, gyro_xy_radps)
        )  # fmt: skip

    def raw_imu(
        self,
        t_s: float,
        accel_body_mps2: Sequence[float],
        gyro_z_radps: float,
        *,
        accel_z_mps2: float | None = None,
        gyro_xy_radps: Sequence[float] = (0.0, 0.0),
    ) -> bytes:
        """RAW_IMU as ArduPilot fills it (GCS_Common.cpp send_raw_imu: mG and mrad/s, FRD), as `scaled_imu`."""
        fields = _imu_fields(accel_body_mps2, gyro_z_radps, accel_z_mps2, gyro_xy_radps)
        return self.encoder.frame(mavlink.MAVLink_raw_imu_message, _usec(t_s - self.boot_s), *fields, 0, 0)

    def wheel_distance(self, t_s: float, distance_m: Sequence[float], count: int = 2) -> bytes:
        """WHEEL_DISTANCE with `count` wheels (left, right), cumulative metres."""
        distances = [float(distance_m[0]), float(distance_m[1])] + [0.0] * 14
        usec = _usec(t_s - self.boot_s)
        return self.encoder.frame(mavlink.MAVLink_wheel_distance_message, usec, int(count), distances)

    def rc_channels(self, t_s: float, pwm_us: Sequence[int], channel_count: int) -> bytes:
        """RC_CHANNELS: the autopilot's RC inputs (us; 0 = none), 18 channels, RSSI unknown (255)."""
        values = _uint16s(pwm_us, 18)
        ms = _ms(t_s - self.boot_s)
        return self.encoder.frame(mavlink.MAVLink_rc_channels_message, ms, int(channel_count), *values, 255)

    def servo_output_raw(self, t_s: float, pwm_us: Sequence[int]) -> bytes:
        """SERVO_OUTPUT_RAW: the outputs SERVO1..16 (us; 0 = no output)."""
        values = _uint16s(pwm_us, 16)
        usec = _usec(t_s - self.boot_s) & 0xFFFFFFFF
        return self.encoder.frame(mavlink.MAVLink_servo_output_raw_message, usec, 0, *values)

    def home_position(self, t_s: float, lat_e7: int, lon_e7: int, alt_m: float = 0.0) -> bytes:
        """HOME_POSITION as ArduPilot sends it (GCS_Common.cpp send_home_position): lat/lon degE7, altitude mm,
        local position 0 (home is the origin here), q NaN, approach 0."""
        nan = math.nan
        return self.encoder.frame(
            mavlink.MAVLink_home_position_message,
            int(lat_e7),
            int(lon_e7),
            round(alt_m * 1000.0),
            0.0,
            0.0,
            0.0,
            [nan] * 4,
            0.0,
            0.0,
            0.0,
            _usec(t_s - self.boot_s),
        )

    def autopilot_version(self, capabilities: int, flight_sw_version: int, custom_version: bytes, uid: int) -> bytes:
        """AUTOPILOT_VERSION (GCS_Common.cpp send_autopilot_version): capabilities bitmask, the firmware version
        (major << 24 | minor << 16 | patch << 8 | type), the git hash's first 8 bytes, a unique id."""
        custom = list(bytes(custom_version)[:8].ljust(8, b"\0"))
        return self.encoder.frame(
            mavlink.MAVLink_autopilot_version_message,
            int(capabilities),
            int(flight_sw_version),
            0,
            0,
            0,
            custom,
            [0] * 8,
            [0] * 8,
            0,
            0,
            int(uid),
            [0] * 18,
        )

    def statustext(self, severity: int, text: str) -> bytes:
        """STATUSTEXT as ArduPilot sends a text (GCS_Common.cpp GCS::send_textv): up to 50 characters in one message
        with id 0; a longer text in 50-character chunks sharing a non-zero id, chunk_seq 0, 1, ... (a chunk shorter
        than 50, possibly empty, ends it), at most 30 chunks."""
        raw = text.encode("ascii", "replace")
        if len(raw) <= 50:
            return self.encoder.frame(mavlink.MAVLink_statustext_message, int(severity), raw, 0, 0)
        self._text_id = self._text_id % 65535 + 1
        out = bytearray()
        for seq in range(30):
            chunk, raw = raw[:50], raw[50:]
            out += self.encoder.frame(mavlink.MAVLink_statustext_message, int(severity), chunk, self._text_id, seq)
            if len(chunk) < 50:
                break
        return bytes(out)

    def battery_status(self, voltage_v: float, remaining_pct: float) -> bytes:
        """BATTERY_STATUS of battery 0 with the pack voltage in the first cell slot (mV), as ArduPilot reports a
        monitor without cell voltages; NaN reports unknown."""
        voltage = UINT16_MAX if not math.isfinite(voltage_v) else min(UINT16_MAX - 1, round(voltage_v * 1000.0))
        remaining = -1 if not math.isfinite(remaining_pct) else round(remaining_pct)
        cells = [voltage] + [UINT16_MAX] * 9
        return self.encoder.frame(mavlink.MAVLink_battery_status_message, 0, 0, 0, 32767, cells, -1, -1, -1, remaining)

    def vfr_hud(self, groundspeed_mps: float, heading_rad: float | None, throttle_pct: float) -> bytes:
        """VFR_HUD: ground speed m/s, heading deg 0..359 from our heading, throttle % (Rover reports reverse as a
        negative int16 in the uint16 field, so -50 % arrives as 65486: GCS_MAVLink_Rover.cpp vfr_hud_throttle)."""
        heading = 0
        if heading_rad is not None and math.isfinite(heading_rad):
            heading = round(math.degrees(yaw_from_heading(heading_rad))) % 360
        speed = float(groundspeed_mps) if math.isfinite(groundspeed_mps) else 0.0
        throttle = (max(-32768, min(32767, round(throttle_pct))) & 0xFFFF) if math.isfinite(throttle_pct) else 0
        return self.encoder.frame(mavlink.MAVLink_vfr_hud_message, speed, speed, heading, throttle, 0.0, 0.0)

    def system_time(self, t_s: float, unix_time_s: float = 0.0) -> bytes:
        """SYSTEM_TIME: Unix time us (0 when unknown) and time since boot ms."""
        unix_us, ms = max(0, int(unix_time_s * 1e6)), _ms(t_s - self.boot_s)
        return self.encoder.frame(mavlink.MAVLink_system_time_message, unix_us, ms)

    def message_interval(self, message_id: int, interval_us: int) -> bytes:
        """MESSAGE_INTERVAL (reply to MAV_CMD_GET_MESSAGE_INTERVAL): -1 = off, 0 = not available."""
        return self.encoder.frame(mavlink.MAVLink_message_interval_message, int(message_id) & 0xFFFF, int(interval_us))

    def sys_status(self, voltage_v: float, remaining_pct: float, sensors: tuple[int, int, int] = (0, 0, 0)) -> bytes:
        """SYS_STATUS with the battery voltage (V) and remaining charge (%; NaN reports unknown) and the
        onboard_control_sensors (present, enabled, health) bit masks (MAV_SYS_STATUS_*)."""
        voltage = UINT16_MAX if not math.isfinite(voltage_v) else round(voltage_v * 1000.0)
        remaining = -1 if not math.isfinite(remaining_pct) else round(remaining_pct)
        return self.encoder.frame(
            mavlink.MAVLink_sys_status_message, *sensors, 0, voltage, -1, remaining, 0, 0, 0, 0, 0, 0
        )

    def command_ack(self, command: int, result: int, target_system: int = 0, target_component: int = 0) -> bytes:
        """COMMAND_ACK of a COMMAND_LONG."""
        return self.encoder.frame(
            mavlink.MAVLink_command_ack_message, command, result, 0, 0, target_system, target_component
        )
