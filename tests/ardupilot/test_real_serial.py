"""bob-autonomy and ArduPilot's own Rover SITL on a serial line, as on a boat: the autopilot's TELEM2 port (SERIAL2:
MAVLink 2 at ArduPilot's default 57,600 baud, `--serial2 uart:PATH`) wired to the companion computer's
USB-serial adapter (pseudo-terminals joined by tests/serial_cable.py). `SIM_BAUDLIMIT_EN = 1` makes the
SITL hold each port to its baud rate, 5,760 bytes/s each way at 57,600 baud (libraries/AP_HAL_SITL/UARTDriver.cpp
`handle_writing_from_writebuffer_to_device`), so its streams share the line as they would on the boat.

Skipped unless ARDUPILOT_SITL names a built `ardurover` (docs/ardupilot.md). Judged by what the autopilot itself
reports on its SERIAL1 (TCP), which the serial line does not carry.
"""

from __future__ import annotations

import logging
import threading
import time

import numpy as np
import pytest
from serial_cable import SerialCable
from sitl_harness import BINARY, NEEDS_SITL, RoverSitl, drive, local_xy, vessel_config

from bob_autonomy.onboard.vessel import VehicleError, Vessel

pytestmark = NEEDS_SITL
TELEM2 = {"SIM_BAUDLIMIT_EN": 1, "SERIAL2_PROTOCOL": 2, "SERIAL2_BAUD": 57}
LINE_BYTES_PER_S = 57600 / 10  # 8 data bits, a start and a stop bit per byte
GOAL = (25.0, 0.0)


def _drive_over(cable: SerialCable, tmp_path, seconds: float):
    """The vessel on the cable's companion end at 57,600 baud, seeking GOAL for `seconds` after its start-up, with
    ArduPilot on the cable's other end. Returns (sitl, track, estimate errors, vessel, the rates (Hz) of the streams
    the vessel asked for at its end, driving window (start, end) in time.monotonic())."""
    with RoverSitl(BINARY, "omni", tmp_path, params=TELEM2, serial2=f"uart:{cable.autopilot_path}") as sitl:
        sitl.wait_initialised()
        config = vessel_config(sitl, GOAL, vehicle=str(cable.companion_path), baud=57600)
        start = time.monotonic()
        track, errors, vessel = drive(sitl, config, seconds)
        rates = vessel.autopilot.stream_rates(vessel.clock.now())
        return sitl, track, errors, vessel, rates, (start, time.monotonic())


def _reached(track, seconds: float = 10.0) -> list[float]:
    """Distances (m) from GOAL over the last `seconds` of a track."""
    return [float(np.hypot(*(xy - GOAL))) for t, xy, _h in track if t > track[-1][0] - seconds]


def test_the_vessel_drives_real_ardupilot_over_its_telem2_port_at_57600_baud(tmp_path, capsys) -> None:
    with SerialCable(tmp_path) as cable:
        sitl, track, errors, vessel, rates, (start, end) = _drive_over(cable, tmp_path, 60.0)
    down = cable.to_companion.bytes_per_s(start + 20.0, end)  # once the start-up's parameter reads are over
    up = cable.to_autopilot.bytes_per_s(start + 20.0, end)
    with capsys.disabled():
        print(f"\n57,600 baud: autopilot -> vessel {down:.0f} B/s, vessel -> autopilot {up:.0f} B/s; rates {rates}")
    assert any(armed for _t, _mode, armed in sitl.seen.modes)
    held = _reached(track)
    assert held and max(held) < 5.0, f"the last 10 s {held}"
    assert float(np.median(errors)) < 2.0
    # Every message the estimator asked for came at its rate over the shared line (the rates asked are
    # bob_autonomy.onboard.autopilot STREAMS_HZ: GPS_RAW_INT 10 Hz, ATTITUDE 20, SCALED_IMU 25).
    assert rates["GPS_RAW_INT"] > 8.0 and rates["ATTITUDE"] > 16.0 and rates["SCALED_IMU"] > 20.0, rates
    assert down < 0.9 * LINE_BYTES_PER_S, "the streams asked for fill the line: ArduPilot would slow them all"
    counters = vessel.vehicle.decoder.counters
    assert counters.bad_crc == 0 and counters.malformed == 0, counters


@pytest.mark.parametrize("seed", [7, 3, 11])
def test_a_noisy_line_costs_frames_but_not_the_vessel(tmp_path, caplog, seed: int) -> None:
    """One byte in 200 lost and one in 200 with a bit flipped, each way: a bad connector or a marginal radio, about
    half the frames spoiled. Found here: a lost SET_MESSAGE_INTERVAL was answered with its whole stream group
    (REQUEST_DATA_STREAM), which overfilled the line and starved ATTITUDE to 0.2 Hz; two rounds of parameter
    requests left FRAME_CLASS unread; three HEARTBEATs lost in a row stopped the boat as if its autopilot were
    silent, while 40 other messages a second came."""
    caplog.set_level(logging.INFO)
    with SerialCable(tmp_path, drop=5e-3, flip=5e-3, seed=seed) as cable:
        sitl, track, errors, vessel, rates, (start, end) = _drive_over(cable, tmp_path, 60.0)
    spoiled = cable.to_companion.dropped + cable.to_companion.flipped
    counters = vessel.vehicle.decoder.counters
    texts = [r.getMessage() for r in caplog.records]
    assert spoiled > 1000 and cable.to_autopilot.dropped + cable.to_autopilot.flipped > 100
    # Each spoiled byte costs the frame it was in (a bad checksum, or bytes skipped to the next frame start), and
    # nothing worse: no frame decoded from bad bytes, the rest read on.
    assert counters.bad_crc + counters.malformed > 0.3 * spoiled, counters
    assert not any("did not report" in t for t in texts), texts  # every parameter read, in more rounds
    # No stream group asked for: EXT_STAT's POWER_STATUS stays at its default 1 Hz, less what the line spoils
    assert counters.by_type.get("POWER_STATUS", 0) < 1.0 * (end - start), counters.by_type
    assert rates["ATTITUDE"] > 5.0 and rates["SCALED_IMU"] > 5.0, rates  # what the estimator needs, at least
    assert vessel.stats.silent_alarms == 0
    assert any(armed for _t, _mode, armed in sitl.seen.modes)
    held = _reached(track)
    assert held and max(held) < 5.0, f"the last 10 s {held}"
    assert float(np.median(errors)) < 2.0
    assert not any(r.levelno >= logging.ERROR for r in caplog.records), texts


def test_an_adapter_shaken_loose_for_four_seconds_hands_the_boat_to_ardupilot_and_back(tmp_path, caplog) -> None:
    """The companion's USB-serial adapter unplugged for 4 s while the boat drives 60 m east: ArduPilot lets the
    overrides lapse after RC_OVERRIDE_TIME (3 s) and holds its own (neutral) inputs; the vessel reopens the port
    by its path when it is back and drives on to the goal."""
    caplog.set_level(logging.INFO)
    goal = (60.0, 0.0)
    outcome: list = []
    with (
        SerialCable(tmp_path) as cable,
        RoverSitl(BINARY, "omni", tmp_path, params=TELEM2, serial2=f"uart:{cable.autopilot_path}") as sitl,
    ):
        sitl.wait_initialised()
        config = vessel_config(sitl, goal, vehicle=str(cable.companion_path), baud=57600)
        driving = threading.Thread(target=lambda: outcome.append(drive(sitl, config, 100.0)), daemon=True)
        driving.start()
        deadline = time.monotonic() + 90.0
        while not (sitl.seen.positions and local_xy(*sitl.seen.positions[-1][1:3])[0] > 10.0):
            assert time.monotonic() < deadline and driving.is_alive(), "the boat did not get 10 m on its way"
            time.sleep(0.2)
        cable.unplug_companion()
        unplugged = time.monotonic()
        time.sleep(4.0)
        cable.replug_companion()
        replugged = time.monotonic()
        driving.join()
    track, _errors, vessel = outcome[0]
    texts = [r.getMessage() for r in caplog.records]
    assert vessel.stats.link_reopens == 1, texts
    assert any("link lost" in t for t in texts) and any("link reopened after" in t for t in texts)
    # ArduPilot's own inputs: the overrides lapsed within the gap (throttle and lateral back at 1500) ...
    lapsed = [rc for t, rc in sitl.seen.rc if unplugged + 3.5 < t < replugged]
    assert lapsed and all(abs(rc[2] - 1500) <= 10 and abs(rc[3] - 1500) <= 10 for rc in lapsed), lapsed
    # ... and were the vessel's again after it (moving the boat east), and the boat reached the goal.
    again = [rc for t, rc in sitl.seen.rc if t > replugged + 3.0]
    assert any(abs(rc[2] - 1500) > 50 or abs(rc[3] - 1500) > 50 for rc in again)
    held = [float(np.hypot(*(xy - goal))) for t, xy, _h in track if t > track[-1][0] - 10.0]
    assert held and max(held) < 5.0, f"the last 10 s {held}"


def test_a_vessel_at_another_baud_rate_than_telem2_is_told_which_rate_to_use(tmp_path) -> None:
    """ArduPilot's TELEM2 set to 921,600 baud (SERIAL2_BAUD 921), the vessel at its default 57,600: what it reads is
    noise; it says the rate the port carries MAVLink at and what to change, and does not start."""
    at_921600 = {**TELEM2, "SERIAL2_BAUD": 921}
    with SerialCable(tmp_path) as cable:
        sitl = RoverSitl(BINARY, "omni", tmp_path, params=at_921600, serial2=f"uart:{cable.autopilot_path}")
        with sitl:
            sitl.wait_initialised()
            vessel = Vessel(vessel_config(sitl, GOAL, vehicle=str(cable.companion_path), arm_timeout_s=5.0))
            with pytest.raises(VehicleError) as caught:
                vessel.arm()
    assert "carries MAVLink at 921600 baud, not 57600: start with --baud 921600" in str(caught.value)
    assert not any(armed for _t, _mode, armed in sitl.seen.modes)
