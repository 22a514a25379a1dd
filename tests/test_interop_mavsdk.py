"""MAVSDK (MAVSDK-Python 4.1, the ctypes binding of MAVSDK's C++ library: a ground-station library we did not write)
as the ground station of a 2-vessel process fleet, on ONE UDP port (issue #11 item 4).

Each vessel's `bob-autonomy run` routes its autopilot's traffic to that port and the ground station's frames for the
autopilot to its vehicle (mavlink-router's job on a companion computer), so MAVSDK must see two systems, each with an
autopilot (component 1: the simulated ArduPilot Rover) and an onboard computer (component 191: the autonomy), and
drive both through their autonomy processes: telemetry, AUTOPILOT_VERSION, parameters of both components, the
autopilot's mission, arm / disarm / hold.

What MAVSDK does that a reader of these tests should know (from its C++ source, repository mavlink/MAVSDK):
- `Param.select_component` returns Result.UNKNOWN even when it worked (ParamImpl::select_component ends with
  `return Param::Result::Unknown`), which the Python binding raises as ParamError(UNKNOWN); the selection holds.
- A refused PARAM_SET (our component answers with the value in force, as ArduPilot does) is retried by MAVSDK until it
  gives up with TIMEOUT (about 0.5 s): the caller cannot tell "refused" from "no answer".
- Telemetry takes GLOBAL_POSITION_INT from every component of a system (TelemetryImpl registers no component filter),
  so `position()` / `heading()` alternate between the autopilot's GPS-based report (about 5 Hz) and component 191's
  estimate (BOB_POS_HZ, 1 Hz; set it to 0 to keep them apart). It took the flight mode from any HEARTBEAT with the
  custom-mode flag (SystemImpl::process_heartbeat) too, which is why component 191's HEARTBEAT now has base_mode 0.
- MAVSDK reports MAV_TYPE_SURFACE_BOAT as Vehicle.GENERIC (its Vehicle enum has no boat).

Measurements (stream rates, command delays, what a ground station sees) go to FINDINGS, printed at the end of the
module (`pytest -s`) and written beside the fleet's outputs as mavsdk-findings.json.
"""

from __future__ import annotations

import json
import math
import random
import statistics
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path

import pytest

mavsdk = pytest.importorskip("mavsdk", minversion="4.1", reason="MAVSDK-Python 4.1+ (pip install -e '.[dev]')")

from interop_fleet import InteropFleet, interop_fleet, wait_for  # noqa: E402
from mavsdk import Autopilot, ComponentType, Configuration, Mavsdk  # noqa: E402
from mavsdk.plugins.action.action import Action  # noqa: E402
from mavsdk.plugins.info.info import Info  # noqa: E402
from mavsdk.plugins.mavlink_direct.mavlink_direct import MavlinkDirect, MavlinkMessage  # noqa: E402
from mavsdk.plugins.mission_raw.mission_raw import MissionItem, MissionRaw  # noqa: E402
from mavsdk.plugins.param.param import Param, ParamError, ParamResult, ProtocolVersion  # noqa: E402
from mavsdk.plugins.telemetry.telemetry import FixType, FlightMode, Telemetry  # noqa: E402
from pymavlink import mavutil  # noqa: E402
from pymavlink.dialects.v20 import ardupilotmega as mavlink  # noqa: E402

from bob_autonomy.ground.params import PARAMS  # noqa: E402

VESSELS = (1, 2)
GCS_SYSTEM_ID = 245  # MAVSDK's ground-station system id (Configuration GROUND_STATION)
AUTOPILOT, AUTONOMY = 1, 191
ROVER_MANUAL = 0  # ArduPilot Rover's mode numbers (Rover/mode.h)
P0_M = 100.0  # what the fleet's scenario gives every vessel (the aggregation lattice held in place)
FINDINGS: dict = {}

realtime = pytest.mark.xdist_group("realtime")  # real time, sockets and processes


@dataclass
class Ground:
    """MAVSDK as the ground station: its instance, and per vessel (system id) the System, a Telemetry plugin made at
    discovery (MAVSDK's getters return what the plugin has heard since it was made) and the STATUSTEXTs heard."""

    sdk: Mavsdk
    fleet: InteropFleet
    systems: dict = field(default_factory=dict)
    telemetry: dict = field(default_factory=dict)
    texts: dict = field(default_factory=dict)
    lock: threading.Lock = field(default_factory=threading.Lock)
    calls: list = field(default_factory=list)  # (wall s at the call and at its return, vessel, request, key)
    jitter: random.Random = field(default_factory=lambda: random.Random(11))

    def timed_call(self, vessel: int, request: str, key: object, call) -> float:
        """Run a blocking MAVSDK call at a random phase of the vessels' control period (so the delays measured are
        not locked to it) and return how long it took (wall s); the call is noted for one_way_delays."""
        time.sleep(self.jitter.uniform(0.0, 0.1))
        start, wall = time.monotonic(), time.time()
        call()
        took = time.monotonic() - start
        self.calls.append((wall, wall + took, vessel, request, key))
        return took

    def texts_of(self, vessel: int) -> list[str]:
        with self.lock:
            return list(self.texts[vessel])


@pytest.fixture(scope="module")
def ground(tmp_path_factory: pytest.TempPathFactory):
    tmp = tmp_path_factory.mktemp("interop-mavsdk")
    with interop_fleet(tmp) as fleet:
        sdk = Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION))
        started = time.monotonic()
        try:
            assert sdk.add_any_connection(f"udpin://127.0.0.1:{fleet.gcs_port}") == 0  # ConnectionResult.SUCCESS
            wait_for(lambda: sdk.system_count() >= len(VESSELS), 60.0, "MAVSDK discovering both vessels", 0.05)
            g = Ground(sdk, fleet)
            FINDINGS["discovered_after_s"] = round(time.monotonic() - started, 2)
            for system in sdk.get_systems():
                vessel = system.get_system_id()
                g.systems[vessel] = system
                g.telemetry[vessel] = Telemetry(system)
                g.texts[vessel] = []

                def heard(text, _user_data, vessel=vessel) -> None:
                    with g.lock:
                        g.texts[vessel].append(text.text)

                g.telemetry[vessel].subscribe_status_text(heard)
            for vessel, tel in g.telemetry.items():  # each autonomy arms its vehicle once the autopilot is ready
                wait_for(tel.armed, 60.0, f"vessel {vessel} armed by its autonomy (MAVSDK telemetry)", 0.05)
            FINDINGS["armed_by_autonomy_after_s"] = round(time.monotonic() - started, 2)
            yield g
        finally:
            if "g" in locals():
                FINDINGS["statustexts"] = {v: sorted(set(g.texts_of(v))) for v in g.texts}
            sdk.destroy()
            FINDINGS["fleet_output_tail"] = fleet.stop().splitlines()[-3:]
            if "g" in locals() and (fleet.out / "vehicles.tlog").exists():
                FINDINGS["one_way_delays_s"] = one_way_delays(fleet.out / "vehicles.tlog", g.calls)
            (tmp / "mavsdk-findings.json").write_text(json.dumps(FINDINGS, indent=1, default=str))
            print("\nMAVSDK findings:", json.dumps(FINDINGS, indent=1, default=str))


def _summary(samples: list[float]) -> dict:
    if not samples:
        return {"n": 0}
    return {"n": len(samples), "median": round(statistics.median(samples), 4), "max": round(max(samples), 4)}


def one_way_delays(tlog: Path, calls: list) -> dict:
    """Both legs of each ground-station call noted by Ground.timed_call, from the fleet's vehicles.tlog, whose frames
    are stamped with the wall time at which the simulated vehicle received or sent them: ground station -> vessel ->
    vehicle (the call to the vehicle's receipt of MAVSDK's request) and vehicle -> vessel -> ground station (the
    vehicle's answer, COMMAND_ACK or PARAM_VALUE, to the return of MAVSDK's blocking call)."""
    requests: dict[tuple, list[float]] = {}
    answers: dict[tuple, list[float]] = {}
    log = mavutil.mavlink_connection(str(tlog))
    kinds = ["COMMAND_LONG", "PARAM_SET", "COMMAND_ACK", "PARAM_VALUE"]
    while (msg := log.recv_match(type=kinds)) is not None:
        kind = msg.get_type()
        key = msg.command if kind.startswith("COMMAND") else msg.param_id
        if kind in ("COMMAND_LONG", "PARAM_SET") and msg.get_srcSystem() == GCS_SYSTEM_ID:
            requests.setdefault((msg.target_system, kind, key), []).append(msg._timestamp)
        elif kind in ("COMMAND_ACK", "PARAM_VALUE") and msg.get_srcComponent() == AUTOPILOT:
            request = "COMMAND_LONG" if kind == "COMMAND_ACK" else "PARAM_SET"
            answers.setdefault((msg.get_srcSystem(), request, key), []).append(msg._timestamp)
    legs: dict[str, list[float]] = {}
    for t_call, t_end, vessel, request, key in calls:
        sent = [t for t in requests.get((vessel, request, key), []) if t_call <= t <= t_end]
        if not sent:
            continue
        legs.setdefault(f"gcs_to_vehicle_{request}", []).append(sent[0] - t_call)
        answered = [t for t in answers.get((vessel, request, key), []) if sent[0] <= t <= t_end]
        if answered:
            legs.setdefault(f"vehicle_to_gcs_{request}", []).append(t_end - answered[0])
    return {name: _summary(samples) for name, samples in sorted(legs.items())}


def _distance_m(a: tuple[float, float], b: tuple[float, float]) -> float:
    north = math.radians(b[0] - a[0]) * 6_371_000.0
    east = math.radians(b[1] - a[1]) * 6_371_000.0 * math.cos(math.radians(a[0]))
    return math.hypot(north, east)


@realtime
def test_mavsdk_discovers_both_vessels_each_with_autopilot_and_autonomy(ground: Ground) -> None:
    assert sorted(ground.systems) == list(VESSELS)
    seen = {}
    for vessel, system in ground.systems.items():
        seen[vessel] = sorted(system.component_ids())
        assert set(system.component_ids()) == {AUTOPILOT, AUTONOMY}, f"vessel {vessel}: {system.component_ids()}"
        assert system.has_autopilot() and system.is_connected()
        assert system.autopilot_type() == Autopilot.ARDUPILOT
    FINDINGS["components"] = seen
    FINDINGS["vehicle_type"] = {v: s.vehicle_type().name for v, s in ground.systems.items()}


@realtime
def test_mavsdk_telemetry_of_each_vessel(ground: Ground) -> None:
    homes = {}
    for vessel, tel in ground.telemetry.items():
        what = f"vessel {vessel}"
        wait_for(lambda t=tel: math.isfinite(t.home().latitude_deg), 10.0, f"{what}: home position")
        wait_for(lambda t=tel: t.gps_info().fix_type >= FixType.FIX_3D, 10.0, f"{what}: 3D fix")
        wait_for(lambda t=tel: math.isfinite(t.battery().remaining_percent), 10.0, f"{what}: battery")
        assert tel.armed(), f"{what}: armed by its autonomy"
        modes = set()
        for _ in range(20):  # 2 s: both components' heartbeats twice; the mode must not flicker
            modes.add(tel.flight_mode())
            time.sleep(0.1)
        assert modes == {FlightMode.MANUAL}, f"{what}: flight modes seen {modes}"
        battery, gps, home = tel.battery(), tel.gps_info(), tel.home()
        assert 0.0 < battery.remaining_percent <= 100.0 and battery.voltage_v > 0.0, f"{what}: {battery}"
        assert gps.num_satellites >= 4, f"{what}: {gps}"
        homes[vessel] = (home.latitude_deg, home.longitude_deg)
        assert _distance_m(homes[vessel], ground.fleet.origin) < 300.0, f"{what}: home {homes[vessel]}"
        heading = tel.heading().heading_deg
        assert math.isfinite(heading) and 0.0 <= heading < 360.0, f"{what}: heading {heading}"
        position = tel.position()
        assert _distance_m((position.latitude_deg, position.longitude_deg), homes[vessel]) < 30.0, what
    # The two vessels are told apart: their homes are their own start points, on a lattice 100 m apart.
    assert _distance_m(homes[1], homes[2]) > 50.0, homes


@realtime
def test_mavsdk_reads_each_autopilots_version(ground: Ground) -> None:
    uids = {}
    for vessel, system in ground.systems.items():
        info = Info(system)
        version = info.get_version()
        assert version.flight_sw_major == 4, f"vessel {vessel}: {version}"
        uids[vessel] = info.get_identification().legacy_uid
        FINDINGS.setdefault("autopilot_version", {})[vessel] = (
            f"{version.flight_sw_major}.{version.flight_sw_minor}.{version.flight_sw_patch} uid {uids[vessel]}"
        )
    assert uids[1] != uids[2], "each autopilot has its own board id"


@realtime
def test_mavsdk_sees_the_routed_streams_of_both_components(ground: Ground) -> None:
    window_s = 5.0
    counts: Counter = Counter()
    lock = threading.Lock()
    direct = {vessel: MavlinkDirect(system) for vessel, system in ground.systems.items()}

    def count(message, _user_data) -> None:
        with lock:
            counts[(message.system_id, message.component_id, message.message_name)] += 1

    handles = {vessel: d.subscribe_message("", count) for vessel, d in direct.items()}
    time.sleep(window_s)
    for vessel, d in direct.items():
        d.unsubscribe_message(handles[vessel])
    with lock:
        rates = {key: n / window_s for key, n in counts.items()}
    assert {key[0] for key in rates} == set(VESSELS), "frames of the two vessels, and of nothing else"
    for vessel in VESSELS:
        assert 0.5 <= rates.get((vessel, AUTOPILOT, "HEARTBEAT"), 0) <= 2.0, f"vessel {vessel}: autopilot heartbeat"
        assert 0.5 <= rates.get((vessel, AUTONOMY, "HEARTBEAT"), 0) <= 2.0, f"vessel {vessel}: autonomy heartbeat"
        for name in ("SYS_STATUS", "GPS_RAW_INT", "GLOBAL_POSITION_INT", "ATTITUDE"):  # what the autonomy asked for
            assert rates.get((vessel, AUTOPILOT, name), 0) >= 0.5, f"vessel {vessel}: {name} from the autopilot"
        FINDINGS.setdefault("rates_hz", {})[vessel] = {
            f"{component}:{name}": round(rate, 1) for (v, component, name), rate in sorted(rates.items()) if v == vessel
        }


def _param_names(all_params) -> dict[str, float]:
    return {p.name: p.value for p in [*all_params.int_params, *all_params.float_params]}


@realtime
def test_mavsdk_reads_every_bob_parameter_and_sets_one(ground: Ground) -> None:
    """Component 191's BOB_* parameters through MAVSDK's param plugin, then the autopilot's (component 1) through
    the vessel's router; the delays of both kinds of PARAM_SET round trip are measured."""
    delays: dict[str, list[float]] = {"autonomy_param_set_s": [], "autopilot_param_set_s": []}
    values = {}
    for vessel, system in ground.systems.items():
        bob = Param(system)
        try:
            bob.select_component(AUTONOMY, ProtocolVersion.V1)
        except ParamError as error:  # MAVSDK answers UNKNOWN even on success (see the module docstring)
            assert error.result == ParamResult.UNKNOWN, error
        everything = bob.get_all_params()
        got = _param_names(everything)
        assert set(got) == {spec.name for spec in PARAMS}, f"vessel {vessel}: {sorted(got)}"
        ints = {p.name for p in everything.int_params}
        assert ints == {spec.name for spec in PARAMS if spec.kind == "int"}, f"vessel {vessel}: INT32 {ints}"
        assert all(spec.minimum <= got[spec.name] <= spec.maximum for spec in PARAMS), got
        assert got["BOB_P0_M"] == P0_M
        # One set, read back; different values on the two vessels show that each set reached its own vessel.
        for k in range(5):
            wanted = P0_M + 10 * vessel + k
            call = partial(bob.set_param_float, "BOB_P0_M", wanted)
            delays["autonomy_param_set_s"].append(ground.timed_call(vessel, "PARAM_SET", "BOB_P0_M", call))
            assert bob.get_param_float("BOB_P0_M") == pytest.approx(wanted)
        values[vessel] = bob.get_param_float("BOB_P0_M")
        # A value out of range is refused: MAVSDK retries until it gives up, and the value stays.
        with pytest.raises(ParamError):
            bob.set_param_float("BOB_P0_M", 5000.0)
        assert bob.get_param_float("BOB_P0_M") == pytest.approx(values[vessel])
        assert any("BOB_P0_M" in text and "out of range" in text for text in ground.texts_of(vessel))
        bob.set_param_float("BOB_P0_M", P0_M)

        autopilot = Param(system)  # the default component: the autopilot, reached through the router
        theirs = _param_names(autopilot.get_all_params())
        assert theirs["FRAME_CLASS"] == 2 and {"RCMAP_ROLL", "RCMAP_THROTTLE", "RCMAP_YAW"} <= set(theirs)
        assert not any(name.startswith("BOB_") for name in theirs), "the autopilot's list is its own"
        FINDINGS.setdefault("autopilot_param_count", {})[vessel] = len(theirs)
        for mode in (4, 0, 4, 0, 4, 0):  # INITIAL_MODE: used at boot only, so harmless to change here
            call = partial(autopilot.set_param_int, "INITIAL_MODE", mode)
            delays["autopilot_param_set_s"].append(ground.timed_call(vessel, "PARAM_SET", "INITIAL_MODE", call))
        assert autopilot.get_param_int("INITIAL_MODE") == 0
    assert values[1] != values[2]
    for name, samples in delays.items():
        FINDINGS[name] = _summary(samples)


@realtime
def test_mavsdk_uploads_and_downloads_each_autopilots_mission(ground: Ground) -> None:
    """mission_raw talks to the autopilot (component 1): ArduPilot keeps item 0 for home (AP_Mission), so the
    upload's item 0 is a placeholder and the download's item 0 is the home position."""
    downloads = {}
    for vessel, system in ground.systems.items():
        home = ground.telemetry[vessel].home()
        lat0, lon0 = int(home.latitude_deg * 1e7), int(home.longitude_deg * 1e7)
        waypoints = [(lat0 + 300 * k * vessel, lon0 + 200 * k) for k in range(1, 4)]
        items = [
            MissionItem(seq=seq, frame=mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, command=16, current=int(seq == 0),
                        autocontinue=1, x=x, y=y, z=0.0, mission_type=0)
            for seq, (x, y) in enumerate([(lat0, lon0), *waypoints])
        ]  # fmt: skip
        mission = MissionRaw(system)
        start = time.monotonic()
        mission.upload_mission(items)
        FINDINGS.setdefault("mission_upload_s", {})[vessel] = round(time.monotonic() - start, 3)
        start = time.monotonic()
        got = mission.download_mission()
        FINDINGS.setdefault("mission_download_s", {})[vessel] = round(time.monotonic() - start, 3)
        assert [item.seq for item in got] == [0, 1, 2, 3], f"vessel {vessel}"
        assert all(item.command == 16 for item in got)
        assert [(item.x, item.y) for item in got[1:]] == waypoints, f"vessel {vessel}"
        # ArduPilot answers MISSION_ITEM_INT with the plain frame (GLOBAL_RELATIVE_ALT = 3), not the _INT one.
        assert {item.frame for item in got[1:]} == {mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT}
        assert abs(got[0].x - lat0) < 100 and abs(got[0].y - lon0) < 100, "item 0 is home (within 1 m)"
        downloads[vessel] = [(item.x, item.y) for item in got[1:]]
    assert downloads[1] != downloads[2], "each vessel's autopilot has its own mission"


def _set_mode(system, vessel: int, mode: int) -> None:
    """DO_SET_MODE to the autopilot through MAVSDK's mavlink_direct (its action plugin has no MANUAL)."""
    fields = {"target_system": vessel, "target_component": AUTOPILOT, "command": mavlink.MAV_CMD_DO_SET_MODE,
              "confirmation": 0, "param1": mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, "param2": mode, "param3": 0,
              "param4": 0, "param5": 0, "param6": 0, "param7": 0}  # fmt: skip
    message = MavlinkMessage(
        message_name="COMMAND_LONG", system_id=245, component_id=190, target_system_id=vessel,
        target_component_id=AUTOPILOT, fields_json=json.dumps(fields),
    )  # fmt: skip
    MavlinkDirect(system).send_message(message)


@realtime
def test_mavsdk_holds_disarms_and_arms_each_vessel(ground: Ground) -> None:
    """Through MAVSDK's action plugin; the autonomy notices HOLD and says so (its STATUSTEXT reaches MAVSDK), and
    drives again once MANUAL is back. Times: the call (COMMAND_ACK round trip) and call -> telemetry."""
    timings: dict[str, list[float]] = {}

    def timed(name: str, call, seen) -> None:
        command = mavlink.MAV_CMD_DO_SET_MODE if name == "hold" else mavlink.MAV_CMD_COMPONENT_ARM_DISARM
        acked = ground.timed_call(vessel, "COMMAND_LONG", command, call)
        assert acked < 1.0, f"vessel {vessel}: {name} acknowledged after {acked:.2f} s"
        shown = wait_for(seen, 5.0, name) + acked
        timings.setdefault(f"{name}_ack_s", []).append(acked)
        timings.setdefault(f"{name}_telemetry_s", []).append(shown)

    for vessel, system in ground.systems.items():
        tel, action = ground.telemetry[vessel], Action(system)
        wait_for(lambda t=tel: t.flight_mode() == FlightMode.MANUAL and t.armed(), 10.0, f"vessel {vessel} ready")
        timed("hold", action.hold, lambda t=tel: t.flight_mode() == FlightMode.HOLD)
        wait_for(
            lambda v=vessel: any("is in HOLD, not MANUAL" in text for text in ground.texts_of(v)),
            5.0,
            f"vessel {vessel}: the autonomy reporting HOLD",
        )
        timed("disarm", action.disarm, lambda t=tel: not t.armed())
        timed("arm", action.arm, lambda t=tel: t.armed())
        _set_mode(system, vessel, ROVER_MANUAL)
        wait_for(lambda t=tel: t.flight_mode() == FlightMode.MANUAL, 5.0, f"vessel {vessel} back in MANUAL")
        wait_for(
            lambda v=vessel: any("back in MANUAL" in text for text in ground.texts_of(v)),
            5.0,
            f"vessel {vessel}: the autonomy driving again",
        )
    FINDINGS["actions"] = {name: _summary(samples) for name, samples in timings.items()}
