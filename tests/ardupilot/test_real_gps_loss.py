"""ArduPilot's GPS fails under a driving vessel: the vessel holds at neutral until fixes come back.

In MANUAL ArduPilot goes on applying whatever RC overrides it gets, GPS or not (Rover's EKF failsafe acts only in
the modes that need a position), so nothing but the vessel can stop a boat whose position estimate has begun to
drift. The SITL's GPS is switched off (SIM_GPS1_ENABLE 0) while the vessel drives to a goal: ArduPilot's own
RC input (RC_CHANNELS on SERIAL1) must come back to trim, and after the GPS is back, its own position must
reach the goal.

Skipped unless ARDUPILOT_SITL names a built `ardurover` (docs/ardupilot.md).
"""

from __future__ import annotations

import threading
import time

import numpy as np
from sitl_harness import BINARY, NEEDS_SITL, RoverSitl, local_xy, vessel_config

from bob_autonomy.onboard.vessel import GPS_LOST_S, Vessel

pytestmark = NEEDS_SITL
GOAL = (60.0, 0.0)  # east, north m from HOME
DRIVING = (2, 3)  # RC_CHANNELS indices of throttle (3) and lateral (4) on the omni frame


def _at_trim(channels: list[int]) -> bool:
    return all(abs(channels[i] - 1500) <= 30 for i in DRIVING)


def _set(sitl: RoverSitl, name: str, value: float) -> None:
    sitl.observer.mav.param_set_send(1, 1, name.encode(), value, 9)  # MAV_PARAM_TYPE_REAL32


def test_a_vessel_holds_its_boat_while_ardupilots_gps_has_no_fix(tmp_path) -> None:
    with RoverSitl(BINARY, "omni", tmp_path) as sitl:
        sitl.wait_initialised()
        vessel = Vessel(vessel_config(sitl, GOAL))
        runner = threading.Thread(target=vessel.run, kwargs={"duration_s": 150.0}, daemon=True)
        runner.start()
        try:
            deadline = time.monotonic() + 90.0
            while not (sitl.seen.rc and not _at_trim(sitl.seen.rc[-1][1]) and vessel.stats.commands > 50):
                assert time.monotonic() < deadline and runner.is_alive(), "the vessel never drove"
                time.sleep(0.2)
            _set(sitl, "SIM_GPS1_ENABLE", 0)
            off_at = time.monotonic()
            deadline = off_at + 15.0
            while not (vessel.stats.gps_outages and sitl.seen.rc and _at_trim(sitl.seen.rc[-1][1])):
                assert time.monotonic() < deadline, f"still driving {time.monotonic() - off_at:.1f} s after"
                time.sleep(0.1)
            held_after = time.monotonic() - off_at
            time.sleep(5.0)
            blind = [channels for t, channels in sitl.seen.rc if t > off_at + held_after + 0.5]
            assert blind and all(_at_trim(channels) for channels in blind)  # held while the GPS stays off
            _set(sitl, "SIM_GPS1_ENABLE", 1)
            deadline = time.monotonic() + 90.0
            while True:
                _t, lat, lon, _hdg = sitl.seen.positions[-1]
                position = np.array(local_xy(lat, lon))
                if np.hypot(*(position - GOAL)) < 3.0:
                    break
                assert time.monotonic() < deadline and runner.is_alive(), f"never reached the goal: at {position}"
                time.sleep(0.2)
        finally:
            vessel.stop()
            runner.join(15.0)
    print(f"\nheld {held_after:.1f} s after the GPS went off; vessel {vessel.stats.summary()}")
    assert vessel.stats.gps_outages == 1 and GPS_LOST_S <= held_after < GPS_LOST_S + 2.0
