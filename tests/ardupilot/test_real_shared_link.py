"""The vessel behind MAVProxy as a router, beside an operator's ground station on the same autopilot link.

On many boats the companion computer runs MAVProxy (or mavlink-router) on the autopilot's port and hands the
link to both the autonomy and the operator (`mavproxy.py --master=/dev/ttyAMA0 --out=udp:...`). The router passes
every autopilot frame to every output, so the autonomy also hears the COMMAND_ACKs ArduPilot addresses to the
operator (target_system, target_component: the command's sender, GCS_Common.cpp handle_command_long). The vessel
takes only those addressed to itself (bob_autonomy/onboard/autopilot.py `_addressed_to_us`): before, it took
any, and an operator's accepted ARM_DISARM could end its own refused start-up as armed
(tests/test_autopilot_session.py). Here ArduPilot's Rover SITL is the autopilot and MAVProxy the router and the
operator's console: the operator changes mode three times while the vessel drives, and the vessel, which
arms and sets its streams on its own acks, reaches its goal and counts the operator's acks as someone else's.

Skipped unless ARDUPILOT_SITL names a built `ardurover` (docs/ardupilot.md).
"""

from __future__ import annotations

import math
import threading
import time

import pytest
from mavproxy_session import MAVPROXY, MavproxySession
from sitl_harness import BINARY, NEEDS_SITL, RoverSitl, free_udp_port, local_xy, vessel_config

from bob_autonomy.onboard.vessel import Vessel

pytestmark = [
    *NEEDS_SITL,
    pytest.mark.skipif(MAVPROXY is None, reason="MAVProxy is not installed (pip install -e '.[dev]')"),
]
GOAL = (25.0, 0.0)  # m east, north of HOME


def test_the_vessel_behind_mavproxy_takes_only_the_acks_ardupilot_addresses_to_it(tmp_path) -> None:
    with RoverSitl(BINARY, "omni", tmp_path) as sitl:
        sitl.wait_initialised()
        port = free_udp_port()
        # MAVProxy on the autopilot's SERIAL0, the vessel on one of its outputs; no stream requests of its own
        # (--streamrate=-1: they would reset the rates the autonomy asks for, as on ArduPilot's own port).
        router = MavproxySession(
            f"tcp:127.0.0.1:{sitl.serial0}",
            tmp_path,
            component=1,
            extra=(f"--out=udpin:127.0.0.1:{port}", "--streamrate=-1", "--source-system=255"),
        )
        vessel = Vessel(vessel_config(sitl, goal=GOAL, vehicle=f"udpout:127.0.0.1:{port}"))
        runner = threading.Thread(target=vessel.run, kwargs={"duration_s": 120.0}, daemon=True)
        try:
            router.expect(r"Detected vehicle 1:1", 30.0)
            runner.start()
            deadline = time.monotonic() + 90.0
            while not (sitl.seen.modes and sitl.seen.modes[-1][2]):
                assert time.monotonic() < deadline, "the vessel never armed ArduPilot through MAVProxy"
                time.sleep(0.5)
            for _ in range(3):  # the operator: MANUAL again (the vessel drives in MANUAL), answered to MAVProxy
                router.command("mode MANUAL", r"Got COMMAND_ACK: DO_SET_MODE: ACCEPTED", 10.0)
            deadline = time.monotonic() + 90.0
            while math.dist(local_xy(*sitl.seen.positions[-1][1:3]), GOAL) > 5.0:
                assert time.monotonic() < deadline, f"never within 5 m of {GOAL}: at {sitl.seen.positions[-1]}"
                time.sleep(0.5)
            session = vessel.autopilot
        finally:
            vessel.stop()
            if runner.is_alive():
                runner.join(10.0)
            router.close()
    taken = sorted({command for _t, command, _r in session.acks})
    print(f"\nacks taken {len(session.acks)} (commands {taken}), for others {session.acks_for_others}")
    assert session.acks_for_others >= 3  # the operator's DO_SET_MODE answers, addressed to MAVProxy
    assert session.intervals_accepted  # its own SET_MESSAGE_INTERVAL answers were taken
    mode = 176  # MAV_CMD_DO_SET_MODE: the vessel's own (at its start-up) only
    assert sum(1 for _t, command, _r in session.acks if command == mode) <= 2
