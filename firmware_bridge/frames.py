"""MAVLink 2 frames packed and unpacked without pymavlink's per-message overhead, byte for byte as pymavlink does.

pymavlink builds a header object and a message object for every frame, and
computes each checksum twice on receipt (once in our framing, once in its own
decode). In a lockstep fleet that is most of the cost of the full stack: 45 vessels
exchange about 430 frames per step. The layouts come from pymavlink's own dialect
classes (field order on the wire, `struct` formats, CRC_EXTRA), so nothing about
the protocol is written twice; tests/test_frames.py checks every frame against
pymavlink's `pack` and every decoded message against its `decode`.

What differs is only the work done: one `struct` call for the payload and one for
the header, the checksum once (CRC-16/MCRF4XX through fastcrc, as pymavlink uses
when fastcrc is installed), and the message object filled in directly.
"""

from __future__ import annotations

import inspect
import operator
import struct
from collections.abc import Sequence
from typing import Any

from fastcrc import crc16
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_bridge.tlog import split_frames

V2_MARKER = 0xFD
# marker, payload length, incompat flags, compat flags, seq, system, component, message id low 16 bits, high 8
V2_HEADER = struct.Struct("<BBBBBBBHB")
V2_HEADER_LEN = V2_HEADER.size
SIGNED_FLAG = mavlink.MAVLINK_IFLAG_SIGNED
checksum = crc16.mcrf4xx  # CRC-16/MCRF4XX (MAVLink's "X.25"): checksum(data, seed=0xFFFF) -> int


def frame_checksum(frame: bytes | bytearray, crc_end: int, crc_extra: int) -> int:
    """The checksum a frame must carry: CRC over its bytes 1..crc_end (header after the marker, payload) and
    the message's CRC_EXTRA byte."""
    return checksum(bytes((crc_extra,)), checksum(bytes(frame[1:crc_end])))


class MessageLayout:
    """One message type's wire layout, taken from its pymavlink class: how the arguments of its `*_encode` (in
    declaration order) become the payload's values (in wire order: sorted by size, arrays flattened), and
    back."""

    def __init__(self, message_class: type) -> None:
        self.message_class = message_class
        self.msg_id: int = message_class.id
        self.crc_extra: int = message_class.crc_extra
        self._crc_extra_byte = bytes((self.crc_extra,))
        self._id_fields = (self.msg_id & 0xFFFF, self.msg_id >> 16)  # the header's message id, low 16 and high 8 bits
        self.struct: struct.Struct = message_class.unpacker
        self.name: str = message_class.msgname
        names = list(message_class.fieldnames)
        types = list(message_class.fieldtypes)  # declaration order
        # Wire order: for each field on the wire, its declaration index and how many struct values it takes
        # (a char array is one bytes value; any other array one value per element). pymavlink lists
        # array_lengths in wire order, fieldtypes in declaration order.
        self._wire: list[tuple[int, int]] = []
        self._strings: list[int] = []
        for wire_name, length in zip(message_class.ordered_fieldnames, message_class.array_lengths, strict=True):
            i = names.index(wire_name)
            if length and types[i] == "char":
                self._strings.append(i)
            self._wire.append((i, length if length and types[i] != "char" else 0))
        self._flat = all(count == 0 for _, count in self._wire)
        self._order = [i for i, _ in self._wire]
        encode = getattr(mavlink.MAVLink, f"{self.name.lower()}_encode", message_class.__init__)
        parameters = list(inspect.signature(encode).parameters.values())[1:]  # defaults as `*_encode` has them
        self._defaults = [p.default for p in parameters]
        self._n_fields = len(names)
        self._tails: dict[int, tuple[Any, ...]] = {}
        # Wire-order values of a flat layout in one C call (a 1-field itemgetter would give the value itself).
        getter = operator.itemgetter(*self._order)
        self._wire_getter = getter if len(self._order) > 1 else (lambda args: (getter(args),))

    def values(self, args: Sequence[Any]) -> Sequence[Any]:
        """The payload's struct values from the `*_encode` arguments (declaration order; trailing ones with
        defaults may be left out)."""
        if len(args) < self._n_fields:
            args = (*args, *self._tail(len(args)))
        if self._flat:
            return self._wire_getter(args)
        out: list[Any] = []
        for i, count in self._wire:
            if count:
                out.extend(args[i][:count])
            else:
                out.append(args[i])
        return out

    def _tail(self, given: int) -> tuple[Any, ...]:
        """The defaults of the arguments after the first `given` (checked once per count: all must have one)."""
        tail = self._tails.get(given)
        if tail is None:
            tail = tuple(self._defaults[given:])
            if any(a is inspect.Parameter.empty for a in tail):
                raise TypeError(f"{self.name}: {self._n_fields} fields, {given} given")
            self._tails[given] = tail
        return tail

    def payload(self, args: Sequence[Any]) -> bytes:
        """The MAVLink 2 payload: packed, trailing zero bytes removed (at least one byte is kept)."""
        return self.struct.pack(*self.values(args)).rstrip(b"\0") or b"\0"

    def frame(self, args: Sequence[Any], seq: int, system_id: int, component_id: int) -> bytes:
        """`pack_frame` of this message type: `values`, `payload` and the header in one call (the telemetry hot
        path: a lockstep fleet of 45 vehicles packs about 430 frames per step)."""
        given = len(args)
        if given < self._n_fields:
            args = (*args, *(self._tails.get(given) or self._tail(given)))
        values = self._wire_getter(args) if self._flat else self.values(args)
        payload = self.struct.pack(*values).rstrip(b"\0") or b"\0"
        body = V2_HEADER.pack(V2_MARKER, len(payload), 0, 0, seq, system_id, component_id, *self._id_fields) + payload
        return body + checksum(body[1:] + self._crc_extra_byte).to_bytes(2, "little")

    def fields(self, payload: bytes | bytearray) -> list[Any]:
        """Declaration-order field values from a (possibly zero-trimmed) payload, as pymavlink's decode gives
        them: arrays as lists, char arrays as bytes without trailing NULs."""
        size = self.struct.size
        raw = bytes(payload[:size])
        if len(raw) < size:
            raw += bytes(size - len(raw))
        flat = self.struct.unpack(raw)
        out: list[Any] = [None] * self._n_fields
        if self._flat:
            for value, i in zip(flat, self._order, strict=True):
                out[i] = value
        else:
            k = 0
            for i, count in self._wire:
                if count:
                    out[i] = list(flat[k : k + count])
                    k += count
                else:
                    out[i] = flat[k]
                    k += 1
        for i in self._strings:
            out[i] = out[i].rstrip(b"\0")
        return out


LAYOUTS: dict[int, MessageLayout] = {}  # by message id, as `layout` builds them


def layout(msg_id: int) -> MessageLayout | None:
    """The layout of a message id the dialect knows (None otherwise); built once per id."""
    found = LAYOUTS.get(msg_id)
    if found is None:
        message_class = mavlink.mavlink_map.get(msg_id)
        if message_class is None:
            return None
        found = LAYOUTS[msg_id] = MessageLayout(message_class)
    return found


def pack_frame(message_class: type, args: Sequence[Any], seq: int, system_id: int, component_id: int) -> bytes:
    """One unsigned MAVLink 2 frame of `message_class` from its `*_encode` arguments: the bytes pymavlink's
    `message.pack(mav)` gives with the same sequence number and source."""
    return layout(message_class.id).frame(args, seq, system_id, component_id)


def renumber(data: bytes | bytearray, first_seq: int) -> tuple[bytes, int]:
    """The frames of `data` numbered first_seq, first_seq + 1, ... (mod 256), their checksums made again; returns
    (the frames, the next number). What a link numbers at send time, as ArduPilot numbers each channel's frames
    (one counter per link, taken when the frame is finalised): a vehicle that answers several peers gives each
    its own unbroken count. Signed frames (the signature covers the number) and frames of a message id the
    dialect does not know are passed on as they are and take no number; bytes outside a whole frame are dropped
    (`split_frames`)."""
    out = bytearray()
    seq = first_seq & 0xFF
    for frame in split_frames(data):
        v2 = frame[0] == V2_MARKER
        spec = layout(int.from_bytes(frame[7:10], "little") if v2 else frame[5])
        if spec is None or (v2 and frame[2] & SIGNED_FLAG):
            out += frame
            continue
        body = bytearray(frame[:-2])
        body[4 if v2 else 2] = seq
        seq = (seq + 1) & 0xFF
        out += body
        out += frame_checksum(body, len(body), spec.crc_extra).to_bytes(2, "little")
    return bytes(out), seq


class FrameHeader:
    """A checked frame's identity without its fields, for a message its receiver does not read (it is still
    counted and its source still judged): what pymavlink's message answers to get_type, get_srcSystem,
    get_srcComponent and get_msgId."""

    __slots__ = ("_component", "_msg_id", "_name", "_system")

    def __init__(self, name: str, msg_id: int, system: int, component: int) -> None:
        self._name, self._msg_id, self._system, self._component = name, msg_id, system, component

    def get_type(self) -> str:
        return self._name

    def get_msgId(self) -> int:  # noqa: N802 - pymavlink's name
        return self._msg_id

    def get_srcSystem(self) -> int:  # noqa: N802
        return self._system

    def get_srcComponent(self) -> int:  # noqa: N802
        return self._component


def decode_unsigned(frame: bytearray, spec: MessageLayout, crc: int) -> object:
    """The pymavlink message of a checked, unsigned MAVLink 2 frame, with the attributes pymavlink's `decode`
    sets (header, payload, msgbuf, crc); `crc` is the frame's checksum, already verified."""
    mlen = frame[1]
    message = spec.message_class(*spec.fields(frame[V2_HEADER_LEN : V2_HEADER_LEN + mlen]))
    message._msgbuf = frame
    message._payload = frame[6:-2]  # sic: pymavlink's decode slices from 6 for either header length
    message._crc = crc
    message._header = mavlink.MAVLink_header(spec.msg_id, frame[2], frame[3], mlen, frame[4], frame[5], frame[6])
    return message
