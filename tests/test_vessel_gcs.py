"""The autonomy process as its vessel's MAVLink component, driven by a mission script over real UDP.

A Vessel (what `bob-autonomy run` executes) drives the stand-in vehicle; `bob_autonomy.ground.mission.MissionClient`
talks to the vessel's GCS port: discovery, parameters that change the behaviour, goal and fence uploads,
start/stop. Plus the supervisor's geometry and the command line's config file and SIGTERM handling.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from vessel_helpers import ORIGIN, SCALE, StandInVehicle

from bob_autonomy.cli import _apply_config_file, _parser, config_from_args
from bob_autonomy.core.behavior_config import BehaviorChoice
from bob_autonomy.core.clock import ScaledWallClock
from bob_autonomy.core.geodesy import LocalFrame
from bob_autonomy.ground.mission import MissionClient
from bob_autonomy.ground.params import ParameterStore
from bob_autonomy.ground.safety import inside_polygon, limit_to_fence, return_inside
from bob_autonomy.ground.supervisor import Supervisor, behavior_params
from bob_autonomy.onboard.vessel import Vessel, VesselConfig

# Real time, sockets and processes: in one xdist worker, so that they never compete with each other.
pytestmark = pytest.mark.xdist_group("realtime")

FRAME = LocalFrame(*ORIGIN)
BOX = np.array([[-10.0, -10.0], [10.0, -10.0], [10.0, 10.0], [-10.0, 10.0]])


def _latlon(x: float, y: float) -> tuple[float, float]:
    lat, lon = FRAME.to_geodetic(x, y)
    return float(lat), float(lon)


# -- geometry and supervisor --------------------------------------------------------------------------


def test_fence_removes_only_the_outward_part_near_an_edge() -> None:
    assert inside_polygon(np.array([0.0, 0.0]), BOX) and not inside_polygon(np.array([11.0, 0.0]), BOX)
    np.testing.assert_allclose(limit_to_fence(np.array([8.0, 0.0]), np.array([1.0, 0.5]), BOX), [0.0, 0.5])
    np.testing.assert_allclose(limit_to_fence(np.array([0.0, 0.0]), np.array([1.0, 0.5]), BOX), [1.0, 0.5])  # far
    np.testing.assert_allclose(limit_to_fence(np.array([8.0, 0.0]), np.array([-1.0, 0.0]), BOX), [-1.0, 0.0])
    back = return_inside(np.array([20.0, 0.0]), BOX, 0.5)
    np.testing.assert_allclose(back, [-0.5, 0.0], atol=1e-12)
    clockwise = BOX[::-1]  # either vertex order
    np.testing.assert_allclose(limit_to_fence(np.array([8.0, 0.0]), np.array([1.0, 0.5]), clockwise), [0.0, 0.5])


def _supervisor(**params) -> Supervisor:
    store = ParameterStore()
    base = BehaviorChoice(behavior="bob-rule", params={"p0": 10.0, "nearest": 6})
    store.set_many(behavior_params(base, FRAME))
    store.set_many(params)
    return Supervisor(store, base, FRAME)


def test_parameters_select_and_rebuild_the_behaviour() -> None:
    sup = _supervisor()
    first = sup.behavior()
    assert (first.p0, first.H, first.nearest, first.goal) == (10.0, 0, 6, None)
    sup.params.set("BOB_P0_M", 5.0)
    sup.params.set_goals([_latlon(30.0, 40.0)])
    sup.params.set("BOB_H", 1)
    second = sup.behavior()
    assert second is not first and second.p0 == 5.0 and second.H == 1 and second.nearest == 6
    np.testing.assert_allclose(second.goal, (30.0, 40.0), atol=0.01)
    sup.params.set("BOB_LEADER_ID", 4)
    assert sup.behavior().leader_id == 3 and sup.behavior().goal is None  # system id 4 = agent 3
    sup.params.set("BOB_BEHAVIOR", 8)
    assert sup.behavior().name == "hold-position"


def test_a_behaviour_rebuilt_from_the_parameters_keeps_the_configured_collision_avoidance() -> None:
    store = ParameterStore()
    base = BehaviorChoice(behavior="bob-rule", params={"p0": 10.0}, avoid_collisions=True,
                          collision_params={"safe_distance_m": 2.0})  # fmt: skip
    store.set_many(behavior_params(base, FRAME))
    sup = Supervisor(store, base, FRAME)
    sup.params.set("BOB_P0_M", 5.0)
    behavior = sup.behavior()
    assert behavior.name == "avoid-collisions+bob-rule" and behavior.safe_distance_m == 2.0
    assert behavior.inner.p0 == 5.0


def test_stopped_or_gcs_lost_holds_and_rally_returns() -> None:
    sup = _supervisor(BOB_GCS_FS_ACT=2, BOB_RALLY_LAT=_latlon(0.0, -50.0)[0], BOB_RALLY_LON=_latlon(0.0, -50.0)[1])
    wish = np.array([1.0, 0.0])
    np.testing.assert_allclose(sup.velocity(np.zeros(2), wish, running=True, gcs_lost=False), wish)
    held = sup.velocity(np.array([3.0, 0.0]), wish, running=False, gcs_lost=False)
    np.testing.assert_allclose(held, [0.0, 0.0])  # the hold point is where it stopped
    back = sup.velocity(np.array([5.0, 0.0]), wish, running=False, gcs_lost=False)
    assert back[0] < 0 and sup.mode == "stopped: hold"
    rally = sup.velocity(np.zeros(2), wish, running=True, gcs_lost=True)
    assert rally[1] < 0 and abs(rally[0]) < 1e-6 and "rally" in sup.mode


def test_fence_breach_brings_the_vessel_back() -> None:
    sup = _supervisor(BOB_FENCE_EN=1, BOB_FENCE_ACT=1)
    sup.params.set_fence([_latlon(x, y) for x, y in BOX])
    limited = sup.velocity(np.array([9.0, 0.0]), np.array([1.0, 0.0]), running=True, gcs_lost=False)
    assert abs(limited[0]) < 1e-3
    back = sup.velocity(np.array([15.0, 0.0]), np.array([1.0, 0.0]), running=True, gcs_lost=False)
    assert back[0] < 0 and sup.mode == "fence breached: back inside"


# -- a vessel and a mission script over UDP ------------------------------------------------------------


@pytest.fixture
def mission_rig(tmp_path: Path):
    vehicle = StandInVehicle()
    vehicle.start()
    client = MissionClient("udpin:127.0.0.1:0", timeout_s=1.0, retries=4)
    port = client.local_address[1]
    choice = BehaviorChoice(behavior="bob-rule", params={"p0": 5.0, "max_speed": 1.0})
    config = VesselConfig(
        vehicle=f"udpout:127.0.0.1:{vehicle.port}",
        system_id=1,
        behavior=choice,
        origin=ORIGIN,
        time_scale=SCALE,
        controller="simple",
        gcs=f"udpout:127.0.0.1:{port}",
        params_file=str(tmp_path / "params.json"),
        autostart=False,
        tlog=str(tmp_path / "vessel.tlog"),
    )
    vessel = Vessel(config, clock=ScaledWallClock(SCALE))
    runner = threading.Thread(target=vessel.run, daemon=True)
    runner.start()
    yield vehicle, client, vessel, tmp_path
    vessel.stop()
    runner.join(5.0)
    client.close()
    vehicle.close()


def test_a_mission_script_steers_a_vessel_with_parameters_goals_and_a_fence(mission_rig) -> None:
    vehicle, client, vessel, tmp_path = mission_rig
    assert client.discover(1, timeout_s=10.0) == [1]
    time.sleep(1.0)
    assert np.hypot(*vehicle.position) < 0.5, "waits for MISSION_START (autostart off)"
    client.set_params({"BOB_H": 1, "BOB_MAX_SPD_MPS": 1.0})
    client.upload_goals([_latlon(40.0, 0.0)])
    client.upload_fence([_latlon(x, y) for x, y in [(-20, -20), (15, -20), (15, 20), (-20, 20)]])
    client.set_param("BOB_FENCE_EN", 1)
    client.start()
    # The goal lies outside the fence: the vessel goes east and stops at the fence (x = 15 m).
    client.wait_until(lambda _client: vehicle.position[0] > 12.0, timeout_s=20.0, what="vessel reaches the fence")
    time.sleep(2.0)
    assert 12.0 < vehicle.position[0] < 16.5, vehicle.position
    reported = client.positions()[1]
    x, _y = FRAME.to_local(reported.lat_deg, reported.lon_deg)
    assert abs(float(x) - vehicle.position[0]) < 3.0  # GLOBAL_POSITION_INT carries the vessel's estimate
    client.stop()
    time.sleep(1.0)
    assert vessel.supervisor.mode == "stopped: hold"
    assert ParameterStore(tmp_path / "params.json").get("BOB_FENCE_EN") == 1  # persisted
    from pymavlink import mavutil

    log = mavutil.mavlink_connection(str(tmp_path / "vessel.tlog"))
    kinds = set()
    while (msg := log.recv_match()) is not None:
        kinds.add(msg.get_type())
    assert {"RC_CHANNELS_OVERRIDE", "GPS_RAW_INT", "HEARTBEAT", "PARAM_VALUE", "MISSION_ACK"} <= kinds


# -- the command line ----------------------------------------------------------------------------------


def test_the_example_service_config_parses() -> None:
    args = _apply_config_file(_parser(), ["run", "--config", "docs/vessel.toml", "--system-id", "9"])
    config = config_from_args(args)
    assert config.system_id == 9 and config.vehicle == "/dev/ttyAMA0" and config.baud == 57600
    assert config.mesh == "/dev/ttyUSB0" and config.mesh_baud == 115200
    assert config.behavior.params == {"p0": 10, "H": 0} and not config.autostart
    assert config.memory_fields == ("goal",) and config.origin == (1.3405, 103.956)


def test_a_bad_config_file_names_the_setting(tmp_path: Path) -> None:
    bad = tmp_path / "vessel.toml"
    bad.write_text('vehicle = "udpout:127.0.0.1:5760"\nsytem_id = 3\n')
    with pytest.raises(ValueError, match=r"unknown setting\(s\) \['sytem_id'\]"):
        _apply_config_file(_parser(), ["run", "--config", str(bad)])


def test_sigterm_leaves_the_thrusters_at_zero(tmp_path: Path) -> None:
    vehicle = StandInVehicle()
    vehicle.start()
    try:
        process = subprocess.Popen(
            [sys.executable, "-m", "bob_autonomy.cli", "run", "--vehicle", f"udpout:127.0.0.1:{vehicle.port}",
             "--system-id", "1", "--behavior", "bob-rule", "--param", "goal=[50, 0]", "--param", "H=1",
             "--origin", f"{ORIGIN[0]},{ORIGIN[1]}", "--time-scale", str(SCALE), "--controller", "simple",
             "--log-file", str(tmp_path / "autonomy.log")],
            env={**os.environ, "PYTHONUNBUFFERED": "1"},
        )  # fmt: skip
        deadline = time.monotonic() + 30.0
        while vehicle.vehicle.counters.commands < 20 and time.monotonic() < deadline:
            time.sleep(0.1)
        assert np.abs(vehicle.vehicle._command).max() > 1.0, "driving before the stop"
        process.send_signal(signal.SIGTERM)
        assert process.wait(timeout=10) == 0
        time.sleep(0.2)
        np.testing.assert_allclose(vehicle.vehicle._command, [0.0, 0.0])
        assert "stopped cleanly" in (tmp_path / "autonomy.log").read_text()
    finally:
        vehicle.close()


def test_run_is_the_default_command(tmp_path: Path) -> None:
    from bob_autonomy.cli import main

    bad = tmp_path / "vessel.toml"
    bad.write_text("sytem_id = 3\n")
    assert main(["--config", str(bad)]) == 2  # parsed as `run --config ...`: the unknown setting is reported


def test_goal_seeking_mission_script_brings_two_vessels_to_the_goal() -> None:
    from test_examples import load_example

    probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    probe.bind(("127.0.0.1", 0))
    port = probe.getsockname()[1]
    probe.close()
    rigs = []
    for system_id, start in ((1, (0.0, 0.0)), (2, (0.0, 8.0))):
        vehicle = StandInVehicle(start, system_id)
        vehicle.start()
        config = VesselConfig(
            vehicle=f"udpout:127.0.0.1:{vehicle.port}",
            system_id=system_id,
            behavior=BehaviorChoice(behavior="bob-rule", params={"p0": 5.0}),
            origin=ORIGIN,
            time_scale=SCALE,
            controller="simple",
            gcs=f"udpout:127.0.0.1:{port}",
            autostart=False,
        )
        vessel = Vessel(config, clock=ScaledWallClock(SCALE))
        thread = threading.Thread(target=vessel.run, daemon=True)
        thread.start()
        rigs.append((vehicle, vessel, thread))
    try:
        example = load_example("mission_goal_seeking")
        code = example.main(
            ["--connection", f"udpin:127.0.0.1:{port}", "--vessels", "2", "--east", "20", "--north", "4",
             "--radius", "6", "--timeout", "40", "--discover-timeout", "20"]
        )  # fmt: skip
        assert code == 0
        for vehicle, _vessel, _thread in rigs:
            assert np.hypot(vehicle.position[0] - 20.0, vehicle.position[1] - 4.0) < 8.0, vehicle.position
    finally:
        for vehicle, vessel, thread in rigs:
            vessel.stop()
            thread.join(5.0)
            vehicle.close()
