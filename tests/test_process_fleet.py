"""The process fleet (sitl/vehicles/vehicle_server.py, sitl/radio/radio_relay.py, sitl/fleets/process_fleet.py) over
real UDP sockets.

(a) simulated vehicles: heartbeat, arming with COMMAND_ACK, RC overrides that move a buoy the right way, the
failsafe after command loss, ports +10 per instance, two clients at once; (b) the radio relay with fake agents
(plain sockets): delivery against distance follows the channel model, invalid and oversize packets counted;
(c) the .tlog read back by pymavlink and mavlogdump.py; (d) end to end with the real `bob-autonomy run`:
5 buoys in separate processes aggregate, no process or port outlives the run; Ctrl-C stops a run cleanly
and still writes its outputs; a vessel that never arms is a clear error.

Ports are drawn at random and checked free, so the tests do not collide with a simulation already running.
"""

from __future__ import annotations

import json
import math
import os
import random
import select
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from bob_autonomy.core.geodesy import LocalFrame
from bob_autonomy.core.interfaces import AgentState, Pose
from bob_autonomy.network.mesh import encode_state
from bob_autonomy.onboard.vehicle_link import VehicleLink
from firmware_bridge.commands import heartbeat
from firmware_bridge.tlog import TlogWriter, split_frames
from sitl.experiments.metrics import METRICS
from sitl.experiments.recorder import TRAJECTORY_COLUMNS
from sitl.experiments.scenario import BehaviorChoice, ScenarioError, scenario_to_toml, validate_scenario
from sitl.experiments.swarm_metrics import nearest_neighbor_m
from sitl.fleets.fleet import build_world, initial_poses
from sitl.fleets.process_fleet import (
    ProcessFleetError,
    ProcessOptions,
    behavior_parameters,
    run_processes_to_directory,
)
from sitl.radio.channel import RadioChannel
from sitl.radio.radio_relay import RadioRelay
from sitl.vehicles.bodies import BUOY
from sitl.vehicles.vehicle_physics import VehiclePhysics
from sitl.vehicles.vehicle_server import VehicleServer, vehicle_port
from sitl.world.environment import CurrentSpec, Environment, WindSpec
from sitl.world.world import World

# Real time, sockets and processes: in one xdist worker, so that they never compete with each other.
pytestmark = pytest.mark.xdist_group("realtime")

HOST = "127.0.0.1"
DT_S = 0.1
ORIGIN = LocalFrame(1.3406, 103.9266)


# ---------------------------------------------------------------- helpers


def _bindable(port: int) -> bool:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        sock.bind((HOST, port))
        return True
    except OSError:
        return False
    finally:
        sock.close()


def _port_range() -> tuple[int, int]:
    """Where this test process picks its ports: below the kernel's ephemeral range (32768 up, where sockets bound to
    port 0 land), one half per pytest-xdist worker, so that a port found free here is not bound by a fleet of the
    other worker before ours binds it (seen once in CI: "Address already in use")."""
    worker = os.environ.get("PYTEST_XDIST_WORKER", "")
    if worker.startswith("gw") and worker[2:].isdigit():
        low = 20000 + 6000 * (int(worker[2:]) % 2)
        return low, low + 6000
    return 20000, 32000


def free_ports(vehicles: int, extra: int = 0) -> tuple[int, list[int]]:
    """A base port whose vehicle ports (base + 10 i) are free, and `extra` more free ports (all in `_port_range`)."""
    low, high = _port_range()
    for _ in range(200):
        base = random.randrange(low, high - 10 * vehicles - extra - 10, 10)
        others = [base + 10 * vehicles + 1 + k for k in range(extra)]
        if all(_bindable(vehicle_port(i, base)) for i in range(vehicles)) and all(map(_bindable, others)):
            return base, others
    raise RuntimeError("no free ports")


class Client:
    """A stand-in ground station or autonomy: a UDP socket that talks MAVLink to one vehicle port."""

    def __init__(self, port: int, system_id: int = 1) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind((HOST, 0))
        self.sock.setblocking(False)
        self.peer = (HOST, port)
        self.link = VehicleLink(system_id, "buoy", VehicleBench.MAX_THRUST_N, time.monotonic)
        self.parser = mavlink.MAVLink(None)
        self.parser.robust_parsing = True
        self.messages: list = []

    def send(self, data: bytes) -> None:
        self.sock.sendto(data, self.peer)

    def drain(self) -> list:
        """Every message received since the last drain."""
        out = []
        while True:
            try:
                data, _ = self.sock.recvfrom(65535)
            except BlockingIOError:
                break
            out += [m for m in (self.parser.parse_buffer(data) or []) if m.get_type() != "BAD_DATA"]
        self.messages += out
        return out

    def close(self) -> None:
        self.sock.close()


class VehicleBench:
    """Three buoys heading north in still water, served on UDP at a free base port, stepped by hand."""

    MAX_THRUST_N = 45.091875

    def __init__(self, tmp_path: Path, failsafe_s: float = 1.0) -> None:
        self.base, _ = free_ports(3)
        n = 3
        self.physics = VehiclePhysics(
            np.full(n, BUOY),
            np.column_stack((50.0 * np.arange(n), np.zeros(n))),
            np.full(n, math.pi / 2),
            Environment(WindSpec(), CurrentSpec(), np.random.default_rng(3)),
            ORIGIN,
            np.random.default_rng(2),
            np.ones(n),
            {},
        )
        self.tlog = TlogWriter(tmp_path / "vehicles.tlog")
        self.server = VehicleServer(
            ["buoy"] * n, [self.MAX_THRUST_N] * n, base_port=self.base, failsafe_s=failsafe_s, tlog=self.tlog
        )

    def step(self, steps: int = 1, each=None) -> None:
        """`steps` steps of DT_S: serve the sockets briefly, apply the actuators, step, send the telemetry."""
        p, world = self.physics, World()
        for _ in range(steps):
            if each is not None:
                each()
            self.server.serve(0.003, p.t)
            act = self.server.actuators(p.t)
            p.step(act[p.buoys], act[p.ebots], DT_S, world)
            self.server.send_telemetry(p.t, p.sense())
        self.server.serve(0.003, p.t)

    def close(self) -> None:
        self.server.close()
        self.tlog.close()


@pytest.fixture
def bench(tmp_path: Path):
    b = VehicleBench(tmp_path)
    yield b
    b.close()


def types(messages: list) -> set[str]:
    return {m.get_type() for m in messages}


# ---------------------------------------------------------------- (a) the vehicles over UDP


def test_heartbeat_then_arm_with_command_ack(bench: VehicleBench) -> None:
    client = Client(bench.server.ports[0])
    client.send(heartbeat())
    bench.step(11)
    beats = [m for m in client.drain() if m.get_type() == "HEARTBEAT"]
    assert beats and beats[0].get_srcSystem() == 1 and beats[0].get_srcComponent() == 1
    assert beats[0].type == mavlink.MAV_TYPE_SURFACE_BOAT
    assert not beats[-1].base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED  # disarmed until the autonomy arms it
    assert not bench.server.armed().any()

    client.send(client.link.arm(True))
    bench.step(11)
    got = client.drain()
    acks = [m for m in got if m.get_type() == "COMMAND_ACK"]
    assert [(a.command, a.result) for a in acks] == [
        (mavlink.MAV_CMD_COMPONENT_ARM_DISARM, mavlink.MAV_RESULT_ACCEPTED)
    ]
    assert [m for m in got if m.get_type() == "HEARTBEAT"][-1].base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED
    assert bench.server.armed().tolist() == [True, False, False]
    client.close()


def test_rc_override_moves_buoys_the_right_way_and_failsafe_stops_them(bench: VehicleBench) -> None:
    forward, left = Client(bench.server.ports[0], 1), Client(bench.server.ports[1], 2)
    for c in (forward, left):
        c.send(c.link.arm(True))
    bench.step(2)
    start = bench.physics.position.copy()

    def command() -> None:  # headings north: forward thrust goes north, thrust to the left goes west
        forward.send(forward.link.command(np.array([20.0, 0.0])))
        left.send(left.link.command(np.array([0.0, 20.0])))

    bench.step(100, command)
    moved = bench.physics.position - start
    assert moved[0, 1] > 5.0 and abs(moved[0, 0]) < 0.2 * moved[0, 1]  # north
    assert moved[1, 0] < -5.0 and abs(moved[1, 1]) < 0.2 * -moved[1, 0]  # west
    assert np.hypot(*moved[2]) < 1e-9  # never armed, never commanded: still
    speed_at_loss = np.hypot(*bench.physics.velocity[:2].T)
    assert (speed_at_loss > 0.3).all()
    assert bench.server.counters()["commands"] == 200

    bench.step(30)  # commands stop: after failsafe_s (1 s) the thrusters stop
    vehicles = bench.server.vehicles
    assert [v.counters.failsafes for v in vehicles[:2]] == [1, 1]
    assert not bench.server.actuators(bench.physics.t).any()
    assert not bench.physics.buoy.thrust_n[:2].any()
    assert (np.hypot(*bench.physics.velocity[:2].T) < 0.4 * speed_at_loss).all()
    forward.close()
    left.close()


def test_ports_follow_the_ardupilot_instance_rule_and_two_clients_get_telemetry(bench: VehicleBench) -> None:
    base = bench.base
    assert bench.server.ports == [base, base + 10, base + 20]
    assert [vehicle_port(i, base) for i in range(3)] == bench.server.ports
    gcs, autonomy, other = Client(base), Client(base), Client(base + 10)
    for c in (gcs, autonomy, other):
        c.send(heartbeat())
    bench.step(12)
    # ArduPilot's default streams (these clients ask for nothing): RAW_IMU, not SCALED_IMU, is in RAW_SENSORS.
    wanted = {"HEARTBEAT", "SYS_STATUS", "GPS_RAW_INT", "GLOBAL_POSITION_INT", "ATTITUDE", "RAW_IMU"}
    for c in (gcs, autonomy):
        got = c.drain()
        assert wanted <= types(got)
        assert {m.get_srcSystem() for m in got} == {1}
    got = other.drain()
    assert wanted <= types(got) and {m.get_srcSystem() for m in got} == {2}
    # GLOBAL_POSITION_INT (what MAVProxy shows) carries the GPS fix.
    gps = [m for m in gcs.messages if m.get_type() == "GPS_RAW_INT"][-1]
    position = [m for m in gcs.messages if m.get_type() == "GLOBAL_POSITION_INT"][-1]
    assert (position.lat, position.lon) == (gps.lat, gps.lon)
    x, y = ORIGIN.to_local(position.lat / 1e7, position.lon / 1e7)
    assert np.hypot(x - 0.0, y - 0.0) < 10.0  # buoy 0 starts at the origin; GPS noise 2 m per axis
    # Unasked, the vehicle streams at Rover's defaults (MAVn_* = 1 Hz): 1.2 s gives one or two of each.
    counts = {t: sum(m.get_type() == t for m in gcs.messages) for t in ("GPS_RAW_INT", "RAW_IMU", "HEARTBEAT")}
    assert all(1 <= n <= 2 for n in counts.values()), counts
    for c in (gcs, autonomy, other):
        c.close()


def test_vehicle_port_in_use_is_a_clear_error(bench: VehicleBench) -> None:
    with pytest.raises(OSError, match=r"vehicle 1 .*UDP 127\.0\.0\.1:\d+.*--base-port"):
        VehicleServer(["buoy"], [1.0], base_port=bench.base)


# ---------------------------------------------------------------- (c) the telemetry log


def test_tlog_is_read_by_pymavlink_and_mavlogdump(bench: VehicleBench) -> None:
    began = time.time()
    client = Client(bench.server.ports[0])
    client.send(heartbeat())
    client.send(client.link.arm(True))
    bench.step(5, lambda: client.send(client.link.command(np.array([10.0, 0.0]))))
    bench.tlog.close()
    path = bench.tlog.path
    log = mavutil.mavlink_connection(str(path))
    messages = []
    while (m := log.recv_match()) is not None:
        messages.append(m)
    assert len(messages) == bench.tlog.frames
    assert {"HEARTBEAT", "COMMAND_LONG", "COMMAND_ACK", "RC_CHANNELS_OVERRIDE", "GPS_RAW_INT"} <= types(messages)
    assert {m.get_srcSystem() for m in messages} == {1, 255}  # the vehicle and its ground station
    assert all(began - 1.0 <= m._timestamp <= time.time() + 1.0 for m in messages)
    dump = subprocess.run(
        [
            sys.executable,
            str(Path(sys.executable).parent / "mavlogdump.py"),
            "--types",
            "GLOBAL_POSITION_INT",
            str(path),
        ],
        capture_output=True,
        text=True,
        timeout=60,
        check=True,
    )
    assert "GLOBAL_POSITION_INT" in dump.stdout and "lat" in dump.stdout
    client.close()


def test_split_frames_skips_noise_and_keeps_whole_frames() -> None:
    a, b = heartbeat(), heartbeat()
    assert split_frames(b"\x00\x01" + a + b"\x07" + b + a[:5]) == [a, b]


# ---------------------------------------------------------------- (b) the radio relay


class FakeAgent:
    """A plain UDP socket that sends valid mesh packets to the relay as agent `agent_id`."""

    def __init__(self, agent_id: int, relay_address: tuple[str, int]) -> None:
        self.agent_id, self.relay = agent_id, relay_address
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind((HOST, 0))
        self.sock.setblocking(False)
        self.seq = 0
        self.inbox: list[bytes] = []

    def packet(self, fields: dict[str, np.ndarray] | None = None) -> bytes:
        self.seq += 1
        state = AgentState(self.agent_id, float(self.seq), Pose(1.0, 2.0, 0.5, 0.1, 0.0), fields or {})
        return encode_state(state, list(fields or {}))

    def send(self, data: bytes | None = None) -> bytes:
        data = self.packet() if data is None else data
        self.sock.sendto(data, self.relay)
        return data

    def received(self) -> list[bytes]:
        """Every packet received so far."""
        while True:
            try:
                self.inbox.append(self.sock.recvfrom(65535)[0])
            except BlockingIOError:
                return list(self.inbox)

    def close(self) -> None:
        self.sock.close()


def make_relay(positions: np.ndarray, channel: RadioChannel | None, clock) -> RadioRelay:
    _, (port,) = free_ports(0, extra=1)
    return RadioRelay(
        len(positions),
        lambda: positions,
        lambda: np.ones(len(positions), dtype=bool),
        channel=channel,
        range_m=300.0,
        broadcast_period_s=1.0,
        rng=np.random.default_rng(7),
        clock=clock,
        port=port,
    )


def wait_readable(sock: socket.socket) -> None:
    select.select([sock], [], [], 1.0)


def test_relay_delivery_follows_the_channel_model_with_distance() -> None:
    """Agent 0 broadcasts 400 packets (one per second of simulated time, so no other transmitter interferes);
    agent 1 is 10 m away, agent 2 250 m: each receives about the channel's delivery probability."""
    positions = np.array([[0.0, 0.0], [10.0, 0.0], [250.0, 0.0]])
    channel = RadioChannel()
    now = [0.0]
    relay = make_relay(positions, channel, lambda: now[0])
    agents = [FakeAgent(k, relay.address) for k in range(3)]
    try:
        for a in agents:  # each agent makes itself known
            a.send()
            wait_readable(relay.sock)
            relay.read()
        rounds = 400
        sent = []
        for k in range(rounds):
            now[0] = 10.0 + k
            sent.append(agents[0].send())
            wait_readable(relay.sock)
            relay.read()
            now[0] += 0.5  # past every latency (gamma, mean 20 ms)
            relay.flush()
            for a in agents[1:]:  # keep the receive buffers from overflowing
                a.received()
        time.sleep(0.05)
        near_all, far_all = agents[1].received(), agents[2].received()
        # Delivered unchanged; besides agent 0's rounds, agent 1 may have heard agent 2 make itself known.
        near = [p for p in near_all if p in sent]
        far = [p for p in far_all if p in sent]
        assert len(near_all) - len(near) <= 1 and len(far_all) == len(far)
        expected = channel.delivery_probability(np.array([10.0, 250.0]), 0.0)
        assert expected[0] > 0.99 and 0.75 < expected[1] < 0.9
        assert abs(len(near) / rounds - expected[0]) < 0.03
        assert abs(len(far) / rounds - expected[1]) < 0.07
        c = relay.counters()
        assert c["sent"] == rounds + 3
        assert c["delivered"] + c["dropped"] == 2 * rounds + 3  # registration: 0 -> none, 1 -> 0, 2 -> 0 and 1
        assert c["invalid"] == 0
    finally:
        relay.close()
        for a in agents:
            a.close()


def test_relay_counts_invalid_and_oversize_packets_and_respects_range() -> None:
    positions = np.array([[0.0, 0.0], [100.0, 0.0], [0.0, 400.0]])
    relay = make_relay(positions, RadioChannel(payload_limit_bytes=40), time.monotonic)
    agents = [FakeAgent(k, relay.address) for k in range(3)]
    try:
        for a in agents:
            a.send()
            relay.serve(0.05)
        stranger = encode_state(AgentState(7, 0.0, Pose(0.0, 0.0, 0.0), {}), [])  # agent 7 of a fleet of 3
        garbage = [b"hello", agents[0].packet()[:-1], stranger]
        for data in garbage:
            agents[0].send(data)
        big = agents[0].send(agents[0].packet({"goal": np.array([1.0, 2.0])}))  # 47 bytes > 40
        assert len(big) > 40
        relay.serve(0.1)
        c = relay.counters()
        assert c["invalid"] == 3
        assert c["oversize"] == 1
        # Agent 2 is 400 m away: beyond the radio's 300 m nominal range, never offered anything.
        assert c["out_of_range"] > 0
        assert agents[2].received() == []
    finally:
        relay.close()
        for a in agents:
            a.close()


def test_relay_without_channel_delivers_everything_in_range_at_once() -> None:
    positions = np.array([[0.0, 0.0], [100.0, 0.0]])
    relay = make_relay(positions, None, time.monotonic)
    a, b = FakeAgent(0, relay.address), FakeAgent(1, relay.address)
    try:
        b.send()
        relay.serve(0.05)
        packets = [a.send() for _ in range(20)]
        relay.serve(0.1)
        assert b.received() == packets
        assert relay.counters()["delivered"] == 20 and relay.counters()["dropped"] == 0
        state, _ = relay.latest[0]
        assert (state.pose.x, state.pose.y) == (1.0, 2.0)
    finally:
        relay.close()
        a.close()
        b.close()


# ---------------------------------------------------------------- set-behavior as MAVLink parameters


def test_behavior_parameters_for_set_behavior_events() -> None:
    base = BehaviorChoice(behavior="bob-rule", params={"p0": 50.0, "H": 0, "speed_scale": 0.8, "nearest": 20})
    params = behavior_parameters(base, BehaviorChoice(behavior="bob-rule", params={"p0": 5.0, "nearest": 20}), ORIGIN)
    assert params["BOB_BEHAVIOR"] == 0 and params["BOB_P0_M"] == 5.0 and params["BOB_H"] == 0
    assert params["BOB_SPD_SCALE"] == 0.5  # left out: the behaviour's default, as in a lockstep run
    with pytest.raises(ScenarioError, match="nearest"):  # no MAVLink parameter carries it
        behavior_parameters(base, BehaviorChoice(behavior="bob-rule", params={"p0": 5.0, "nearest": 5}), ORIGIN)
    with pytest.raises(ScenarioError, match="obstacle avoidance"):
        behavior_parameters(base, BehaviorChoice(behavior="bob-rule", params=base.params, avoid_obstacles=True), ORIGIN)
    with pytest.raises(ScenarioError, match="collision avoidance"):
        colliding = BehaviorChoice(behavior="bob-rule", params=base.params, avoid_collisions=True)
        behavior_parameters(base, colliding, ORIGIN)


# ---------------------------------------------------------------- (d) end to end with bob-autonomy run

# Simulated seconds per wall second of the process fleets here (and in test_motorboat_scenarios). At 5x a world
# step has 20 ms of wall time; on a slow 2-core machine with the other test worker busy the world's own step took
# 17-19 ms, fell behind, the vessels heard their vehicles "silent" and commanded neutral, and the swarm did not
# gather (seen in CI dry runs: 5 buoys ended at 14,045 m2 of 20,049). 3x leaves 33 ms a step.
SPEED = 3.0
DURATION_S = 130.0
SWITCH_S = 10.0


def aggregation_scenario(count: int = 5, duration_s: float = DURATION_S, switch: bool = True):
    """`count` buoys on a square lattice 100 m apart, lossy radio, still water; eq. 5 with H = 0 and p0 = 100 m
    (they hold their places), switched to p0 = 5 m at SWITCH_S (a set-behavior event: MAVLink parameters through
    the ground-station port), or p0 = 5 m from the start."""
    params = {"p0": 100.0 if switch else 5.0, "H": 0, "speed_scale": 0.8, "max_speed": 1.0}
    event = {"t_s": SWITCH_S, "action": "set-behavior", "fraction": 1.0, "choice": {"behavior": "bob-rule"}}
    event["choice"]["params"] = {**params, "p0": 5.0}
    return validate_scenario(
        {
            "name": "aggregation-processes",
            "duration_s": duration_s,
            "dt_s": DT_S,
            "seed": 3,
            "log_period_s": 1.0,
            "fidelity": "physics",
            "network": {"range_m": 300.0, "broadcast_period_s": 0.5, "expiry_s": 3.0, "radio": {}},
            "groups": [
                {
                    "name": "buoys",
                    "count": count,
                    "body": "buoy",
                    "behavior": "bob-rule",
                    "params": params,
                    "start": {"lattice": {"center": [0.0, 0.0], "spacing_m": 100.0, "kind": "square"}},
                }
            ],
            "events": [event] if switch else [],
            "metrics": {"kind": "aggregation"},
        },
        "test scenario",
    )


def gone(pid: int) -> bool:
    """The process has exited and been reaped, and nothing is left in its process group."""
    try:
        os.kill(pid, 0)
        return False
    except ProcessLookupError:
        pass
    try:
        os.killpg(pid, 0)
        return False
    except ProcessLookupError:
        return True


def test_five_buoys_in_separate_processes_aggregate(tmp_path: Path) -> None:
    base, (mesh, gcs) = free_ports(5, extra=2)
    scenario = aggregation_scenario()
    out = tmp_path / "run"
    options = ProcessOptions(speed=SPEED, base_port=base, mesh_port=mesh, gcs_port=gcs)
    result = run_processes_to_directory(scenario, out, options)
    m, fleet = result.metrics, result.fleet

    # Every autonomy process exited by itself on SIGTERM; none is left, nor anything in its group.
    assert m["processes"]["exit_codes"] == [0] * 5 and m["processes"]["killed"] == 0
    assert all(gone(p.pid) for p in fleet.processes)
    assert all(_bindable(vehicle_port(i, base)) for i in range(5)) and _bindable(mesh)

    # The outputs of a lockstep run, plus the telemetry log and the vessels' logs.
    names = {p.name for p in out.iterdir()}
    assert {"trajectory.csv", "metrics.json", "scenario.toml", "environment.json", "trajectories.png"} <= names
    assert "hull_area.png" in names
    assert {"vehicles.tlog"} | {f"vessel-{k:02d}.{x}" for k in range(1, 6) for x in ("log", "out")} <= names
    rows = (out / "trajectory.csv").read_text().splitlines()
    assert rows[0].split(",") == list(TRAJECTORY_COLUMNS)
    assert len(rows) == 1 + 5 * (round(DURATION_S / scenario.log_period_s) + 1)
    assert json.loads((out / "metrics.json").read_text())["area_final_m2"] == m["area_final_m2"]
    # Same start as the lockstep fleet: same world, same seeded poses.
    rng = np.random.default_rng(scenario.seed)
    start, _ = initial_poses(scenario, build_world(scenario, rng), rng)
    np.testing.assert_allclose(result.recorder.frames[0].position, start)

    # p0 went from 100 m to 5 m over MAVLink at SWITCH_S; every vessel had it within a few simulated seconds.
    assert fleet.events_log == [{"t_s": SWITCH_S, "action": "set-behavior", "agents": [0, 1, 2, 3, 4]}]
    # One round trip for the whole set (set_params): 0.1 simulated s here (0.6 one parameter at a time); a lost
    # echo costs a retry (1 wall s, 3 simulated s at this speed).
    delays = m["event_delays_s"]
    assert len(delays) == 1 and delays[0] < 5.0 and "event_errors" not in m, (delays, m["gcs_kernel_drops"])
    # The swarm aggregates: hull area and nearest-neighbour distances fall (the aggregation metrics).
    assert m["area_before_m2"] == pytest.approx(20_000.0, rel=0.1)  # held the 100 m lattice until the switch
    assert m["area_final_m2"] < 0.1 * m["area_before_m2"]
    nn_start = nearest_neighbor_m(result.recorder.frames[0].position).mean()
    nn_end = nearest_neighbor_m(result.recorder.frames[-1].position).mean()
    assert nn_start == pytest.approx(100.0) and nn_end < 30.0
    assert m == {**m, **METRICS["aggregation"](fleet, result.recorder, {})}  # the lockstep run's metrics
    area = f"hull area {m['area_before_m2']:.0f} -> {m['area_final_m2']:.0f} m2"
    print(f"\n{area}, mean NN {nn_start:.1f} -> {nn_end:.1f} m")
    print(f"realtime {m['realtime']}, startup {m['processes']['startup_wall_s']} s")

    # The full stack was in the loop: MAVLink commands, the lossy relay, beliefs from the mesh.
    assert m["vehicles"]["commands"] > 5 * 0.5 * DURATION_S / DT_S
    assert m["vehicles"]["acks"] >= 5 and m["vehicles"]["refused"] == 0
    net = m["network"]
    assert net["sent"] > 0 and net["delivered"] > 0 and net["invalid"] == 0
    assert m["estimation"]["buoy"]["position_rms_m"] < 5.0
    assert m["realtime"]["late_fraction"] < 0.25
    log = mavutil.mavlink_connection(str(out / "vehicles.tlog"))
    systems = set()
    while (msg := log.recv_match(type="HEARTBEAT")) is not None:
        systems.add(msg.get_srcSystem())
    assert systems == {1, 2, 3, 4, 5, 255}


def fleet_children(pid: int) -> list[int]:
    """PIDs of the processes whose parent is `pid` (Linux /proc)."""
    children = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                stat = (entry / "stat").read_text()
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
                children.append(int(entry.name))
    return children


def start_fleet_cli(tmp_path: Path, count: int) -> tuple[subprocess.Popen, Path, int, int, bool]:
    """`bob-sitl fleet --processes` on `count` aggregation vessels (600 s, no p0 switch) on free ports, as a
    child process: (process, output directory, base port, mesh port, whether every vessel logged that it armed
    within 60 s). The caller stops it."""
    base, (mesh, gcs) = free_ports(count, extra=2)
    path = tmp_path / "fleet.toml"
    path.write_text(scenario_to_toml(aggregation_scenario(count=count, duration_s=600.0, switch=False)))
    out = tmp_path / "out"
    command = [sys.executable, "-m", "sitl.cli", "fleet", str(path), "--processes", "--speed", str(SPEED)]
    command += ["--out", str(out), "--quiet", "--base-port", str(base), "--mesh-port", str(mesh)]
    command += ["--gcs-port", str(gcs)]
    cli = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 60.0
    while time.monotonic() < deadline and cli.poll() is None:
        logs = list(tmp_path.glob(".out.*/vessel-0*.log"))
        if len(logs) == count and all("armed" in p.read_text() for p in logs):
            return cli, out, base, mesh, True
        time.sleep(0.2)
    return cli, out, base, mesh, False


def test_ctrl_c_stops_the_fleet_cleanly_and_writes_its_outputs(tmp_path: Path) -> None:
    cli, out, base, mesh, started = start_fleet_cli(tmp_path, 2)
    try:
        assert started, cli.stderr.read() if cli.poll() is not None else "vessels did not arm"
        time.sleep(1.0)
        forks = fleet_children(cli.pid)  # the fork server, whose children are the vessels
        assert len(forks) == 1
        children = [*forks, *fleet_children(forks[0])]
        assert len(children) == 3
        cli.send_signal(signal.SIGINT)
        stdout, stderr = cli.communicate(timeout=30)
    finally:
        if cli.poll() is None:
            cli.kill()
    assert cli.returncode == 1, stderr  # written, but an interrupted run does not pass
    metrics = json.loads((out / "metrics.json").read_text())
    assert 0.0 < metrics["interrupted_at_s"] < 600.0 and metrics["passed"] is False
    assert metrics["processes"]["exit_codes"] == [0, 0] and metrics["processes"]["killed"] == 0
    assert metrics["processes"]["launcher"] == "fork-server" and len(metrics["processes"]["stop_s"]) == 2
    assert all(0.0 < t < 6.0 for t in metrics["processes"]["stop_s"])
    assert (out / "trajectory.csv").exists() and (out / "vehicles.tlog").stat().st_size > 0
    assert '"interrupted_at_s"' in stdout
    assert all(gone(pid) for pid in children)
    assert all(_bindable(vehicle_port(i, base)) for i in range(2)) and _bindable(mesh)
    assert not list(tmp_path.glob(".out.*"))  # no staging directory left


def test_a_vessel_that_never_arms_is_a_clear_error(tmp_path: Path) -> None:
    fake = tmp_path / "fake_autonomy.py"
    fake.write_text(
        "import sys, time\n"
        "if '--help' in sys.argv:\n"
        "    print('usage: fake run --vehicle V --system-id N --mesh M')\n"
        "    sys.exit(0)\n"
        "print('fake autonomy: never arming', flush=True)\n"
        "time.sleep(600)\n"
    )
    base, (mesh, gcs) = free_ports(2, extra=2)
    options = ProcessOptions(
        speed=SPEED, base_port=base, mesh_port=mesh, gcs_port=gcs, arm_timeout_s=2.0,
        autonomy=(sys.executable, str(fake)),
    )  # fmt: skip
    out = tmp_path / "out"
    with pytest.raises(ProcessFleetError, match=r"vessel 1 \(system id 1, UDP \d+\) was not armed") as error:
        run_processes_to_directory(aggregation_scenario(count=2, duration_s=10.0, switch=False), out, options)
    assert "never arming" in str(error.value)  # the tail of its log
    assert not out.exists() and not list(tmp_path.glob(".out.*"))
    assert all(_bindable(vehicle_port(i, base)) for i in range(2)) and _bindable(mesh)
    assert running(str(fake)) == []


def running(text: str) -> list[int]:
    """PIDs of the processes whose command line contains `text` (Linux /proc)."""
    pids = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                if text in (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace"):
                    pids.append(int(entry.name))
            except OSError:
                continue
    return pids
