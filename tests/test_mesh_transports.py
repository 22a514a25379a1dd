"""The swarm's mesh on the transports a vessel uses (docs/mesh.md, "Transports"):

- UDP broadcast (`udpbcast:ADDRESS:PORT`, firmware_bridge.links.UdpBroadcastLink), as on an IP radio (Wi-Fi, or a
  mesh radio carrying Ethernet): real sockets sharing one port, datagrams to this host's loopback broadcast address
  127.255.255.255, which the kernel delivers to every socket bound to the port;
- XBees in transparent mode on serial ports, as the paper's robots: real pseudo-terminals, joined by a radio that
  does what an XBee does with the bytes (below).
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import select
import socket
import sys
import threading
import time
from collections.abc import Iterator

import numpy as np
import pytest
from vessel_helpers import PluggedPty

from bob_autonomy.cli import main
from bob_autonomy.core.interfaces import AgentState, Pose
from bob_autonomy.network.mesh import LinkMesh, encode_state, packet_agent_id
from firmware_bridge import ebot_bridge
from firmware_bridge.links import LinkError, ReopeningLink, UdpBroadcastLink, open_link, parse_connection_string

KEY = hashlib.sha256(b"fleet key").digest()
BROADCAST = "127.255.255.255"


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("", 0))
        return s.getsockname()[1]


@contextlib.contextmanager
def on_one_port(*kinds: str) -> Iterator[list]:
    """Links of these kinds ("udpbcast", "udpout") to the loopback broadcast address on one free port, closed after."""
    port = free_udp_port()
    with contextlib.ExitStack() as stack:
        yield [stack.enter_context(open_link(f"{kind}:{BROADCAST}:{port}")) for kind in kinds]


def state(agent_id: int, x: float) -> AgentState:
    return AgentState(agent_id, 5.0, Pose(x, -4.0, 0.5, 0.2, -0.1), {"goal": np.array([1.0, 2.0])})


def heard(mesh: LinkMesh, count: int, timeout_s: float = 2.0) -> list[AgentState]:
    """What `mesh` receives until it has `count` states or `timeout_s` passed (datagrams take a moment)."""
    states: list[AgentState] = []
    end = time.monotonic() + timeout_s
    while len(states) < count and time.monotonic() < end:
        states += mesh.receive()
        time.sleep(0.01)
    return states


def test_udpbcast_connection_strings() -> None:
    assert parse_connection_string("udpbcast:192.168.1.255:15000") == ("udpbcast", "192.168.1.255", 15000)
    for bad in ("udpbcast:192.168.1.255", "udpbcast::15000", "udpbcast:192.168.1.255:0"):
        with pytest.raises(LinkError, match="bad connection string"):
            parse_connection_string(bad)


def test_every_member_hears_every_other_and_never_itself() -> None:
    with on_one_port("udpbcast", "udpbcast", "udpbcast") as links:
        assert all(isinstance(link, UdpBroadcastLink) for link in links)
        meshes = [LinkMesh(link, agent, ["goal"], lambda: 0.0) for agent, link in enumerate(links)]
        for agent, mesh in enumerate(meshes):
            mesh.broadcast(state(agent, x=10.0 * agent))
        for agent, mesh in enumerate(meshes):
            states = heard(mesh, 2)
            others = sorted((s.agent_id, s.pose.x) for s in states)
            assert others == [(a, 10.0 * a) for a in range(3) if a != agent], f"agent {agent} heard {others}"
            assert mesh.received == 2 and mesh.sent == 1
            time.sleep(0.02)
            assert mesh.receive() == []  # its own broadcast came back too, and was dropped as an echo
            assert (mesh.echoes, mesh.same_id) == (1, 0)


def test_a_keyed_broadcast_mesh_refuses_a_member_without_the_key() -> None:
    """On a broadcast network anyone in radio range can send to the port: the fleet key is what keeps them out."""
    with on_one_port("udpbcast", "udpbcast", "udpout") as (a, b, outsider):
        member_a = LinkMesh(a, 1, ["goal"], lambda: 0.0, key=KEY)
        member_b = LinkMesh(b, 2, ["goal"], lambda: 0.0, key=KEY)
        with pytest.raises(LinkError, match="Permission denied"):  # a plain socket may not even send there
            outsider.write(encode_state(state(0, x=300.0), ["goal"]))
        outsider.sock.setsockopt(socket.SOL_SOCKET, socket.SO_BROADCAST, 1)
        outsider.write(encode_state(state(0, x=300.0), ["goal"]))  # a keyless radio claiming to be agent 0
        member_a.broadcast(state(1, x=1.0))
        states = heard(member_b, 1)
        time.sleep(0.05)
        states += member_b.receive()
        assert [(s.agent_id, s.pose.x) for s in states] == [(1, 1.0)]
        assert {reason: n for reason, n in member_b.counters()["rejected"].items() if n} == {"unsigned": {"0": 1}}


def test_two_vessels_with_one_system_id_are_told_why_they_hear_nothing_of_each_other(caplog) -> None:
    """Every ArduPilot leaves the factory as MAVLink system 1, and each autonomy's agent id is its system id - 1:
    two vessels nobody renumbered drop each other's packets as their own. They say so."""
    with on_one_port("udpbcast", "udpbcast") as (a, b):
        first, second = (LinkMesh(link, 0, ["goal"], lambda: 0.0) for link in (a, b))
        first.broadcast(state(0, x=1.0))
        second.broadcast(state(0, x=2.0))
        time.sleep(0.1)
        assert first.receive() == [] and second.receive() == []
        assert [(m.echoes, m.same_id) for m in (first, second)] == [(1, 1), (1, 1)]
        assert second.counters()["same_id"] == 1
    warnings = [r.getMessage() for r in caplog.records if "our agent id 0" in r.getMessage()]
    assert len(warnings) == 2 and "MAVLink system id 1" in warnings[0] and "MAV_SYSID" in warnings[0]


def test_on_a_keyed_mesh_a_keyless_radio_using_our_id_is_refused_not_taken_for_a_member_on_our_system_id() -> None:
    with on_one_port("udpbcast", "udpbcast", "udpbcast") as (a, b, outsider):
        ours, twin = LinkMesh(a, 1, ["goal"], lambda: 0.0, key=KEY), LinkMesh(b, 1, ["goal"], lambda: 0.0, key=KEY)
        outsider.write(encode_state(state(1, x=300.0), ["goal"]))  # no key, claiming agent 1
        twin.broadcast(state(1, x=2.0))  # a member with the key, misconfigured on our id
        time.sleep(0.1)
        assert ours.receive() == []
        assert (ours.same_id, ours.echoes) == (1, 0)
        assert {reason: n for reason, n in ours.counters()["rejected"].items() if n} == {"unsigned": {"1": 1}}


@pytest.mark.parametrize("role", ["--vehicle", "--gcs"])
def test_udpbcast_is_refused_for_the_vehicle_and_the_ground_station(role, capsys, tmp_path) -> None:
    """A link to an autopilot or a ground station talks to one peer; one that hears every host on the network
    would let any of them command the vessel."""
    links = {"--vehicle": "udpout:127.0.0.1:9", "--gcs": None}
    links[role] = f"udpbcast:{BROADCAST}:{free_udp_port()}"
    argv = ["run", "--system-id", "1", "--origin", "1.3,103.8", "--behavior", "bob-rule"]
    argv += ["--log-file", str(tmp_path / "vessel.log")]
    for option, value in links.items():
        argv += [option, value] if value else []
    assert main(argv) == 2
    error = capsys.readouterr().err
    assert "udpbcast is for the swarm's mesh only" in error and "use udpout:HOST:PORT" in error


def test_the_ebot_bridge_refuses_udpbcast_for_its_mavlink_link(capsys) -> None:
    with pytest.raises(SystemExit) as stopped:
        ebot_bridge.main(["--serial", "/dev/null", "--mavlink", f"udpbcast:{BROADCAST}:14550"])
    assert stopped.value.code == 2
    assert "udpbcast is for a swarm's mesh, not a vehicle's link" in capsys.readouterr().err


class TransparentXbees:
    """n XBees in transparent mode, one per pseudo-terminal (`devices`, what each vessel opens), on one channel. As
    an XBee does, the bytes a vessel writes go out in RF packets of at most 100 bytes (what its serial buffer held
    when the packetization timeout ran out), and each packet comes out of every other XBee's serial port whole,
    between other packets but never mixed with them. `corrupt(k)`: the next packet to XBee k has one byte changed
    (an error the radio's own CRC missed; a vessel must drop it, not read it). `noise(k, data)`: bytes out of
    XBee k's port that no vessel sent (a module booting, a line glitch)."""

    RF_PAYLOAD = 100

    def __init__(self, n: int) -> None:
        pairs = [os.openpty() for _ in range(n)]
        self.masters = [master for master, _slave in pairs]
        self._slaves = [slave for _master, slave in pairs]
        self.devices = [os.ttyname(slave) for slave in self._slaves]
        self.packets = 0
        self._corrupt: set[int] = set()
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._carry, daemon=True)
        self._thread.start()

    def corrupt(self, k: int) -> None:
        with self._lock:
            self._corrupt.add(k)

    def noise(self, k: int, data: bytes) -> None:
        with self._lock:
            os.write(self.masters[k], data)

    def _carry(self) -> None:
        while not self._stop.is_set():
            ready, _, _ = select.select(self.masters, [], [], 0.05)
            for sender in ready:
                try:
                    data = os.read(sender, 4096)
                except OSError:
                    return
                for start in range(0, len(data), self.RF_PAYLOAD):
                    self._deliver(sender, data[start : start + self.RF_PAYLOAD])

    def _deliver(self, sender: int, packet: bytes) -> None:
        with self._lock:
            self.packets += 1
            for k, master in enumerate(self.masters):
                if master == sender:
                    continue
                out = bytearray(packet)
                if k in self._corrupt:
                    self._corrupt.discard(k)
                    out[len(out) // 2] ^= 0x5A
                os.write(master, bytes(out))

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
        for fd in self.masters + self._slaves:
            os.close(fd)


@pytest.mark.skipif(sys.platform == "win32", reason="pseudo-terminals are POSIX")
def test_a_signed_mesh_of_xbees_on_serial_ports_hears_every_packet_through_noise_and_a_corrupted_one() -> None:
    xbees = TransparentXbees(3)
    links = [open_link(device, baud=57600) for device in xbees.devices]
    try:
        meshes = [LinkMesh(link, agent, ["goal"], lambda: 0.0, key=KEY) for agent, link in enumerate(links)]
        xbees.noise(2, b"\x00\xffXBee boot\r\n")
        heard: list[list[AgentState]] = [[] for _ in meshes]
        for step in range(20):
            if step == 10:
                xbees.corrupt(2)  # the next packet reaching XBee 2 is damaged
            for agent, mesh in enumerate(meshes):
                mesh.broadcast(state(agent, x=100.0 * agent + step))
                time.sleep(0.01)  # one packet per RF packet, as at a broadcast period
            for agent, mesh in enumerate(meshes):
                heard[agent] += mesh.receive()
        end = time.monotonic() + 2.0
        while time.monotonic() < end and sum(map(len, heard)) < 3 * 40 - 1:
            time.sleep(0.05)
            for agent, mesh in enumerate(meshes):
                heard[agent] += mesh.receive()
        for agent in (0, 1):  # every packet of the two others, in the order sent
            assert [(s.agent_id, s.pose.x) for s in heard[agent] if s.agent_id != agent] == [
                (a, 100.0 * a + step) for step in range(20) for a in range(3) if a != agent
            ]
        # XBee 2 lost the damaged packet only, and dropped the noise; nothing broken was read as a state
        assert len(heard[2]) == 39 and meshes[2].reader.bad > 0
        assert sorted({s.agent_id for s in heard[2]}) == [0, 1]
        assert all(m.invalid == 0 and m.counters()["rejected"]["bad_mac"] == {} for m in meshes)
    finally:
        for link in links:
            link.close()
        xbees.close()


@pytest.mark.skipif(sys.platform == "win32", reason="pseudo-terminals are POSIX")
def test_a_vessel_opens_its_xbee_at_the_mesh_baud_rate_not_the_vehicles() -> None:
    """An XBee's serial rate (its BD setting) is its own: a vessel whose autopilot talks at 57600 may have its
    XBee at 9600, the factory setting."""
    from bob_autonomy.core.behavior_config import BehaviorChoice
    from bob_autonomy.onboard.vessel import Vessel, VesselConfig

    master, slave = os.openpty()
    config = VesselConfig(
        vehicle="udpout:127.0.0.1:9",
        baud=57600,
        system_id=1,
        behavior=BehaviorChoice(behavior="bob-rule", params={"H": 0}),
        origin=(1.3, 103.8),
        mesh=os.ttyname(slave),
        mesh_baud=9600,
    )
    vessel = Vessel(config)
    try:
        assert vessel.mesh_link.link.port.baudrate == 9600
    finally:
        for link in (vessel.vehicle_link, vessel.mesh_link):
            link.close()
        os.close(master)
        os.close(slave)


class PluggedXbee(PluggedPty):
    """An XBee on a USB serial adapter (`vessel_helpers.PluggedPty`); `master` is the radio's side."""

    def sent(self, timeout_s: float = 2.0) -> bytes:
        """What the vessel wrote to the radio, waiting up to timeout_s for the first bytes."""
        ready, _, _ = select.select([self.master], [], [], timeout_s)
        return os.read(self.master, 4096) if ready else b""


@pytest.mark.skipif(sys.platform == "win32", reason="pseudo-terminals are POSIX")
def test_an_xbee_shaken_loose_is_reopened_by_its_path_and_the_mesh_goes_on(tmp_path, caplog) -> None:
    xbee = PluggedXbee(tmp_path / "ttyXBEE")
    link = ReopeningLink(lambda: open_link(str(xbee.path), baud=115200), period_s=0.2)
    mesh = LinkMesh(link, 1, ["goal"], lambda: 0.0)
    try:
        mesh.broadcast(state(1, x=1.0))
        assert packet_agent_id(xbee.sent()) == 1
        os.write(xbee.master, encode_state(state(0, x=5.0), ["goal"]))
        assert [s.pose.x for s in heard(mesh, 1)] == [5.0]

        xbee.unplug()
        for step in range(6):  # the vessel's loop goes on: nothing raises, nothing is heard
            mesh.broadcast(state(1, x=2.0 + step))
            assert mesh.receive() == []
            time.sleep(0.1)
        assert link.losses == 1 and link.reopens == 0 and mesh.send_errors >= 1

        xbee.replug()
        end = time.monotonic() + 3.0
        while link.reopens == 0 and time.monotonic() < end:
            mesh.receive()
            time.sleep(0.05)
        assert link.reopens == 1
        os.write(xbee.master, encode_state(state(0, x=6.0), ["goal"]))
        assert [s.pose.x for s in heard(mesh, 1)] == [6.0]
        mesh.broadcast(state(1, x=9.0))
        assert packet_agent_id(xbee.sent()) == 1
    finally:
        link.close()
        if xbee.master is not None:
            xbee.unplug()
    said = [r.getMessage() for r in caplog.records if r.name == "firmware_bridge.links"]
    assert len(said) == 2 and "lost" in said[0] and "reopened after" in said[1], said


def test_a_udp_mesh_link_whose_sends_fail_keeps_its_socket_hears_on_and_sends_again_when_it_can(caplog) -> None:
    """An IP radio's interface going down fails every send (here: the socket's broadcast permission withdrawn,
    EACCES). The socket is kept, and with it its port, by which a relay or a ground station knows the vessel."""
    port = free_udp_port()
    link = ReopeningLink(lambda: open_link(f"udpbcast:{BROADCAST}:{port}"), period_s=0.2, keep_open=True)
    with open_link(f"udpbcast:{BROADCAST}:{port}") as peer_link:
        ours, peer = LinkMesh(link, 1, ["goal"], lambda: 0.0), LinkMesh(peer_link, 2, ["goal"], lambda: 0.0)
        sock = link.link.sock
        address = sock.getsockname()
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_BROADCAST, 0)
        for step in range(8):
            ours.broadcast(state(1, x=float(step)))
            time.sleep(0.05)
        assert (link.losses, ours.send_errors) == (1, 1) and link.dropped_writes == 7
        peer.broadcast(state(2, x=7.0))
        assert [s.pose.x for s in heard(ours, 1)] == [7.0]  # it still hears its swarm
        assert heard(peer, 1, timeout_s=0.3) == []
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_BROADCAST, 1)
        end = time.monotonic() + 2.0
        while link.reopens == 0 and time.monotonic() < end:
            ours.broadcast(state(1, x=9.0))
            time.sleep(0.05)
        assert link.reopens == 1 and link.link.sock is sock and sock.getsockname() == address
        assert 9.0 in [s.pose.x for s in heard(peer, 1)]
    link.close()
    said = [r.getMessage() for r in caplog.records if r.name == "firmware_bridge.links"]
    assert len(said) == 2 and "failing" in said[0] and "works again after" in said[1], said


def test_a_vessel_avoiding_collisions_on_broadcasts_too_slow_for_it_says_so(caplog) -> None:
    """Two vessels avoiding each other act on each other's last broadcast course: at a broadcast every 10 s with a
    5 s horizon each has turned long before the other hears of it (behaviors.collision_avoidance)."""
    from bob_autonomy.core.behavior_config import BehaviorChoice
    from bob_autonomy.onboard.vessel import Vessel, VesselConfig

    said = {}
    for period in (0.1, 10.0):
        config = VesselConfig(
            vehicle="udpout:127.0.0.1:9",
            system_id=1,
            behavior=BehaviorChoice(behavior="bob-rule", params={"H": 0}, avoid_collisions=True),
            origin=(1.3, 103.8),
            mesh="udpout:127.0.0.1:9",
            broadcast_period_s=period,
        )
        caplog.clear()
        with caplog.at_level("WARNING", logger="bob_autonomy.onboard.vessel"):
            vessel = Vessel(config)
        for link in (vessel.vehicle_link, vessel.mesh_link):
            link.close()
        said[period] = [r.getMessage() for r in caplog.records if "collision avoidance" in r.getMessage()]
    assert said[0.1] == []
    assert len(said[10.0]) == 1 and "every 10 s" in said[10.0][0] and "--broadcast-period" in said[10.0][0]
