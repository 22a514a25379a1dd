"""ArduPilot's IMU and attitude, read from its link in bursts, keep the times ArduPilot sent them at.

A vessel reads its link once a loop; between two reads ArduPilot has sent several SCALED_IMU and ATTITUDE
messages, each stamped with its `time_boot_ms` (libraries/GCS_MAVLink/GCS_Common.cpp: `AP_HAL::millis()` when
sent). The decoder dates each by that stamp, placed on the local clock (firmware_bridge/autopilot_clock.py), so
the readings of one burst are spaced as ArduPilot sent them rather than all stamped with the burst's arrival.

Skipped unless ARDUPILOT_SITL names a built `ardurover` (docs/ardupilot.md).
"""

from __future__ import annotations

import socket
import time

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink
from sitl_harness import BINARY, NEEDS_SITL, RoverSitl, asking_link, sent_s

from firmware_bridge.decoder import TelemetryDecoder
from firmware_bridge.readings import CompassReading, ImuReading

pytestmark = NEEDS_SITL

READ_EVERY_S = 0.3  # as a vessel whose loop reads its link every 0.3 s
BURSTS = 40
# The messages read as IMU or attitude readings: RAW_IMU comes too, at ArduPilot's RAW_SENS rate.
SENT_STAMPED = frozenset({"SCALED_IMU", "ATTITUDE", "RAW_IMU"})


def _read_all(link: socket.socket) -> bytes:
    """Everything the link holds now (without waiting for more)."""
    data = bytearray()
    link.setblocking(False)
    try:
        while True:
            try:
                part = link.recv(65536)
            except BlockingIOError:
                break
            if not part:
                break
            data += part
    finally:
        link.setblocking(True)
    return bytes(data)


def test_readings_of_one_burst_keep_the_times_ardupilot_sent_them_at(tmp_path) -> None:
    with RoverSitl(BINARY, "omni", tmp_path) as sitl:
        sitl.wait_initialised()
        with asking_link(sitl, (mavlink.MAVLINK_MSG_ID_SCALED_IMU, mavlink.MAVLINK_MSG_ID_ATTITUDE), 25.0) as link:
            decoder = TelemetryDecoder(source_system=1, source_component=1)  # as a vessel
            sent = []  # ArduPilot's time of sending (s since boot) of each IMU and attitude message, in stream order
            decoder.message_hook = lambda msg: sent.append(sent_s(msg)) if msg.get_type() in SENT_STAMPED else None
            bursts = []  # per burst: (its arrival, [(placed time, ArduPilot's time s) of each IMU and attitude])
            for _ in range(BURSTS):
                time.sleep(READ_EVERY_S)
                data = _read_all(link)
                before = len(sent)
                readings = decoder.feed(data)
                arrival = time.monotonic()
                placed = [float(r.t_s[0]) for r in readings if isinstance(r, ImuReading | CompassReading)]
                bursts.append((arrival, list(zip(placed, sent[before:], strict=True))))
    learnt = [pairs for arrival, pairs in bursts[3:] if pairs]  # once the clock has had a few samples
    assert len(learnt) >= BURSTS - 5
    distinct = [len({round(placed, 4) for placed, _ in pairs}) for pairs in learnt]
    assert min(distinct) >= 4, distinct  # 25 Hz x 0.3 s: about 7 sending times a burst (with arrival stamps: 1)
    for pairs in learnt:  # within a burst, spaced as ArduPilot sent them (its stamps are whole ms)
        placed, ardupilot = np.array(pairs).T
        np.testing.assert_allclose(np.diff(placed), np.diff(ardupilot), atol=0.0025)
    placed = np.array([p for pairs in learnt for p, _ in pairs])
    ardupilot = np.array([a for pairs in learnt for _, a in pairs])
    arrived = np.array([arrival for arrival, pairs in bursts[3:] if pairs for _ in pairs])
    offset = placed - ardupilot  # the clocks' offset, plus the error of the placement
    # What moves it: the clock's estimate is the smallest delay seen, leaked at 10 ms/s, and a burst's freshest
    # message is 0-40 ms old when read (22-28 ms in runs of 2026-11-28; by arrival, 307 ms).
    spread, by_arrival = np.ptp(offset), np.ptp(arrived - ardupilot)
    print(f"offset spread {spread * 1e3:.1f} ms over {len(placed)} readings (by arrival {by_arrival * 1e3:.0f} ms)")
    assert spread < 0.05 and by_arrival > 0.25
    assert all(p <= arrival for arrival, pairs in bursts for p, _ in pairs)
