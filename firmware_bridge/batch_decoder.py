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
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_bridge.decoder import (
    _CONVERTERS,
    STANDARD_GRAVITY_MPS2,
    UINT16_MAX,
    TelemetryDecoder,
    heading_from_yaw,
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


# The types decoded column-wise and the reading kind each becomes.
_COLUMNAR = {
    mavlink.MAVLINK_MSG_ID_GPS_RAW_INT: GpsFix,
    mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: GpsFix,
    mavlink.MAVLINK_MSG_ID_ATTITUDE: CompassReading,
    mavlink.MAVLINK_MSG_ID_SCALED_IMU: ImuReading,
    mavlink.MAVLINK_MSG_ID_RAW_IMU: ImuReading,
}
_DTYPES = {msg_id: _wire_dtype(mavlink.mavlink_map[msg_id]) for msg_id in _COLUMNAR}


class Row(NamedTuple):
    """One reading's row in a `Columns` store: `key` = (reading type, which optional fields it has), as
    `sitl.vehicles.reading_batches` groups readings; `index` into that key's columns."""

    key: tuple
    index: int


@dataclass
class _Frame:
    decoder: int
    start: int
    length: int
    msg_id: int


class Columns:
    """The rows of the column-wise decoded readings, per key (`Row.key`); `take` builds one reading of some."""

    def __init__(self) -> None:
        self._columns: dict[tuple, dict[str, list]] = {}

    def add(self, key: tuple, **values) -> Row:
        columns = self._columns.get(key)
        if columns is None:
            columns = self._columns[key] = {name: [] for name in values}
        for name, value in values.items():
            columns[name].append(value)
        return Row(key, len(columns["agents"]) - 1)

    def take(self, key: tuple, indices: Sequence[int]) -> object:
        """One reading of type key[0] holding rows `indices` in that order (as `feed` gives them one by one)."""
        columns = self._columns[key]
        kind = key[0]
        values = {}
        for name, column in columns.items():
            picked = [column[i] for i in indices]
            values[name] = np.array(picked, dtype=np.intp if name == "agents" else np.float64)
        return kind(**values)


def _frames(chunk: bytes, decoder: int, out: list[_Frame]) -> bool:
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
        out.append(_Frame(decoder, pos, end - pos, msg_id))
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
        if chunk and not (_fast_path(decoder) and _frames(chunk, k, frames)):
            return None
    per_decoder: list[list[object]] = [[] for _ in decoders]
    times: list[float | None] = [None] * len(decoders)
    believed: list[_Frame] = []
    for decoder, chunk in zip(decoders, chunks, strict=True):
        if chunk:  # `feed` is not called for nothing
            decoder.counters.bytes_fed += len(chunk)
            decoder.counters.pending_bytes = 0
    for frame in frames:
        decoder, chunk = decoders[frame.decoder], chunks[frame.decoder]
        c = decoder.counters
        c.received += 1
        c.frame_bytes += frame.length
        c.decoded += 1
        name = mavlink.mavlink_map[frame.msg_id].msgname
        c.by_type[name] = c.by_type.get(name, 0) + 1
        system, component = chunk[frame.start + 5], chunk[frame.start + 6]
        if system != decoder.source_system:
            c.other_system += 1
            continue
        if decoder.source_component is not None and component != decoder.source_component:
            c.other_component += 1
            continue
        if times[frame.decoder] is None:
            times[frame.decoder] = float(decoder.clock())
        believed.append(frame)
    columns = Columns()
    slots = _decode_columnar(decoders, chunks, believed, times, columns)
    for frame, slot in zip(believed, slots, strict=True):
        if slot is _NOT_COLUMNAR:
            slot = _decode_one(decoders[frame.decoder], chunks[frame.decoder], frame, times[frame.decoder])
        if slot is not None:
            per_decoder[frame.decoder].append(slot)
    return per_decoder, columns


_NOT_COLUMNAR = object()


def _decode_one(decoder: TelemetryDecoder, chunk: bytes, frame: _Frame, t_s: float) -> object:
    """A frame of a type read one message at a time (HEARTBEAT, battery, acks, wheels): as `feed` reads it."""
    name = mavlink.mavlink_map[frame.msg_id].msgname
    convert = _CONVERTERS.get(name)
    if convert is None or frame.msg_id in decoder._unread:
        return None
    raw = bytearray(chunk[frame.start : frame.start + frame.length])
    crc = raw[-2] | (raw[-1] << 8)
    try:
        return convert(decoder, decode_unsigned(raw, layout(frame.msg_id), crc), t_s)
    except (TypeError, ValueError, OverflowError, AttributeError, IndexError):
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
    for i, frame in enumerate(believed):
        if frame.msg_id in _COLUMNAR and frame.msg_id not in decoders[frame.decoder]._unread:
            by_type.setdefault(frame.msg_id, []).append(i)
        elif frame.msg_id in _COLUMNAR:
            slots[i] = None
    for msg_id, members in by_type.items():
        dtype = _DTYPES[msg_id]
        size = dtype.itemsize
        payloads = []
        for i in members:
            f = believed[i]
            payload = chunks[f.decoder][f.start + V2_HEADER_LEN : f.start + f.length - _CRC_LEN]
            payloads.append(payload[:size].ljust(size, b"\0"))
        records = np.frombuffer(b"".join(payloads), dtype=dtype)
        convert = _COLUMN_CONVERTERS[msg_id]
        for slot, row in zip(members, convert(decoders, believed, members, records, times, columns), strict=True):
            slots[slot] = row
    return slots


def _agent(decoders: Sequence[TelemetryDecoder], frame: _Frame) -> int:
    return int(decoders[frame.decoder].agent)


def _gps_raw_int(decoders, believed, members, records, times, columns) -> list[object]:
    """TelemetryDecoder._gps_raw_int, per row: lat, lon deg; velocity (east, north) m/s from speed and course."""
    lat, lon = records["lat"] / 1e7, records["lon"] / 1e7
    out: list[object] = []
    for j, i in enumerate(members):
        frame = believed[i]
        record = records[j]
        if record["fix_type"] < 2:
            decoders[frame.decoder].counters.no_fix += 1
            out.append(None)
            continue
        vel, cog = int(record["vel"]), int(record["cog"])
        common = {"agents": _agent(decoders, frame), "t_s": times[frame.decoder], "lat_deg": lat[j], "lon_deg": lon[j]}
        if vel != UINT16_MAX and cog != UINT16_MAX:
            speed, course = vel / 100.0, math.radians(cog / 100.0)
            velocity = (speed * math.sin(course), speed * math.cos(course))
            out.append(columns.add((GpsFix, (True, True, True, True, True)), **common, velocity_mps=velocity))
        else:
            out.append(columns.add((GpsFix, (True, True, True, True, False)), **common))
    return out


def _global_position_int(decoders, believed, members, records, times, columns) -> list[object]:
    """TelemetryDecoder._global_position_int (the decoder wants the fused position): velocity from NED cm/s."""
    out: list[object] = []
    for j, i in enumerate(members):
        frame = believed[i]
        record = records[j]
        if record["lat"] == 0 and record["lon"] == 0:
            decoders[frame.decoder].counters.no_fix += 1
            out.append(None)
            continue
        velocity = (int(record["vy"]) / 100.0, int(record["vx"]) / 100.0)
        row = columns.add(
            (GpsFix, (True, True, True, True, True)),
            agents=_agent(decoders, frame),
            t_s=times[frame.decoder],
            lat_deg=int(record["lat"]) / 1e7,
            lon_deg=int(record["lon"]) / 1e7,
            velocity_mps=velocity,
        )
        out.append(row)
    return out


def _attitude(decoders, believed, members, records, times, columns) -> list[object]:
    """TelemetryDecoder._attitude: heading from the yaw (None when the yaw is not finite)."""
    out: list[object] = []
    for j, i in enumerate(members):
        frame = believed[i]
        yaw = float(records[j]["yaw"])
        if not math.isfinite(yaw):
            out.append(None)
            continue
        row = columns.add(
            (CompassReading, (True, True, True)),
            agents=_agent(decoders, frame),
            t_s=times[frame.decoder],
            heading_rad=heading_from_yaw(yaw),
        )
        out.append(row)
    return out


def _imu(decoders, believed, members, records, times, columns) -> list[object]:
    """TelemetryDecoder._imu: body acceleration (x forward, y left) m/s^2 from mG, yaw rate (CCW) from mrad/s."""
    g = STANDARD_GRAVITY_MPS2 / 1000.0
    ax, ay = records["xacc"] * g, -records["yacc"].astype(np.int64) * g
    rate = -records["zgyro"].astype(np.int64) / 1000.0
    out: list[object] = []
    for j, i in enumerate(members):
        frame = believed[i]
        row = columns.add(
            (ImuReading, (True, True, True, True)),
            agents=_agent(decoders, frame),
            t_s=times[frame.decoder],
            accel_body_mps2=(ax[j], ay[j]),
            gyro_z_radps=rate[j],
        )
        out.append(row)
    return out


_COLUMN_CONVERTERS = {
    mavlink.MAVLINK_MSG_ID_GPS_RAW_INT: _gps_raw_int,
    mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: _global_position_int,
    mavlink.MAVLINK_MSG_ID_ATTITUDE: _attitude,
    mavlink.MAVLINK_MSG_ID_SCALED_IMU: _imu,
    mavlink.MAVLINK_MSG_ID_RAW_IMU: _imu,
}
