"""Many vehicles' telemetry decoded at once: the readings `TelemetryDecoder.feed` gives, with numpy per message type.

Why: a lockstep fleet hands each of its 45 vessels about ten MAVLink frames a
step, and decoding them one message object at a time was a fifth of the full
stack's time. Here every vessel's bytes are framed and checked as before (one
checksum per frame), then the frames of each high-volume type (GPS_RAW_INT,
GLOBAL_POSITION_INT, ATTITUDE, SCALED_IMU, RAW_IMU) are unpacked for all vessels
in one numpy call and converted column-wise, and a reading is only built when
rows of one kind are handed over together (`Columns.take`). SYS_STATUS and
BATTERY_STATUS are unpacked and converted column-wise too, each row its own
`Battery` (a link keeps the latest); HEARTBEAT is read from its payload's fields
without a pymavlink message object; other types as `feed` reads them.

What it guarantees: for well-formed input (every chunk a run of whole, unsigned
MAVLink 2 frames of known ids with good checksums, nothing pending in any
decoder, no message hook, a known source system) the counters and the readings
are exactly those of `feed` per decoder; tests/test_batch_decoder.py checks this
on random telemetry. Anything else (noise, a partial frame, a signed link) makes
`decode_batch` return None before it touches a decoder, and the caller feeds
the chunks one by one as before.
"""

from __future__ import annotations

import functools
import math
import operator
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
    Battery,
    TelemetryDecoder,
    heartbeat_reading,
    sent_stamp_us,
)
from firmware_bridge.frames import V2_HEADER, V2_HEADER_LEN, V2_MARKER, checksum, decode_unsigned, layout
from firmware_bridge.readings import CompassReading, GpsFix, ImuReading

_STRUCT_TO_NUMPY = {"Q": "<u8", "q": "<i8", "I": "<u4", "i": "<i4", "H": "<u2", "h": "<i2", "B": "u1", "b": "i1",
                    "f": "<f4", "d": "<f8"}  # fmt: skip
_CRC_LEN = 2


def _wire_dtype(message_class: type) -> np.dtype:
    """A message's payload as a numpy record, fields named and ordered as on the wire (a numeric array as a
    sub-array)."""
    codes = re.findall(r"(\d*)([A-Za-z])", message_class.unpacker.format.lstrip("<"))
    if "s" in (code for _, code in codes) or len(codes) != len(message_class.ordered_fieldnames):
        raise ValueError(f"{message_class.msgname}: only numeric layouts are decoded column-wise")
    return np.dtype([(name, _STRUCT_TO_NUMPY[code], (int(count),)) if count else (name, _STRUCT_TO_NUMPY[code])
                     for name, (count, code) in zip(message_class.ordered_fieldnames, codes, strict=True)])  # fmt: skip


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
_CRC_EXTRA = {msg_id: bytes((cls.crc_extra,)) for msg_id, cls in mavlink.mavlink_map.items()}  # as `layout` has it


def checked_frames(chunk: bytes, decoder: int, out: list[_Frame]) -> bool:
    """Append the frames of one chunk; False when it is anything but whole, unsigned, known, checked MAVLink 2
    frames back to back (then `feed`'s own framing must judge it)."""
    pos, n = 0, len(chunk)
    crc_extra = _CRC_EXTRA
    unpack_header = V2_HEADER.unpack_from
    while pos < n:
        if n - pos < V2_HEADER_LEN:
            return False
        marker, payload_len, incompat, compat, _, system, component, id_low, id_high = unpack_header(chunk, pos)
        if marker != V2_MARKER or incompat or compat:
            return False
        end = pos + V2_HEADER_LEN + payload_len + _CRC_LEN
        msg_id = id_low | (id_high << 16)
        extra = crc_extra.get(msg_id)
        if end > n or extra is None:
            return False
        if checksum(extra, checksum(chunk[pos + 1 : end - _CRC_LEN])) != chunk[end - 2] | (chunk[end - 1] << 8):
            return False
        out.append((decoder, pos, end - pos, msg_id, system, component))
        pos = end
    return True


def _fast_path(decoder: TelemetryDecoder) -> bool:
    return (
        not decoder._buf
        and decoder.message_hook is None
        and decoder.source_system is not None
        and decoder._mav.signing.secret_key is None
    )


# How a decoder reads a believed frame (`_routes`): not at all, column-wise, or one at a time (`_decode_one`).
_UNREAD, _COLUMN, _ONE_BY_ONE = range(3)


def decode_batch(
    decoders: Sequence[TelemetryDecoder], chunks: Sequence[bytes]
) -> tuple[list[list[object]], Columns] | None:
    """Feed chunks[k] to decoders[k], all at once. Returns, per decoder, what its `feed` would return, in the
    same order, except that readings of the column-wise types are `Row`s of the returned `Columns`; None
    (nothing fed, nothing counted) when some chunk or decoder is off the fast path (module docstring)."""
    frames: list[_Frame] = []
    ends: list[int] = []  # per decoder, where its frames end in `frames`
    for k, (decoder, chunk) in enumerate(zip(decoders, chunks, strict=True)):
        if chunk and not (_fast_path(decoder) and checked_frames(chunk, k, frames)):
            return None
        ends.append(len(frames))
    # Counted as `feed` counts, each decoder's frames in stream order; each believed frame read gets its place in
    # its decoder's readings (filled below; None where it gives no reading).
    per_decoder: list[list[object]] = [[] for _ in decoders]
    times: list[float | None] = [None] * len(decoders)
    column_wise: dict[int, list[tuple[int, int, _Frame]]] = {}  # per message id: (decoder, place, frame)
    one_by_one: list[tuple[int, int, _Frame]] = []
    names = _NAMES
    first = 0
    for k, (decoder, chunk, last) in enumerate(zip(decoders, chunks, ends, strict=True)):
        if first == last:
            continue  # `feed` is not called for nothing (and a chunk on the fast path holds a frame)
        c = decoder.counters
        c.bytes_fed += len(chunk)
        c.pending_bytes = 0
        c.received += last - first
        c.decoded += last - first
        c.frame_bytes += len(chunk)  # the frames are the whole chunk
        by_type = c.by_type
        system, component = decoder.source_system, decoder.source_component
        routes = _routes(decoder._unread)
        readings = per_decoder[k]
        believed = False
        for i in range(first, last):
            frame = frames[i]
            msg_id = frame[3]
            name = names[msg_id]
            by_type[name] = by_type.get(name, 0) + 1
            if frame[4] != system:
                c.other_system += 1
            elif component is not None and frame[5] != component:
                c.other_component += 1
            else:
                believed = True
                route = routes[msg_id]
                if route == _COLUMN:
                    column_wise.setdefault(msg_id, []).append((k, len(readings), frame))
                    readings.append(None)
                elif route == _ONE_BY_ONE:
                    one_by_one.append((k, len(readings), frame))
                    readings.append(None)
        if believed:
            times[k] = float(decoder.clock())
        first = last
    columns = Columns()
    _decode_columnar(decoders, chunks, column_wise, times, columns, per_decoder)
    for k, place, frame in one_by_one:  # after the clock samples of the column-wise types, as `feed` orders them
        per_decoder[k][place] = _decode_one(decoders[k], chunks[k], frame, times[k])
    for k, readings in enumerate(per_decoder):
        if None in readings:
            per_decoder[k] = [r for r in readings if r is not None]
    return per_decoder, columns


_NAMES = {msg_id: cls.msgname for msg_id, cls in mavlink.mavlink_map.items()}


class _FieldReader:
    """Some fields of one message type straight from its payload (as pymavlink's decode gives their values; an
    array as a tuple), without a message object."""

    def __init__(self, message_class: type, *names: str) -> None:
        types = dict(zip(message_class.fieldnames, message_class.fieldtypes, strict=True))
        where, at = {}, 0
        for name, length in zip(message_class.ordered_fieldnames, message_class.array_lengths, strict=True):
            count = length if length and types[name] != "char" else 1  # a char array is one struct value
            where[name] = slice(at, at + count) if length and types[name] != "char" else at
            at += count
        if len(names) < 2:
            raise ValueError("a reader takes two fields or more")
        self.struct = message_class.unpacker
        self._get = operator.itemgetter(*(where[name] for name in names))

    def __call__(self, payload: bytes) -> tuple:
        size = self.struct.size
        return self._get(self.struct.unpack(payload[:size].ljust(size, b"\0")))


_HEARTBEAT = _FieldReader(
    mavlink.MAVLink_heartbeat_message, "type", "autopilot", "base_mode", "custom_mode", "system_status"
)


def _heartbeat(decoder: TelemetryDecoder, payload: bytes, frame: _Frame, t_s: float) -> object:
    return heartbeat_reading(t_s, frame[4], frame[5], *_HEARTBEAT(payload))


# The types a vehicle sends that `TelemetryDecoder` reads one at a time, read from their fields alone (the same
# arithmetic: the decoder's converter calls the same function of the fields).
_FIELD_READERS = {mavlink.MAVLINK_MSG_ID_HEARTBEAT: _heartbeat}


def _decode_one(decoder: TelemetryDecoder, chunk: bytes, frame: _Frame, t_s: float) -> object:
    """A frame of a type read one at a time (HEARTBEAT, battery, acks, wheels): the reading `feed` makes of it,
    or None."""
    _, start, length, msg_id, _, _ = frame
    read = _FIELD_READERS.get(msg_id)
    if read is not None:
        return read(decoder, chunk[start + V2_HEADER_LEN : start + length - _CRC_LEN], frame, t_s)
    raw = bytearray(chunk[start : start + length])
    crc = raw[-2] | (raw[-1] << 8)
    try:  # a checked frame of a known layout always decodes; whatever a converter refuses gives no reading
        return _CONVERTERS[_NAMES[msg_id]](decoder, decode_unsigned(raw, layout(msg_id), crc), t_s)
    except Exception:  # never raised into a fleet's step
        return None


@functools.cache
def _routes(unread: frozenset[int]) -> dict[int, int]:
    """How a decoder that does not read the message ids `unread` reads each message id (`_UNREAD`...)."""
    routes = {}
    for msg_id, cls in mavlink.mavlink_map.items():
        if msg_id in unread or cls.msgname not in _CONVERTERS:
            routes[msg_id] = _UNREAD
        else:
            routes[msg_id] = _COLUMN if msg_id in _COLUMNAR else _ONE_BY_ONE
    return routes


def _decode_columnar(
    decoders: Sequence[TelemetryDecoder],
    chunks: Sequence[bytes],
    column_wise: dict[int, list[tuple[int, int, _Frame]]],
    times: list[float | None],
    columns: Columns,
    per_decoder: list[list[object]],
) -> None:
    """The believed frames of the column-wise types, (decoder, place, frame) per message id: each decoder's
    clock samples noted, then each frame's `Row` (or None: no reading) put in its place in per_decoder."""
    records_of: dict[int, np.ndarray] = {}
    boot_times: dict[int, list[float]] = {}  # per decoder, its messages' times of sending (`feed`'s clock samples)
    for msg_id, members in column_wise.items():
        dtype = _DTYPES[msg_id]
        size = dtype.itemsize
        payloads = [
            chunks[k][start + V2_HEADER_LEN : start + length - _CRC_LEN][:size].ljust(size, b"\0")
            for k, _, (_, start, length, _, _, _) in members
        ]
        records = records_of[msg_id] = np.frombuffer(b"".join(payloads), dtype=dtype)
        if msg_id in SENT_TIME_FIELDS:
            field_name, unit = SENT_TIME_FIELDS[msg_id]
            for (k, _, _), boot_s in zip(members, (records[field_name] * unit).tolist(), strict=True):
                boot_times.setdefault(k, []).append(boot_s)
    for k, boot_s in boot_times.items():
        decoders[k].note_boot_times(boot_s, times[k])
    for msg_id, members in column_wise.items():
        records = records_of[msg_id]
        owners = [k for k, _, _ in members]
        agents = np.array([decoders[k].agent for k in owners], dtype=np.intp)
        if msg_id in SENT_TIME_FIELDS:  # dated when sent (`TelemetryDecoder.sent_time`), each row as `feed` does
            stamps = records[SENT_TIME_FIELDS[msg_id][0]].astype(np.int64) * sent_stamp_us(msg_id, 1)  # exact: us
            sent = zip(owners, stamps.tolist(), strict=True)
            t_s = np.array([decoders[k].sent_time(stamp_us, times[k]) for k, stamp_us in sent])
        else:
            t_s = np.array([times[k] for k in owners], dtype=np.float64)
        rows = _COLUMN_CONVERTERS[msg_id](records, agents, t_s, [decoders[k] for k in owners], columns)
        for (k, place, _), row in zip(members, rows, strict=True):
            per_decoder[k][place] = row


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


def _sys_status(records, agents, t_s, decoders, columns: Columns) -> list[object]:
    """TelemetryDecoder.sys_status_battery, per row: voltage V from mV, remaining %; NaN where unknown."""
    raw = records["voltage_battery"]
    voltage = np.where(raw == UINT16_MAX, np.nan, raw / 1000.0)
    return _batteries(agents, t_s, voltage, records["battery_remaining"])


def _battery_status(records, agents, t_s, decoders, columns: Columns) -> list[object]:
    """TelemetryDecoder.battery_status_battery, per row: the sum of the reported cells (V; the sum in integers,
    as the decoder's), NaN when none is."""
    cells = records["voltages"].astype(np.int64)
    extra = records["voltages_ext"].astype(np.int64)
    reported = cells != UINT16_MAX
    reported_extra = (extra != 0) & (extra != UINT16_MAX)
    total = (cells * reported).sum(axis=1) + (extra * reported_extra).sum(axis=1)
    counted = reported.any(axis=1) | reported_extra.any(axis=1)
    return _batteries(agents, t_s, np.where(counted, total / 1000.0, np.nan), records["battery_remaining"])


def _batteries(agents, t_s, voltage, remaining_pct) -> list[object]:
    """One `Battery` per row, its arrays one-row views of the columns (a link keeps the latest)."""
    remaining = np.where(remaining_pct < 0, np.nan, remaining_pct.astype(np.float64))
    return [
        Battery(agents[j : j + 1], t_s[j : j + 1], voltage[j : j + 1], remaining[j : j + 1]) for j in range(len(agents))
    ]


_COLUMN_CONVERTERS = {
    mavlink.MAVLINK_MSG_ID_SYS_STATUS: _sys_status,
    mavlink.MAVLINK_MSG_ID_BATTERY_STATUS: _battery_status,
    mavlink.MAVLINK_MSG_ID_GPS_RAW_INT: _gps_raw_int,
    mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: _global_position_int,
    mavlink.MAVLINK_MSG_ID_ATTITUDE: _attitude,
    mavlink.MAVLINK_MSG_ID_SCALED_IMU: _imu,
    mavlink.MAVLINK_MSG_ID_RAW_IMU: _imu,
}
# The types decoded column-wise, and their payloads as numpy records.
_COLUMNAR = frozenset(_COLUMN_CONVERTERS)
_DTYPES = {msg_id: _wire_dtype(mavlink.mavlink_map[msg_id]) for msg_id in _COLUMNAR}
