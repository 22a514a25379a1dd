"""Telemetry decoding speed: messages per second through `TelemetryDecoder.feed`, and a lockstep fleet's step
decoded vehicle by vehicle against all at once (`firmware_bridge.batch_decoder`).

A realistic mix for one vehicle (GPS_RAW_INT 5 Hz, ATTITUDE 10 Hz, SCALED_IMU 50 Hz, plus HEARTBEAT and
SYS_STATUS 1 Hz) is encoded once, then fed in 512-byte chunks, as a link would deliver it. The fleet figure:
45 vehicles, each with the frames a simulated buoy sends in one 0.5 s step, decoded by 45 decoders that keep
only their vehicle's telemetry (as `VehicleLink`), one `feed` each and then one `decode_batch`. Prints one
JSON line per figure.

    python benchmarks/mavlink_decode.py [--seconds 60] [--repeats 5]
"""

from __future__ import annotations

import argparse
import json
import math
import time

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_bridge.batch_decoder import decode_batch
from firmware_bridge.decoder import TelemetryDecoder
from firmware_bridge.telemetry import TelemetryEncoder


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


def fleet_step_chunks(vehicles: int) -> list[bytes]:
    """Each simulated buoy's frames of one 0.5 s step: GPS, both positions, attitude, IMUs, housekeeping."""
    chunks = []
    for k in range(vehicles):
        enc = TelemetryEncoder(k + 1)
        velocity, heading = (0.3 + 0.01 * k, -0.2), 0.1 * k
        chunks.append(
            enc.heartbeat(mavlink.MAV_TYPE_SURFACE_BOAT, True, 0)
            + enc.sys_status(12.6, 100.0)
            + enc.gps_raw_int(10.0, 47.39 + 1e-5 * k, 8.54, velocity)
            + enc.global_position_int(10.0, 47.39 + 1e-5 * k, 8.54, velocity, heading)
            + enc.attitude(10.0, heading)
            + enc.scaled_imu(10.0, (0.1, -0.05), 0.02)
            + enc.raw_imu(10.0, (0.1, -0.05), 0.02)
            + enc.rc_channels(10.0, [1500] * 16, 16)
            + enc.rc_channels(10.0, [1500] * 16, 16)
            + enc.system_time(10.0)
        )
    return chunks


def fleet_figures(vehicles: int, repeats: int) -> dict[str, object]:
    """Microseconds per message of one fleet step, feed per vehicle and decode_batch, best of `repeats`."""
    chunks = fleet_step_chunks(vehicles)
    frames = 0

    def decoders() -> list[TelemetryDecoder]:
        return [TelemetryDecoder(lambda: 10.0, agent=k, source_system=k + 1, source_component=1, fused_position=False)
                for k in range(vehicles)]  # fmt: skip

    one_by_one = batched = math.inf
    for _ in range(repeats * 20):
        alone = decoders()
        start = time.perf_counter()
        for decoder, chunk in zip(alone, chunks, strict=True):
            decoder.feed(chunk)
        one_by_one = min(one_by_one, time.perf_counter() - start)
        together = decoders()
        start = time.perf_counter()
        assert decode_batch(together, chunks) is not None
        batched = min(batched, time.perf_counter() - start)
        frames = sum(d.counters.decoded for d in together)
    return {
        "benchmark": "mavlink_decode_fleet_step",
        "vehicles": vehicles,
        "messages": frames,
        "feed_us_per_message": round(1e6 * one_by_one / frames, 2),
        "batch_us_per_message": round(1e6 * batched / frames, 2),
        "speedup": round(one_by_one / batched, 2),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=int, default=60, help="seconds of telemetry in the stream")
    parser.add_argument("--repeats", type=int, default=5, help="timed passes (best is reported)")
    parser.add_argument("--chunk", type=int, default=512, help="bytes per feed call")
    parser.add_argument("--vehicles", type=int, default=45, help="vehicles in the fleet-step figure")
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

    print(json.dumps(fleet_figures(args.vehicles, args.repeats)))


if __name__ == "__main__":
    main()
