"""ArduPilot sends GPS_RAW_INT at the rate asked, each copy stamped with the time of its fix: the vessel's decoder
reads each fix once.

Rover SITL's GPS runs at 5 Hz (SIM_GPS1_HZ); the vessel asks for GPS_RAW_INT at 10 Hz. ArduPilot then sends every
fix twice with the same time_usec (libraries/AP_GPS/AP_GPS.cpp send_mavlink_gps_raw: last_fix_time_ms). Before
the decoder knew this, each copy became a fix stamped with its own arrival time, and the estimator fused every
position twice, the second time 0.1 s late. Our simulated autopilot sent only new fixes, so no test saw it.

Skipped unless ARDUPILOT_SITL names a built `ardurover` (docs/ardupilot.md).
"""

from __future__ import annotations

import math
import socket
import time

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink
from sitl_harness import BINARY, NEEDS_SITL, RoverSitl

from firmware_bridge.autopilot_requests import set_message_interval
from firmware_bridge.commands import Encoder
from firmware_bridge.decoder import TelemetryDecoder
from firmware_bridge.readings import GpsFix

pytestmark = NEEDS_SITL


def test_the_decoder_reads_each_of_ardupilots_fixes_once(tmp_path) -> None:
    with RoverSitl(BINARY, "omni", tmp_path) as sitl:
        sitl.wait_initialised()
        with socket.create_connection(("127.0.0.1", sitl.serial0), timeout=5.0) as link:
            link.sendall(set_message_interval(Encoder(), 1, mavlink.MAVLINK_MSG_ID_GPS_RAW_INT, 10.0))
            decoder = TelemetryDecoder(source_system=1, source_component=1, fused_position=False)  # as a vessel
            raw = []  # every GPS_RAW_INT with a fix, as pymavlink reads it
            decoder.message_hook = lambda msg: raw.append(msg) if msg.get_type() == "GPS_RAW_INT" else None
            deadline = time.monotonic() + 60.0
            while not any(isinstance(r, GpsFix) for r in decoder.feed(link.recv(65536))):  # the GPS's first fix
                assert time.monotonic() < deadline, "ArduPilot's GPS never had a fix"
            raw.clear()
            read_before = decoder.last_fix_usec  # its second copy may come in the window: not read again
            repeats_before = decoder.counters.repeated_fix
            fixes, end = 0, time.monotonic() + 10.0
            while time.monotonic() < end:
                fixes += sum(isinstance(r, GpsFix) for r in decoder.feed(link.recv(65536)))
    with_fix = [msg for msg in raw if msg.fix_type >= 2]
    stamps = {msg.time_usec for msg in with_fix}
    assert 90 <= len(with_fix) <= 110, len(with_fix)  # 10 Hz for 10 s
    assert 45 <= len(stamps) <= 55, len(stamps)  # a 5 Hz GPS: every fix sent twice
    assert fixes == len(stamps - {read_before})
    assert decoder.counters.repeated_fix - repeats_before == len(with_fix) - fixes


def test_the_decoder_dates_each_of_ardupilots_fixes_by_the_time_ardupilot_read_it(tmp_path) -> None:
    """A fix goes out at a GPS_RAW_INT slot after ArduPilot read it, and arrival stamps are late by that wait.
    Placed by ArduPilot's clock (learnt from ATTITUDE's time_boot_ms), the fixes keep ArduPilot's own times to a
    few ms, and none is dated after its arrival."""
    with RoverSitl(BINARY, "omni", tmp_path) as sitl:
        sitl.wait_initialised()
        with socket.create_connection(("127.0.0.1", sitl.serial0), timeout=5.0) as link:
            for message in (mavlink.MAVLINK_MSG_ID_GPS_RAW_INT, mavlink.MAVLINK_MSG_ID_ATTITUDE):
                link.sendall(set_message_interval(Encoder(), 1, message, 10.0))
            decoder = TelemetryDecoder(source_system=1, source_component=1, fused_position=False)  # as a vessel
            stamps = []  # (fix time placed, arrival, ArduPilot's time_usec) of each fix read
            deadline = time.monotonic() + 60.0
            while time.monotonic() < deadline and len(stamps) < 60:  # 12 s of a 5 Hz GPS
                readings = decoder.feed(link.recv(65536))
                arrival = time.monotonic()  # just after the decoder's own reading of the clock
                for reading in readings:
                    if isinstance(reading, GpsFix):
                        stamps.append((float(reading.t_s[0]), arrival, decoder.last_fix_usec * 1e-6))
    assert len(stamps) == 60, "ArduPilot's GPS never had a fix"
    placed, arrival, read = (np.array(column[10:]) for column in zip(*stamps, strict=True))  # once the clock is learnt
    assert np.all(placed <= arrival)
    offset = placed - read  # the offset between the clocks, plus an error
    assert np.ptp(offset) < 0.01, np.ptp(offset)
    age = arrival - placed  # what arrival stamps were late by (76-100 ms, mean 88, in a run of 2026-11-28)
    assert np.all((age >= 0.0) & (age < 0.25)), (age.min(), age.max())


def test_the_decoder_reads_the_accuracies_ardupilots_gps_reports(tmp_path) -> None:
    """ArduPilot sends its GPS's own one-sigma horizontal and speed accuracies in GPS_RAW_INT's h_acc (mm) and
    vel_acc (mm/s); its simulated u-blox reports SIM_GPS1_ACC as the former. The vessel's decoder reads them in m
    and m/s, as pymavlink reads the same frames, and its EKF fuses each fix with the larger of them and its own noise
    parameters (bob_autonomy.estimation.BuoyEkfBank.update_gps)."""
    with RoverSitl(BINARY, "omni", tmp_path, params={"SIM_GPS1_ACC": 6.5}) as sitl:
        sitl.wait_initialised()
        with socket.create_connection(("127.0.0.1", sitl.serial0), timeout=5.0) as link:
            link.sendall(set_message_interval(Encoder(), 1, mavlink.MAVLINK_MSG_ID_GPS_RAW_INT, 5.0))
            decoder = TelemetryDecoder(source_system=1, source_component=1, fused_position=False)  # as a vessel
            raw = []
            decoder.message_hook = lambda msg: raw.append(msg) if msg.get_type() == "GPS_RAW_INT" else None
            read: list[tuple[float, float, object]] = []
            deadline = time.monotonic() + 60.0
            while time.monotonic() < deadline and len(read) < 10:
                for r in decoder.feed(link.recv(65536)):
                    if isinstance(r, GpsFix):
                        read.append((float(r.accuracy_m[0]), float(r.speed_accuracy_mps[0]), raw[-1]))
    assert len(read) == 10, "ArduPilot's GPS never had a fix"
    assert [h for h, _, _ in read[-5:]] == [6.5] * 5, read  # the first fixes may come before the driver's accuracy
    for horizontal, speed, msg in read:
        assert horizontal == msg.h_acc / 1000.0 or (msg.h_acc == 0 and math.isnan(horizontal))
        assert speed == msg.vel_acc / 1000.0 or (msg.vel_acc == 0 and math.isnan(speed))
