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
"""

from __future__ import annotations

import binascii
import logging
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


class PacketError(ValueError):
    """A mesh packet that cannot be encoded or decoded; the message says what was wrong."""


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
    head = _HEAD.pack(MAGIC, VERSION, length, state.agent_id, state.t, p.x, p.y, p.heading, p.vx, p.vy, len(fields))
    packet = head + bytes(body)
    return packet + _CRC.pack(_crc(packet))


def packet_agent_id(packet: bytes) -> int | None:
    """The sender's agent id of a complete, valid packet; None if it is not one."""
    try:
        return decode_state(packet, ()).agent_id
    except PacketError:
        return None


def decode_state(packet: bytes, fields: Sequence[str]) -> AgentState:
    """The state in one complete packet; memory fields named by position in `fields` (extra ones dropped).
    Raises PacketError saying what is wrong."""
    if len(packet) < _HEAD.size + _CRC.size:
        raise PacketError(f"packet of {len(packet)} bytes is shorter than the {_HEAD.size + _CRC.size}-byte minimum")
    magic, version, length, agent_id, t, x, y, heading, vx, vy, count = _HEAD.unpack_from(packet)
    if magic != MAGIC:
        raise PacketError(f"bad magic {magic!r}")
    if version != VERSION:
        raise PacketError(f"unsupported packet version {version}")
    if length != len(packet):
        raise PacketError(f"length byte says {length} bytes, the packet has {len(packet)}")
    (crc,) = _CRC.unpack_from(packet, length - _CRC.size)
    if crc != _crc(packet[: length - _CRC.size]):
        raise PacketError("bad CRC")
    memory: dict[str, np.ndarray] = {}
    offset = _HEAD.size
    for k in range(count):
        if offset >= length - _CRC.size:
            raise PacketError(f"memory field {k} runs past the end of the packet")
        n = packet[offset]
        end = offset + 1 + 4 * n
        if end > length - _CRC.size:
            raise PacketError(f"memory field {k} runs past the end of the packet")
        if k < len(fields):
            memory[fields[k]] = np.frombuffer(packet[offset + 1 : end], dtype="<f4").astype(float)
        offset = end
    return AgentState(int(agent_id), float(t), Pose(float(x), float(y), float(heading), float(vx), float(vy)), memory)


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
            if packet_agent_id(packet) is None:
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
    back are ignored; undecodable ones are counted in `reader.bad` and `invalid`."""

    def __init__(self, link, agent_id: int, fields: Sequence[str], clock: Callable[[], float]) -> None:
        self.link, self.agent_id, self.fields, self.clock = link, agent_id, list(fields), clock
        self.reader = PacketReader()
        self.sent = 0
        self.received = 0
        self.invalid = 0
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
                except PacketError:
                    self.invalid += 1
                    continue
                valid = True
                if state.agent_id != self.agent_id:
                    self.received += 1
                    states.append(state)
            if valid:
                self.link.confirm_peer(sender)  # a udpin mesh link answers only senders of valid packets
        return states
