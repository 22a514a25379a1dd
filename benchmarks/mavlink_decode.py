"""Telemetry decoding speed: messages per second through `TelemetryDecoder.feed`.

A realistic mix for one vehicle (GPS_RAW_INT 5 Hz, ATTITUDE 10 Hz, SCALED_IMU 50 Hz, plus HEARTBEAT and
SYS_STATUS 1 Hz) is encoded once, then fed in 512-byte chunks, as a link would deliver it. Prints one
JSON line.

    python benchmarks/mavlink_decode.py [--seconds 60] [--repeats 5]
"""

from __future__ import annotations

import argparse
import json
import math
import time

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_bridge.decoder import TelemetryDecoder


def telemetry(seconds: int) -> tuple[bytes, int]:
    """Encoded stream of `seconds` of telemetry, and its number of messages."""
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    frames: list[bytes] = []

    def add(message) -> None:
        frames.append(bytes(message.pack(mav)))
        mav.seq = (mav.seq + 1) % 256

    for tick in range(seconds * 50):  # 50 Hz base rate
        t_ms = tick * 20
        add(mav.scaled_imu_encode(t_ms, 12, -30, -1000, 4, -2, 150, 200, 10, -400))
        if tick % 5 == 0:
            add(mav.attitude_encode(t_ms, 0.01, -0.02, math.sin(tick / 100.0), 0.0, 0.0, 0.1))
        if tick % 10 == 0:
            add(mav.gps_raw_int_encode(t_ms * 1000, 3, 473977420 + tick, 85455940 - tick, 500, 90, 120, 150, 4500, 12))
        if tick % 50 == 0:
            add(mav.heartbeat_encode(10, 3, 0, 0, 4))
            add(mav.sys_status_encode(0, 0, 0, 0, 12600, 100, 80, 0, 0, 0, 0, 0, 0))
    return b"".join(frames), len(frames)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=int, default=60, help="seconds of telemetry in the stream")
    parser.add_argument("--repeats", type=int, default=5, help="timed passes (best is reported)")
    parser.add_argument("--chunk", type=int, default=512, help="bytes per feed call")
    args = parser.parse_args()
    stream, count = telemetry(args.seconds)
    best = math.inf
    readings = 0
    for _ in range(args.repeats):
        decoder = TelemetryDecoder()
        start = time.perf_counter()
        readings = sum(len(decoder.feed(stream[i : i + args.chunk])) for i in range(0, len(stream), args.chunk))
        best = min(best, time.perf_counter() - start)
        assert decoder.counters.decoded == count, decoder.counters
    print(
        json.dumps(
            {
                "benchmark": "mavlink_decode",
                "messages": count,
                "bytes": len(stream),
                "readings": readings,
                "chunk_bytes": args.chunk,
                "messages_per_s": round(count / best),
                "mbytes_per_s": round(len(stream) / best / 1e6, 3),
                "us_per_message": round(1e6 * best / count, 2),
                "realtime_factor": round(args.seconds / best),
            }
        )
    )


if __name__ == "__main__":
    main()
