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
from sitl_harness import BINARY, NEEDS_SITL, RoverSitl

from firmware_bridge.autopilot_requests import set_message_interval
from firmware_bridge.commands import Encoder
from firmware_bridge.decoder import TelemetryDecoder
from firmware_bridge.readings import CompassReading, ImuReading

pytestmark = NEEDS_SITL

READ_EVERY_S = 0.3  # as a vessel whose loop reads its link every 0.3 s
BURSTS = 40


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
        with socket.create_connection(("127.0.0.1", sitl.serial0), timeout=5.0) as link:
            for message in (mavlink.MAVLINK_MSG_ID_SCALED_IMU, mavlink.MAVLINK_MSG_ID_ATTITUDE):
                link.sendall(set_message_interval(Encoder(), 1, message, 25.0))
            decoder = TelemetryDecoder(source_system=1, source_component=1)  # as a vessel
            sent = []  # ArduPilot's time_boot_ms of each SCALED_IMU and ATTITUDE, in stream order
            wanted = ("SCALED_IMU", "ATTITUDE")
            decoder.message_hook = lambda msg: sent.append(msg.time_boot_ms) if msg.get_type() in wanted else None
            bursts = []  # per burst: (its arrival, [(placed time, ArduPilot's time s) of each IMU and attitude])
            for _ in range(BURSTS):
                time.sleep(READ_EVERY_S)
                data = _read_all(link)
                before = len(sent)
                readings = decoder.feed(data)
                arrival = time.monotonic()
                placed = [float(r.t_s[0]) for r in readings if isinstance(r, ImuReading | CompassReading)]
                bursts.append((arrival, list(zip(placed, [ms * 1e-3 for ms in sent[before:]], strict=True))))
    learnt = [pairs for arrival, pairs in bursts[3:] if pairs]  # once the clock has had a few samples
    assert len(learnt) >= BURSTS - 5
    distinct = [len({round(placed, 4) for placed, _ in pairs}) for pairs in learnt]
    assert min(distinct) >= 4, distinct  # 25 Hz x 0.3 s: about 7 sending times a burst (with arrival stamps: 1)
    placed = np.array([p for pairs in learnt for p, _ in pairs])
    ardupilot = np.array([a for pairs in learnt for _, a in pairs])
    offset = placed - ardupilot  # the clocks' offset, plus the error of the placement
    print(f"offset spread {np.ptp(offset) * 1e3:.1f} ms over {len(placed)} readings; times per burst {distinct}")
    assert np.ptp(offset) < 0.01
    assert all(p <= arrival for arrival, pairs in bursts for p, _ in pairs)
