"""Swarms on ArduPilot's own autopilots: Rover SITL instances, each driven by its own `bob-autonomy run` as on a
vessel's computer, talking over a UDP broadcast mesh (`udpbcast`, as on an IP radio; no relay of ours between them).

- Four omni rovers (the buoy's stand-in) start at the corners of a 60 m square and aggregate by eq. (5) with H = 0:
  each alone would stay where it is, so only the mesh can bring them together. Eq. (5) balances four agents on a
  square of side s where sqrt(2) (1 - p0^2/s^2) + 1 - p0^2/(2 s^2) = 0, i.e. s^2 = p0^2 (sqrt(2) + 1/2) /
  (sqrt(2) + 1), s = 0.89 p0 (diagonal 1.26 p0).
- The same four waiting for their start, one ground station (pymavlink) for all: one MISSION_START to system 0
  starts them, one PARAM_SET of BOB_P0_M to system 0 resizes their square.
- A mixed swarm on a mesh signed with the fleet key: an omni leader drives 60 m east; an omni rover and two
  motorboats (ArduPilot's SITL motorboat: rudder and throttle) follow it (H = 1, the leader's position as goal),
  while a radio without the key broadcasts that the leader is 300 m north-east.

Skipped unless ARDUPILOT_SITL names a built `ardurover` (docs/ardupilot.md). Judged by what each autopilot itself
reports on its second serial port (GLOBAL_POSITION_INT), and by the vessels' own mesh counters for what they refused.
"""

from __future__ import annotations

import contextlib
import itertools
import json
import math
import os
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink
from sitl_harness import BINARY, HOME, NEEDS_SITL, RoverSitl, free_udp_port, home_at, local_xy

from bob_autonomy.core.interfaces import AgentState, Pose
from bob_autonomy.network.mesh import encode_state

pytestmark = NEEDS_SITL

RUN_S = 150.0  # each autonomy's run after its start-up, s
CORNERS = [(-30.0, -30.0), (30.0, -30.0), (30.0, 30.0), (-30.0, 30.0)]  # east, north m from HOME
P0_M = 15.0
SIDE_M = P0_M / math.sqrt((math.sqrt(2) + 1) / (math.sqrt(2) + 0.5))  # eq. (5)'s square (module docstring)
SETTLED_S = 20.0  # the aggregation is judged over the last this many seconds of the run
LEADER_GOAL = (60.0, 0.0)
FOLLOW_RADIUS_M = 25.0  # every follower this close to the leader at the end


def _autonomy(
    sitl: RoverSitl, mesh: str, log: Path, behavior: dict, *extra: str, duration_s: float = RUN_S
) -> subprocess.Popen:
    command = [
        sys.executable, "-m", "bob_autonomy.cli", "run",
        "--vehicle", f"tcp:127.0.0.1:{sitl.serial0}", "--system-id", str(sitl.system_id),
        f"--origin={HOME[0]},{HOME[1]}", "--mesh", mesh, "--broadcast-period", "0.5", "--neighbor-expiry", "3",
        "--behavior-json", json.dumps(behavior), "--arm-timeout", "60", "--duration", str(duration_s),
        "--log-file", str(log), *extra,
    ]  # fmt: skip
    return subprocess.Popen(command, env={**os.environ, "PYTHONUNBUFFERED": "1"})


def _start(stack: contextlib.ExitStack, tmp: Path, fleet: list[tuple[str, tuple[float, float]]]) -> list[RoverSitl]:
    """One SITL per (model, (east, north) m from HOME), system ids 1.., each initialised and at its place."""
    sitls = []
    for k, (model, place) in enumerate(fleet):
        workdir = tmp / f"vessel{k + 1}"
        workdir.mkdir()
        params = {"MAV_SYSID": k + 1}  # the vessel's agent id on the mesh is its system id - 1
        sitls.append(stack.enter_context(RoverSitl(BINARY, model, workdir, params=params, home=home_at(*place))))
    for sitl in sitls:
        sitl.wait_initialised()
    places = np.array([place for _model, place in fleet])
    deadline = time.monotonic() + 60.0  # until each reports its place (0, 0 before its GPS has a fix)
    while time.monotonic() < deadline:
        starts = np.array([_where(sitl, time.monotonic()) for sitl in sitls])
        if np.allclose(starts, places, atol=3.0):
            return sitls
        time.sleep(0.5)
    raise AssertionError(f"the vehicles start at {np.round(starts, 1)}, not {places.tolist()}")


def _run_to_the_end(processes: list[subprocess.Popen], logs: Path) -> None:
    try:
        codes = [p.wait(timeout=RUN_S + 120) for p in processes]
    finally:
        for p in processes:
            if p.poll() is None:
                p.kill()
    assert codes == [0] * len(processes), f"exit codes {codes}; see {logs}/vessel*.log"


def _where(sitl: RoverSitl, t: float) -> np.ndarray:
    """The autopilot's own position (east, north m) last reported before wall time t."""
    _t, lat, lon, _hdg = [p for p in sitl.seen.positions if p[0] <= t][-1]
    return np.array(local_xy(lat, lon))


def _pairwise(points: np.ndarray) -> list[float]:
    return [float(np.hypot(*(points[i] - points[j]))) for i, j in itertools.combinations(range(len(points)), 2)]


def _mesh_counters(log: Path) -> dict:
    """The mesh counters the vessel logs when it stops."""
    found = re.search(r"mesh: (\{.*\})$", log.read_text(), flags=re.MULTILINE)
    assert found, f"no mesh counters in {log}"
    return json.loads(found.group(1))


def test_four_ardupilot_buoys_aggregate_over_a_broadcast_mesh(tmp_path) -> None:
    mesh = f"udpbcast:127.255.255.255:{free_udp_port()}"
    aggregate = {"behavior": "bob-rule", "params": {"H": 0, "p0": P0_M, "max_speed": 1.5, "speed_scale": 1.0}}
    with contextlib.ExitStack() as stack:
        sitls = _start(stack, tmp_path, [("omni", corner) for corner in CORNERS])
        starts = np.array([_where(s, time.monotonic()) for s in sitls])
        started = time.monotonic()
        _run_to_the_end([_autonomy(s, mesh, tmp_path / f"vessel{s.system_id}.log", aggregate) for s in sitls], tmp_path)
        ended = time.monotonic()
        closest = min(  # over the whole run, every half second
            min(_pairwise(np.array([_where(s, t) for s in sitls]))) for t in np.arange(started + 1.0, ended, 0.5)
        )
        settled = [np.array([_where(s, t) for s in sitls]) for t in np.arange(ended - SETTLED_S, ended, 1.0)]
        spacing = sorted(_pairwise(settled[-1]))
        moved = max(float(np.ptp(np.array([frame[k] for frame in settled]), axis=0).max()) for k in range(4))
        print(
            f"start pairs {np.round(sorted(_pairwise(starts)), 1)} m; end pairs {np.round(spacing, 1)} m "
            f"(eq. 5: sides {SIDE_M:.1f}, diagonals {SIDE_M * math.sqrt(2):.1f}); closest ever {closest:.1f} m; "
            f"largest drift over the last {SETTLED_S:g} s {moved:.1f} m"
        )
        # From 60-85 m apart to the square eq. (5) balances: four sides and two diagonals, each within 10 %.
        expected = [SIDE_M] * 4 + [SIDE_M * math.sqrt(2)] * 2
        assert np.allclose(spacing, expected, rtol=0.1), f"pairs {np.round(spacing, 1)} m, eq. (5) {expected}"
        assert closest > 0.4 * P0_M, f"two rovers came within {closest:.1f} m"
        assert moved < 3.0, f"still moving: a rover drifted {moved:.1f} m over the last {SETTLED_S:g} s"


class KeylessRadio:
    """A radio without the fleet key on the mesh's port, broadcasting every 0.2 s that agent `agent_id` is at
    (east, north) m: what a stranger sends, or a member whose key was not loaded."""

    def __init__(self, mesh: str, agent_id: int, east_north: tuple[float, float]) -> None:
        _kind, address, port = mesh.split(":")
        self.destination = (address, int(port))
        self.agent_id, self.east_north = agent_id, east_north
        self.sent = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._send, daemon=True)

    def _send(self) -> None:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_BROADCAST, 1)
            while not self._stop.wait(0.2):
                claim = AgentState(self.agent_id, time.time(), Pose(*self.east_north, 0.0, 0.0, 0.0))
                sock.sendto(encode_state(claim, []), self.destination)
                self.sent += 1

    def __enter__(self) -> KeylessRadio:
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join(timeout=2)


def test_a_mixed_swarm_follows_its_leader_on_a_signed_broadcast_mesh_and_refuses_a_keyless_radio(tmp_path) -> None:
    mesh = f"udpbcast:127.255.255.255:{free_udp_port()}"
    key = tmp_path / "fleet.key"
    key.write_text("fleet passphrase for the real swarm\n")
    fleet = [("omni", (0.0, 0.0)), ("omni", (-15.0, -10.0)), ("motorboat", (-15.0, 10.0)), ("motorboat", (-30.0, 0.0))]
    lead = {"behavior": "waypoints", "params": {"waypoints": [list(LEADER_GOAL)], "speed": 0.5, "arrival_radius_m": 3}}
    follow = {"behavior": "bob-rule", "params": {"H": 1, "leader_id": 0, "p0": 8.0, "max_speed": 1.5, "speed_scale": 1}}
    with contextlib.ExitStack() as stack:
        sitls = _start(stack, tmp_path, fleet)
        start = _where(sitls[0], time.monotonic())
        logs = [tmp_path / f"vessel{s.system_id}.log" for s in sitls]
        with KeylessRadio(mesh, 0, (300.0, 300.0)) as intruder:
            processes = []
            for k, (sitl, log, (model, _place)) in enumerate(zip(sitls, logs, fleet, strict=True)):
                kind = "motorboat" if model == "motorboat" else "buoy"
                behavior = lead if k == 0 else follow
                processes.append(_autonomy(sitl, mesh, log, behavior, "--mesh-key", str(key), "--kind", kind))
            started = time.monotonic()
            _run_to_the_end(processes, tmp_path)
        ended = time.monotonic()
        leader_end = _where(sitls[0], ended)
        behind = [float(np.hypot(*(_where(s, ended) - leader_end))) for s in sitls[1:]]
        toward_claim = max(  # the farthest any follower went north-east, towards the keyless radio's claim, m
            float(np.dot(_where(s, t), (1.0, 1.0))) / math.sqrt(2)
            for s in sitls[1:]
            for t in np.arange(started, ended, 1.0)
        )
        closest = min(  # between any two vessels over the run, every half second
            min(_pairwise(np.array([_where(s, t) for s in sitls]))) for t in np.arange(started + 1.0, ended, 0.5)
        )
        counters = [_mesh_counters(log) for log in logs]
        refused = [c["rejected"]["unsigned"].get("0", 0) for c in counters]
        print(
            f"leader from {np.round(start, 1)} to {np.round(leader_end, 1)} m; followers {np.round(behind, 1)} m "
            f"from it at the end, closest pair {closest:.1f} m; the keyless radio sent {intruder.sent}, the "
            f"vessels refused {refused} (the leader, whose id it claims, too); members "
            f"heard {[c['received'] for c in counters]}"
        )
        assert np.hypot(*(leader_end - LEADER_GOAL)) < 5.0, f"the leader ended at {np.round(leader_end, 1)}"
        assert max(behind) < FOLLOW_RADIUS_M, f"followers {np.round(behind, 1)} m from the leader"
        assert closest > 2.0, f"two vessels came within {closest:.1f} m of each other"
        assert toward_claim < 60.0, f"a follower went {toward_claim:.0f} m towards the keyless radio's claim"
        # Every vessel refuses its packets as unsigned, the leader whose id it claims too (not taken for another
        # member on the leader's system id).
        assert all(n > 0.5 * intruder.sent for n in refused), f"refused {refused} of {intruder.sent}"
        assert counters[0]["same_id"] == 0, counters[0]
        assert all(c["received"] > 100 for c in counters), "the members did not hear each other"


class FleetGroundStation:
    """A ground station for a whole fleet, on pymavlink's own MAVLink (system 255): one UDP port that every
    vessel's `--gcs udpout:` points at; what it sends goes to every vessel heard, with a HEARTBEAT a second (the
    vessels' ground-station failsafe counts those). `heard` keeps each (system, component)'s last HEARTBEAT time,
    `acks` each COMMAND_ACK and `params` each PARAM_VALUE, with the sender's system."""

    def __init__(self) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.1)
        self.port = self.sock.getsockname()[1]
        self.mav = mavlink.MAVLink(None, srcSystem=255, srcComponent=mavlink.MAV_COMP_ID_MISSIONPLANNER)
        self.vessels: dict[int, tuple[str, int]] = {}  # system id -> its address
        self.heard: dict[tuple[int, int], float] = {}
        self.acks: list[tuple[int, int, int]] = []  # (system, command, result)
        self.params: list[tuple[int, str, float]] = []  # (system, name, value)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, daemon=True)

    def send_to_all(self, msg) -> None:
        data = msg.pack(self.mav)
        for address in list(self.vessels.values()):
            self.sock.sendto(data, address)

    def _serve(self) -> None:
        next_beat = 0.0
        while not self._stop.is_set():
            if time.monotonic() >= next_beat:
                next_beat = time.monotonic() + 1.0
                beat = self.mav.heartbeat_encode(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
                self.send_to_all(beat)
            try:
                data, address = self.sock.recvfrom(65535)
            except TimeoutError:
                continue
            for msg in self.mav.parse_buffer(data) or []:
                system, component = msg.get_srcSystem(), msg.get_srcComponent()
                self.vessels[system] = address
                name = msg.get_type()
                if name == "HEARTBEAT":
                    self.heard[(system, component)] = time.monotonic()
                elif name == "COMMAND_ACK" and component == mavlink.MAV_COMP_ID_ONBOARD_COMPUTER:
                    self.acks.append((system, msg.command, msg.result))
                elif name == "PARAM_VALUE" and component == mavlink.MAV_COMP_ID_ONBOARD_COMPUTER:
                    self.params.append((system, msg.param_id, msg.param_value))

    def __enter__(self) -> FleetGroundStation:
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
        self.sock.close()


def _square(sitls: list[RoverSitl], p0_m: float, t: float) -> tuple[list[float], list[float]]:
    """The sorted pair distances at wall time t, and those of eq. (5)'s square for p0_m."""
    side = p0_m / math.sqrt((math.sqrt(2) + 1) / (math.sqrt(2) + 0.5))
    return sorted(_pairwise(np.array([_where(s, t) for s in sitls]))), [side] * 4 + [side * math.sqrt(2)] * 2


def test_one_ground_station_starts_a_waiting_swarm_and_resizes_it_with_one_message_each(tmp_path) -> None:
    """The swarm of the first test, waiting for its start (`--wait-for-start`), each vessel's ground-station link
    on one ground station: one MISSION_START to system 0 starts all four, each acknowledging; one PARAM_SET of
    BOB_P0_M to system 0 later resizes the square they hold to the new p0."""
    mesh = f"udpbcast:127.255.255.255:{free_udp_port()}"
    aggregate = {"behavior": "bob-rule", "params": {"H": 0, "p0": P0_M, "max_speed": 1.5, "speed_scale": 1.0}}
    new_p0 = 25.0
    with contextlib.ExitStack() as stack:
        sitls = _start(stack, tmp_path, [("omni", corner) for corner in CORNERS])
        gcs = stack.enter_context(FleetGroundStation())
        extra = ("--wait-for-start", "--gcs", f"udpout:127.0.0.1:{gcs.port}")
        processes = [
            _autonomy(s, mesh, tmp_path / f"vessel{s.system_id}.log", aggregate, *extra, duration_s=RUN_S + 120)
            for s in sitls
        ]
        try:
            deadline = time.monotonic() + 90.0  # all four components 191 heard, and every vessel armed
            while time.monotonic() < deadline:
                armed = [s.seen.modes and s.seen.modes[-1][2] for s in sitls]
                if all(armed) and all((k, 191) in gcs.heard for k in (1, 2, 3, 4)):
                    break
                time.sleep(0.5)
            assert all(armed), f"armed {armed}; heard {sorted(gcs.heard)}"
            time.sleep(10.0)  # waiting for the start: held where they are
            waited = _square(sitls, P0_M, time.monotonic())[0]
            assert waited[0] > 55.0, f"the swarm moved before its start: pairs {np.round(waited, 1)} m"

            gcs.send_to_all(gcs.mav.command_long_encode(0, 191, mavlink.MAV_CMD_MISSION_START, 0, 0, 0, 0, 0, 0, 0, 0))
            time.sleep(2.0)
            started = sorted(system for system, command, result in gcs.acks if command == 300 and result == 0)
            assert started == [1, 2, 3, 4], gcs.acks
            time.sleep(RUN_S - 30.0)
            first, expected = _square(sitls, P0_M, time.monotonic())
            assert np.allclose(first, expected, rtol=0.1), f"pairs {np.round(first, 1)} m, eq. (5) {expected}"

            gcs.send_to_all(gcs.mav.param_set_encode(0, 191, b"BOB_P0_M", new_p0, mavlink.MAV_PARAM_TYPE_REAL32))
            time.sleep(2.0)
            echoed = sorted(system for system, name, value in gcs.params if name == "BOB_P0_M" and value == new_p0)
            assert echoed == [1, 2, 3, 4], gcs.params
            time.sleep(80.0)
            resized, expected = _square(sitls, new_p0, time.monotonic())
            print(f"p0 {P0_M:g} m: pairs {np.round(first, 1)} m; p0 {new_p0:g} m: pairs {np.round(resized, 1)} m")
            assert np.allclose(resized, expected, rtol=0.1), f"pairs {np.round(resized, 1)} m, eq. (5) {expected}"
        finally:
            for p in processes:
                p.send_signal(signal.SIGTERM)
            _run_to_the_end(processes, tmp_path)
