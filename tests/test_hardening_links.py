"""Issue 17, items 2 and 3, over real UDP sockets, as an attacker on the same network would try them.

Item 2: no datagram moves a udpin link's reply address; with signing, only a ground station whose frames are
signed with the key is answered (the vessel's heartbeats and acknowledgements never go to an attacker).
Item 3: a udpout link hears only the address it sends to; the vehicle link believes only the vehicle's
autopilot (its system id, component 1); mesh packets with NaN, infinite or absurd values are dropped.
"""

from __future__ import annotations

import hashlib
import socket
import time
from pathlib import Path

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from bob_autonomy.behavior_config import BehaviorChoice
from bob_autonomy.clock import ScaledWallClock
from bob_autonomy.gcs import MavlinkCodec
from bob_autonomy.vessel import Vessel, VesselConfig
from firmware_bridge import commands
from firmware_bridge.decoder import contains_mavlink_frame
from firmware_bridge.links import UdpLink, open_link

pytestmark = pytest.mark.xdist_group("realtime")

KEY = hashlib.sha256(b"fleet key for the link tests").digest()
ORIGIN = (1.3405, 103.9560)


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
    config = VesselConfig(
        vehicle=f"udpout:127.0.0.1:{port}",
        system_id=2,
        behavior=BehaviorChoice(behavior="bob-rule", params={"p0": 10.0}),
        origin=ORIGIN,
        estimator="simple",
        controller="simple",
        gcs="udpin:127.0.0.1:0",
        signing_key_file=None if key_file is None else str(key_file),
        autostart=False,
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
