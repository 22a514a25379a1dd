"""TelemetryDecoder: real pymavlink-encoded frames in, typed readings out; bad bytes counted, never raised."""

from __future__ import annotations

import math
import random

import numpy as np
import pytest
from pymavlink.dialects.v10 import ardupilotmega as mavlink_v1
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_bridge.decoder import (
    Battery,
    CommandAck,
    Heartbeat,
    HeartbeatWatch,
    TelemetryDecoder,
    WheelDistance,
    heading_from_yaw,
)
from firmware_bridge.readings import CompassReading, GpsFix, ImuReading

G = 9.80665


@pytest.fixture
def mav():
    return mavlink.MAVLink(None, srcSystem=1, srcComponent=1)


def pack(mav, message) -> bytes:
    data = bytes(message.pack(mav))
    mav.seq = (mav.seq + 1) % 256
    return data


def decoder(t: float = 12.5) -> TelemetryDecoder:
    return TelemetryDecoder(clock=lambda: t)


def assert_consistent(d: TelemetryDecoder) -> None:
    c = d.counters
    assert c.received == c.decoded + c.bad_crc + c.unknown + c.malformed
    assert c.bytes_fed == c.frame_bytes + c.skipped_bytes + c.pending_bytes


def gps(mav, fix_type=3, lat=473977420, lon=85455940, vel=250, cog=9000, time_usec=0):
    """A GPS_RAW_INT; time_usec 0 (a GPS without time) is never taken for a repeat."""
    return pack(mav, mav.gps_raw_int_encode(time_usec, fix_type, lat, lon, 500, 100, 100, vel, cog, 9))


def attitude(mav, yaw):
    return pack(mav, mav.attitude_encode(1000, 0.0, 0.0, yaw, 0.0, 0.0, 0.0))


def test_gps_raw_int_lat_lon_exact_and_velocity_from_course():
    m = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    d = decoder(7.0)
    (fix,) = d.feed(gps(m, lat=-337654321, lon=1512345678, vel=250, cog=9000))
    assert isinstance(fix, GpsFix)
    assert fix.lat_deg[0] == -337654321 / 1e7
    assert fix.lon_deg[0] == 1512345678 / 1e7
    assert fix.agents.tolist() == [0] and fix.t_s.tolist() == [7.0]
    # course 90 deg (east) at 2.5 m/s -> east 2.5, north 0
    np.testing.assert_allclose(fix.velocity_mps, [[2.5, 0.0]], atol=1e-12)
    (fix,) = d.feed(gps(m, vel=100, cog=18000))  # south
    np.testing.assert_allclose(fix.velocity_mps, [[0.0, -1.0]], atol=1e-12)
    (fix,) = d.feed(gps(m, vel=65535, cog=65535))
    assert fix.velocity_mps is None


def test_a_fix_sent_again_with_its_own_time_is_read_once(mav):
    """ArduPilot sends GPS_RAW_INT at the rate asked, stamped with its fix's time: Rover SITL, asked 10 Hz of its
    5 Hz GPS, sent every fix twice (AP_GPS::send_mavlink_gps_raw), and repeats a silent GPS's last fix for 4 s.
    A copy read again would be fused as a newer measurement of an old position."""
    d = decoder()
    stream = [
        gps(mav, time_usec=1_000_000),
        gps(mav, time_usec=1_000_000),  # the same fix again
        gps(mav, fix_type=1, time_usec=1_000_000),  # no fix: not a reading, and not a repeat
        gps(mav, lat=473977500, time_usec=1_200_000),  # the next fix
        gps(mav, lat=473977500, time_usec=1_200_000),
        gps(mav, lat=473977500, time_usec=1_200_000),
        gps(mav, time_usec=0),  # a GPS without time: every copy is read
        gps(mav, time_usec=0),
        gps(mav, time_usec=1_000_000),  # an older time than the last, but not the last one: read
    ]
    fixes = [r for frame in stream for r in d.feed(frame)]
    assert [f.lat_deg[0] for f in fixes] == [47.397742, 47.39775, 47.397742, 47.397742, 47.397742]
    assert d.counters.repeated_fix == 3 and d.counters.no_fix == 1 and d.counters.decoded == 9
    assert_consistent(d)


def test_the_receivers_own_accuracies_are_read_from_h_acc_and_vel_acc(mav):
    """ArduPilot puts its GPS's one-sigma horizontal and speed accuracies in GPS_RAW_INT's extension fields h_acc
    (mm) and vel_acc (mm/s) (AP_GPS::send_mavlink_gps_raw); 0 means not reported, and a MAVLink 1 frame has no
    extensions at all. Its EKF3 caps them at 100 m and 50 m/s."""
    d = decoder()
    sent = [(2_500, 300, 2.5, 0.3), (0, 0, None, None), (250_000, 90_000, 100.0, 50.0), (1, 1, 0.001, 0.001)]
    for h_acc_mm, vel_acc_mmps, metres, mps in sent:
        message = mav.gps_raw_int_encode(
            0, 3, 473977420, 85455940, 500, 100, 100, 250, 9000, 9, 0, h_acc_mm, 0, vel_acc_mmps
        )
        (fix,) = d.feed(pack(mav, message))
        for got, want in ((fix.accuracy_m[0], metres), (fix.speed_accuracy_mps[0], mps)):
            assert math.isnan(got) if want is None else got == want
    v1 = mavlink_v1.MAVLink(None, srcSystem=1, srcComponent=1)  # MAVLink 1 as ArduPilot sends it: base fields
    (fix,) = d.feed(bytes(v1.gps_raw_int_encode(0, 3, 473977420, 85455940, 500, 100, 100, 250, 9000, 9).pack(v1)))
    assert math.isnan(fix.accuracy_m[0]) and math.isnan(fix.speed_accuracy_mps[0])


def test_gps_without_fix_gives_nothing(mav):
    d = decoder()
    assert d.feed(gps(mav, fix_type=1)) == []
    assert d.counters.no_fix == 1 and d.counters.decoded == 1


def test_global_position_int_velocity_ned_to_east_north(mav):
    d = decoder()
    (fix,) = d.feed(pack(mav, mav.global_position_int_encode(0, 100000000, -200000000, 0, 0, 120, -340, 0, 0)))
    assert fix.lat_deg[0] == 10.0 and fix.lon_deg[0] == -20.0
    np.testing.assert_allclose(fix.velocity_mps, [[-3.4, 1.2]])


@pytest.mark.parametrize(
    ("yaw", "heading"),
    [
        (0.0, math.pi / 2),
        (math.pi / 2, 0.0),
        (math.pi, -math.pi / 2),
        (-math.pi / 2, math.pi),
        (3 * math.pi / 4, -math.pi / 4),
    ],
)
def test_attitude_yaw_to_heading(mav, yaw, heading):
    (reading,) = decoder().feed(attitude(mav, yaw))
    assert isinstance(reading, CompassReading)
    # yaw travels as float32, so compare on the circle (west may land just either side of +-pi)
    difference = math.remainder(reading.heading_rad[0] - heading, 2 * math.pi)
    assert difference == pytest.approx(0.0, abs=1e-6)
    assert -math.pi < reading.heading_rad[0] <= math.pi


def test_heading_wraps_to_half_open_interval():
    assert heading_from_yaw(-math.pi / 2) == pytest.approx(math.pi)
    assert heading_from_yaw(-math.pi / 2) > 0
    assert heading_from_yaw(3 * math.pi / 2) == pytest.approx(math.pi)


@pytest.mark.parametrize("kind", ["scaled", "raw"])
def test_imu_signs_and_units(mav, kind):
    if kind == "scaled":
        message = mav.scaled_imu_encode(5, 1000, 500, -1000, 10, 20, 300, 0, 0, 0)
    else:
        message = mav.raw_imu_encode(5, 1000, 500, -1000, 10, 20, 300, 0, 0, 0)
    (imu,) = decoder().feed(pack(mav, message))
    assert isinstance(imu, ImuReading)
    # 1000 mG forward -> +9.80665 m/s^2; 500 mG to the RIGHT -> -4.903325 m/s^2 to the left
    np.testing.assert_allclose(imu.accel_body_mps2, [[G, -0.5 * G]])
    # 300 mrad/s about z-down (clockwise seen from above) -> -0.3 rad/s counter-clockwise
    np.testing.assert_allclose(imu.gyro_z_radps, [-0.3])


def test_wheel_distance_battery_heartbeat_ack(mav):
    d = decoder()
    data = pack(mav, mav.wheel_distance_encode(0, 2, [1.25, -0.5] + [0.0] * 14))
    data += pack(mav, mav.sys_status_encode(0, 0, 0, 0, 12600, -1, 76, 0, 0, 0, 0, 0, 0))
    data += pack(mav, mav.battery_status_encode(0, 0, 0, 0, [4000, 4100, 4200] + [65535] * 7, -1, -1, -1, -1))
    data += pack(mav, mav.heartbeat_encode(10, 3, mavlink.MAV_MODE_FLAG_SAFETY_ARMED, 4, 4))
    data += pack(mav, mav.command_ack_encode(400, 0))
    wheels, status, battery, beat, ack = d.feed(data)
    assert isinstance(wheels, WheelDistance)
    np.testing.assert_array_equal(wheels.distance_m, [[1.25, -0.5]])
    assert isinstance(status, Battery) and status.voltage_v[0] == pytest.approx(12.6)
    assert status.remaining_pct[0] == 76.0
    assert battery.voltage_v[0] == pytest.approx(12.3) and math.isnan(battery.remaining_pct[0])
    assert isinstance(beat, Heartbeat) and beat.armed and beat.mav_type == 10 and beat.custom_mode == 4
    assert isinstance(ack, CommandAck) and (ack.command, ack.result) == (400, 0)


def test_flipped_byte_counts_bad_crc_and_next_message_still_decodes(mav):
    bad = bytearray(attitude(mav, 0.3))
    bad[14] ^= 0x40  # inside the payload
    good = gps(mav)
    d = decoder()
    readings = d.feed(bytes(bad) + good)
    assert d.counters.bad_crc == 1
    assert [type(r) for r in readings] == [GpsFix]
    assert d.counters.decoded == 1
    assert_consistent(d)


def test_corrupted_length_byte_does_not_swallow_the_next_frame(mav):
    bad = bytearray(attitude(mav, 0.3))
    bad[1] = 200  # claims a long payload reaching over the next frames
    stream = bytes(bad) + b"".join(gps(mav) for _ in range(10))
    d = decoder()
    readings = d.feed(stream)
    assert len(readings) == 10
    assert d.counters.bad_crc >= 1
    assert_consistent(d)


def test_frames_split_across_feeds(mav):
    stream = b"".join(attitude(mav, 0.1 * i) for i in range(20))
    d = decoder()
    got = []
    for i in range(0, len(stream), 7):
        got += d.feed(stream[i : i + 7])
    assert len(got) == 20 and d.counters.pending_bytes == 0
    assert_consistent(d)


def test_truncated_frame_then_good_frame(mav):
    truncated = attitude(mav, 0.2)[:20]
    d = decoder()
    readings = d.feed(truncated + gps(mav))
    assert [type(r) for r in readings] == [GpsFix]
    assert d.counters.bad_crc + d.counters.malformed >= 1
    assert_consistent(d)
    # A truncated frame at the end waits for more bytes and is accounted as pending.
    d2 = decoder()
    assert d2.feed(truncated) == []
    assert d2.counters.pending_bytes == len(truncated)
    assert_consistent(d2)


def test_unknown_message_id_counted(mav):
    frame = bytearray(attitude(mav, 0.0))
    frame[7:10] = (0xEE, 0xEE, 0x0E)  # a message id no dialect defines
    d = decoder()
    readings = d.feed(bytes(frame) + gps(mav))
    assert d.counters.unknown == 1
    assert [type(r) for r in readings] == [GpsFix]
    assert_consistent(d)


def test_mavlink1_frames_decode(mav):
    data = bytes(mav.attitude_encode(0, 0.0, 0.0, math.pi / 2, 0.0, 0.0, 0.0).pack(mav, force_mavlink1=True))
    assert data[0] == 0xFE
    (reading,) = decoder().feed(data)
    assert reading.heading_rad[0] == pytest.approx(0.0, abs=1e-6)


def test_source_system_filter(mav):
    other = mavlink.MAVLink(None, srcSystem=7, srcComponent=1)
    d = TelemetryDecoder(clock=lambda: 0.0, source_system=1)
    readings = d.feed(attitude(other, 0.0) + attitude(mav, 0.0))
    assert len(readings) == 1 and d.counters.other_system == 1


def test_random_bytes_never_raise_and_counters_add_up():
    rng = random.Random(1234)
    noise = bytes(rng.getrandbits(8) for _ in range(100_000))
    d = decoder()
    for i in range(0, len(noise), 997):
        d.feed(noise[i : i + 997])
    assert d.counters.bytes_fed == len(noise)
    assert d.counters.decoded == 0
    assert d.counters.skipped_bytes > 0
    assert_consistent(d)


def test_fuzz_mutated_frames(mav):
    rng = random.Random(99)
    frames = [
        attitude(mav, 0.5),
        gps(mav),
        pack(mav, mav.scaled_imu_encode(5, 1000, 500, -1000, 10, 20, 300, 0, 0, 0)),
        pack(mav, mav.sys_status_encode(0, 0, 0, 0, 12600, -1, 76, 0, 0, 0, 0, 0, 0)),
        pack(mav, mav.heartbeat_encode(10, 3, 0, 0, 4)),
        pack(mav, mav.wheel_distance_encode(0, 2, [1.0] * 16)),
    ]
    d = decoder()
    good_after = 0
    for case in range(3000):
        frame = bytearray(rng.choice(frames))
        for _ in range(rng.randint(1, 4)):
            if rng.random() < 0.2 and len(frame) > 1:
                del frame[rng.randrange(1, len(frame)) :]  # truncate
            else:
                frame[rng.randrange(len(frame))] = rng.getrandbits(8)
        d.feed(bytes(frame))
        if case % 10 == 0:
            # A valid frame after garbage is decoded once any claimed length has been consumed.
            before = d.counters.decoded
            d.feed(b"\x00" * 300 + frames[0])
            good_after += d.counters.decoded - before
    c = d.counters
    assert c.received > 0 and c.bad_crc > 1000
    assert good_after >= 300
    assert_consistent(d)


def test_heartbeat_watch():
    now = [100.0]
    watch = HeartbeatWatch(2.0, clock=lambda: now[0])
    assert not watch.is_silent()
    now[0] = 102.5
    assert watch.is_silent()
    m = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    d = TelemetryDecoder(clock=lambda: now[0])
    watch.observe(d.feed(pack(m, m.heartbeat_encode(10, 3, 0, 0, 4))))
    assert not watch.is_silent() and watch.last_beat_s == 102.5
    now[0] = 104.0
    assert not watch.is_silent()
    now[0] = 104.6
    assert watch.is_silent() and watch.silent_for_s() == pytest.approx(2.1)
    with pytest.raises(ValueError):
        HeartbeatWatch(0.0)


def test_fused_position_can_be_ignored_so_raw_gps_is_not_fused_twice():
    from firmware_bridge.telemetry import TelemetryEncoder

    enc = TelemetryEncoder(1)
    fused = enc.encoder.pack(enc.mav.global_position_int_encode(0, 13405000, 1039560000, 0, 0, 10, 20, 0, 0))
    raw = enc.gps_raw_int(0.0, 1.3405, 103.956)
    assert len(TelemetryDecoder().feed(fused + raw)) == 2
    only_raw = TelemetryDecoder(fused_position=False)
    assert len(only_raw.feed(fused + raw)) == 1 and only_raw.counters.decoded == 2


def test_heartbeat_watch_restart_counts_silence_from_now():
    now = [0.0]
    watch = HeartbeatWatch(3.0, clock=lambda: now[0])
    now[0] = 5.0
    assert watch.is_silent()
    watch.restart()
    assert not watch.is_silent() and watch.silent_for_s() == 0.0
    now[0] = 8.5
    assert watch.is_silent()
