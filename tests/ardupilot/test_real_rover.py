"""bob-autonomy against ArduPilot's own Rover SITL: the autopilot we did not write.

Skipped unless ARDUPILOT_SITL names a built `ardurover` (see docs/ardupilot.md). Each test starts a fresh
SITL (wiped EEPROM, the autotest default parameters of the model) and judges by what the autopilot itself
reports on its second serial port (position, RC inputs, mode), never by our own logs.
"""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from sitl_harness import BINARY, HOME, NEEDS_SITL, RoverSitl, drive, vessel_config

from bob_autonomy.onboard.vessel import VehicleError, Vessel, VesselConfig

pytestmark = NEEDS_SITL
ORIGIN = (HOME[0], HOME[1])
LEG_S = 75.0


def _drive(sitl: RoverSitl, config: VesselConfig, seconds: float) -> tuple[list, list]:
    track, errors, _vessel = drive(sitl, config, seconds)
    return track, errors


def test_omni_buoy_reaches_goals_in_four_directions_and_holds_heading(tmp_path) -> None:
    corners = [(50.0, 0.0), (50.0, 50.0), (0.0, 50.0), (0.0, 0.0)]  # east, north, west, south legs of 50 m
    with RoverSitl(BINARY, "omni", tmp_path) as sitl:
        sitl.wait_initialised()
        all_errors = []
        for goal in corners:
            track, errors = _drive(sitl, vessel_config(sitl, goal), LEG_S)
            all_errors += errors
            held = [np.hypot(*(xy - goal)) for t, xy, _ in track if t > track[-1][0] - 10.0]
            assert held and max(held) < 5.0, f"goal {goal}: last 10 s at {held}"
            headings = np.radians([h for _t, _xy, h in track])
            spread = np.degrees(np.max(np.abs(np.angle(np.exp(1j * (headings - headings[0]))))))
            assert spread < 15.0, f"heading wandered {spread:.1f} deg on the leg to {goal}"
        assert float(np.median(all_errors)) < 2.0


def test_sigterm_puts_the_vehicle_at_neutral_within_half_a_second(tmp_path) -> None:
    with RoverSitl(BINARY, "omni", tmp_path) as sitl:
        sitl.wait_initialised()
        command = [
            sys.executable,
            "-m",
            "bob_autonomy.cli",
            "run",
            "--vehicle",
            f"tcp:127.0.0.1:{sitl.serial0}",
            "--system-id",
            "1",
            f"--origin={ORIGIN[0]},{ORIGIN[1]}",
            "--behavior",
            "bob-rule",
            "--param",
            "H=1",
            "--param",
            "goal=[200,0]",
            "--param",
            "max_speed=1.5",
            "--param",
            "speed_scale=1",
            "--log-file",
            str(tmp_path / "vessel.log"),
        ]
        process = subprocess.Popen(command, env={**os.environ, "PYTHONUNBUFFERED": "1"})
        deadline = time.monotonic() + 90
        while time.monotonic() < deadline:  # wait until it drives (throttle or lateral away from trim)
            if sitl.seen.rc and any(abs(c - 1500) > 100 for c in sitl.seen.rc[-1][1][2:4]):
                break
            time.sleep(0.2)
        else:
            process.kill()
            pytest.fail("the vessel never drove")
        time.sleep(3.0)
        stopped_at = time.monotonic()
        process.send_signal(signal.SIGTERM)
        assert process.wait(timeout=10) == 0
        after = [(t - stopped_at, ch) for t, ch in sitl.seen.rc if t > stopped_at]
        neutral = [t for t, ch in after if all(abs(c - 1500) <= 30 for c in ch[:4])]
        assert neutral and neutral[0] < 0.5, after[:10]
        print(f"every RC channel at trim {neutral[0]:.2f} s after SIGTERM")


def test_a_buoy_on_a_motorboat_is_refused_with_what_to_change(tmp_path) -> None:
    with RoverSitl(BINARY, "motorboat", tmp_path) as sitl:
        sitl.wait_initialised()
        vessel = Vessel(vessel_config(sitl, (50.0, 0.0)))
        with pytest.raises(VehicleError, match=r"cannot move sideways"):
            vessel.run(duration_s=5.0)
        assert not any(armed for _t, _mode, armed in sitl.seen.modes)


def test_without_an_rc_receiver_the_vessel_still_arms_and_drives(tmp_path) -> None:
    # A buoy has no transmitter: ArduPilot boots in radio failsafe; neutral overrides first, then arming.
    with RoverSitl(BINARY, "omni", tmp_path, params={"SIM_RC_FAIL": 1}) as sitl:
        sitl.wait_initialised()
        track, _errors = _drive(sitl, vessel_config(sitl, (20.0, 0.0)), 45.0)
        assert track and np.hypot(*(track[-1][1] - (20.0, 0.0))) < 5.0
        assert math.isfinite(track[-1][2])


def test_an_autopilot_taking_mavlink_only_from_its_ground_station_is_started_and_driven(tmp_path) -> None:
    # MAV_OPTIONS bit 0 with MAV_GCS_SYSID 200: before the vessel asked as its own system until it knew that id,
    # ArduPilot answered none of its queries and the start-up ended "would not arm" without a reason.
    params = {"MAV_GCS_SYSID": 200, "MAV_OPTIONS": 1}
    with RoverSitl(BINARY, "omni", tmp_path, params=params) as sitl:
        sitl.wait_initialised()
        track, _errors, vessel = drive(sitl, vessel_config(sitl, (20.0, 0.0)), 45.0)
        assert vessel.autopilot.profile.gcs_system_id == 200
        assert track and np.hypot(*(track[-1][1] - (20.0, 0.0))) < 5.0, track[-1]


def test_skid_steer_rover_as_an_ebot_reaches_goals_with_gps(tmp_path) -> None:
    # The eBot kind outdoors: no wheel encoders (WENC_TYPE unset), position from GPS, wheel speeds scaled to the
    # rover's own full-throttle speed (CRUISE_SPEED / CRUISE_THROTTLE).
    with RoverSitl(BINARY, "skid", tmp_path) as sitl:
        sitl.wait_initialised()
        for goal in [(30.0, 0.0), (30.0, 30.0)]:
            track, errors = _drive(sitl, vessel_config(sitl, goal, kind="ebot"), 50.0)
            held = [np.hypot(*(xy - goal)) for t, xy, _ in track if t > track[-1][0] - 5.0]
            assert held and max(held) < 5.0, f"goal {goal}: last 5 s at {held}"
            assert float(np.median(errors)) < 2.0
