"""Interop with MAVProxy (from PyPI, in the dev extras): it shows a simulated vehicle of a `bob-sitl fleet`
run (heartbeat, armed, position), and it lists and sets the parameters of a running autonomy process and
uploads waypoints to it, as a field engineer would from a ground station."""

from __future__ import annotations

import queue
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from vessel_helpers import ORIGIN, StandInVehicle

from bob_autonomy.behavior_config import BehaviorChoice
from bob_autonomy.clock import ScaledWallClock
from bob_autonomy.vessel import Vessel, VesselConfig

MAVPROXY = shutil.which("mavproxy.py", path=str(Path(sys.executable).parent)) or shutil.which("mavproxy.py")
pytestmark = [
    pytest.mark.skipif(MAVPROXY is None, reason="MAVProxy is not installed (pip install -e '.[dev]')"),
    pytest.mark.xdist_group("realtime"),  # real time and processes: never beside the other real-time tests
]


class MavproxySession:
    """mavproxy.py with its console on pipes: send a command line, wait for a line matching a pattern."""

    def __init__(self, master: str, cwd: Path, component: int = 191) -> None:
        self.process = subprocess.Popen(
            [MAVPROXY, f"--master={master}", "--target-system=1", f"--target-component={component}", "--nowait",
             "--no-state", "--state-basedir", str(cwd)],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=cwd,
        )  # fmt: skip
        self.lines: queue.Queue[str] = queue.Queue()
        self.transcript: list[str] = []
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        for line in self.process.stdout:
            self.lines.put(line.rstrip())

    def send(self, command: str) -> None:
        self.process.stdin.write(command + "\n")
        self.process.stdin.flush()

    def expect(self, pattern: str, timeout_s: float) -> re.Match:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            try:
                line = self.lines.get(timeout=0.1)
            except queue.Empty:
                continue
            self.transcript.append(line)
            match = re.search(pattern, line)
            if match:
                return match
        raise AssertionError(f"MAVProxy never printed /{pattern}/; it printed:\n" + "\n".join(self.transcript[-40:]))

    def close(self) -> None:
        try:
            self.send("exit")
            self.process.wait(timeout=5)
        except (OSError, subprocess.TimeoutExpired):
            self.process.kill()
            self.process.wait()


def test_mavproxy_lists_and_sets_parameters_and_uploads_waypoints(tmp_path: Path) -> None:
    vehicle = StandInVehicle()
    vehicle.start()
    config = VesselConfig(
        vehicle=f"udpout:127.0.0.1:{vehicle.port}",
        system_id=1,
        behavior=BehaviorChoice(behavior="bob-rule", params={"p0": 10.0}),
        origin=ORIGIN,
        controller="simple",
        gcs="udpin:127.0.0.1:0",
        autostart=False,
    )
    vessel = Vessel(config, clock=ScaledWallClock(1.0))
    runner = threading.Thread(target=vessel.run, daemon=True)
    runner.start()
    port = vessel.gcs_link.local_address[1]
    waypoints = tmp_path / "goals.txt"
    waypoints.write_text(
        "QGC WPL 110\n"
        f"0\t1\t0\t16\t0\t0\t0\t0\t{ORIGIN[0]}\t{ORIGIN[1]}\t0\t1\n"
        f"1\t0\t3\t16\t0\t0\t0\t0\t{ORIGIN[0] + 0.0002}\t{ORIGIN[1] + 0.0001}\t0\t1\n"
    )
    session = MavproxySession(f"udpout:127.0.0.1:{port}", tmp_path)
    try:
        session.expect(r"Detected vehicle 1:191", 20.0)
        count = int(session.expect(r"Received (\d+) parameters", 40.0).group(1))
        assert count == len(vessel.params)
        session.send("param show BOB_P0_M")
        session.expect(r"BOB_P0_M\s+10(\.0+)?\b", 10.0)
        session.send("param set BOB_P0_M 7.5")
        time.sleep(1.0)  # the vessel answers the set with the PARAM_VALUE in force, which updates MAVProxy's copy
        session.send("param show BOB_P0_M")
        session.expect(r"BOB_P0_M\s+7\.5", 10.0)
        session.send(f"wp load {waypoints}")
        session.expect(r"MISSION_ACK: TYPE_MISSION: ACCEPTED", 15.0)
    finally:
        session.close()
        vessel.stop()
        runner.join(5.0)
        vehicle.close()
    assert vessel.params.get("BOB_P0_M") == 7.5
    assert vessel.supervisor.behavior().p0 == 7.5
    assert vessel.params.goals == [ORIGIN, (ORIGIN[0] + 0.0002, ORIGIN[1] + 0.0001)]


def test_mavproxy_shows_a_simulated_vehicle_of_a_process_fleet(tmp_path: Path) -> None:
    from test_process_fleet import aggregation_scenario, free_ports

    from sitl.scenario import scenario_to_toml, validate_scenario

    base, (mesh, gcs) = free_ports(1, extra=2)
    data = aggregation_scenario(count=1, duration_s=600.0).model_dump()
    data["events"] = []
    path = tmp_path / "one.toml"
    path.write_text(scenario_to_toml(validate_scenario(data, "one buoy")))
    fleet = subprocess.Popen(
        [sys.executable, "-m", "sitl.cli", "fleet", str(path), "--processes", "--base-port", str(base),
         "--mesh-port", str(mesh), "--gcs-port", str(gcs), "--out", str(tmp_path / "run"), "--quiet"],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
    session = MavproxySession(f"udpout:127.0.0.1:{base}", tmp_path, component=1)
    try:
        session.expect(r"Detected vehicle 1:1", 60.0)
        session.expect(r"ARMED", 30.0)  # armed by its bob-autonomy process
        time.sleep(3.0)
        session.send("status GLOBAL_POSITION_INT")
        match = session.expect(r"GLOBAL_POSITION_INT \{.*lat : (-?\d+), lon : (-?\d+)", 10.0)
        lat, lon = int(match.group(1)) / 1e7, int(match.group(2)) / 1e7
        origin = validate_scenario(data, "one buoy").origin
        assert abs(lat - origin.lat_deg) < 1e-3 and abs(lon - origin.lon_deg) < 1e-3  # at the scenario's origin
        session.send("status HEARTBEAT")
        session.expect(r"HEARTBEAT \{type : 11, autopilot : 3", 10.0)  # a surface boat, ArduPilot-like
    finally:
        session.close()
        fleet.send_signal(signal.SIGINT)
        fleet.wait(timeout=60)
