"""Decode raw MAVLink telemetry bytes into typed readings.

`TelemetryDecoder.feed(data)` takes whatever bytes a link delivered (any
chunking: half frames, several frames, noise) and returns the readings of the
frames completed by them. Nothing raises into the caller: noise, truncated
frames, bad checksums and messages of ids the dialect does not know are
counted in `TelemetryDecoder.counters` and skipped.

Framing is done here (so that after a bad frame the search for the next one
restarts one byte after the bad frame's start marker, rather than after the
whole bad frame, whose length byte may itself be the corrupted one); the
checksum and the payload decoding are pymavlink's (`MAVLink.decode` of the
ardupilotmega MAVLink 2 dialect; MAVLink 1 frames are accepted too).

Timestamps: a reading's `t_s` is on the decoder's clock (default
`time.monotonic`), read once per `feed` call (the local time of reception of
the chunk), and placed through the autopilot's clock since boot
(`firmware_bridge.autopilot_clock`, learnt from the time_boot_ms of ATTITUDE
and the IMU messages) where the message carries ArduPilot's time: ATTITUDE,
SCALED_IMU, RAW_IMU, GLOBAL_POSITION_INT and WHEEL_DISTANCE are dated when they
were sent, so that messages read together keep their own times; a GPS fix
(GPS_RAW_INT, stamped with the time its GPS driver read it and repeated at the
rate asked) when it was read, less `gps_lag_s`. Other readings (battery,
ranges, light, heartbeats) keep the time of reception. Frames and sign conventions: see
docs/mavlink-mapping.md.
"""

from __future__ import annotations

import functools
import math
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_bridge.autopilot_clock import AutopilotClock
from firmware_bridge.frames import FrameHeader, decode_unsigned, frame_checksum, layout
from firmware_bridge.readings import (
    CompassReading,
    FloatArray,
    GpsFix,
    ImuReading,
    IntArray,
    LightReading,
    RangeReading,
)

STANDARD_GRAVITY_MPS2 = 9.80665
UINT16_MAX = 65535
MAX_GPS_LAG_S = 1.0  # a GPS lag above this is a setting's mistake (ArduPilot's defaults are 0.08-0.22 s)

# The messages a decoder reads that carry the autopilot's time of sending: (field, s per unit).
SENT_TIME_FIELDS: dict[int, tuple[str, float]] = {
    mavlink.MAVLINK_MSG_ID_ATTITUDE: ("time_boot_ms", 1e-3),
    mavlink.MAVLINK_MSG_ID_SCALED_IMU: ("time_boot_ms", 1e-3),
    mavlink.MAVLINK_MSG_ID_RAW_IMU: ("time_usec", 1e-6),
    mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: ("time_boot_ms", 1e-3),
}


# Reported accuracies are capped here, as ArduPilot's EKF3 caps gpsPosAccuracy (m) and gpsSpdAccuracy (m/s).
MAX_GPS_ACCURACY_M = 100.0
MAX_GPS_SPEED_ACCURACY_MPS = 50.0


def reported_accuracy(milli: int, cap: float) -> float:
    """GPS_RAW_INT's h_acc (mm) or vel_acc (mm/s), one sigma, in m or m/s, at most `cap`; NaN when 0 (not
    reported: MAVLink 1 has no such field, and many GPS drivers leave it 0)."""
    return min(milli / 1000.0, cap) if milli > 0 else math.nan


def _boot_time_s(msg) -> float:
    """The autopilot's time since boot (s) at which msg (one of SENT_TIME_FIELDS) was sent."""
    field_name, unit = SENT_TIME_FIELDS[msg.get_msgId()]
    return float(getattr(msg, field_name)) * unit


def sent_stamp_us(msg_id: int, value: int) -> int:
    """A SENT_TIME_FIELDS time field's value in us since the autopilot's boot."""
    return int(value) * round(SENT_TIME_FIELDS[msg_id][1] * 1e6)


_V1 = mavlink.PROTOCOL_MARKER_V1
_V2 = mavlink.PROTOCOL_MARKER_V2
_SIGNED = mavlink.MAVLINK_IFLAG_SIGNED
_SIGNATURE_LEN = mavlink.MAVLINK_SIGNATURE_BLOCK_LEN
_MARKERS = (bytes([_V1]), bytes([_V2]))
# A v2 header is 10 bytes, v1 6; both are followed by payload and a 2-byte CRC.
_HEADER_LEN = {_V1: mavlink.HEADER_LEN_V1, _V2: mavlink.HEADER_LEN_V2}


@dataclass(frozen=True, eq=False)
class WheelDistance:
    """Wheel travel from WHEEL_DISTANCE: agent indices (k,), reception times t_s (k,), and cumulative
    distance_m (k, 2) (left, right) in metres, positive forward. (EncoderReading holds ticks; a stock
    autopilot reports metres, so this is its own type.)"""

    agents: IntArray
    t_s: FloatArray
    distance_m: FloatArray


@dataclass(frozen=True, eq=False)
class Battery:
    """Battery state from SYS_STATUS or BATTERY_STATUS: agent indices (k,), reception times t_s (k,),
    voltage_v (k,) total pack voltage and remaining_pct (k,) 0..100, NaN where the autopilot reports unknown."""

    agents: IntArray
    t_s: FloatArray
    voltage_v: FloatArray
    remaining_pct: FloatArray


@dataclass(frozen=True)
class Heartbeat:
    """A HEARTBEAT: who sent it, its type, mode and whether it is armed (MAV_MODE_FLAG_SAFETY_ARMED)."""

    t_s: float
    system: int
    component: int
    mav_type: int
    autopilot: int
    base_mode: int
    custom_mode: int
    system_status: int
    armed: bool


def heartbeat_reading(
    t_s: float, system: int, component: int, mav_type: int, autopilot: int, base_mode: int, custom_mode: int,
    system_status: int,
) -> Heartbeat:  # fmt: skip
    """The reading of a HEARTBEAT with these fields from system, component, arrived at t_s (a function of the fields
    alone, so that the batch decoder can read them without a message object)."""
    armed = bool(base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
    return Heartbeat(t_s, system, component, mav_type, autopilot, base_mode, custom_mode, system_status, armed)


@dataclass(frozen=True)
class CommandAck:
    """A COMMAND_ACK: the MAV_CMD acknowledged and its MAV_RESULT (0 = accepted)."""

    t_s: float
    command: int
    result: int


Reading = (
    GpsFix
    | CompassReading
    | ImuReading
    | WheelDistance
    | RangeReading
    | LightReading
    | Battery
    | Heartbeat
    | CommandAck
)
LIGHT_NAMES = {"light_l": 0, "light_r": 1}  # NAMED_VALUE_FLOAT names of the eBot's left and right light sensors


@dataclass
class DecoderCounters:
    """What the decoder has seen. Every byte fed ends up in exactly one of: a frame counted in `decoded`
    or `unknown` (`frame_bytes`), `skipped_bytes` (noise, bad frames, resynchronisation), or `pending_bytes`
    (an incomplete frame awaiting more data); and every complete candidate frame (`received`) is exactly
    one of `decoded`, `bad_crc`, `unknown` or `malformed`."""

    bytes_fed: int = 0
    received: int = 0
    decoded: int = 0
    bad_crc: int = 0
    unknown: int = 0
    malformed: int = 0
    skipped_bytes: int = 0
    frame_bytes: int = 0
    pending_bytes: int = 0
    no_fix: int = 0
    repeated_fix: int = 0  # GPS_RAW_INT carrying a fix already read (its time_usec again): not read twice
    other_system: int = 0
    other_component: int = 0
    not_yet_known: int = 0
    by_type: dict[str, int] = field(default_factory=dict)


def wrap_angle(angle_rad: float) -> float:
    """Wrap an angle to (-pi, pi]."""
    return math.pi - (math.pi - angle_rad) % (2.0 * math.pi)


def heading_from_yaw(yaw_rad: float) -> float:
    """Our heading (from east, counter-clockwise) from a MAVLink yaw (from north, clockwise), in (-pi, pi]."""
    return wrap_angle(math.pi / 2.0 - yaw_rad)


def classify_frame(
    frame: bytearray, mav: mavlink.MAVLink, followed: bool, unread: frozenset[int] = frozenset()
) -> tuple[str, object]:
    """Judge one complete candidate frame: ("ok", message), ("unknown", None), ("bad_crc", None) or
    ("malformed", None). `followed`: the frame ends the data so far or another start marker follows it.
    Unsigned MAVLink 2 frames of the message ids in `unread` come back as a `FrameHeader` (checked, not
    decoded: their receiver does not read their fields).

    The checksum of a message id the dialect does not know cannot be verified (no CRC_EXTRA), so an unknown
    frame is only believed when `followed`; otherwise its start marker is taken for noise. Signatures are
    not checked here (see bob_autonomy.ground.gcs for signed links)."""
    magic = frame[0]
    if magic == _V2:
        if frame[2] & ~_SIGNED:
            return "malformed", None
        msg_id = frame[7] | (frame[8] << 8) | (frame[9] << 16)
    else:
        msg_id = frame[5]
    msg_type = mavlink.mavlink_map.get(msg_id)
    if msg_type is None:
        return ("unknown", None) if followed else ("malformed", None)
    signed = magic == _V2 and frame[2] & _SIGNED
    crc_end = len(frame) - (_SIGNATURE_LEN if signed else 0)
    crc = frame[crc_end - 2] | (frame[crc_end - 1] << 8)
    if frame_checksum(frame, crc_end - 2, msg_type.crc_extra) != crc:
        return "bad_crc", None
    try:
        if magic == _V2 and not signed and mav.signing.secret_key is None:
            if msg_id in unread:
                return "ok", FrameHeader(msg_type.msgname, msg_id, frame[5], frame[6])
            return "ok", decode_unsigned(frame, layout(msg_id), crc)  # pymavlink's decode, checksum not redone
        return "ok", mav.decode(frame)
    except Exception:
        return "malformed", None


MAX_CANDIDATES = 32  # start markers examined by contains_mavlink_frame before it gives up (bounded work)
_CHECK_MAV = mavlink.MAVLink(None, srcSystem=0, srcComponent=0)


def contains_mavlink_frame(data: bytes) -> bool:
    """Whether `data` (e.g. one UDP datagram) holds at least one complete MAVLink frame of a message the
    dialect knows, with the right checksum. Signatures are not checked. Looks at the first MAX_CANDIDATES
    start markers only, so that a datagram of markers costs little; a real datagram starts with its frame."""
    buf = bytearray(data)
    n = len(buf)
    pos = 0
    for _ in range(MAX_CANDIDATES):
        start = next_marker(buf, pos)
        if start < 0 or n - start < 3:
            return False
        length = _HEADER_LEN[buf[start]] + buf[start + 1] + 2
        if buf[start] == _V2 and buf[start + 2] & _SIGNED:
            length += _SIGNATURE_LEN
        if start + length <= n:
            try:
                verdict, _ = classify_frame(bytearray(buf[start : start + length]), _CHECK_MAV, followed=True)
            except Exception:  # pragma: no cover - defensive: classify_frame catches decoding errors
                verdict = "malformed"
            if verdict == "ok":
                return True
        pos = start + 1
    return False


class TelemetryDecoder:
    """Bytes in, typed readings out, for one vehicle (readings carry `agents = [agent]`).

    Whose telemetry is believed (issue 17: another sender on a serial or UDP link must not move an estimate):
    `source_system`, when given, keeps only messages from that MAVLink system id (others are counted in
    `counters.other_system`); `source_component` keeps only that component's (`other_component`), e.g. 1, the
    autopilot (MAV_COMP_ID_AUTOPILOT1), so that a companion computer or a ground station on the same system
    id is not taken for the vehicle. `learn_source=True` with no `source_system`: the system id is learnt
    from the first HEARTBEAT of an autopilot (`autopilot` not MAV_AUTOPILOT_INVALID, from `source_component`
    or 1), and until then no readings are made (`not_yet_known`). `message_hook` and `feed_messages` see
    every decoded message, of any source. `fused_position=False` ignores GLOBAL_POSITION_INT (the
    autopilot's own fused position), so that an estimator fed GPS_RAW_INT does not fuse every fix twice.
    """

    def __init__(
        self,
        clock: Callable[[], float] = time.monotonic,
        *,
        agent: int = 0,
        source_system: int | None = None,
        source_component: int | None = None,
        learn_source: bool = False,
        fused_position: bool = True,
        gps_lag_s: float = 0.0,
    ) -> None:
        if not (math.isfinite(gps_lag_s) and 0.0 <= gps_lag_s <= MAX_GPS_LAG_S):
            raise ValueError(f"gps_lag_s must be within 0..{MAX_GPS_LAG_S} s; got {gps_lag_s!r}")
        self.clock = clock
        self.gps_lag_s = float(gps_lag_s)
        self.autopilot_clock = AutopilotClock()  # where the autopilot's time since boot falls on `clock`
        self.fused_position = fused_position
        self.agent = agent
        self.source_system = source_system
        self.source_component = source_component
        self.learn_source = learn_source
        self.counters = DecoderCounters()
        self._mav = mavlink.MAVLink(None, srcSystem=0, srcComponent=0)
        self._buf = bytearray()
        self._agents = np.array([agent], dtype=np.intp)
        self.message_hook: Callable[[object], None] | None = None  # sees every decoded message (e.g. a tlog)
        self._unread = _unread_ids(fused_position)  # checked and counted by `feed`, not decoded
        self._clock_ids = frozenset(SENT_TIME_FIELDS) - self._unread  # the messages read that sample the clock
        self.last_fix_usec = 0  # time_usec of the last GPS_RAW_INT fix read (0: none, or a GPS without time)

    # -- framing ---------------------------------------------------------------------------------------

    def feed(self, data: bytes) -> list[Reading]:
        """Add received bytes; return the readings of the messages they complete, in stream order."""
        readings: list[Reading] = []
        unread = self._unread if self.message_hook is None else frozenset()
        believed = [msg for msg in self.feed_messages(data, unread) if self._from_source(msg)]
        if not believed:
            return readings
        t_s = float(self.clock())
        self.note_boot_times([_boot_time_s(msg) for msg in believed if msg.get_msgId() in self._clock_ids], t_s)
        for msg in believed:
            try:
                reading = self._convert(msg, t_s)
            except (TypeError, ValueError, OverflowError, AttributeError, IndexError):
                reading = None
            if reading is not None:
                readings.append(reading)
        return readings

    def feed_messages(self, data: bytes, unread: frozenset[int] = frozenset()) -> list:
        """Add received bytes; return the pymavlink messages they complete (checksums verified), in stream
        order, of any type and any source system (those of ids in `unread` as `FrameHeader`s). For the
        vehicle side, which reads commands, not telemetry."""
        messages: list = []
        try:
            self._feed(bytes(data), messages, unread)
        except Exception:  # pragma: no cover - defensive: nothing may escape into the caller
            self.counters.malformed += 1
            self.counters.skipped_bytes += len(self._buf)
            self._buf.clear()
        self.counters.pending_bytes = len(self._buf)
        return messages

    def _feed(self, data: bytes, messages: list, unread: frozenset[int]) -> None:
        c = self.counters
        c.bytes_fed += len(data)
        buf = self._buf
        buf.extend(data)
        pos = 0
        n = len(buf)
        while pos < n:
            start = next_marker(buf, pos)
            if start < 0:
                c.skipped_bytes += n - pos
                pos = n
                break
            c.skipped_bytes += start - pos
            pos = start
            magic = buf[pos]
            header_len = _HEADER_LEN[magic]
            if n - pos < 3:
                break  # need the length (and v2 flags) byte(s)
            length = header_len + buf[pos + 1] + 2
            if magic == _V2 and buf[pos + 2] & _SIGNED:
                length += _SIGNATURE_LEN
            if n - pos < length:
                break  # incomplete: wait for more bytes
            frame = bytearray(buf[pos : pos + length])
            c.received += 1
            end = pos + length
            verdict, msg = classify_frame(frame, self._mav, end == n or buf[end] in (_V1, _V2), unread)
            if verdict == "unknown":
                c.unknown += 1
            elif verdict != "ok":
                if verdict == "bad_crc":
                    c.bad_crc += 1
                else:
                    c.malformed += 1
                # Resynchronise one byte on: the next frame may start inside this one.
                c.skipped_bytes += 1
                pos += 1
                continue
            c.frame_bytes += length
            pos += length
            if msg is None:
                continue
            c.decoded += 1
            name = msg.get_type()
            c.by_type[name] = c.by_type.get(name, 0) + 1
            messages.append(msg)
            if self.message_hook is not None:
                self.message_hook(msg)
        del buf[:pos]

    def _from_source(self, msg) -> bool:
        """Whether msg comes from the vehicle whose telemetry we believe (counting those that do not)."""
        c = self.counters
        component = msg.get_srcComponent()
        if self.source_system is None and self.learn_source:
            autopilot = self.source_component if self.source_component is not None else 1
            if (
                msg.get_type() == "HEARTBEAT"
                and component == autopilot
                and msg.autopilot != mavlink.MAV_AUTOPILOT_INVALID
            ):
                self.source_system = msg.get_srcSystem()  # the first autopilot heard is the vehicle
            else:
                c.not_yet_known += 1
                return False
        if self.source_system is not None and msg.get_srcSystem() != self.source_system:
            c.other_system += 1
            return False
        if self.source_component is not None and component != self.source_component:
            c.other_component += 1
            return False
        return True

    # -- conversion ------------------------------------------------------------------------------------

    def _convert(self, msg, t_s: float) -> Reading | None:
        name = msg.get_type()
        convert = _CONVERTERS.get(name)
        if convert is None:
            return None
        return convert(self, msg, t_s)

    def note_boot_times(self, boot_s: list[float], t_s: float) -> None:
        """The autopilot's times since boot (s) of one chunk's messages that carry the time they were sent, all
        arrived at t_s: the newest is a sample of the autopilot's clock (`AutopilotClock.observe`)."""
        if boot_s:
            self.autopilot_clock.observe(max(boot_s), t_s)

    def fix_time(self, time_usec: int, t_s: float) -> float:
        """When a GPS fix stamped time_usec (us since the autopilot's boot) that arrived at t_s was taken, on the
        decoder's clock (s): its stamp placed by the autopilot's clock, less `gps_lag_s`."""
        return self.autopilot_clock.place(time_usec, t_s) - self.gps_lag_s

    def sent_time(self, time_usec: int, t_s: float) -> float:
        """When a message stamped with the autopilot's time of sending, time_usec (us since its boot), that
        arrived at t_s was sent, on the decoder's clock (s): so that readings read from the link together (a
        serial port read in bursts, a busy loop) keep their own times and spacing."""
        return self.autopilot_clock.place(time_usec, t_s)

    def _sent_time_of(self, msg, t_s: float) -> float:
        """`sent_time` of msg (one of SENT_TIME_FIELDS), arrived at t_s."""
        msg_id = msg.get_msgId()
        return self.sent_time(sent_stamp_us(msg_id, getattr(msg, SENT_TIME_FIELDS[msg_id][0])), t_s)

    def _rows(self, t_s: float) -> tuple[IntArray, FloatArray]:
        return self._agents.copy(), np.array([t_s])

    def _gps_raw_int(self, msg, t_s: float) -> GpsFix | None:
        if msg.fix_type < 2:
            self.counters.no_fix += 1
            return None
        if not self.fresh_fix(int(msg.time_usec)):
            return None
        velocity = None
        if msg.vel != UINT16_MAX and msg.cog != UINT16_MAX:
            speed = msg.vel / 100.0
            course = math.radians(msg.cog / 100.0)  # from north, clockwise
            velocity = np.array([[speed * math.sin(course), speed * math.cos(course)]])
        agents, times = self._rows(self.fix_time(int(msg.time_usec), t_s))
        accuracy = np.array([reported_accuracy(int(getattr(msg, "h_acc", 0)), MAX_GPS_ACCURACY_M)])
        speed_accuracy = np.array([reported_accuracy(int(getattr(msg, "vel_acc", 0)), MAX_GPS_SPEED_ACCURACY_MPS)])
        lat, lon = np.array([msg.lat / 1e7]), np.array([msg.lon / 1e7])
        return GpsFix(agents, times, lat, lon, velocity, accuracy, speed_accuracy)

    def fresh_fix(self, time_usec: int) -> bool:
        """Whether a GPS_RAW_INT fix stamped time_usec is new; counts a repeat in `counters.repeated_fix`.

        ArduPilot sends GPS_RAW_INT at the rate asked whatever its GPS's rate, each copy stamped with the time of
        the fix it holds (libraries/AP_GPS/AP_GPS.cpp send_mavlink_gps_raw: last_fix_time_ms): asked 10 Hz of a
        5 Hz GPS, Rover SITL sent each fix twice with the same time_usec; and a GPS gone silent is repeated, same
        time and position, until its 4 s timeout. Read again with a later arrival time, a copy would be fused as
        a second, newer measurement of an old position. time_usec 0 (a GPS without time) is never a repeat."""
        if time_usec and time_usec == self.last_fix_usec:
            self.counters.repeated_fix += 1
            return False
        self.last_fix_usec = time_usec
        return True

    def _global_position_int(self, msg, t_s: float) -> GpsFix | None:
        if not self.fused_position:
            return None
        if msg.lat == 0 and msg.lon == 0:
            self.counters.no_fix += 1  # the autopilot has no position (yet)
            return None
        agents, times = self._rows(self._sent_time_of(msg, t_s))
        velocity = np.array([[msg.vy / 100.0, msg.vx / 100.0]])  # NED x north, y east -> east, north
        return GpsFix(agents, times, np.array([msg.lat / 1e7]), np.array([msg.lon / 1e7]), velocity)

    def _attitude(self, msg, t_s: float) -> CompassReading | None:
        if not math.isfinite(msg.yaw):
            return None
        agents, times = self._rows(self._sent_time_of(msg, t_s))
        rates = np.array([[msg.rollspeed, msg.pitchspeed, msg.yawspeed]], dtype=np.float64)
        return CompassReading(agents, times, np.array([heading_from_yaw(msg.yaw)]), np.array([float(msg.roll)]),
                              np.array([float(msg.pitch)]), rates)  # fmt: skip

    def _imu(self, msg, t_s: float) -> ImuReading:
        # MAVLink body frame: x forward, y right, z down; ours: x forward, y left, yaw rate CCW (about up).
        g = STANDARD_GRAVITY_MPS2 / 1000.0
        agents, times = self._rows(self._sent_time_of(msg, t_s))
        accel = np.array([[msg.xacc * g, -msg.yacc * g]])
        gyro_xy = np.array([[msg.xgyro / 1000.0, -msg.ygyro / 1000.0]])
        return ImuReading(agents, times, accel, np.array([-msg.zgyro / 1000.0]), np.array([-msg.zacc * g]), gyro_xy)

    def _wheel_distance(self, msg, t_s: float) -> WheelDistance | None:
        if msg.count < 2:
            return None
        agents, times = self._rows(self.sent_time(int(msg.time_usec), t_s))  # Rover: millis() * 1000 when sent
        return WheelDistance(agents, times, np.array([[float(msg.distance[0]), float(msg.distance[1])]]))

    def _distance_sensor(self, msg, t_s: float) -> RangeReading:
        beyond = msg.current_distance > msg.max_distance or msg.current_distance < msg.min_distance
        distance = math.nan if beyond else msg.current_distance / 100.0
        agents, times = self._rows(t_s)
        return RangeReading(agents, times, np.array([msg.id], dtype=np.intp), np.array([distance]))

    def _named_value_float(self, msg, t_s: float) -> LightReading | None:
        name = msg.name.decode("ascii", "replace") if isinstance(msg.name, bytes) else str(msg.name)
        side = LIGHT_NAMES.get(name.rstrip("\x00"))
        if side is None or not math.isfinite(msg.value):
            return None
        agents, times = self._rows(t_s)
        return LightReading(agents, times, np.array([side], dtype=np.intp), np.array([float(msg.value)]))

    def _sys_status(self, msg, t_s: float) -> Battery:
        voltage = math.nan if msg.voltage_battery == UINT16_MAX else msg.voltage_battery / 1000.0
        remaining = math.nan if msg.battery_remaining < 0 else float(msg.battery_remaining)
        agents, times = self._rows(t_s)
        return Battery(agents, times, np.array([voltage]), np.array([remaining]))

    def _battery_status(self, msg, t_s: float) -> Battery:
        cells = [v for v in msg.voltages if v != UINT16_MAX]
        cells += [v for v in getattr(msg, "voltages_ext", ()) if v not in (0, UINT16_MAX)]
        voltage = sum(cells) / 1000.0 if cells else math.nan
        remaining = math.nan if msg.battery_remaining < 0 else float(msg.battery_remaining)
        agents, times = self._rows(t_s)
        return Battery(agents, times, np.array([voltage]), np.array([remaining]))

    def _heartbeat(self, msg, t_s: float) -> Heartbeat:
        fields = (msg.type, msg.autopilot, msg.base_mode, msg.custom_mode, msg.system_status)
        return heartbeat_reading(t_s, msg.get_srcSystem(), msg.get_srcComponent(), *fields)

    def _command_ack(self, msg, t_s: float) -> CommandAck:
        return CommandAck(t_s=t_s, command=msg.command, result=msg.result)


@functools.cache
def _unread_ids(fused_position: bool) -> frozenset[int]:
    """The message ids a decoder makes no reading of (HEARTBEAT is read: it may name the source), so that
    `feed` need not decode them unless a message hook wants every message whole."""
    ignored = set() if fused_position else {"GLOBAL_POSITION_INT"}
    names = {msg_id: cls.msgname for msg_id, cls in mavlink.mavlink_map.items()}
    return frozenset(msg_id for msg_id, name in names.items() if name not in _CONVERTERS or name in ignored)


_CONVERTERS: dict[str, Callable[[TelemetryDecoder, object, float], Reading | None]] = {
    "GPS_RAW_INT": TelemetryDecoder._gps_raw_int,
    "GLOBAL_POSITION_INT": TelemetryDecoder._global_position_int,
    "ATTITUDE": TelemetryDecoder._attitude,
    "SCALED_IMU": TelemetryDecoder._imu,
    "RAW_IMU": TelemetryDecoder._imu,  # ArduPilot sends RAW_IMU scaled like SCALED_IMU (mG, mrad/s)
    "WHEEL_DISTANCE": TelemetryDecoder._wheel_distance,
    "DISTANCE_SENSOR": TelemetryDecoder._distance_sensor,
    "NAMED_VALUE_FLOAT": TelemetryDecoder._named_value_float,
    "SYS_STATUS": TelemetryDecoder._sys_status,
    "BATTERY_STATUS": TelemetryDecoder._battery_status,
    "HEARTBEAT": TelemetryDecoder._heartbeat,
    "COMMAND_ACK": TelemetryDecoder._command_ack,
}


def next_marker(buf: bytearray, pos: int) -> int:
    """Index of the next MAVLink start marker (v1 or v2) at or after pos, or -1."""
    a = buf.find(_MARKERS[0], pos)
    b = buf.find(_MARKERS[1], pos)
    if a < 0:
        return b
    if b < 0:
        return a
    return min(a, b)


class HeartbeatWatch:
    """Is the link alive? Silent when no HEARTBEAT has been seen for `timeout_s` (counted from construction
    until the first one). Feed it the decoder's readings with `observe`, or call `beat` directly."""

    def __init__(self, timeout_s: float, clock: Callable[[], float] = time.monotonic, *, system: int | None = None):
        if not timeout_s > 0:
            raise ValueError(f"timeout_s must be positive, got {timeout_s!r}")
        self.timeout_s = float(timeout_s)
        self.clock = clock
        self.system = system
        self.last_beat_s: float | None = None
        self._since_s = float(clock())

    def beat(self, t_s: float | None = None) -> None:
        """Record a heartbeat received at t_s (default: now)."""
        t = float(self.clock()) if t_s is None else float(t_s)
        if self.last_beat_s is None or t > self.last_beat_s:
            self.last_beat_s = t

    def observe(self, readings: Iterable[object]) -> None:
        """Record the heartbeats among decoder readings (of `system` only, when given)."""
        for reading in readings:
            if isinstance(reading, Heartbeat) and (self.system is None or reading.system == self.system):
                self.beat(reading.t_s)

    def silent_for_s(self) -> float:
        """Seconds since the last heartbeat (or since construction, before the first)."""
        reference = self._since_s if self.last_beat_s is None else self.last_beat_s
        return float(self.clock()) - reference

    def restart(self) -> None:
        """Count silence from now until the next heartbeat (e.g. once a slow start-up is over)."""
        self.last_beat_s = None
        self._since_s = float(self.clock())

    def is_silent(self) -> bool:
        return self.silent_for_s() > self.timeout_s
