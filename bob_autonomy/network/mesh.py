"""The swarm mesh: an agent's state as a small binary packet, and a broadcast network over any byte link.

Packet (little-endian), at most `MAX_PACKET_BYTES` (the XBee payload limit):

    magic "BoB" (3 B) | version (1 B) | length of the whole packet (1 B) | agent id (uint16)
    | t (float64, s, the sender's clock) | x, y (float32, m) | heading (float32, rad) | vx, vy (float32, m/s)
    | field count (uint8) | per memory field: value count (uint8) + values (float32 each)
    | [version 2 only: signature trailer, timestamp (uint48) + tag (8 B), see `bob_autonomy.network.mesh_auth`]
    | CRC-16/CCITT (uint16)

Version 1 packets are unsigned (a mesh without a fleet key); version 2 packets carry the signature trailer
(`bob_autonomy.network.mesh_auth`), 14 bytes more. A mesh with a key sends version 2 and refuses version 1; a mesh
without one sends version 1 and reads both (it cannot check a tag, so it ignores the trailer). The CRC
stays: it frames packets in a byte stream and catches noise before any tag is computed.

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
from collections import deque
from collections.abc import Callable, Sequence

import numpy as np

from bob_autonomy.core.interfaces import AgentState, Pose
from bob_autonomy.network.mesh_auth import (
    DEFAULT_WINDOW_S,
    TRAILER_BYTES,
    AuthError,
    MeshSigner,
    MeshVerifier,
    unix_mesh_clock,
)

logger = logging.getLogger(__name__)

MAGIC = b"BoB"
VERSION = 1  # unsigned packet
VERSION_SIGNED = 2  # packet with the signature trailer of bob_autonomy.network.mesh_auth
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


def packet_bytes(value_counts: Sequence[int], signed: bool = False) -> int:
    """On-air size (bytes) of a packet whose memory fields hold `value_counts` float32 values each, signed or
    not: 38 bytes plus 1 + 4 k per field of k values, plus 14 signed."""
    return _HEAD.size + sum(1 + 4 * int(k) for k in value_counts) + (TRAILER_BYTES if signed else 0) + _CRC.size


def encode_state(state: AgentState, fields: Sequence[str], signer: MeshSigner | None = None) -> bytes:
    """The packet for `state`, with its memory fields in the order of `fields` (missing fields: no values);
    signed (version 2) by `signer` when one is given."""
    p = state.pose
    body = bytearray()
    for name in fields:
        values = np.asarray(state.memory.get(name, ()), dtype=np.float32).ravel()
        if values.size > 255:
            raise PacketError(f"memory field {name!r} has {values.size} values; at most 255 fit")
        body += struct.pack("<B", values.size) + values.tobytes()
    length = _HEAD.size + len(body) + (TRAILER_BYTES if signer is not None else 0) + _CRC.size
    if length > MAX_PACKET_BYTES:
        raise PacketError(f"state of agent {state.agent_id} needs {length} bytes; the radio takes {MAX_PACKET_BYTES}")
    if not 0 <= state.agent_id <= 0xFFFF:
        raise PacketError(f"agent id {state.agent_id} is outside 0..65535")
    heading = _wrap(p.heading) if math.isfinite(p.heading) else p.heading
    version = VERSION if signer is None else VERSION_SIGNED
    head = _HEAD.pack(MAGIC, version, length, state.agent_id, state.t, p.x, p.y, heading, p.vx, p.vy, len(fields))
    packet = head + bytes(body)
    if signer is not None:
        packet = signer.sign(packet)
    return packet + _CRC.pack(_crc(packet))


def signed_part(packet: bytes) -> bytes | None:
    """The bytes a version 2 packet's tag covers, followed by the tag (everything before the CRC); None for an
    unsigned (version 1) packet. `packet` must have passed the framing checks (PacketReader's)."""
    if packet[3] != VERSION_SIGNED:
        return None
    return packet[: len(packet) - _CRC.size]


def header_agent_id(packet: bytes) -> int:
    """The agent id in the header of a framed packet (not yet checked against any key)."""
    return int(_HEAD.unpack_from(packet)[3])


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
    if version not in (VERSION, VERSION_SIGNED):
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
    _, version, length, agent_id, t, x, y, heading, vx, vy, count = _HEAD.unpack_from(packet)
    _check_values(agent_id, t, x, y, heading, vx, vy)
    memory: dict[str, np.ndarray] = {}
    offset = _HEAD.size
    stop = length - _CRC.size - (TRAILER_BYTES if version == VERSION_SIGNED else 0)
    if stop < offset:
        raise PacketError(f"signed packet of {length} bytes has no room for its {TRAILER_BYTES}-byte trailer")
    for k in range(count):
        if offset >= stop:
            raise PacketError(f"memory field {k} runs past the end of the packet")
        n = packet[offset]
        end = offset + 1 + 4 * n
        if end > stop:
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


RECENT_SENT = 8  # own packets remembered, to tell our own echo (a broadcast comes back) from another radio


class LinkMesh:
    """A broadcast network (the `Network` protocol) over a byte link: a UDP socket to a radio relay or a
    broadcast address, or a serial XBee. `fields`: the swarm's memory field names, in order. `clock`: the
    agent's clock (s), for logs.

    key: the fleet key (32 bytes, `bob_autonomy.network.mesh_auth.load_mesh_key`), or None for an open mesh. With a
    key every packet sent is signed and every packet received must pass `MeshVerifier` (signed, right tag,
    newer than the last from its sender, within `window_s` of `mesh_clock`); refused ones are counted in
    `verifier.rejected` by reason and claimed sender, and logged (the first ten, then every thousandth).
    mesh_clock: the shared time base of the timestamps (`unix_mesh_clock`, UTC, on a vessel).

    Own packets echoed back are ignored (counted in `echoes`). A packet with our agent id that we did not send is
    never a neighbour either: with a key, one that fails the checks is refused as any other (under our id); one
    that passes them, or any on an open mesh, is counted in `same_id` and logged: another vessel with our system
    id (each autonomy's agent id is its vehicle's MAVLink system id - 1, so two autopilots both left at MAV_SYSID
    1 never hear each other), or on an open mesh a radio sending as us. Noise and broken packets are counted in
    `reader.bad`, well-formed packets that cannot be decoded in `invalid`, of which those with a value out of
    range (NaN pose, ...) also in `out_of_range`: none of them is ever returned."""

    def __init__(
        self,
        link,
        agent_id: int,
        fields: Sequence[str],
        clock: Callable[[], float],
        key: bytes | None = None,
        mesh_clock: Callable[[], float] = unix_mesh_clock,
        window_s: float = DEFAULT_WINDOW_S,
    ) -> None:
        self.link, self.agent_id, self.fields, self.clock = link, agent_id, list(fields), clock
        self.signer = MeshSigner(key, mesh_clock) if key is not None else None
        self.verifier = MeshVerifier(key, mesh_clock, window_s) if key is not None else None
        self.reader = PacketReader()
        self.sent = 0
        self.received = 0
        self.invalid = 0
        self.out_of_range = 0
        self.send_errors = 0
        self.echoes = 0
        self.same_id = 0
        self._recent_sent: deque[bytes] = deque(maxlen=RECENT_SENT)
        self._refused_logged = 0

    def broadcast(self, state: AgentState) -> None:
        try:
            packet = encode_state(state, self.fields, self.signer)
            self.link.write(packet)
            self.sent += 1
            self._recent_sent.append(packet)
        except OSError as error:  # the radio is down: count and carry on, the swarm tolerates lost packets
            self.send_errors += 1
            if self.send_errors <= 3 or self.send_errors % 1000 == 0:
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
                ours = header_agent_id(packet) == self.agent_id
                if ours and bytes(packet) in self._recent_sent:
                    self.echoes += 1
                    continue
                if self.verifier is not None and not self._authentic(packet):
                    continue  # a radio without the key, as anyone it claims (us too), is refused as such
                if ours:
                    self._same_id()  # never a neighbour
                    continue
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
                self.received += 1
                states.append(state)
            if valid:
                self.link.confirm_peer(sender)  # a udpin mesh link answers only senders of valid packets
        return states

    def _same_id(self) -> None:
        self.same_id += 1
        if self.same_id <= 3 or self.same_id % 1000 == 0:
            logger.warning(
                "mesh packet from another radio with our agent id %d (%d so far): is another vessel's autopilot on "
                "our MAVLink system id %d? Give each vessel its own (MAV_SYSID)",
                self.agent_id,
                self.same_id,
                self.agent_id + 1,
            )

    def _authentic(self, packet: bytes) -> bool:
        try:
            self.verifier.check(header_agent_id(packet), signed_part(packet))
        except AuthError as error:
            self._refused_logged += 1
            if self._refused_logged <= 10 or self._refused_logged % 1000 == 0:
                logger.warning("mesh packet refused (%s, %d so far): %s", error.reason, self._refused_logged, error)
            return False
        return True

    def counters(self) -> dict:
        """What the mesh sent, received and refused, for the vessel's log: sent, received (neighbour states
        returned), invalid and out_of_range (see the class docstring), noise (broken frames), send_errors,
        echoes (our own packets back) and same_id (another radio's with our agent id),
        and with a key `rejected`: reason -> {claimed agent id -> packets}
        (`bob_autonomy.network.mesh_auth.REASONS`)."""
        out: dict = {
            "sent": self.sent,
            "received": self.received,
            "invalid": self.invalid,
            "out_of_range": self.out_of_range,
            "noise": self.reader.bad,
            "send_errors": self.send_errors,
            "echoes": self.echoes,
            "same_id": self.same_id,
        }
        if self.verifier is not None:
            out["rejected"] = self.verifier.counters()
        return out
