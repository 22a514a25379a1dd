"""Authenticated mesh packets (bob_autonomy.network.mesh_auth, bob_autonomy.network.mesh): written as an attacker
would."""

from __future__ import annotations

import binascii
import hashlib
import hmac
import socket
import struct
import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bob_autonomy.core.interfaces import AgentState, Pose
from bob_autonomy.network.mesh import (
    MAX_PACKET_BYTES,
    VERSION_SIGNED,
    LinkMesh,
    PacketError,
    PacketReader,
    decode_state,
    encode_state,
    packet_agent_id,
    packet_bytes,
    signed_part,
)
from bob_autonomy.network.mesh_auth import (
    TAG_BYTES,
    TRAILER_BYTES,
    AuthError,
    MeshSigner,
    MeshVerifier,
    load_mesh_key,
    stamp_seconds,
)
from firmware_bridge.links import open_link

KEY = hashlib.sha256(b"fleet key").digest()
OTHER_KEY = hashlib.sha256(b"another fleet").digest()


class Clock:
    """A mesh clock the test moves by hand, s."""

    def __init__(self, t: float = 1000.0) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t


def state(agent_id: int = 3, x: float = 10.0, goal=(1.0, 2.0)) -> AgentState:
    return AgentState(agent_id, 5.0, Pose(x, -4.0, 0.5, 0.2, -0.1), {"goal": np.array(goal)})


def recrc(packet: bytes) -> bytes:
    """`packet` with its CRC made right again (what an attacker who changes bytes does)."""
    body = packet[:-2]
    return body + struct.pack("<H", binascii.crc_hqx(body, 0xFFFF))


def signed_packet(clock: Clock, key: bytes = KEY, **kw) -> bytes:
    return encode_state(state(**kw), ["goal"], MeshSigner(key, clock))


# -- format -------------------------------------------------------------------------------------------------


def test_a_signed_packet_is_14_bytes_longer_carries_version_2_and_decodes_to_the_same_state() -> None:
    clock = Clock()
    plain = encode_state(state(), ["goal"])
    signed = encode_state(state(), ["goal"], MeshSigner(KEY, clock))
    assert len(signed) == len(plain) + TRAILER_BYTES == packet_bytes([2], signed=True) == 61
    assert len(plain) == packet_bytes([2]) == 47
    assert signed[3] == VERSION_SIGNED and signed[4] == len(signed)
    a, b = decode_state(signed, ["goal"]), decode_state(plain, ["goal"])
    assert (a.agent_id, a.t, a.pose) == (b.agent_id, b.t, b.pose)
    assert a.memory["goal"].tolist() == b.memory["goal"].tolist() == [1.0, 2.0]
    assert packet_agent_id(signed) == 3
    # The trailer: timestamp (10 us units of the mesh clock) and HMAC-SHA256 of everything before the tag.
    part = signed_part(signed)
    assert part == signed[:-2]
    stamp = int.from_bytes(part[-TRAILER_BYTES:-TAG_BYTES], "little")
    assert stamp == 1000 * 100_000
    assert part[-TAG_BYTES:] == hmac.new(KEY, part[:-TAG_BYTES], hashlib.sha256).digest()[:TAG_BYTES]
    assert signed_part(plain) is None


def test_the_stream_reader_frames_signed_and_unsigned_packets_in_noise() -> None:
    clock = Clock()
    signed, plain = signed_packet(clock), encode_state(state(agent_id=4), ["goal"])
    reader = PacketReader()
    out = reader.feed(b"\x00BoB\xff" + signed + b"noise" + plain + signed[:10])
    assert out == [signed, plain]
    assert reader.feed(signed[10:]) == [signed]  # a packet split across two reads is put back together
    assert reader.feed(signed[:30] + plain) == [plain]  # a packet cut short is skipped, the next one found


def test_a_signed_packet_must_fit_the_radio_payload() -> None:
    big = AgentState(1, 0.0, Pose(0.0, 0.0, 0.0), {"m": np.zeros(13)})
    assert len(encode_state(big, ["m"])) == packet_bytes([13]) == 91  # fits unsigned
    with pytest.raises(PacketError, match="105 bytes; the radio takes 100"):
        encode_state(big, ["m"], MeshSigner(KEY, Clock()))
    assert packet_bytes([13], signed=True) > MAX_PACKET_BYTES


# -- verification -------------------------------------------------------------------------------------------


def test_unsigned_forged_wrong_key_replayed_and_stale_packets_are_refused_and_counted_by_claimed_sender() -> None:
    sender_clock, clock = Clock(), Clock()
    signer = MeshSigner(KEY, sender_clock)
    verifier = MeshVerifier(KEY, clock, window_s=5.0)
    first = encode_state(state(agent_id=0), ["goal"], signer)
    assert verifier.check(0, signed_part(first)) == 1000 * 100_000
    cases = [
        ("unsigned", encode_state(state(agent_id=0), ["goal"])),
        ("bad_mac", encode_state(state(agent_id=0), ["goal"], MeshSigner(OTHER_KEY, sender_clock))),
        ("replay", first),
    ]
    for reason, packet in cases:
        with pytest.raises(AuthError) as caught:
            verifier.check(0, signed_part(packet))
        assert caught.value.reason == reason
    sender_clock.t = 1006.0  # the sender's clock runs 6 s ahead of the receiver's
    with pytest.raises(AuthError, match=r"\+6\.000 s .*outside the \+-5 s window") as caught:
        verifier.check(0, signed_part(encode_state(state(agent_id=0), ["goal"], signer)))
    assert caught.value.reason == "stale"
    clock.t = 1004.0  # the receiver catches up: the next packet is fresh again
    verifier.check(0, signed_part(encode_state(state(agent_id=0), ["goal"], signer)))
    assert verifier.counters() == {
        "unsigned": {"0": 1},
        "bad_mac": {"0": 1},
        "replay": {"0": 1},
        "stale": {"0": 1},
    }
    assert verifier.accepted == 2


def test_a_recording_played_back_later_is_stale_even_to_a_receiver_that_never_heard_the_sender() -> None:
    old = signed_packet(Clock(1000.0))
    fresh_receiver = MeshVerifier(KEY, Clock(1060.0))
    with pytest.raises(AuthError) as caught:
        fresh_receiver.check(3, signed_part(old))
    assert caught.value.reason == "stale"


def test_a_forged_packet_with_a_far_future_stamp_never_advances_the_stream() -> None:
    clock = Clock()
    verifier = MeshVerifier(KEY, clock)
    genuine = signed_packet(clock)
    part = bytearray(signed_part(genuine))
    part[-TRAILER_BYTES:-TAG_BYTES] = (2**48 - 1).to_bytes(6, "little")  # the attacker's stamp, old tag
    with pytest.raises(AuthError):
        verifier.check(3, bytes(part))
    assert verifier.check(3, signed_part(genuine)) == 1000 * 100_000


def test_stamps_are_strictly_increasing_even_when_the_clock_stands_still_or_steps_back() -> None:
    clock = Clock()
    signer = MeshSigner(KEY, clock)
    stamps = [signer.next_stamp() for _ in range(3)]
    clock.t = 999.0
    stamps.append(signer.next_stamp())
    assert stamps == [100_000_000, 100_000_001, 100_000_002, 100_000_003]
    assert stamp_seconds(stamps[0]) == 1000.0
    verifier = MeshVerifier(KEY, Clock())
    for _ in range(3):  # three packets sent within one clock tick are all accepted, in order
        verifier.check(3, signed_part(encode_state(state(), ["goal"], signer)))


@settings(max_examples=200, deadline=None, database=None)
@given(position=st.integers(min_value=0, max_value=60), bit=st.integers(min_value=0, max_value=7))
def test_any_single_bit_changed_anywhere_in_a_signed_packet_is_refused(position: int, bit: int) -> None:
    clock = Clock()
    packet = bytearray(signed_packet(clock))
    assert len(packet) == 61
    if position >= len(packet) - 2:
        position = len(packet) - 3  # the CRC itself is recomputed anyway
    packet[position] ^= 1 << bit
    tampered = recrc(bytes(packet))
    verifier = MeshVerifier(KEY, clock)
    reader = PacketReader()
    framed = reader.feed(tampered)
    if not framed:  # the attacker broke the framing (magic, version, length): not even a packet
        return
    with pytest.raises(AuthError) as caught:
        verifier.check(packet_agent_id(tampered) or 0, signed_part(framed[0]))
    assert caught.value.reason in ("unsigned", "bad_mac")


def test_keys_are_read_like_mavlink_signing_keys(tmp_path) -> None:
    raw = tmp_path / "raw.key"
    raw.write_bytes(KEY)
    phrase = tmp_path / "phrase.key"
    phrase.write_text("fleet key\n")
    assert load_mesh_key(str(raw)) == load_mesh_key(str(phrase)) == KEY
    with pytest.raises(ValueError, match="32 bytes"):
        MeshSigner(b"short", Clock())
    with pytest.raises(ValueError, match="window"):
        MeshVerifier(KEY, Clock(), window_s=0.0)


# -- LinkMesh over real UDP sockets ---------------------------------------------------------------------------


def udp_socket() -> socket.socket:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    return s


@pytest.mark.xdist_group("realtime")
def test_a_keyed_mesh_hears_its_fleet_and_refuses_an_intruder_as_agent_0() -> None:
    relay = udp_socket()
    clock = Clock()
    link = open_link(f"udpout:127.0.0.1:{relay.getsockname()[1]}")
    mesh = LinkMesh(link, 5, ["goal"], lambda: 0.0, key=KEY, mesh_clock=clock)
    try:
        mesh.broadcast(state(agent_id=5))  # learn the mesh's address; the packet is signed
        relay.settimeout(1.0)
        own, address = relay.recvfrom(200)
        assert own[3] == VERSION_SIGNED and packet_agent_id(own) == 5
        member = MeshSigner(KEY, clock)
        genuine = encode_state(state(agent_id=0, x=1.0), ["goal"], member)
        forged = encode_state(state(agent_id=0, x=300.0), ["goal"])  # the intruder has no key
        other_key = encode_state(state(agent_id=0, x=300.0), ["goal"], MeshSigner(OTHER_KEY, clock))
        for packet in (forged, genuine, other_key, genuine, own):
            relay.sendto(packet, address)
        time.sleep(0.05)
        states = mesh.receive()
        assert [(s.agent_id, s.pose.x) for s in states] == [(0, 1.0)]
        counters = mesh.counters()
        assert counters["rejected"] == {
            "unsigned": {"0": 1},
            "bad_mac": {"0": 1},
            "replay": {"0": 1},
            "stale": {},
        }
        assert counters["received"] == 1
    finally:
        link.close()
        relay.close()


@pytest.mark.xdist_group("realtime")
def test_a_keyless_mesh_reads_signed_and_unsigned_packets_as_today() -> None:
    relay = udp_socket()
    link = open_link(f"udpout:127.0.0.1:{relay.getsockname()[1]}")
    mesh = LinkMesh(link, 5, ["goal"], lambda: 0.0)
    try:
        mesh.broadcast(state(agent_id=5))
        relay.settimeout(1.0)
        own, address = relay.recvfrom(200)
        assert own[3] == 1 and len(own) == 47  # unsigned, as before the key existed
        relay.sendto(signed_packet(Clock(), agent_id=1), address)
        relay.sendto(encode_state(state(agent_id=2), ["goal"]), address)
        time.sleep(0.05)
        assert sorted(s.agent_id for s in mesh.receive()) == [1, 2]
        assert "rejected" not in mesh.counters()
    finally:
        link.close()
        relay.close()


# -- an intruder on the process fleet's simulated radio (sitl.radio.radio_relay) -------------------------------------


@pytest.mark.xdist_group("realtime")
def test_the_relay_hosts_an_intruder_whose_packets_keyed_members_refuse_and_open_members_take() -> None:
    from sitl.radio.mesh_security import IntruderSpec
    from sitl.radio.radio_relay import RadioRelay

    positions = np.array([[0.0, 0.0], [10.0, 0.0], [20.0, 0.0]])
    now = [0.0]
    intruder = IntruderSpec(claims_agent=0, position=(0.0, 500.0), reach_m=600.0, start_s=1.0)
    relay = RadioRelay(
        3,
        lambda: positions,
        lambda: np.ones(3, dtype=bool),
        channel=None,
        range_m=300.0,
        broadcast_period_s=1.0,
        rng=np.random.default_rng(1),
        clock=lambda: now[0],
        port=0,
        memory_fields=["goal"],
        intruders=[intruder],
    )
    clock = Clock()
    links = [open_link(f"udpout:127.0.0.1:{relay.address[1]}") for _ in range(3)]
    meshes = [
        LinkMesh(links[0], 0, ["goal"], lambda: 0.0, key=KEY, mesh_clock=clock),
        LinkMesh(links[1], 1, ["goal"], lambda: 0.0, key=KEY, mesh_clock=clock),
        LinkMesh(links[2], 2, ["goal"], lambda: 0.0),  # a member without the key: an open mesh
    ]
    try:
        for k, mesh in enumerate(meshes):  # each makes itself known to the relay
            mesh.broadcast(state(agent_id=k, x=10.0 * k))
        time.sleep(0.05)
        relay.read()
        assert relay.next_due_s() == 1.0  # the intruder's first transmission wakes the fleet's loop
        for t in (1.0, 2.0, 3.5):
            now[0] = t
            relay.flush()
        time.sleep(0.05)
        heard = [mesh.receive() for mesh in meshes]
        counters = relay.counters()
        assert (counters["intruder_sent"], counters["intruder_delivered"]) == (3, 6)  # agent 0 ignores its own id
        assert counters["spoofed"] == 0  # no address on the air to check
        assert 0 not in [s.agent_id for s in heard[0]]  # agent 0: its own id is never a neighbour
        assert all(s.pose.y != 500.0 for s in heard[1])  # the keyed member refuses the intruder ...
        assert meshes[1].counters()["rejected"]["unsigned"]["0"] == 3  # ... and counts it
        # The member without the key takes all three: only the key (or plausibility) stops the intruder.
        assert [(s.agent_id, s.pose.y) for s in heard[2] if s.pose.y == 500.0] == [(0, 500.0)] * 3
    finally:
        relay.close()
        for link in links:
            link.close()
