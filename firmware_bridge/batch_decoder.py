"""Many vehicles' telemetry decoded at once: the readings `TelemetryDecoder.feed` gives, with numpy per message type.

Why: a lockstep fleet hands each of its 45 vessels about ten MAVLink frames a
step, and decoding them one message object at a time was a fifth of the full
stack's time. Here every vessel's bytes are framed and checked as before (one
checksum per frame), then the frames of each high-volume type (GPS_RAW_INT,
GLOBAL_POSITION_INT, ATTITUDE, SCALED_IMU, RAW_IMU) are unpacked for all vessels
in one numpy call and converted column-wise, and a reading is only built when
rows of one kind are handed over together (`Columns.take`).

What it guarantees: for well-formed input (every chunk a run of whole, unsigned
MAVLink 2 frames of known ids with good checksums, nothing pending in any
decoder, no message hook, a known source system) the counters and the readings
are exactly those of `feed` per decoder; tests/test_batch_decoder.py checks this
on random telemetry. Anything else (noise, a partial frame, a signed link) makes
`decode_batch` return None before it touches a decoder, and the caller feeds
the chunks one by one as before.
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_bridge.decoder import (
    _CONVERTERS,
    MAX_GPS_ACCURACY_M,
    MAX_GPS_SPEED_ACCURACY_MPS,
    SENT_TIME_FIELDS,
    STANDARD_GRAVITY_MPS2,
    UINT16_MAX,
    TelemetryDecoder,
    sent_stamp_us,
)
from firmware_bridge.frames import V2_HEADER_LEN, V2_MARKER, checksum, decode_unsigned, layout
from firmware_bridge.readings import CompassReading, GpsFix, ImuReading

_STRUCT_TO_NUMPY = {"Q": "<u8", "q": "<i8", "I": "<u4", "i": "<i4", "H": "<u2", "h": "<i2", "B": "u1", "b": "i1",
                    "f": "<f4", "d": "<f8"}  # fmt: skip
_CRC_LEN = 2


def _wire_dtype(message_class: type) -> np.dtype:
    """A flat message's payload as a numpy record, fields named and ordered as on the wire."""
    codes = re.findall(r"(\d*)([A-Za-z])", message_class.unpacker.format.lstrip("<"))
    if any(count for count, _ in codes) or len(codes) != len(message_class.ordered_fieldnames):
        raise ValueError(f"{message_class.msgname}: only flat layouts are decoded column-wise")
    return np.dtype([(name, _STRUCT_TO_NUMPY[code]) for name, (_, code) in
                     zip(message_class.ordered_fieldnames, codes, strict=True)])  # fmt: skip


class Row(NamedTuple):
    """One reading's row in a `Columns` store: `key` = (reading type, which optional fields it has), as
    `sitl.vehicles.reading_batches` groups readings; `index` into that key's columns."""

    key: tuple
    index: int


class Columns:
    """The rows of the column-wise decoded readings, per key (`Row.key`), added a block of rows at a time;
    `take` builds one reading of some of them."""

    def __init__(self) -> None:
        self._blocks: dict[tuple, list[dict[str, np.ndarray]]] = {}
        self._sizes: dict[tuple, int] = {}
        self._joined: dict[tuple, dict[str, np.ndarray]] = {}

    def add(self, key: tuple, **columns: np.ndarray) -> list[Row]:
        """Rows for the given columns (each with one entry per row, `agents` first); returns their `Row`s."""
        first = self._sizes.get(key, 0)
        count = len(columns["agents"])
        self._blocks.setdefault(key, []).append(columns)
        self._sizes[key] = first + count
        self._joined.pop(key, None)
        return [Row(key, i) for i in range(first, first + count)]

    def take(self, key: tuple, indices: Sequence[int]) -> object:
        """One reading of type key[0] holding rows `indices` in that order (as `feed` gives them one by one)."""
        joined = self._joined.get(key)
        if joined is None:
            blocks = self._blocks[key]
            joined = self._joined[key] = {name: np.concatenate([b[name] for b in blocks]) for name in blocks[0]}
        picked = np.asarray(indices, dtype=np.intp)
        return key[0](**{name: column[picked] for name, column in joined.items()})


# A frame found in a chunk: (decoder index, start, length, message id, source system, source component).
_Frame = tuple[int, int, int, int, int, int]


def checked_frames(chunk: bytes, decoder: int, out: list[_Frame]) -> bool:
    """Append the frames of one chunk; False when it is anything but whole, unsigned, known, checked MAVLink 2
    frames back to back (then `feed`'s own framing must judge it)."""
    pos, n = 0, len(chunk)
    while pos < n:
        if n - pos < V2_HEADER_LEN or chunk[pos] != V2_MARKER or chunk[pos + 2] or chunk[pos + 3]:
            return False
        end = pos + V2_HEADER_LEN + chunk[pos + 1] + _CRC_LEN
        if end > n:
            return False
        msg_id = chunk[pos + 7] | (chunk[pos + 8] << 8) | (chunk[pos + 9] << 16)
        spec = layout(msg_id)
        if spec is None:
            return False
        crc = checksum(spec._crc_extra_byte, checksum(chunk[pos + 1 : end - _CRC_LEN]))
        if crc != chunk[end - 2] | (chunk[end - 1] << 8):
            return False
        out.append((decoder, pos, end - pos, msg_id, chunk[pos + 5], chunk[pos + 6]))
        pos = end
    return True


def _fast_path(decoder: TelemetryDecoder) -> bool:
    return (
        not decoder._buf
        and decoder.message_hook is None
        and decoder.source_system is not None
        and decoder._mav.signing.secret_key is None
    )


def decode_batch(
    decoders: Sequence[TelemetryDecoder], chunks: Sequence[bytes]
) -> tuple[list[list[object]], Columns] | None:
    """Feed chunks[k] to decoders[k], all at once. Returns, per decoder, what its `feed` would return, in the
    same order, except that readings of the column-wise types are `Row`s of the returned `Columns`; None
    (nothing fed, nothing counted) when some chunk or decoder is off the fast path (module docstring)."""
    frames: list[_Frame] = []
    for k, (decoder, chunk) in enumerate(zip(decoders, chunks, strict=True)):
        if chunk and not (_fast_path(decoder) and checked_frames(chunk, k, frames)):
            return None
    for decoder, chunk in zip(decoders, chunks, strict=True):
        if chunk:  # `feed` is not called for nothing
            decoder.counters.bytes_fed += len(chunk)
            decoder.counters.pending_bytes = 0
    times: list[float | None] = [None] * len(decoders)
    believed: list[_Frame] = []
    names = _NAMES
    for frame in frames:
        k, _, length, msg_id, system, component = frame
        decoder = decoders[k]
        c = decoder.counters
        c.received += 1
        c.frame_bytes += length
        c.decoded += 1
        name = names[msg_id]
        c.by_type[name] = c.by_type.get(name, 0) + 1
        if system != decoder.source_system:
            c.other_system += 1
        elif decoder.source_component is not None and component != decoder.source_component:
            c.other_component += 1
        else:
            if times[k] is None:
                times[k] = float(decoder.clock())
            believed.append(frame)
    columns = Columns()
    slots = _decode_columnar(decoders, chunks, believed, times, columns)
    per_decoder: list[list[object]] = [[] for _ in decoders]
    for frame, slot in zip(believed, slots, strict=True):
        k = frame[0]
        if slot is _NOT_COLUMNAR:
            slot = _decode_one(decoders[k], chunks[k], frame, times[k])
        if slot is not None:
            per_decoder[k].append(slot)
    return per_decoder, columns


_NAMES = {msg_id: cls.msgname for msg_id, cls in mavlink.mavlink_map.items()}
_NOT_COLUMNAR = object()


def _decode_one(decoder: TelemetryDecoder, chunk: bytes, frame: _Frame, t_s: float) -> object:
    """A frame of a type read one message at a time (HEARTBEAT, battery, acks, wheels): as `feed` reads it."""
    _, start, length, msg_id, _, _ = frame
    convert = _CONVERTERS.get(_NAMES[msg_id])
    if convert is None or msg_id in decoder._unread:
        return None
    raw = bytearray(chunk[start : start + length])
    crc = raw[-2] | (raw[-1] << 8)
    try:  # a checked frame of a known layout always decodes; whatever a converter refuses gives no reading
        return convert(decoder, decode_unsigned(raw, layout(msg_id), crc), t_s)
    except Exception:  # never raised into a fleet's step
        return None


def _decode_columnar(
    decoders: Sequence[TelemetryDecoder],
    chunks: Sequence[bytes],
    believed: list[_Frame],
    times: list[float | None],
    columns: Columns,
) -> list[object]:
    """Per believed frame: a `Row`, None (no reading) or _NOT_COLUMNAR (to be read one at a time)."""
    slots: list[object] = [_NOT_COLUMNAR] * len(believed)
    by_type: dict[int, list[int]] = {}
    for i, (k, _, _, msg_id, _, _) in enumerate(believed):
        if msg_id in _COLUMNAR:
            if msg_id in decoders[k]._unread:
                slots[i] = None
            else:
                by_type.setdefault(msg_id, []).append(i)
    records_of: dict[int, np.ndarray] = {}
    boot_times: dict[int, list[float]] = {}  # per decoder, its messages' times of sending (`feed`'s clock samples)
    for msg_id, members in by_type.items():
        dtype = _DTYPES[msg_id]
        size = dtype.itemsize
        payloads = []
        for i in members:
            k, start, length, _, _, _ = believed[i]
            payloads.append(chunks[k][start + V2_HEADER_LEN : start + length - _CRC_LEN][:size].ljust(size, b"\0"))
        records = records_of[msg_id] = np.frombuffer(b"".join(payloads), dtype=dtype)
        if msg_id in SENT_TIME_FIELDS:
            field_name, unit = SENT_TIME_FIELDS[msg_id]
            for i, boot_s in zip(members, (records[field_name] * unit).tolist(), strict=True):
                boot_times.setdefault(believed[i][0], []).append(boot_s)
    for k, boot_s in boot_times.items():
        decoders[k].note_boot_times(boot_s, times[k])
    for msg_id, members in by_type.items():
        records = records_of[msg_id]
        owners = [believed[i][0] for i in members]
        agents = np.array([decoders[k].agent for k in owners], dtype=np.intp)
        if msg_id in SENT_TIME_FIELDS:  # dated when sent (`TelemetryDecoder.sent_time`), each row as `feed` does
            stamps = zip(owners, records[SENT_TIME_FIELDS[msg_id][0]].tolist(), strict=True)
            t_s = np.array([decoders[k].sent_time(sent_stamp_us(msg_id, stamp), times[k]) for k, stamp in stamps])
        else:
            t_s = np.array([times[k] for k in owners], dtype=np.float64)
        rows = _COLUMN_CONVERTERS[msg_id](records, agents, t_s, [decoders[k] for k in owners], columns)
        for i, row in zip(members, rows, strict=True):
            slots[i] = row
    return slots


def _place(rows: list[object], where: np.ndarray, placed: list[Row]) -> None:
    """Put `placed` (one per True of `where`, in order) into `rows` at the True positions."""
    for i, row in zip(np.flatnonzero(where), placed, strict=True):
        rows[i] = row


def _gps_raw_int(records, agents, t_s, decoders, columns: Columns) -> list[object]:
    """TelemetryDecoder._gps_raw_int, per row: lat, lon deg; velocity (east, north) m/s from speed and course
    (the trigonometry in Python's math, as the decoder does it, for the same last bit); a repeated fix (its
    time_usec again, `TelemetryDecoder.fresh_fix`) is not read, each decoder's rows taken in stream order; a
    fix's time is when it was taken (`TelemetryDecoder.fix_time`)."""
    rows: list[object] = [None] * len(records)
    read = records["fix_type"] >= 2  # a fix, and not one already read
    t_s = t_s.copy()
    for j, (fix, stamp) in enumerate(zip(read.tolist(), records["time_usec"].tolist(), strict=True)):
        if not fix:
            decoders[j].counters.no_fix += 1
        elif not decoders[j].fresh_fix(stamp):
            read[j] = False
        else:
            t_s[j] = decoders[j].fix_time(stamp, float(t_s[j]))  # when it was taken
    moving = read & (records["vel"] != UINT16_MAX) & (records["cog"] != UINT16_MAX)
    lat, lon = records["lat"] / 1e7, records["lon"] / 1e7
    h_acc, vel_acc = records["h_acc"], records["vel_acc"]
    accuracy = np.where(h_acc > 0, np.minimum(h_acc / 1000.0, MAX_GPS_ACCURACY_M), np.nan)
    speed_accuracy = np.where(vel_acc > 0, np.minimum(vel_acc / 1000.0, MAX_GPS_SPEED_ACCURACY_MPS), np.nan)
    if moving.any():
        speed = records["vel"][moving] / 100.0
        course = [math.radians(c / 100.0) for c in records["cog"][moving].tolist()]
        velocity = np.array([(s * math.sin(c), s * math.cos(c)) for s, c in zip(speed.tolist(), course, strict=True)])
        placed = columns.add((GpsFix, (True,) * 7), agents=agents[moving], t_s=t_s[moving], lat_deg=lat[moving],
                             lon_deg=lon[moving], velocity_mps=velocity, accuracy_m=accuracy[moving],
                             speed_accuracy_mps=speed_accuracy[moving])  # fmt: skip
        _place(rows, moving, placed)
    still = read & ~moving
    if still.any():
        placed = columns.add((GpsFix, (True, True, True, True, False, True, True)), agents=agents[still],
                             t_s=t_s[still], lat_deg=lat[still], lon_deg=lon[still], accuracy_m=accuracy[still],
                             speed_accuracy_mps=speed_accuracy[still])  # fmt: skip
        _place(rows, still, placed)
    return rows


def _global_position_int(records, agents, t_s, decoders, columns: Columns) -> list[object]:
    """TelemetryDecoder._global_position_int (the decoder wants the fused position): velocity from NED cm/s."""
    rows: list[object] = [None] * len(records)
    known = (records["lat"] != 0) | (records["lon"] != 0)
    for j in np.flatnonzero(~known):
        decoders[j].counters.no_fix += 1  # the autopilot has no position (yet)
    if known.any():
        r = records[known]
        velocity = np.column_stack((r["vy"] / 100.0, r["vx"] / 100.0))  # NED x north, y east -> east, north
        placed = columns.add((GpsFix, (True,) * 5 + (False, False)), agents=agents[known], t_s=t_s[known],
                             lat_deg=r["lat"] / 1e7, lon_deg=r["lon"] / 1e7, velocity_mps=velocity)  # fmt: skip
        _place(rows, known, placed)
    return rows


def _attitude(records, agents, t_s, decoders, columns: Columns) -> list[object]:
    """TelemetryDecoder._attitude: heading = wrap(pi/2 - yaw), the decoder's arithmetic (numpy's remainder is
    Python's float modulo); no reading where the yaw is not finite."""
    rows: list[object] = [None] * len(records)
    yaw = records["yaw"].astype(np.float64)
    finite = np.isfinite(yaw)
    if finite.any():
        heading = np.pi - np.remainder(np.pi - (np.pi / 2.0 - yaw[finite]), 2.0 * np.pi)
        r = records[finite]
        rates = np.column_stack((r["rollspeed"], r["pitchspeed"], r["yawspeed"])).astype(np.float64)
        placed = columns.add((CompassReading, (True,) * 6), agents=agents[finite], t_s=t_s[finite],
                             heading_rad=heading, roll_rad=r["roll"].astype(np.float64),
                             pitch_rad=r["pitch"].astype(np.float64), body_rates_frd_radps=rates)  # fmt: skip
        _place(rows, finite, placed)
    return rows


def _imu(records, agents, t_s, decoders, columns: Columns) -> list[object]:
    """TelemetryDecoder._imu: body acceleration (x forward, y left; z up) m/s^2 from mG, rates (yaw CCW) from
    mrad/s."""
    g = STANDARD_GRAVITY_MPS2 / 1000.0
    accel = np.column_stack((records["xacc"] * g, -records["yacc"].astype(np.int64) * g))
    rate = -records["zgyro"].astype(np.int64) / 1000.0
    gyro_xy = np.column_stack((records["xgyro"] / 1000.0, -records["ygyro"].astype(np.int64) / 1000.0))
    return columns.add((ImuReading, (True,) * 6), agents=agents, t_s=t_s, accel_body_mps2=accel, gyro_z_radps=rate,
                       accel_z_mps2=-records["zacc"].astype(np.int64) * g, gyro_xy_radps=gyro_xy)  # fmt: skip


_COLUMN_CONVERTERS = {
    mavlink.MAVLINK_MSG_ID_GPS_RAW_INT: _gps_raw_int,
    mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: _global_position_int,
    mavlink.MAVLINK_MSG_ID_ATTITUDE: _attitude,
    mavlink.MAVLINK_MSG_ID_SCALED_IMU: _imu,
    mavlink.MAVLINK_MSG_ID_RAW_IMU: _imu,
}
# The types decoded column-wise, and their payloads as numpy records.
_COLUMNAR = frozenset(_COLUMN_CONVERTERS)
_DTYPES = {msg_id: _wire_dtype(mavlink.mavlink_map[msg_id]) for msg_id in _COLUMNAR}
