"""The swarm mesh: an agent's state as a small binary packet, and a broadcast network over any byte link.

Packet (little-endian), at most `MAX_PACKET_BYTES` (the XBee payload limit):

    magic "BoB" (3 B) | version (1 B) | length of the whole packet (1 B) | agent id (uint16)
    | t (float64, s, the sender's clock) | x, y (float32, m) | heading (float32, rad) | vx, vy (float32, m/s)
    | field count (uint8) | per memory field: value count (uint8) + values (float32 each) | CRC-16/CCITT (uint16)

Memory fields are sent in the order of the list every agent of the swarm is
configured with (the union of the memory fields of the swarm's behaviours), so
names never travel. Packets are self-delimiting (length byte, CRC), so the same
format runs over UDP datagrams and over a serial byte stream (an XBee in
transparent mode): the reader resynchronizes after noise and counts it.

Values are checked on decoding (issue 17: a packet must not move a neighbour to
NaN or to the other side of the planet): t finite within +-MAX_TIME_S, x and y
finite within +-MAX_POSITION_M, heading finite within [-pi, pi] (float32
rounding allowed; wrapped into (-pi, pi]), vx and vy finite within
+-MAX_SPEED_MPS, memory values not infinite (NaN is a behaviour's "unknown").
A packet that fails is refused (`PacketValueError`), counted and never returned.
"""

from __future__ import annotations

import binascii
import logging
import math
import struct
from collections.abc import Callable, Sequence

import numpy as np

from bob_autonomy.interfaces import AgentState, Pose

logger = logging.getLogger(__name__)

MAGIC = b"BoB"
VERSION = 1
MAX_PACKET_BYTES = 100
_HEAD = struct.Struct("<3sBBHdfffffB")  # magic, version, length, id, t, x, y, heading, vx, vy, field count
_CRC = struct.Struct("<H")
MAX_TIME_S = 1e10  # |t| of a sender's clock (s): more than 300 years is no clock
MAX_POSITION_M = 1e7  # |x|, |y| from the swarm's origin (m): a quarter of the Earth's circumference
MAX_SPEED_MPS = 100.0  # |vx|, |vy| (m/s): far above any surface vessel or ground robot of the swarm
_HEADING_SLACK = 1e-6  # rad: float32 rounding of a heading of +-pi


class PacketError(ValueError):
    """A mesh packet that cannot be encoded or decoded; the message says what was wrong."""


class PacketValueError(PacketError):
    """A well-formed mesh packet (magic, length, CRC right) carrying a value that is not finite or out of range."""


def _crc(data: bytes) -> int:
    return binascii.crc_hqx(data, 0xFFFF)


def encode_state(state: AgentState, fields: Sequence[str]) -> bytes:
    """The packet for `state`, with its memory fields in the order of `fields` (missing fields: no values)."""
    p = state.pose
    body = bytearray()
    for name in fields:
        values = np.asarray(state.memory.get(name, ()), dtype=np.float32).ravel()
        if values.size > 255:
            raise PacketError(f"memory field {name!r} has {values.size} values; at most 255 fit")
        body += struct.pack("<B", values.size) + values.tobytes()
    length = _HEAD.size + len(body) + _CRC.size
    if length > MAX_PACKET_BYTES:
        raise PacketError(f"state of agent {state.agent_id} needs {length} bytes; the radio takes {MAX_PACKET_BYTES}")
    if not 0 <= state.agent_id <= 0xFFFF:
        raise PacketError(f"agent id {state.agent_id} is outside 0..65535")
    heading = _wrap(p.heading) if math.isfinite(p.heading) else p.heading
    head = _HEAD.pack(MAGIC, VERSION, length, state.agent_id, state.t, p.x, p.y, heading, p.vx, p.vy, len(fields))
    packet = head + bytes(body)
    return packet + _CRC.pack(_crc(packet))


def _wrap(angle: float) -> float:
    """An angle wrapped into (-pi, pi]."""
    return math.pi - (math.pi - angle) % (2.0 * math.pi)


def packet_agent_id(packet: bytes) -> int | None:
    """The sender's agent id of a complete, valid packet (values in range too); None if it is not one."""
    try:
        return decode_state(packet, ()).agent_id
    except PacketError:
        return None


def _check_frame(packet: bytes) -> None:
    """PacketError unless `packet` is one whole packet: magic, version, length and CRC right."""
    if len(packet) < _HEAD.size + _CRC.size:
        raise PacketError(f"packet of {len(packet)} bytes is shorter than the {_HEAD.size + _CRC.size}-byte minimum")
    magic, version, length = _HEAD.unpack_from(packet)[:3]
    if magic != MAGIC:
        raise PacketError(f"bad magic {magic!r}")
    if version != VERSION:
        raise PacketError(f"unsupported packet version {version}")
    if length != len(packet):
        raise PacketError(f"length byte says {length} bytes, the packet has {len(packet)}")
    (crc,) = _CRC.unpack_from(packet, length - _CRC.size)
    if crc != _crc(packet[: length - _CRC.size]):
        raise PacketError("bad CRC")


def _check_values(agent_id: int, t: float, x: float, y: float, heading: float, vx: float, vy: float) -> None:
    """PacketValueError naming the first value that is not finite or out of range."""
    for name, value, limit in (
        ("t", t, MAX_TIME_S),
        ("x", x, MAX_POSITION_M),
        ("y", y, MAX_POSITION_M),
        ("heading", heading, math.pi + _HEADING_SLACK),
        ("vx", vx, MAX_SPEED_MPS),
        ("vy", vy, MAX_SPEED_MPS),
    ):
        if not math.isfinite(value):
            raise PacketValueError(f"agent {agent_id}: {name} = {value!r} is not finite")
        if abs(value) > limit:
            raise PacketValueError(f"agent {agent_id}: {name} = {value!r} is outside +-{limit:g}")


def decode_state(packet: bytes, fields: Sequence[str]) -> AgentState:
    """The state in one complete packet; memory fields named by position in `fields` (extra ones dropped).
    Raises PacketError saying what is wrong (PacketValueError for a value out of range, see the module
    docstring)."""
    _check_frame(packet)
    _, _, length, agent_id, t, x, y, heading, vx, vy, count = _HEAD.unpack_from(packet)
    _check_values(agent_id, t, x, y, heading, vx, vy)
    memory: dict[str, np.ndarray] = {}
    offset = _HEAD.size
    for k in range(count):
        if offset >= length - _CRC.size:
            raise PacketError(f"memory field {k} runs past the end of the packet")
        n = packet[offset]
        end = offset + 1 + 4 * n
        if end > length - _CRC.size:
            raise PacketError(f"memory field {k} runs past the end of the packet")
        values = np.frombuffer(packet[offset + 1 : end], dtype="<f4").astype(float)
        if np.isinf(values).any():
            raise PacketValueError(f"agent {agent_id}: memory field {k} holds an infinite value")
        if k < len(fields):
            memory[fields[k]] = values
        offset = end
    pose = Pose(float(x), float(y), _wrap(float(heading)), float(vx), float(vy))
    return AgentState(int(agent_id), float(t), pose, memory)


class PacketReader:
    """Complete packets out of a byte stream (or datagrams); noise and bad packets counted and skipped."""

    def __init__(self) -> None:
        self._buf = bytearray()
        self.packets = 0
        self.bad = 0
        self.skipped_bytes = 0

    def feed(self, data: bytes) -> list[bytes]:
        buf = self._buf
        buf += data
        out: list[bytes] = []
        while True:
            start = buf.find(MAGIC)
            if start < 0:
                keep = 2 if buf.endswith(MAGIC[:2]) else 1 if buf.endswith(MAGIC[:1]) else 0
                self.skipped_bytes += len(buf) - keep
                del buf[: len(buf) - keep]
                return out
            self.skipped_bytes += start
            del buf[:start]
            if len(buf) < 5:
                return out
            length = buf[4]
            if length < _HEAD.size + _CRC.size or length > MAX_PACKET_BYTES:
                self._drop_marker()
                continue
            if len(buf) < length:
                return out
            packet = bytes(buf[:length])
            try:
                _check_frame(packet)  # framing only: values are judged by decode_state, and counted there
            except PacketError:
                self._drop_marker()
                continue
            del buf[:length]
            self.packets += 1
            out.append(packet)

    def _drop_marker(self) -> None:
        self.bad += 1
        self.skipped_bytes += 1
        del self._buf[:1]


class LinkMesh:
    """A broadcast network (the `Network` protocol) over a byte link: a UDP socket to a radio relay or a
    broadcast address, or a serial XBee. `fields`: the swarm's memory field names, in order. Own packets echoed
    back are ignored; noise and broken packets are counted in `reader.bad`, well-formed packets that cannot
    be decoded in `invalid`, of which those with a value out of range (NaN pose, ...) also in
    `out_of_range`: none of them is ever returned."""

    def __init__(self, link, agent_id: int, fields: Sequence[str], clock: Callable[[], float]) -> None:
        self.link, self.agent_id, self.fields, self.clock = link, agent_id, list(fields), clock
        self.reader = PacketReader()
        self.sent = 0
        self.received = 0
        self.invalid = 0
        self.out_of_range = 0
        self.send_errors = 0

    def broadcast(self, state: AgentState) -> None:
        try:
            self.link.write(encode_state(state, self.fields))
            self.sent += 1
        except OSError as error:  # the radio is down: count and carry on, the swarm tolerates lost packets
            self.send_errors += 1
            logger.warning("mesh send failed (%d so far): %s", self.send_errors, error)

    def receive(self) -> list[AgentState]:
        states: list[AgentState] = []
        while True:
            try:
                data, sender = self.link.read_from(65535, 0.0)
            except OSError as error:
                logger.warning("mesh read failed: %s", error)
                break
            if not data:
                break
            valid = False
            for packet in self.reader.feed(data):
                try:
                    state = decode_state(packet, self.fields)
                except PacketError as error:
                    self.invalid += 1
                    if isinstance(error, PacketValueError):
                        self.out_of_range += 1
                        if self.out_of_range <= 10 or self.out_of_range % 1000 == 0:
                            logger.warning("mesh packet dropped (%d so far): %s", self.out_of_range, error)
                    continue
                valid = True
                if state.agent_id != self.agent_id:
                    self.received += 1
                    states.append(state)
            if valid:
                self.link.confirm_peer(sender)  # a udpin mesh link answers only senders of valid packets
        return states
