"""ArduPilot sends one IMU sample in both RAW_IMU and SCALED_IMU, and a vessel fuses it once.

bob_autonomy/onboard/imu_repeats.py drops an IMU row equal to its agent's last within 3.5 ms, on the claim (read in
libraries/GCS_MAVLink/GCS_Common.cpp send_raw_imu and send_scaled_imu) that both messages carry the IMU's
current sample in the same units, so that when they go out in one pass of update_send they are equal field for
field. Here the real Rover SITL sends both at 25 Hz (one interval: one of its stream buckets, sent in one pass);
the test finds the pairs in the messages themselves (ArduPilot's own send times) and checks that the vessel's
decoder and `ImuRepeats` drop only the second message of a pair, and nearly all of them. The first run, with a
20 ms window, also dropped samples of their own: at rest the SITL sends the same values again 20 ms later.

Skipped unless ARDUPILOT_SITL names a built `ardurover` (docs/ardupilot.md).
"""

from __future__ import annotations

import itertools
import time

from pymavlink.dialects.v20 import ardupilotmega as mavlink
from sitl_harness import BINARY, NEEDS_SITL, RoverSitl, asking_link, sent_s

from bob_autonomy.onboard.imu_repeats import ImuRepeats
from firmware_bridge.decoder import TelemetryDecoder
from firmware_bridge.readings import ImuReading

pytestmark = NEEDS_SITL

LISTEN_S = 8.0
IMU_FIELDS = ("xacc", "yacc", "zacc", "xgyro", "ygyro", "zgyro")
IMU_MESSAGES = frozenset({"SCALED_IMU", "RAW_IMU"})


def test_ardupilot_sends_an_imu_sample_twice_and_the_vessel_keeps_one(tmp_path) -> None:
    messages = []  # (type, ArduPilot's time of sending s, the six IMU fields as sent)
    dropped = []  # per IMU message, in stream order: whether the vessel dropped it as a repeat
    with RoverSitl(BINARY, "omni", tmp_path) as sitl:
        sitl.wait_initialised()
        with asking_link(sitl, (mavlink.MAVLINK_MSG_ID_SCALED_IMU, mavlink.MAVLINK_MSG_ID_RAW_IMU), 25.0) as link:
            decoder = TelemetryDecoder(source_system=1, source_component=1)  # as a vessel
            decoder.message_hook = lambda msg: (
                messages.append((msg.get_type(), sent_s(msg), tuple(getattr(msg, f) for f in IMU_FIELDS)))
                if msg.get_type() in IMU_MESSAGES
                else None
            )
            repeats = ImuRepeats(1)
            link.settimeout(0.5)
            end = time.monotonic() + LISTEN_S
            while time.monotonic() < end:
                try:
                    data = link.recv(65536)
                except TimeoutError:
                    continue
                for reading in decoder.feed(data):
                    if isinstance(reading, ImuReading):  # one row: one message
                        dropped.append(repeats.fresh(reading) is None)
    # A pair: a message equal field for field to the one before it, of the other type, sent in the same pass
    # (within 1 ms: RAW_IMU's time is in us, SCALED_IMU's in whole ms).
    second_of_pair = [False] + [
        after[2] == before[2] and after[0] != before[0] and abs(after[1] - before[1]) <= 0.0015
        for before, after in itertools.pairwise(messages)
    ]
    raw = sum(1 for kind, _, _ in messages if kind == "RAW_IMU")
    scaled, pairs = len(messages) - raw, sum(second_of_pair)
    again = sum(  # the same values again in the next message, sent in a later pass: new samples
        1
        for before, after in itertools.pairwise(messages)
        if after[2] == before[2] and abs(after[1] - before[1]) > 0.0015
    )
    print(f"{scaled} SCALED_IMU, {raw} RAW_IMU, {pairs} pairs, {sum(dropped)} dropped, {again} equal samples later")
    assert scaled >= 0.6 * 25 * LISTEN_S and raw >= 0.6 * 25 * LISTEN_S  # both streams ran near 25 Hz
    assert pairs >= 0.8 * min(raw, scaled)  # one interval, one bucket: nearly every sample went out twice
    assert len(dropped) == len(messages)
    lost = [i for i, (drop, paired) in enumerate(zip(dropped, second_of_pair, strict=True)) if drop and not paired]
    assert not lost, [messages[i - 1 : i + 1] for i in lost]  # no sample of its own dropped
    # A pair split between two reads may be placed a few ms apart (the clock's offset moves) and kept: rare.
    assert sum(dropped) >= 0.95 * pairs
