"""Readings dated when the autopilot sent them, not when the vessel read them (firmware_bridge/autopilot_clock.py).

ArduPilot stamps ATTITUDE and SCALED_IMU with `AP_HAL::millis()`, RAW_IMU with `micros64()` and WHEEL_DISTANCE
with `1000 * millis()` when it sends them (libraries/GCS_MAVLink/GCS_Common.cpp send_raw_imu, send_attitude;
Rover/GCS_MAVLink_Rover.cpp send_wheel_encoder_distance). A vessel that reads its link in bursts (a serial port
read every loop, a loop held up by a solve) gets several of them in one chunk; stamped with the chunk's arrival
they would all fall at one instant, and the EKF would integrate the gyro and the accelerometer over the wrong
intervals. Placed through the autopilot's clock, they keep their own times.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from bob_autonomy.core.geodesy import LocalFrame
from bob_autonomy.onboard.pipeline import BuoyPipeline
from firmware_bridge.autopilot_clock import LEAK_PER_S
from firmware_bridge.batch_decoder import Row, decode_batch
from firmware_bridge.decoder import TelemetryDecoder
from firmware_bridge.readings import CompassReading, ImuReading
from firmware_bridge.telemetry import TelemetryEncoder

ORIGIN = LocalFrame(1.3405, 103.956)
BOOT_S = 100.0  # the autopilot booted at local time 100 s
DELAY_S = 0.01  # the link's delay


def _chunk(encoder: TelemetryEncoder) -> tuple[bytes, list[float]]:
    """Telemetry sent at local times 110.00, 110.04, ... 110.16 (one message each), and those times."""
    sent = [110.0, 110.04, 110.08, 110.12, 110.16]
    data = (
        encoder.scaled_imu(sent[0], (0.1, 0.2), 0.01)
        + encoder.attitude(sent[1], 0.5)
        + encoder.raw_imu(sent[2], (0.1, 0.2), 0.01)
        + encoder.wheel_distance(sent[3], (1.0, 2.0))
        + encoder.global_position_int(sent[4], 1.3405, 103.956, (0.5, 0.5), 0.5)
        + encoder.sys_status(12.6, 100.0)
    )
    return data, sent


def _decoders(now: list[float], n: int) -> list[TelemetryDecoder]:
    return [TelemetryDecoder(lambda: now[0], agent=0, source_system=1, source_component=1) for _ in range(n)]


def _times(readings: list[object]) -> list[float]:
    return [float(r.t_s[0]) for r in readings if hasattr(r, "agents")]


def test_messages_read_together_keep_the_times_they_were_sent_in_both_decoders() -> None:
    encoder = TelemetryEncoder(1, boot_s=BOOT_S)
    now = [0.0]
    per_message, batched = _decoders(now, 1)[0], _decoders(now, 1)[0]
    for k in range(10):  # a second of messages read on time teaches both where the autopilot's clock lies
        now[0] = 109.0 + 0.1 * k + DELAY_S
        on_time = encoder.attitude(109.0 + 0.1 * k, 0.5)
        per_message.feed(on_time)
        decode_batch([batched], [on_time])
    data, sent = _chunk(encoder)
    now[0] = 110.35  # read 0.19 s after the newest was sent
    got = per_message.feed(data)
    result = decode_batch([batched], [data])
    assert result is not None
    rows, columns = result
    got_batched = [columns.take(r.key, [r.index]) if isinstance(r, Row) else r for r in rows[0]]

    # The clock's offset: the smallest delay seen (DELAY_S), leaked since the last message read on time; SYS_STATUS
    # carries no time: its arrival.
    offset = DELAY_S + LEAK_PER_S * (110.35 - (109.9 + DELAY_S))
    want = [t + offset for t in sent] + [110.35]
    assert _times(got) == pytest.approx(want, abs=1.001e-3)  # the stamps are whole ms (us for RAW_IMU), truncated
    assert _times(got_batched) == _times(got)  # the same floats


def test_a_time_that_cannot_be_placed_is_the_arrival() -> None:
    encoder = TelemetryEncoder(1, boot_s=BOOT_S)
    now = [110.5]
    decoder = _decoders(now, 1)[0]
    # No clock sample yet (nothing before), then a message younger than the clocks' resolution, then one stamped
    # after its arrival (an autopilot clock running fast): never dated later than it arrived.
    assert _times(decoder.feed(encoder.scaled_imu(110.2, (0.0, 0.0), 0.0))) == [110.5]
    now[0] = 110.6
    assert _times(decoder.feed(encoder.scaled_imu(110.599, (0.0, 0.0), 0.0))) == [110.6]
    assert _times(decoder.feed(encoder.attitude(110.9, 0.1))) == [110.6]


R_M, SPEED_MPS = 8.0, 1.5  # a buoy going round a circle, its bow along its track
YAW_RATE = SPEED_MPS / R_M


def _truth(t: float) -> tuple[np.ndarray, float]:
    angle = YAW_RATE * t
    return np.array([R_M * math.cos(angle), R_M * math.sin(angle)]), angle + math.pi / 2


def _telemetry(seed: int, duration_s: float) -> list[tuple[float, bytes]]:
    """(time sent, frame): SCALED_IMU at 25 Hz, ATTITUDE at 12.5 Hz (1 deg noise), GPS_RAW_INT at 5 Hz."""
    rng = np.random.default_rng(seed)
    encoder = TelemetryEncoder(1)
    out = []
    for i in range(1, round(duration_s / 0.04) + 1):
        t = 0.04 * i
        position, heading = _truth(t)
        accel = np.array([0.0, YAW_RATE * SPEED_MPS]) + rng.normal(0.0, 0.03, 2)  # centripetal, to the left
        out.append((t, encoder.scaled_imu(t, accel, YAW_RATE + rng.normal(0.0, 0.002))))
        if i % 2 == 0:
            out.append((t, encoder.attitude(t, heading + rng.normal(0.0, math.radians(1.0)))))
        if i % 5 == 0:
            lat, lon = ORIGIN.to_geodetic(*(position + rng.normal(0.0, 0.5, 2)))
            velocity = SPEED_MPS * np.array([math.cos(heading), math.sin(heading)]) + rng.normal(0.0, 0.05, 2)
            out.append((t, encoder.gps_raw_int(t, lat, lon, tuple(velocity))))
    return out


def _heading_error_rms(seed: int, read_every_s: float | None, *, by_arrival: bool = False) -> float:
    """RMS heading error (rad) of the EKF after the first 10 s of 25, the link read every `read_every_s` (None:
    each message as it arrives); `by_arrival`: readings stamped with their chunk's arrival (before this change)."""
    now = [0.0]
    decoder = _decoders(now, 1)[0]
    if by_arrival:
        decoder.sent_time = lambda time_usec, t_s: t_s
    pipeline = BuoyPipeline(1, ORIGIN, np.array([45.0]), estimator="ekf", controller="simple")
    telemetry = _telemetry(seed, 25.0)
    arrivals = [t + DELAY_S for t, _ in telemetry]
    reads = arrivals if read_every_s is None else np.arange(read_every_s, 25.0 + 1e-9, read_every_s).tolist()
    errors, i = [], 0
    for read_s in reads:
        chunk = bytearray()
        while i < len(telemetry) and arrivals[i] <= read_s + 1e-12:
            chunk += telemetry[i][1]
            i += 1
        if not chunk:
            continue
        now[0] = read_s
        readings = decoder.feed(bytes(chunk))
        assert all(r.t_s[0] <= read_s for r in readings if isinstance(r, CompassReading | ImuReading))
        pipeline.feed(readings)
        if read_s > 10.0:
            _, heading = _truth(read_s)
            error = float(pipeline.estimate(read_s).heading[0]) - heading
            errors.append(math.remainder(error, 2 * math.pi))
    return float(np.sqrt(np.mean(np.square(errors))))


@pytest.mark.parametrize("seed", range(5))
def test_a_turning_buoy_whose_link_is_read_in_bursts_keeps_its_heading(seed: int) -> None:
    """Read every 0.3 s (7-8 IMU readings a chunk), the EKF's heading stays within a few mrad of the one read
    message by message (seeds 0-4: 0.7-4.2 mrad read on time, 2.4-6.3 placed); dated by the chunks' arrival, a
    chunk's IMU readings fall at one instant and the error is several times that (28-31 mrad: 1.7 deg while
    turning at 0.19 rad/s). What is left is the clock's: its offset is the smallest delay it
    has seen, here the freshest message of a chunk's."""
    on_time = _heading_error_rms(seed, None)
    placed = _heading_error_rms(seed, 0.3)
    by_arrival = _heading_error_rms(seed, 0.3, by_arrival=True)
    print(f"seed {seed}: heading RMS {on_time * 1e3:.1f} mrad read on time, {placed * 1e3:.1f} placed, "
          f"{by_arrival * 1e3:.1f} by arrival")  # fmt: skip
    assert placed < on_time + 0.003
    assert by_arrival > 4 * placed
