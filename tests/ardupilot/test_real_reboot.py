"""ArduPilot restarts under a driving vessel (a brownout, a watchdog reset): the vessel gets it back into service.

ArduPilot's SITL reboots by executing itself again (libraries/AP_HAL_SITL/HAL_SITL_Class.cpp), as a real autopilot
does after a brownout: the vessel's TCP connection closes, the autopilot comes back disarmed, streaming its
defaults only, its clock since boot near zero, and the simulated boat back at HOME. Before, the vessel logged a
failed read at every pump forever and never drove again. Now it reopens the link, sees the autopilot's clock go
back, runs the whole start-up again (streams, parameters, mode, ready, armed) and drives on to its goal. The judge
is the autopilot itself on SERIAL1: armed again, and its own position at the goal.

Skipped unless ARDUPILOT_SITL names a built `ardurover` (docs/ardupilot.md).
"""

from __future__ import annotations

import threading
import time

import numpy as np
from pymavlink import mavutil
from sitl_harness import BINARY, NEEDS_SITL, RoverSitl, local_xy, vessel_config

from bob_autonomy.onboard.vessel import Vessel

pytestmark = NEEDS_SITL
GOAL = (30.0, 0.0)  # east, north m from HOME
FORCE_REBOOT_WHILE_ARMED = 20190226  # ArduPilot refuses to reboot when armed without it (GCS_Common.cpp)


def _observer(port: int, timeout_s: float = 30.0) -> mavutil.mavfile:
    """A fresh pymavlink connection to the restarted autopilot's SERIAL1 (the old one closed with the process)."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            return mavutil.mavlink_connection(f"tcp:127.0.0.1:{port}", source_system=254)
        except OSError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.5)


def test_a_vessel_brings_a_rebooted_autopilot_back_into_service_and_reaches_its_goal(tmp_path) -> None:
    with RoverSitl(BINARY, "omni", tmp_path) as sitl:
        sitl.wait_initialised()
        vessel = Vessel(vessel_config(sitl, GOAL))
        # The vessel runs until the test stops it: a run bounded by its own duration ended before the restarted
        # autopilot was seen armed once, when the whole real suite loaded the host (it drove late).
        runner = threading.Thread(target=vessel.run, kwargs={"duration_s": 600.0}, daemon=True)
        runner.start()
        started = time.monotonic()
        deadline = started + 90.0
        while not (sitl.seen.modes and sitl.seen.modes[-1][2] and vessel.stats.commands > 50):
            assert time.monotonic() < deadline and runner.is_alive(), "the vessel never drove"
            time.sleep(0.2)
        sitl.observer.mav.command_int_send(
            1, 1, 0, mavutil.mavlink.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, 0, 0, 1, 0, 0, 0, 0, FORCE_REBOOT_WHILE_ARMED, 0
        )
        rebooted_at = time.monotonic()
        drove_after_s = rebooted_at - started
        sitl.stop_watching()  # its connection closes with the process
        time.sleep(3.0)
        observer = _observer(sitl.serial1)
        armed_again, position = None, None
        try:
            deadline = time.monotonic() + 120.0
            while time.monotonic() < deadline and runner.is_alive():
                observer.mav.command_long_send(1, 1, 511, 0, 33, 2e5, 0, 0, 0, 0, 0)  # GLOBAL_POSITION_INT at 5 Hz
                msg = observer.recv_match(type=["HEARTBEAT", "GLOBAL_POSITION_INT"], blocking=True, timeout=1.0)
                if msg is None or msg.get_srcComponent() != 1:
                    continue
                if msg.get_type() == "HEARTBEAT":
                    if msg.base_mode & mavutil.mavlink.MAV_MODE_FLAG_SAFETY_ARMED and armed_again is None:
                        armed_again = time.monotonic() - rebooted_at
                else:
                    position = np.array(local_xy(msg.lat * 1e-7, msg.lon * 1e-7))
                    if armed_again is not None and np.hypot(*(position - GOAL)) < 3.0:
                        break
        finally:
            observer.close()
            vessel.stop()
            runner.join(15.0)
    stats = vessel.stats
    print(
        f"\ndriving {drove_after_s:.1f} s after the start; rebooted; armed again {armed_again} s after the reboot; "
        f"at {position}; vessel {stats.summary()}"
    )
    assert stats.link_reopens >= 1 and stats.autopilot_reboots == 1 and stats.restarts >= 1
    assert armed_again is not None, "the restarted autopilot was never armed again"
    assert position is not None and np.hypot(*(position - GOAL)) < 3.0, f"the autopilot ended at {position}"
