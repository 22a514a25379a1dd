"""A GPS fix is fused when it was taken, not when its message arrived (firmware_bridge.autopilot_clock).

ArduPilot stamps GPS_RAW_INT with the time it read the fix and repeats it at the rate asked, so a fix arrives up to
one stream interval after it was read. The decoder places the stamp on its own clock through the autopilot's clock
since boot, learnt from the time_boot_ms of the messages it sends. The frames here are pymavlink's, built as
ArduPilot sends them: a 5 Hz GPS, GPS_RAW_INT and ATTITUDE at 10 Hz, over a link with random delays.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from bob_autonomy.estimation import BuoyEkf
from firmware_bridge.autopilot_clock import JUMP_S, WINDOW_S, AutopilotClock
from firmware_bridge.decoder import TelemetryDecoder
from firmware_bridge.readings import GpsFix

SEEDS = range(10)


def _delays(rng: np.random.Generator, n: int) -> np.ndarray:
    """Link delays, s: at least 2 ms, usually a few more, now and then 50 ms or more (a burst ahead)."""
    return 0.002 + rng.exponential(0.01, n) + np.where(rng.random(n) < 0.05, rng.uniform(0.05, 0.3, n), 0.0)


@pytest.mark.parametrize("seed", SEEDS)
def test_the_estimate_is_the_clock_offset_plus_the_smallest_recent_delay(seed: int) -> None:
    rng = np.random.default_rng(seed)
    offset = float(rng.uniform(-1e4, 1e4))  # local time minus autopilot time, s
    boot = np.arange(0.0, 120.0, 0.05) + float(rng.uniform(0, 1000))  # 20 Hz of messages
    arrival = boot + offset + _delays(rng, boot.size)
    clock = AutopilotClock()
    errors = []
    for b, a in zip(boot.tolist(), arrival.tolist(), strict=True):
        clock.observe(b, a)
        errors.append(clock.offset_s - offset)
    errors = np.array(errors[20:])  # after the first second
    assert errors.min() >= 0.0  # every sample is the offset plus a delay >= 0
    assert errors.max() < 0.015, errors.max()  # never worse than a delay the link gives often
    assert np.median(errors) < 0.006


@pytest.mark.parametrize("rate", [0.9, 0.995, 1.0001, 1.02])
def test_an_autopilot_clock_running_at_another_rate_is_followed(rate: float) -> None:
    """A simulated world that lags the wall clock (rate < 1), a quartz that drifts, one that runs fast: the
    estimate follows. Without the leak a slow clock is followed only by restarts, JUMP_S apart."""
    worst = {}
    for leak in (None, 0.0):
        rng = np.random.default_rng(11)
        local = np.arange(0.0, 300.0, 0.05)
        boot = rate * local  # the autopilot's clock, started with ours
        arrival = local + _delays(rng, local.size)
        clock = AutopilotClock() if leak is None else AutopilotClock(leak_per_s=leak)
        errors = []
        for b, a, t in zip(boot.tolist(), arrival.tolist(), local.tolist(), strict=True):
            clock.observe(b, a)
            errors.append(clock.offset_s - (t - b))  # against the true offset now
        worst[leak] = float(np.max(np.abs(errors[20:])))
    if rate < 0.99:  # more than the leak follows: restarts, a window apart
        assert worst[None] < JUMP_S + 2 * WINDOW_S * (1 - rate) + 0.02, worst
    else:
        assert worst[None] < 0.02, worst
    if 0.99 < rate < 1.0:
        assert worst[0.0] > 0.6 * JUMP_S, worst  # what the leak is for


def test_a_restarted_autopilot_restarts_the_estimate() -> None:
    clock = AutopilotClock()
    for k in range(100):
        clock.observe(500.0 + 0.1 * k, 1000.0 + 0.1 * k + 0.004)
    assert clock.offset_s == pytest.approx(500.004)
    clock.observe(0.0, 1010.503)  # rebooted at local time 1010.5: its clock starts again from 0
    assert clock.restarts == 1
    assert clock.offset_s == pytest.approx(1010.503)
    clock.observe(0.1, 1010.6 + 0.25)  # a late message changes nothing
    clock.observe(0.05, 1010.6 + 0.001)  # nor one slightly out of order
    assert clock.restarts == 1
    assert clock.offset_s == pytest.approx(1010.503 + 0.01 * 0.347)  # the leak over the 0.347 s between them


@pytest.mark.parametrize("wild_boot_s", [9_000.0, 1.5])
def test_one_message_with_a_wild_time_is_forgotten_at_once(wild_boot_s: float) -> None:
    """A message whose time_boot_ms is wrong (a glitch, a forged frame on an unsigned link) gives a sample far off.
    Far ahead (9000 s): it pulls the smallest sample far down, and fixes dated by it would be older than the
    estimator's replay window; the next true message goes back from it, which restarts the estimate. Behind
    (1.5 s, from an autopilot at 5 s): a sample above the estimate, which the min ignores."""
    clock = AutopilotClock()
    for k in range(50):
        clock.observe(0.1 * k, 100.0 + 0.1 * k + 0.003)
    clock.observe(wild_boot_s, 105.0)
    clock.observe(5.0, 105.003)
    assert clock.offset_s == pytest.approx(100.003, abs=0.002)
    assert clock.place(4_800_000, 105.05) == pytest.approx(104.803, abs=0.002)


def test_what_cannot_be_placed_is_stamped_at_its_arrival() -> None:
    clock = AutopilotClock()
    assert clock.place(5_000_000, 100.0) == 100.0  # no clock sample yet
    clock.observe(10.0, 100.0)  # offset 90 s
    assert clock.place(9_800_000, 100.0) == pytest.approx(99.8)  # read 0.2 s before its arrival
    assert clock.place(0, 100.0) == 100.0  # a GPS without time
    assert clock.place(1_700_000_000_000_000, 100.0) == 100.0  # UNIX time (another autopilot's habit)
    assert clock.place(9_999_000, 100.0) == 100.0  # 1 ms: within the clocks' resolution
    assert clock.place(10_500_000, 100.0) == 100.0  # "later than its arrival": never
    for bad in (math.nan, math.inf):
        clock.observe(bad, 101.0)
    clock.observe(2e9, 101.0)  # no time since boot
    assert clock.offset_s == 90.0


def _ardupilot_stream(rng: np.random.Generator, offset_s: float) -> list[tuple[float, bytes, float]]:
    """(arrival s, frames, fix read time on the local clock s) per 10 Hz slot: ATTITUDE and GPS_RAW_INT as
    ArduPilot sends them (the newest fix, stamped with the time it was read), pymavlink-encoded."""
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    mav.robust_parsing = True
    fix_reads = np.arange(rng.uniform(0, 0.2), 60.0, 0.2)  # a 5 Hz GPS, read at these times since boot
    slots = np.arange(0.05, 60.0, 0.1)
    delays = _delays(rng, slots.size)
    stream = []
    for slot, delay in zip(slots.tolist(), delays.tolist(), strict=True):
        frames = mav.attitude_encode(round(slot * 1000), 0.0, 0.0, 0.3, 0.0, 0.0, 0.0).pack(mav)
        fix_ms = round(float(fix_reads[fix_reads <= slot].max(initial=-1.0)) * 1000)
        if fix_ms >= 0:  # nothing before the first fix
            frames += mav.gps_raw_int_encode(fix_ms * 1000, 3, 473977000, 85455000, 0, 90, 65535, 120, 4500, 12).pack(
                mav
            )
        stream.append((slot + offset_s + delay, frames, fix_ms / 1000 + offset_s))
    return stream


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("lag_s", [0.0, 0.12])
def test_the_decoder_stamps_each_fix_when_the_autopilot_read_it_less_the_lag(seed: int, lag_s: float) -> None:
    rng = np.random.default_rng(seed)
    offset = float(rng.uniform(-100, 100))
    now = [0.0]
    decoder = TelemetryDecoder(lambda: now[0], source_system=1, source_component=1, fused_position=False,
                               gps_lag_s=lag_s)  # fmt: skip
    placed, read, arrived = [], [], []
    for arrival, frames, fix_read in _ardupilot_stream(rng, offset):
        now[0] = arrival
        for reading in decoder.feed(frames):
            if isinstance(reading, GpsFix):
                placed.append(float(reading.t_s[0]))
                read.append(fix_read)
                arrived.append(arrival)
    placed, read, arrived = np.array(placed), np.array(read), np.array(arrived)
    assert len(placed) == len(set(read.tolist())) >= 299  # each fix once
    assert decoder.counters.repeated_fix == decoder.counters.by_type["GPS_RAW_INT"] - len(placed)  # copies dropped
    error = placed[5:] - (read[5:] - lag_s)
    assert error.min() >= -0.001 and error.max() < 0.025 and np.median(error) < 0.008, (error.min(), error.max())
    # what the arrival stamps were off by: up to a stream interval, and every link delay
    assert np.max(arrived - read) > 0.1 > 0.05 > np.max(error)


def test_a_bad_gps_lag_is_refused() -> None:
    for bad in (-0.1, 1.5, math.nan):
        with pytest.raises(ValueError, match="gps_lag_s must be within"):
            TelemetryDecoder(gps_lag_s=bad)


@pytest.mark.parametrize("seed", range(5))
def test_a_boat_is_estimated_where_it_is_only_with_its_fixes_dated_when_they_were_read(seed: int) -> None:
    """A boat at 2 m/s east: its IMU is fused as it arrives (25 Hz), its fixes (5 Hz, 0.2 m noise) arrive 77-100
    ms after the autopilot read them, as on Rover SITL. Dated at their arrival, the estimate trails the boat by
    speed x age (about 0.18 m); dated by the autopilot's clock, it does not."""
    speed, heading = 2.0, 0.0  # m/s, rad from east
    ages = np.random.default_rng(seed).uniform(0.077, 0.1, 1000)
    bias = {}
    for dated in (False, True):
        noise = np.random.default_rng(seed + 100)  # the same readings both ways
        f = BuoyEkf(position_m=[0.0, 0.0], heading_rad=heading)
        behind = []
        for k in range(1000):  # 40 s of IMU rounds
            t = 0.04 * k
            f.predict(t, np.zeros(2))
            if k % 2 == 0:
                f.update_compass(t, heading + 0.01 * noise.standard_normal())
            if k % 5 == 0 and k > 0:
                read = t - ages[k]
                fix = np.array([speed * read, 0.0]) + 0.2 * noise.standard_normal(2)
                f.update_gps(read if dated else t, fix, np.array([speed, 0.0]) + 0.05 * noise.standard_normal(2))
            if k >= 250:  # after 10 s
                behind.append(speed * t - float(f.estimate(t)[0][0]))
        bias[dated] = float(np.mean(behind))
    assert 0.14 < bias[False] - bias[True] < 0.22, bias  # speed x mean age: 0.18 m
    assert abs(bias[True]) < 0.06, bias
