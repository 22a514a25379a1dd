"""MAVSDK uploads and downloads a mission to the real ArduPilot through the vessel: two partners we did not write.

tests/test_interop_mavsdk.py makes the same round trip with our simulated autopilot behind the vessel and asserts
what it believes of ArduPilot's mission protocol: item 0 is kept for home (AP_Mission), so an upload's item 0 is a
placeholder and a download's item 0 is the home position, and items come back in the plain frame
(GLOBAL_RELATIVE_ALT), not the _INT one that was sent. A belief checked only against our own simulator would be
wrong twice and pass; here ArduPilot's own Rover SITL answers, routed both ways by the vessel (the mission
microservice: MISSION_COUNT, MISSION_REQUEST_INT, MISSION_ITEM_INT, MISSION_ACK).

Skipped unless ARDUPILOT_SITL names a built `ardurover` (docs/ardupilot.md).
"""

from __future__ import annotations

import math
import threading
import time

import pytest
from sitl_harness import BINARY, NEEDS_SITL, RoverSitl, vessel_config

mavsdk = pytest.importorskip("mavsdk", minversion="4.1", reason="MAVSDK-Python 4.1+ (pip install -e '.[dev]')")

from mavsdk import ComponentType, Configuration, Mavsdk  # noqa: E402
from mavsdk.plugins.mission_raw.mission_raw import MissionItem, MissionRaw  # noqa: E402
from mavsdk.plugins.telemetry.telemetry import Telemetry  # noqa: E402
from pymavlink.dialects.v20 import ardupilotmega as mavlink  # noqa: E402

from bob_autonomy.onboard.vessel import Vessel  # noqa: E402

pytestmark = NEEDS_SITL


def _wait(predicate, timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        assert time.monotonic() < deadline, f"{what}: not within {timeout_s} s"
        time.sleep(0.05)


def test_mavsdk_uploads_and_downloads_real_ardupilots_mission_through_the_vessel(tmp_path) -> None:
    with RoverSitl(BINARY, "omni", tmp_path) as sitl:
        sitl.wait_initialised()
        config = vessel_config(sitl, gcs="udpin:127.0.0.1:0")
        vessel = Vessel(config)
        runner = threading.Thread(target=vessel.run, kwargs={"duration_s": 120.0}, daemon=True)
        runner.start()
        sdk = Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION))
        try:
            assert sdk.add_any_connection(f"udpout://127.0.0.1:{vessel.gcs_link.local_address[1]}") == 0
            _wait(lambda: sdk.system_count() >= 1, 60.0, "MAVSDK discovering the vessel")
            system = sdk.get_systems()[0]
            telemetry = Telemetry(system)
            _wait(lambda: math.isfinite(telemetry.home().latitude_deg), 60.0, "ArduPilot's home through MAVSDK")
            home = telemetry.home()
            lat0, lon0 = int(home.latitude_deg * 1e7), int(home.longitude_deg * 1e7)
            waypoints = [(lat0 + 300 * k, lon0 + 200 * k) for k in range(1, 4)]
            items = [
                MissionItem(seq=seq, frame=mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, command=16,
                            current=int(seq == 0), autocontinue=1, x=x, y=y, z=0.0, mission_type=0)
                for seq, (x, y) in enumerate([(lat0, lon0), *waypoints])
            ]  # fmt: skip
            mission = MissionRaw(system)
            mission.upload_mission(items)
            got = mission.download_mission()
        finally:
            sdk.destroy()
            vessel.stop()
            runner.join(10.0)
    assert [item.seq for item in got] == [0, 1, 2, 3]
    assert all(item.command == 16 for item in got)
    assert [(item.x, item.y) for item in got[1:]] == waypoints
    assert {item.frame for item in got[1:]} == {mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT}, "the plain frame back"
    assert abs(got[0].x - lat0) < 100 and abs(got[0].y - lon0) < 100, "item 0 is home (within 1 m)"
    assert vessel.stats.routed_to_vehicle >= len(items) + 2  # the count, the items, the download's requests
