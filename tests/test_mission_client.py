"""MissionClient over real UDP sockets on 127.0.0.1: several vessels (GcsComponent served by a small loop in a
thread, each on its own socket) all talking to one client port."""

from __future__ import annotations

import hashlib
import select
import socket
import threading
import time
from collections.abc import Callable

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from bob_autonomy.core.geodesy import LocalFrame
from bob_autonomy.ground.gcs import GcsComponent
from bob_autonomy.ground.mission import MissionClient, MissionError, MissionTimeoutError
from bob_autonomy.ground.params import PARAMS, ParamError, ParameterStore, ParamSpec

KEY = hashlib.sha256(b"fleet passphrase").digest()
HOME = (45.0, 7.0)
GOALS = [(45.0003, 7.0004), (45.0005, 7.0006), (45.0007, 7.0008)]
FENCE = [(44.99, 6.99), (44.99, 7.01), (45.01, 7.01), (45.01, 6.99)]


class Vessel:
    """One vessel's autonomy component on its own UDP socket, served by a thread; it sends everything to the
    client's port. While its behaviour runs it moves its reported position most of the way to its first
    goal every tick (a stand-in for the real process). `drop(frame)` may drop outgoing frames; `routed(frame)`
    gives frames its autopilot sent, which the vessel routes to the client before that frame."""

    def __init__(
        self, system_id: int, client: tuple[str, int], store: ParameterStore, *, key=None, drop=None, routed=None
    ):
        self.system_id = system_id
        self.client = client
        self.component = GcsComponent(
            system_id, store, signing_key=key, heartbeat_period_s=0.2, mission_timeout_s=0.25, mission_retries=3
        )
        self.drop: Callable[[bytes], bool] | None = drop
        self.routed: Callable[[bytes], list[bytes]] | None = routed
        self.dropped = 0
        frame = LocalFrame(*HOME)
        self.position = frame.to_geodetic(10.0 * system_id, -20.0)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            ready, _, _ = select.select([self.sock], [], [], 0.01)
            if ready:
                data, _ = self.sock.recvfrom(65535)
                self.component.receive(data, datagram=True)
            goals = self.component.goals
            if self.component.behavior_running and goals:
                lat, lon = self.position
                self.position = (lat + 0.3 * (goals[0][0] - lat), lon + 0.3 * (goals[0][1] - lon))
            self.component.report_position(float(self.position[0]), float(self.position[1]), heading_rad=0.0)
            self.component.tick()
            for frame in self.component.outgoing():
                for before in self.routed(frame) if self.routed is not None else []:
                    self.sock.sendto(before, self.client)
                if self.drop is not None and self.drop(frame):
                    self.dropped += 1
                    continue
                self.sock.sendto(frame, self.client)

    def close(self) -> None:
        self._stop.set()
        self.thread.join(timeout=2)
        self.sock.close()


@pytest.fixture
def make_fleet(tmp_path):
    """make_fleet(ids, key=..., client_key=..., stores={id: store}, drops={id: fn}) -> (client, {id: Vessel})."""
    opened: list = []

    def make(ids=(1, 2, 3), *, key=None, client_key=None, stores=None, drops=None, routed=None):
        client = MissionClient("udpin:127.0.0.1:0", signing_key=client_key, timeout_s=0.5, retries=2)
        opened.append(client)
        vessels = {}
        for sid in ids:
            store = (stores or {}).get(sid) or ParameterStore(tmp_path / f"vessel{sid}.json")
            vessels[sid] = Vessel(
                sid, client.local_address, store, key=key, drop=(drops or {}).get(sid), routed=(routed or {}).get(sid)
            )
            opened.append(vessels[sid])
        return client, vessels

    yield make
    for thing in reversed(opened):
        thing.close()


def test_discover_vessels_on_one_port(make_fleet) -> None:
    client, _ = make_fleet((1, 2, 7))
    assert client.discover(3, timeout_s=3) == [1, 2, 7]
    with pytest.raises(MissionTimeoutError, match=r"found 3 of 4 vessels .*\(1, 2, 7\)"):
        client.discover(4, timeout_s=0.3)


def test_parameters_fleet_wide_and_per_vessel(make_fleet) -> None:
    client, vessels = make_fleet()
    client.discover(3, timeout_s=3)
    assert client.set_param("BOB_P0_M", 5.0) == {1: 5.0, 2: 5.0, 3: 5.0}
    assert all(v.component.params.get("BOB_P0_M") == 5.0 for v in vessels.values())
    client.set_param("BOB_LEADER_ID", 1, vessels=[2, 3])
    assert client.get_param("BOB_LEADER_ID") == {1: 0.0, 2: 1.0, 3: 1.0}
    client.set_behavior("perimeter-defense", vessels=[3])
    assert vessels[3].component.params.behavior_name == "perimeter-defense"
    assert vessels[1].component.params.behavior_name == "bob-rule"
    with pytest.raises(ParamError, match=r"BOB_P0_M.*out of range"):
        client.set_param("BOB_P0_M", -1.0)  # refused before anything is sent
    with pytest.raises(ParamError, match="unknown parameter"):
        client.set_param("BOB_NOPE", 1.0)
    with pytest.raises(MissionError, match="vessel 9: never heard"):
        client.set_param("BOB_H", 1, vessels=[9])


def test_a_vessel_that_refuses_is_named_with_its_reason(make_fleet) -> None:
    strict = [ParamSpec(s.name, s.kind, s.default, s.minimum, 30.0 if s.name == "BOB_P0_M" else s.maximum, s.units,
                        s.description) for s in PARAMS]  # fmt: skip
    client, vessels = make_fleet((1, 2), stores={2: ParameterStore(specs=strict)})
    client.discover(2, timeout_s=3)
    with pytest.raises(MissionError) as info:
        client.set_param("BOB_P0_M", 50.0)
    assert set(info.value.failures) == {2}
    assert "refused" in info.value.failures[2] and "out of range" in info.value.failures[2]
    assert "vessel 2" in str(info.value) and "BOB_P0_M" in str(info.value)
    assert vessels[1].component.params.get("BOB_P0_M") == 50.0


def test_start_stop_goals_fence_and_waiting(make_fleet) -> None:
    drops_left = {"n": 1}

    def drop_first_request_for_item_1(frame: bytes) -> bool:
        # MISSION_REQUEST_INT (id 51) for seq 1 of the goal mission, once: the vessel must ask again.
        if frame[7:10] == bytes([51, 0, 0]) and frame[10] == 1 and drops_left["n"] > 0:
            drops_left["n"] -= 1
            return True
        return False

    client, vessels = make_fleet(drops={2: drop_first_request_for_item_1})
    client.discover(3, timeout_s=3)
    client.upload_goals(GOALS)
    assert vessels[2].dropped == 1 and vessels[2].component.counters.mission_retries >= 1
    for vessel in vessels.values():
        assert [(round(a, 7), round(b, 7)) for a, b in vessel.component.goals] == GOALS
    downloaded = client.download(mavlink.MAV_MISSION_TYPE_MISSION, 2)
    assert [(round(a, 7), round(b, 7)) for a, b in downloaded] == GOALS
    client.upload_fence(FENCE)
    assert all(len(v.component.fence) == 4 for v in vessels.values())
    assert len(client.download(mavlink.MAV_MISSION_TYPE_FENCE, 3)) == 4

    client.start()  # one MISSION_START to system 0
    client.wait_until(lambda c: all(c.behavior_running().values()), 2.0, "every behaviour running")
    assert all(v.component.behavior_running for v in vessels.values())
    distances = client.wait_all_within(GOALS[0], radius_m=10.0, timeout_s=5.0)
    assert set(distances) == {1, 2, 3} and max(distances.values()) <= 10.0

    client.stop(vessels=[3])
    assert not vessels[3].component.behavior_running and vessels[1].component.behavior_running
    client.set_goal(45.001, 7.001, vessels=[3])  # vessel 3 holds: it never gets there
    assert vessels[3].component.goals == [(45.001, 7.001)]
    with pytest.raises(MissionTimeoutError) as info:
        client.wait_all_within((45.001, 7.001), radius_m=10.0, timeout_s=0.4, vessels=[3])
    assert set(info.value.failures) == {3} and "m away" in info.value.failures[3]
    positions = client.positions()
    assert set(positions) == {1, 2, 3} and positions[1].heading_rad == pytest.approx(0.0)


def test_refused_commands_and_uploads_say_why(make_fleet) -> None:
    client, _ = make_fleet((4,))
    client.discover(1, timeout_s=3)
    with pytest.raises(MissionError, match="vessel 4: MAV_RESULT_UNSUPPORTED"):
        client.command(mavlink.MAV_CMD_DO_SET_SERVO, (1, 1500))
    with pytest.raises(MissionError, match="vessel 4: MAV_RESULT_DENIED"):
        client.command(mavlink.MAV_CMD_USER_1, (42,))
    with pytest.raises(ParamError, match="3 vertices"):
        client.upload_fence(FENCE[:2])


def test_an_answer_the_vessel_routes_from_its_autopilot_to_itself_is_not_taken_for_the_clients(make_fleet) -> None:
    """The vessel passes its autopilot's frames on to the ground station, among them the COMMAND_ACKs that answer
    the vessel's own commands: same system id as the client (255), addressed to the vessel's component 191. Just
    before the vessel refuses the client's DO_SET_SERVO, its autopilot's acceptance of a DO_SET_SERVO of the
    vessel's goes by: the client must still report the refusal (it took the first ack for its system)."""
    autopilot = mavlink.MAVLink(None, srcSystem=4, srcComponent=mavlink.MAV_COMP_ID_AUTOPILOT1)

    def autopilot_answer_first(frame: bytes) -> list[bytes]:
        if frame[7:10] != bytes([77, 0, 0]):  # COMMAND_ACK
            return []
        ack = autopilot.command_ack_encode(mavlink.MAV_CMD_DO_SET_SERVO, mavlink.MAV_RESULT_ACCEPTED, 0, 0, 255, 191)
        return [bytes(ack.pack(autopilot))]

    client, _ = make_fleet((4,), routed={4: autopilot_answer_first})
    client.discover(1, timeout_s=3)
    with pytest.raises(MissionError, match="vessel 4: MAV_RESULT_UNSUPPORTED"):
        client.command(mavlink.MAV_CMD_DO_SET_SERVO, (1, 1500))


def test_signed_fleet(make_fleet) -> None:
    client, vessels = make_fleet((1, 2), key=KEY, client_key=KEY)
    client.discover(2, timeout_s=3)
    client.set_param("BOB_H", 1)
    client.start()
    assert all(v.component.behavior_running for v in vessels.values())
    assert all(v.component.counters.unsigned_rejected == 0 for v in vessels.values())


def test_an_unsigned_client_is_refused_by_a_signed_fleet(make_fleet) -> None:
    client, vessels = make_fleet((1, 2), key=KEY, client_key=None)
    client.discover(2, timeout_s=3)  # without a key the client accepts the vessels' signed frames
    with pytest.raises(MissionError) as info:
        client.set_param("BOB_H", 1)
    assert set(info.value.failures) == {1, 2} and all("no answer" in why for why in info.value.failures.values())
    assert all(v.component.counters.unsigned_rejected >= 3 for v in vessels.values())
    assert all(v.component.params.get("BOB_H") == 0 for v in vessels.values())


def test_a_client_with_the_wrong_key_hears_nobody(make_fleet) -> None:
    client, _ = make_fleet((1,), key=KEY, client_key=hashlib.sha256(b"wrong").digest())
    with pytest.raises(MissionTimeoutError, match="found 0 of 1"):
        client.discover(1, timeout_s=0.5)
    assert client.counters.bad_signature > 0


def test_set_params_sends_the_whole_set_before_it_waits_and_retries_only_what_was_not_echoed(make_fleet) -> None:
    """The vessel's echoes are lost until it holds every value of the set: a client that waited for each echo
    before sending the next parameter would never get one. The vessel serves one datagram per loop and echoes it
    at once, so the echoes of the first two parameters are lost and the retry carries just those two."""
    wanted = {"BOB_H": 1, "BOB_P0_M": 7.5, "BOB_MAX_SPD_MPS": 0.75}  # exact in float32
    holder: dict[str, Vessel] = {}

    def lose_echoes_until_all_set(frame: bytes) -> bool:
        if frame[7:10] != bytes([22, 0, 0]):  # PARAM_VALUE
            return False
        params = holder["vessel"].component.params
        return any(params.get(name) != value for name, value in wanted.items())

    client, vessels = make_fleet((1,), drops={1: lose_echoes_until_all_set})
    holder["vessel"] = vessels[1]
    client.discover(1, timeout_s=3)
    assert client.set_params(wanted) == {1: wanted}
    assert vessels[1].dropped == 2 and vessels[1].component.counters.params_set == 3 + 2
    with pytest.raises(ParamError, match=r"BOB_P0_M.*out of range"):
        client.set_params({"BOB_H": 0, "BOB_P0_M": -1.0})  # checked before anything is sent
    assert vessels[1].component.counters.params_set == 5 and vessels[1].component.params.get("BOB_H") == 1


def test_the_client_counts_datagrams_the_kernel_dropped_for_it(make_fleet) -> None:
    """While the receiver thread is held up, a flood overflows the socket's buffer: the kernel's drop count (Linux
    SO_RXQ_OVFL, carried by the datagrams queued after the drops) becomes `kernel_drops`, which a failed exchange
    reports."""
    client, _ = make_fleet(())
    flood = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        with client._lock:  # the receiver blocks in its first datagram's handling
            for _ in range(40_000):
                flood.sendto(b"\xfd" + bytes(40), client.local_address)
        deadline = time.monotonic() + 10.0
        while client.kernel_drops == 0 and time.monotonic() < deadline:
            flood.sendto(b"\xfd" + bytes(40), client.local_address)  # the count rides on datagrams queued later
            time.sleep(0.05)
    finally:
        flood.close()
    assert client.kernel_drops > 0
    assert client.counters.bytes_received > 0
