"""Issue 17, items 2 and 3, over real UDP sockets, as an attacker on the same network would try them.

Item 2: no datagram moves a udpin link's reply address; with signing, only a ground station whose frames are
signed with the key is answered (the vessel's heartbeats and acknowledgements never go to an attacker).
Item 3: a udpout link hears only the address it sends to; the vehicle link believes only the vehicle's
autopilot (its system id, component 1); mesh packets with NaN, infinite or absurd values are dropped.
"""

from __future__ import annotations

import binascii
import hashlib
import math
import socket
import struct
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pymavlink.dialects.v20 import ardupilotmega as mavlink
from vessel_helpers import ground_station_vessel_config

from bob_autonomy.core.clock import ScaledWallClock
from bob_autonomy.core.interfaces import AgentState, Pose
from bob_autonomy.ground.gcs import MavlinkCodec
from bob_autonomy.network.mesh import (
    LinkMesh,
    PacketError,
    PacketValueError,
    decode_state,
    encode_state,
    packet_agent_id,
)
from bob_autonomy.onboard.vehicle_link import VehicleLink
from bob_autonomy.onboard.vessel import Vessel
from firmware_bridge import commands
from firmware_bridge.commands import Encoder
from firmware_bridge.decoder import TelemetryDecoder, contains_mavlink_frame
from firmware_bridge.links import UdpLink, open_link
from firmware_bridge.telemetry import TelemetryEncoder

pytestmark = pytest.mark.xdist_group("realtime")

KEY = hashlib.sha256(b"fleet key for the link tests").digest()


def udp_socket() -> socket.socket:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    s.setblocking(False)
    return s


def drain(sock: socket.socket) -> list[bytes]:
    out = []
    while True:
        try:
            out.append(sock.recv(65535))
        except BlockingIOError:
            return out


def messages(codec: MavlinkCodec, datagrams: list[bytes]) -> list:
    return [m for d in datagrams for m in codec.decode(d, datagram=True)]


class ManualClock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


# -- item 2: udpin ------------------------------------------------------------------------------------------


def test_udpin_junk_does_not_move_the_reply_address() -> None:
    with open_link("udpin:127.0.0.1:0") as link:
        gcs, attacker = udp_socket(), udp_socket()
        address = link.local_address
        try:
            beat = commands.heartbeat()
            gcs.sendto(beat, address)
            assert link.read(65535, 1.0) == beat
            for junk in (b"\x00", b"\xfd" * 300, b"\xfe\x09junk", beat[:-1]):
                attacker.sendto(junk, address)
                assert link.read(65535, 1.0) == junk  # the bytes are the caller's to judge ...
            link.write(b"reply")  # ... but the reply goes to the ground station only
            time.sleep(0.05)
            assert drain(gcs) == [b"reply"] and drain(attacker) == []
            assert link.unconfirmed == 4 and list(link.peers) == [gcs.getsockname()]
        finally:
            gcs.close()
            attacker.close()


def test_udpin_without_authentication_answers_every_sender_of_a_well_formed_frame() -> None:
    """Without signing a well-formed frame is all there is to check: both senders are answered (as a
    vehicle answers every ground station), and neither displaces the other."""
    with open_link("udpin:127.0.0.1:0") as link:
        a, b = udp_socket(), udp_socket()
        try:
            for s in (a, b):
                s.sendto(commands.heartbeat(), link.local_address)
                link.read(65535, 1.0)
            link.write(b"both")
            time.sleep(0.05)
            assert drain(a) == [b"both"] and drain(b) == [b"both"]
        finally:
            a.close()
            b.close()


def test_udpin_peers_expire_and_read_from_never_confirms() -> None:
    clock = ManualClock()
    link = UdpLink("udpin:127.0.0.1:0", "udpin", "127.0.0.1", 0, peer_timeout_s=10.0, clock=clock)
    sender = udp_socket()
    try:
        beat = commands.heartbeat()
        sender.sendto(beat, link.local_address)
        data, source = link.read_from(65535, 1.0)
        assert data == beat and source == sender.getsockname()
        assert link.live_peers() == []  # read_from leaves the decision to the caller
        link.confirm_peer(source)
        assert link.live_peers() == [source] and link.peer == source
        clock.t = 10.5
        assert link.live_peers() == [] and link.peer is None
        link.write(b"nobody")  # no peer: nothing sent, no error
        time.sleep(0.05)
        assert drain(sender) == []
    finally:
        sender.close()
        link.close()


def test_contains_mavlink_frame() -> None:
    beat = commands.heartbeat()
    assert contains_mavlink_frame(beat) and contains_mavlink_frame(b"noise" + beat)
    assert not contains_mavlink_frame(beat[:-1]) and not contains_mavlink_frame(beat[:-1] + bytes([beat[-1] ^ 1]))
    assert not contains_mavlink_frame(b"\xfd" * 65000) and not contains_mavlink_frame(b"")


def _vessel(tmp_path: Path, *, key: bool) -> Vessel:
    vehicle = udp_socket()  # nobody answers: the test drives only the ground-station side
    port = vehicle.getsockname()[1]
    vehicle.close()
    key_file = None
    if key:
        key_file = tmp_path / "bob.key"
        key_file.write_bytes(KEY)
    config = ground_station_vessel_config(
        port, system_id=2, estimator="simple", signing_key_file=None if key_file is None else str(key_file)
    )
    return Vessel(config, clock=ScaledWallClock(50.0))  # heartbeats at 50 Hz of wall time


def _attacks(codec: MavlinkCodec, wrong: MavlinkCodec) -> list[bytes]:
    """What an attacker without the key can send: junk, unsigned frames (an unsigned RADIO_STATUS is let
    through by the codec, as MAVProxy does, but must not make the attacker a peer), wrongly signed ones."""
    request = codec.mav.command_long_encode(2, 191, mavlink.MAV_CMD_REQUEST_MESSAGE, 0, 0, 0, 0, 0, 0, 0, 0)
    return [
        b"\x00",
        b"\xfd" * 40,
        codec.pack(codec.mav.heartbeat_encode(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)),
        codec.pack(request),
        codec.pack(codec.mav.radio_status_encode(200, 200, 100, 0, 0, 0, 0)),
        wrong.pack(request),
    ]


@pytest.mark.parametrize("signed", [True, False])
def test_an_attacker_never_receives_the_vessels_frames_and_the_gcs_keeps_them(tmp_path: Path, signed: bool) -> None:
    vessel = _vessel(tmp_path, key=signed)
    gcs, attacker = udp_socket(), udp_socket()
    gcs_codec = MavlinkCodec(255, 190, signing_key=KEY if signed else None)
    unsigned = MavlinkCodec(254, 190)
    wrong = MavlinkCodec(254, 190, signing_key=hashlib.sha256(b"a guess").digest())
    address = vessel.gcs_link.local_address
    request = gcs_codec.mav.command_long_encode(2, 191, mavlink.MAV_CMD_REQUEST_MESSAGE, 0, 0, 0, 0, 0, 0, 0, 0)
    try:
        gcs.sendto(gcs_codec.pack(gcs_codec.mav.heartbeat_encode(mavlink.MAV_TYPE_GCS, 8, 0, 0, 0)), address)
        got: list[bytes] = []
        for round_ in range(8):
            attacks = _attacks(unsigned, wrong) if signed else [b"\x00", b"\xfd" * 40, b"junk" * 10]
            for datagram in attacks:  # the attacker speaks last before every serve
                attacker.sendto(datagram, address)
            if round_ % 3 == 0:
                gcs.sendto(gcs_codec.pack(request), address)
            time.sleep(0.02)
            vessel.serve_gcs()
            time.sleep(0.01)
            got += drain(gcs)
        heard = messages(gcs_codec, got)
        assert drain(attacker) == []  # not one frame to the attacker
        assert len([m for m in heard if m.get_type() == "HEARTBEAT"]) >= 5
        acks = [m for m in heard if m.get_type() == "COMMAND_ACK"]
        assert len(acks) == 3 and {a.result for a in acks} == {mavlink.MAV_RESULT_ACCEPTED}
        assert list(vessel.gcs_link.peers) == [gcs.getsockname()]
        c = vessel.gcs.counters
        if signed:
            assert c.unsigned_rejected == 8 * 2 and c.bad_signature == 8 and c.authenticated == 4
    finally:
        gcs.close()
        attacker.close()
        vessel.shutdown()


# -- item 3: udpout and the vehicle link ----------------------------------------------------------------------

LAT, LON = 1.3405, 103.9560


def flat(readings) -> list:
    """Readings as comparable values: type name and every field's numbers (NaN, a value not reported, as "nan")."""

    def numbers(v) -> list:
        return ["nan" if x != x else x for x in np.asarray(v, float).ravel().round(9).tolist()]

    out = []
    for r in readings:
        values = {k: None if v is None else numbers(v) for k, v in vars(r).items()}
        out.append((type(r).__name__, values))
    return out


def _telemetry(enc: TelemetryEncoder, fake: bool) -> list[bytes]:
    """A vehicle's telemetry, or an attacker's forgery with the same ids and other values."""
    k = 1.0 if fake else 0.0
    return [
        enc.heartbeat(mavlink.MAV_TYPE_SURFACE_BOAT, not fake),
        enc.gps_raw_int(1.0, LAT + 3e-4 * k, LON, (0.5 + 5 * k, 0.0)),
        enc.attitude(1.0, 0.3 + 2 * k),
        enc.scaled_imu(1.0, (0.1 + 9 * k, 0.0), 0.01 + k),
    ]


def test_a_third_socket_cannot_inject_telemetry_into_a_udpout_vehicle_link() -> None:
    vehicle, attacker = udp_socket(), udp_socket()
    clock = lambda: 5.0  # noqa: E731 - a fixed reception time, so readings compare exactly
    link = open_link(f"udpout:127.0.0.1:{vehicle.getsockname()[1]}")
    vessel_side = VehicleLink(1, "buoy", 45.0, clock)
    try:
        link.write(vessel_side.arm(True))  # the vessel speaks first: the vehicle learns its address
        vehicle.settimeout(1.0)
        _, address = vehicle.recvfrom(65535)
        real, fake = _telemetry(TelemetryEncoder(1), False), _telemetry(TelemetryEncoder(1), True)
        for forged, frame in zip(fake, real, strict=True):
            attacker.sendto(forged, address)  # same system and component ids, from another port
            vehicle.sendto(frame, address)
            attacker.sendto(forged * 2, address)
        readings = []
        deadline = time.monotonic() + 0.5
        while time.monotonic() < deadline:
            data = link.read(65535, 0.05)
            if data:
                readings += vessel_side.receive(data)
        expected_side = VehicleLink(1, "buoy", 45.0, clock)
        expected = expected_side.receive(b"".join(real))
        assert len(expected) == 3 and flat(readings) == flat(expected)
        assert vessel_side.last_heartbeat is not None and vessel_side.armed  # the forged heartbeat says disarmed
        assert link.foreign == 2 * len(fake)
    finally:
        link.close()
        vehicle.close()
        attacker.close()


@pytest.mark.parametrize(
    ("system", "component"),
    [(2, 1), (255, 190), (1, 191), (1, 0), (1, 2), (1, 250)],
    ids=["another-vehicle", "a-gcs", "a-companion-on-our-system", "component-0", "component-2", "component-250"],
)
def test_the_vehicle_link_believes_only_its_autopilot(system: int, component: int) -> None:
    link = VehicleLink(1, "buoy", 45.0, lambda: 5.0)
    forged = b"".join(_telemetry(TelemetryEncoder(system, component), True))
    assert link.receive(forged) == []
    c = link.decoder.counters
    assert (c.other_system if system != 1 else c.other_component) == 4
    assert link.last_heartbeat is None
    real = link.receive(b"".join(_telemetry(TelemetryEncoder(1), False)))
    assert len(real) == 3 and link.armed


def test_a_decoder_learns_its_vehicle_from_the_first_autopilot_heartbeat() -> None:
    decoder = TelemetryDecoder(lambda: 0.0, learn_source=True, source_component=1)
    vehicle, other = TelemetryEncoder(4), TelemetryEncoder(5)
    gcs = Encoder(255, 190)
    assert decoder.feed(vehicle.attitude(0.0, 0.1)) == []  # nobody known yet
    gcs_beat = gcs.pack(gcs.mav.heartbeat_encode(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0))
    assert decoder.feed(gcs_beat) == [] and decoder.source_system is None  # a ground station is no autopilot
    assert len(decoder.feed(vehicle.heartbeat(mavlink.MAV_TYPE_SURFACE_BOAT, False))) == 1
    assert decoder.source_system == 4
    assert decoder.feed(other.heartbeat(mavlink.MAV_TYPE_SURFACE_BOAT, False) + other.attitude(0.0, 1.0)) == []
    assert len(decoder.feed(vehicle.attitude(0.0, 0.1))) == 1
    c = decoder.counters
    assert (c.not_yet_known, c.other_system) == (2, 2)


# -- item 3: the mesh ---------------------------------------------------------------------------------------


OFFSET = {"t": (7, "<d"), "x": (15, "<f"), "y": (19, "<f"), "heading": (23, "<f"), "vx": (27, "<f"), "vy": (31, "<f")}


def _packet(**changes) -> bytes:
    """Agent 4's packet, good but for `changes` written straight into its fields (as a forger would, without
    encode_state's wrapping of the heading), with a correct CRC."""
    raw = bytearray(encode_state(AgentState(4, 12.5, Pose(10.0, -20.0, 0.5, 0.3, -0.2), {}), []))
    for name, value in changes.items():
        offset, fmt = OFFSET[name]
        struct.pack_into(fmt, raw, offset, value)
    raw[-2:] = struct.pack("<H", binascii.crc_hqx(bytes(raw[:-2]), 0xFFFF))
    return bytes(raw)


@pytest.mark.parametrize("field", ["t", "x", "y", "heading", "vx", "vy"])
@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf, 1e30, -1e30])
def test_mesh_packets_with_non_finite_or_absurd_values_are_refused(field: str, value: float) -> None:
    packet = _packet(**{field: value})
    with pytest.raises(PacketValueError, match=field):
        decode_state(packet, [])
    assert packet_agent_id(packet) is None


def test_mesh_headings_are_wrapped_and_memory_may_be_unknown_but_not_infinite() -> None:
    assert decode_state(_packet(heading=math.pi), []).pose.heading == pytest.approx(-math.pi, abs=1e-6)
    assert decode_state(_packet(heading=-math.pi), []).pose.heading == pytest.approx(math.pi, abs=1e-6)
    for heading in (3.2, -3.2, 100.0):
        with pytest.raises(PacketValueError, match="heading"):
            decode_state(_packet(heading=heading), [])
    sent = encode_state(AgentState(4, 1.0, Pose(0.0, 0.0, 3.5), {}), [])  # a sender's heading is wrapped first
    assert decode_state(sent, []).pose.heading == pytest.approx(3.5 - 2 * math.pi, abs=1e-6)
    unknown = encode_state(AgentState(4, 1.0, Pose(0.0, 0.0, 0.0), {"goal": np.array([np.nan, np.nan])}), ["goal"])
    assert np.isnan(decode_state(unknown, ["goal"]).memory["goal"]).all()
    infinite = encode_state(AgentState(4, 1.0, Pose(0.0, 0.0, 0.0), {"goal": np.array([np.inf, 0.0])}), ["goal"])
    with pytest.raises(PacketValueError, match="memory"):
        decode_state(infinite, ["goal"])


def test_a_mesh_packet_with_nan_x_is_never_returned_by_the_mesh() -> None:
    relay = udp_socket()
    link = open_link(f"udpout:127.0.0.1:{relay.getsockname()[1]}")
    mesh = LinkMesh(link, 0, [], lambda: 0.0)
    try:
        link.write(b"hello")  # learn our address
        relay.settimeout(1.0)
        _, address = relay.recvfrom(100)
        for packet in (_packet(x=math.nan), _packet(), _packet(heading=math.inf), _packet(x=1e30)):
            relay.sendto(packet, address)
        time.sleep(0.05)
        states = mesh.receive()
        assert [(s.agent_id, s.pose.x) for s in states] == [(4, 10.0)]
        assert (mesh.invalid, mesh.out_of_range, mesh.received) == (3, 3, 1)
    finally:
        link.close()
        relay.close()


@settings(max_examples=300, deadline=None, database=None)
@given(
    values=st.lists(st.floats(allow_nan=True, allow_infinity=True, width=64), min_size=6, max_size=6),
    memory=st.lists(st.floats(width=32), max_size=4),
)
def test_any_state_decodes_to_finite_values_in_range_or_is_refused(values, memory) -> None:
    t, x, y, heading, vx, vy = values
    state = AgentState(9, t, Pose(x, y, heading, vx, vy), {"m": np.array(memory, dtype=float)})
    try:
        packet = encode_state(state, ["m"])
    except (PacketError, OverflowError, struct.error):
        return  # not even encodable (e.g. 1e300 into a float32): nothing to send
    try:
        decoded = decode_state(packet, ["m"])
    except PacketValueError:
        return
    p = decoded.pose
    assert all(math.isfinite(v) for v in (decoded.t, p.x, p.y, p.heading, p.vx, p.vy))
    assert -math.pi < p.heading <= math.pi and abs(p.x) <= 1e7 and abs(p.vx) <= 100 and abs(decoded.t) <= 1e10
    assert not np.isinf(decoded.memory["m"]).any()
