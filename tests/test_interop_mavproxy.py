"""Interop with MAVProxy (from PyPI, in the dev extras): it shows a simulated vehicle of a `bob-sitl fleet`
run (heartbeat, armed, position), and it lists and sets the parameters of a running autonomy process and
uploads waypoints to it, as a field engineer would from a ground station.

And as the ground station of a 2-vessel process fleet on one UDP port (issue #11 item 4), the checks the MAVSDK tests
make (tests/test_interop_mavsdk.py) as far as MAVProxy goes: both vessels with their autopilot and autonomy detected;
per vessel armed, mode, battery, GPS, home, a finite heading and AUTOPILOT_VERSION; every BOB_* parameter of
component 191 fetched and one set; the autopilot's parameters fetched; a mission loaded to the autopilot and listed
back; hold, disarm, arm and back to MANUAL. MAVProxy prints what it hears only from its current target (`vehicle
N:C`), so a small MAVProxy module (tests/mavproxy_probe.py, MAVProxy's module API) reports what arrived from every
system and component.

What MAVProxy does that a reader should know: it fetches parameters over MAVFTP first (@PARAM/param.pck) and falls
back to PARAM_REQUEST_LIST only when that times out (several seconds); neither the simulated autopilot nor component
191 serves MAVFTP, so the session turns it off (`set param_ftp 0`). (It used to say "fence breach" at start: the
simulated autopilot's SYS_STATUS left out the sensor bits, MAV_SYS_STATUS_GEOFENCE's health among them, which
ArduPilot sets whenever its fence has not failed; it now reports them as a Rover SITL does.)
"""

from __future__ import annotations

import json
import math
import threading
import time
from pathlib import Path

import pytest
from interop_fleet import interop_fleet
from mavproxy_session import MAVPROXY, MavproxySession
from vessel_helpers import ORIGIN, StandInVehicle, ground_station_vessel_config

from bob_autonomy.core.clock import ScaledWallClock
from bob_autonomy.onboard.vessel import Vessel

pytestmark = [
    pytest.mark.skipif(MAVPROXY is None, reason="MAVProxy is not installed (pip install -e '.[dev]')"),
    pytest.mark.xdist_group("realtime"),  # real time and processes: never beside the other real-time tests
]


def test_mavproxy_lists_and_sets_parameters_and_uploads_waypoints(tmp_path: Path) -> None:
    vehicle = StandInVehicle()
    vehicle.start()
    config = ground_station_vessel_config(vehicle.port)
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
        deadline = time.monotonic() + 10.0
        # The vessel answers the set with the PARAM_VALUE in force, which updates MAVProxy's copy.
        while _shown(session, "BOB_P0_M") != 7.5:
            assert time.monotonic() < deadline, "BOB_P0_M never became 7.5 in MAVProxy's copy"
            time.sleep(0.3)
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


# -- MAVProxy as the ground station of a 2-vessel process fleet on one UDP port (issue #11 item 4) -----------------

VESSELS = (1, 2)
AUTOPILOT, AUTONOMY = 1, 191
ROVER_MANUAL, ROVER_HOLD = 0, 4  # Rover/mode.h
ARMED = 128  # MAV_MODE_FLAG_SAFETY_ARMED
P0_M = 100.0  # the fleet scenario's p0 (tests/interop_fleet.py)
BOB_PARAMS = 17  # bob_autonomy.ground.params.PARAMS
FINDINGS: dict = {}


def _distance_m(a: tuple[float, float], b: tuple[float, float]) -> float:
    north = math.radians(b[0] - a[0]) * 6_371_000.0
    east = math.radians(b[1] - a[1]) * 6_371_000.0 * math.cos(math.radians(a[0]))
    return math.hypot(north, east)


@pytest.fixture(scope="module")
def ground(tmp_path_factory: pytest.TempPathFactory):
    """A 2-vessel fleet whose ground-station links all reach one MAVProxy (udpin), with the probe module loaded;
    yields (fleet, session, {(sysid, compid) detected}) once both autonomies have armed their vehicles."""
    tmp = tmp_path_factory.mktemp("interop-mavproxy")
    with interop_fleet(tmp) as fleet:
        session = MavproxySession(f"udpin:127.0.0.1:{fleet.gcs_port}", tmp, component=None)
        try:
            started = time.monotonic()
            detected: set[tuple[int, int]] = set()
            while len(detected) < 4:
                match = session.expect(r"Detected vehicle (\d+):(\d+)", 60.0)
                detected.add((int(match.group(1)), int(match.group(2))))
            FINDINGS["detected_after_s"] = round(time.monotonic() - started, 2)
            session.command("module load mavproxy_probe", r"Loaded module mavproxy_probe")
            session.send("set param_ftp 0")  # see the module docstring

            def both_armed() -> bool:
                last = session.probe()["last"]
                return all(last.get(f"{v}:1", {}).get("HEARTBEAT", {}).get("base_mode", 0) & ARMED for v in VESSELS)

            deadline = time.monotonic() + 60.0
            while not both_armed():
                assert time.monotonic() < deadline, "the autonomies never armed their vehicles (MAVProxy's view)"
                time.sleep(0.5)
            yield fleet, session, detected
        finally:
            session.close()
            fleet.stop()
            print("\nMAVProxy findings:", json.dumps(FINDINGS, indent=1))


def test_mavproxy_detects_both_vessels_each_with_autopilot_and_autonomy(ground) -> None:
    _fleet, _session, detected = ground
    assert detected == {(v, c) for v in VESSELS for c in (AUTOPILOT, AUTONOMY)}


def test_mavproxy_sees_each_vessels_telemetry_and_version(ground) -> None:
    fleet, session, _ = ground
    for vessel in VESSELS:
        session.command(f"vehicle {vessel}:{AUTOPILOT}", rf"Set vehicle {vessel}:{AUTOPILOT}")
        session.send("version")  # MAVProxy's own command: REQUEST_MESSAGE AUTOPILOT_VERSION
        session.send("long REQUEST_MESSAGE 242")  # HOME_POSITION, by MAVProxy's generic COMMAND_LONG
    deadline = time.monotonic() + 10.0
    while True:
        report = session.probe()
        last = report["last"]
        if all({"AUTOPILOT_VERSION", "HOME_POSITION"} <= set(last.get(f"{v}:1", {})) for v in VESSELS):
            break
        assert time.monotonic() < deadline, f"no AUTOPILOT_VERSION / HOME_POSITION from each autopilot: {last}"
        time.sleep(0.5)
    homes = {}
    for vessel in VESSELS:
        got = last[f"{vessel}:1"]
        beat = got["HEARTBEAT"]
        assert (beat["type"], beat["autopilot"]) == (11, 3), f"vessel {vessel}: a surface boat, ArduPilot: {beat}"
        assert beat["base_mode"] & ARMED and beat["custom_mode"] == ROVER_MANUAL, f"vessel {vessel}: {beat}"
        status = got["SYS_STATUS"]
        assert status["voltage_battery"] > 0 and 0 < status["battery_remaining"] <= 100, f"vessel {vessel}: {status}"
        assert got["GPS_RAW_INT"]["fix_type"] >= 3 and got["GPS_RAW_INT"]["satellites_visible"] >= 4
        home = got["HOME_POSITION"]
        homes[vessel] = (home["latitude"] / 1e7, home["longitude"] / 1e7)
        assert _distance_m(homes[vessel], fleet.origin) < 300.0, f"vessel {vessel}: home {homes[vessel]}"
        assert 0 <= got["GLOBAL_POSITION_INT"]["hdg"] < 36000, "a heading (65535 would be 'unknown')"
        assert got["AUTOPILOT_VERSION"]["flight_sw_version"] >> 24 == 4, got["AUTOPILOT_VERSION"]
        assert last[f"{vessel}:191"]["HEARTBEAT"]["type"] == 18  # MAV_TYPE_ONBOARD_CONTROLLER
    assert _distance_m(homes[1], homes[2]) > 50.0, homes
    time.sleep(5.0)  # the streams over 5 s (the rates MAVProxy sees; the vessels' request made them)
    later = session.probe()
    window = later["elapsed_s"] - report["elapsed_s"]
    before = report["counts"]
    FINDINGS["rates_hz"] = {
        source: {kind: round((n - before.get(source, {}).get(kind, 0)) / window, 1) for kind, n in counts.items()}
        for source, counts in sorted(later["counts"].items())
    }
    for vessel in VESSELS:
        rates = FINDINGS["rates_hz"][f"{vessel}:1"]
        assert all(rates.get(kind, 0) >= 0.5 for kind in ("HEARTBEAT", "SYS_STATUS", "GPS_RAW_INT")), rates
        # MAVProxy asked 4 Hz of everything on connecting (REQUEST_DATA_STREAM); the vessel keeps that from its
        # autopilot, whose ATTITUDE stays at what the vessel's estimator asked (it needs 5 Hz at least).
        assert rates.get("ATTITUDE", 0) >= 5.0, f"vessel {vessel}: {rates}"


def _fetch(session: MavproxySession, vessel: int, component: int) -> tuple[int, float]:
    session.command(f"vehicle {vessel}:{component}", rf"Set vehicle {vessel}:{component}")
    start = time.monotonic()
    count = int(session.command("param fetch", r"Received (\d+) parameters", 30.0).group(1))
    return count, time.monotonic() - start


def _shown(session: MavproxySession, name: str) -> float:
    return float(session.command(f"param show {name}", rf"{name}\s+(-?[\d.]+)").group(1))


def test_mavproxy_fetches_every_bob_parameter_and_sets_one(ground) -> None:
    _fleet, session, _ = ground
    for vessel in VESSELS:
        count, took = _fetch(session, vessel, AUTONOMY)
        assert count == BOB_PARAMS, f"vessel {vessel}: {count} parameters from component 191"
        FINDINGS.setdefault("param_fetch_s", {})[f"{vessel}:191"] = round(took, 2)
        assert _shown(session, "BOB_P0_M") == P0_M
        for wanted in (P0_M + vessel, P0_M):  # set, then back (MAVProxy waits for the echo of its current target)
            session.send(f"param set BOB_P0_M {wanted}")
            deadline = time.monotonic() + 5.0
            while _shown(session, "BOB_P0_M") != wanted:  # MAVProxy shows the PARAM_VALUE the vessel answered
                assert time.monotonic() < deadline, f"vessel {vessel}: BOB_P0_M never became {wanted}"
                time.sleep(0.3)
        count, took = _fetch(session, vessel, AUTOPILOT)  # the autopilot's own list, through the router
        assert count > BOB_PARAMS, f"vessel {vessel}: {count} parameters from the autopilot"
        assert _shown(session, "FRAME_CLASS") == 2  # a boat
        FINDINGS.setdefault("param_fetch_s", {})[f"{vessel}:1"] = round(took, 2)


def test_mavproxy_loads_and_lists_each_autopilots_mission(ground) -> None:
    fleet, session, _ = ground
    lat0, lon0 = fleet.origin
    for vessel in VESSELS:
        points = [(lat0 + 0.0003 * vessel, lon0 + 0.0002 * k) for k in (1, 2)]
        path = session.cwd / f"mission-{vessel}.txt"
        lines = ["QGC WPL 110", f"0\t1\t0\t16\t0\t0\t0\t0\t{lat0:.7f}\t{lon0:.7f}\t0\t1"]
        lines += [f"{k}\t0\t3\t16\t0\t0\t0\t0\t{lat:.7f}\t{lon:.7f}\t0\t1" for k, (lat, lon) in enumerate(points, 1)]
        path.write_text("\n".join(lines) + "\n")
        session.command(f"vehicle {vessel}:{AUTOPILOT}", rf"Set vehicle {vessel}:{AUTOPILOT}")
        session.command(f"wp load {path}", r"MISSION_ACK: TYPE_MISSION: ACCEPTED", 15.0)
        session.command("wp list", r"Requesting 3 waypoints", 10.0)
        items = [session.expect(r"(?:^|\s)16 (\d+) (-?\d+\.\d+) (-?\d+\.\d+) ", 10.0) for _ in range(3)]
        listed = [(float(m.group(2)), float(m.group(3))) for m in items]
        assert _distance_m(listed[0], fleet.origin) < 300.0, f"vessel {vessel}: item 0 is home, {listed[0]}"
        assert listed[1:] == [pytest.approx(p, abs=1e-7) for p in points], f"vessel {vessel}: {listed}"


def test_mavproxy_holds_disarms_and_arms_each_vessel(ground) -> None:
    _fleet, session, _ = ground

    def autopilot_heartbeat(vessel: int) -> dict:
        return session.probe()["last"][f"{vessel}:1"]["HEARTBEAT"]

    def until(vessel: int, check, what: str) -> float:
        start = time.monotonic()
        while not check(autopilot_heartbeat(vessel)):
            assert time.monotonic() - start < 5.0, f"vessel {vessel}: {what} not seen within 5 s"
            time.sleep(0.1)
        return time.monotonic() - start

    for vessel in VESSELS:
        session.command(f"vehicle {vessel}:{AUTOPILOT}", rf"Set vehicle {vessel}:{AUTOPILOT}")
        session.command("mode HOLD", r"Got COMMAND_ACK: DO_SET_MODE: ACCEPTED")
        until(vessel, lambda b: b["custom_mode"] == ROVER_HOLD, "HOLD")
        session.command("disarm", r"Got COMMAND_ACK: COMPONENT_ARM_DISARM: ACCEPTED")
        until(vessel, lambda b: not b["base_mode"] & ARMED, "disarmed")
        session.command("arm throttle", r"Got COMMAND_ACK: COMPONENT_ARM_DISARM: ACCEPTED")
        until(vessel, lambda b: b["base_mode"] & ARMED, "armed")
        session.command("mode MANUAL", r"Got COMMAND_ACK: DO_SET_MODE: ACCEPTED")
        until(vessel, lambda b: b["custom_mode"] == ROVER_MANUAL, "MANUAL again")


def test_mavproxy_shows_a_simulated_vehicle_of_a_process_fleet(ground) -> None:
    """A second ground station straight on vehicle 0's port (docs/sitl-fleet.md), beside the vessel's autonomy.
    That port is the companion's, so the session asks for no streams (--streamrate=-1): MAVProxy's default 4 Hz
    request would reset the stream rates the autonomy asked of its autopilot, as on ArduPilot's own port."""
    fleet, _session, _ = ground
    work = fleet.out.parent / "vehicle-port"
    work.mkdir(exist_ok=True)
    session = MavproxySession(f"udpout:127.0.0.1:{fleet.base_port}", work, component=1, extra=("--streamrate=-1",))
    try:
        session.expect(r"Detected vehicle 1:1", 20.0)
        session.expect(r"ARMED", 10.0)  # armed by its bob-autonomy process
        match = session.retry("status GLOBAL_POSITION_INT", r"GLOBAL_POSITION_INT \{.*lat : (-?\d+), lon : (-?\d+)")
        position = (int(match.group(1)) / 1e7, int(match.group(2)) / 1e7)
        assert _distance_m(position, fleet.origin) < 300.0, position  # at its start point near the origin
        session.retry("status HEARTBEAT", r"HEARTBEAT \{type : 11, autopilot : 3")  # a surface boat, ArduPilot-like
        # This port's frames are numbered for this link alone, as on each ArduPilot channel: MAVProxy's loss (from
        # gaps in the numbers) is the link's, not the count of replies the vehicle sent the vessel.
        time.sleep(3.0)
        link = session.command("link", r"\((\d+) packets, \d+ bytes, [\d.]+s delay, (\d+) lost")
        packets, lost = int(link.group(1)), int(link.group(2))
        assert packets > 100 and lost <= packets // 100, (packets, lost)
    finally:
        session.close()
