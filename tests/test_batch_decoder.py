"""Many vehicles' telemetry decoded at once (firmware_bridge.batch_decoder): the same counters and readings as each
decoder's own `feed`, on random telemetry of every kind the vehicles send; anything off the fast path falls back."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from bob_autonomy.onboard.vehicle_link import VehicleLink, receive_all
from firmware_bridge.batch_decoder import Row, decode_batch
from firmware_bridge.decoder import UINT16_MAX, TelemetryDecoder, heading_from_yaw
from firmware_bridge.readings import GpsFix
from firmware_bridge.telemetry import TelemetryEncoder
from sitl.vehicles.reading_batches import merge_by_round

SEEDS = range(20)


def _random_telemetry(rng: np.random.Generator, encoder: TelemetryEncoder, count: int) -> bytes:
    """`count` frames of the kinds a vehicle sends, with edge values: no fix, no velocity, NaN and extreme
    values, a zero position."""
    out = bytearray()
    fix_times = [0.0, float(rng.uniform(0, 100))]  # a GPS without time (0), and a fix repeated (as ArduPilot does)
    for _ in range(count):
        kind = rng.integers(12)
        t = float(rng.uniform(0, 100))
        special = rng.random() < 0.2
        if kind == 0:
            velocity = None if special else tuple(rng.normal(0, 2, 2))
            fix = int(rng.choice([0, 1, 3])) if rng.random() < 0.2 else 3
            lat, lon = rng.uniform(-89, 89), rng.uniform(-179, 179)
            t_fix = fix_times[int(rng.integers(2))] if rng.random() < 0.5 else t
            # unreported, 0 (unknown), reported, over the cap; picked by the latitude (no draw: the stream stays)
            h_acc = [None, 0.0, 0.4, 3.7, 250.0][int(abs(lat) * 1000) % 5]
            vel_acc = [None, 0.0, 0.05, 0.6, 80.0][int(abs(lon) * 1000) % 5]
            out += encoder.gps_raw_int(t_fix, lat, lon, velocity, fix_type=fix, h_acc_m=h_acc, vel_acc_mps=vel_acc)
        elif kind == 1:
            lat, lon = (0.0, 0.0) if special else (rng.uniform(-89, 89), rng.uniform(-179, 179))
            out += encoder.global_position_int(t, lat, lon, tuple(rng.normal(0, 200, 2)), rng.uniform(-4, 4))
        elif kind == 2:
            # roll, pitch and their rates from the time (no draw: the stream stays), NaN now and then
            tilt = {"roll_rad": math.nan if t % 7 < 0.5 else math.sin(t), "pitch_rad": math.cos(3 * t) / 2,
                    "roll_pitch_rates_radps": (t % 1.3 - 0.6, t % 0.7 - 0.3)}  # fmt: skip
            out += encoder.attitude(t, math.nan if special else float(rng.uniform(-10, 10)), **tilt)
        elif kind in (3, 4):
            accel = rng.normal(0, 400 if special else 2, 2)
            imu = encoder.scaled_imu if kind == 3 else encoder.raw_imu
            z, xy = 9.0 + (t % 2.0) if t % 5 > 1 else 600.0, (t % 1.1 - 0.5, t % 0.9 - 0.4)
            out += imu(t, accel, float(rng.normal(0, 40 if special else 1)), accel_z_mps2=z, gyro_xy_radps=xy)
        elif kind == 5:
            out += encoder.heartbeat(int(rng.integers(20)), bool(rng.integers(2)), int(rng.integers(16)))
        elif kind == 6:
            out += encoder.sys_status(float(rng.uniform(10, 13)), float(rng.uniform(0, 100)))
        elif kind == 7:
            out += encoder.battery_status(float(rng.uniform(10, 13)), float(rng.uniform(0, 100)))
        elif kind == 8:
            out += encoder.command_ack(int(rng.integers(500)), int(rng.integers(5)))
        elif kind == 9:
            out += encoder.wheel_distance(t, tuple(rng.normal(0, 10, 2)), int(rng.integers(1, 3)))
        elif kind == 10:
            out += encoder.system_time(t)
        else:
            out += encoder.rc_channels(t, [int(v) for v in rng.integers(1000, 2000, 16)], 16)
    return bytes(out)


def _fleet(rng: np.random.Generator, n: int) -> tuple[list[TelemetryDecoder], list[TelemetryDecoder], list[bytes]]:
    """Two identical sets of decoders (one per way of decoding) and a chunk for each, some from another system
    or component, some empty."""
    sets: tuple[list, list] = ([], [])
    chunks = []
    for k in range(n):
        fused = bool(rng.integers(2))
        lag = float(rng.choice([0.0, 0.12]))  # fixes placed by the autopilot's clock, less this lag
        for decoders in sets:
            decoders.append(TelemetryDecoder(lambda: 12.5, agent=3 * k, source_system=k + 1, source_component=1,
                                             fused_position=fused, gps_lag_s=lag))  # fmt: skip
        system = k + 1 if rng.random() < 0.8 else k + 2
        component = 1 if rng.random() < 0.9 else 191
        empty = rng.random() < 0.1
        chunks.append(b"" if empty else _random_telemetry(rng, TelemetryEncoder(system, component), 12))
    return sets[0], sets[1], chunks


def _fields(reading) -> dict:
    if not dataclasses.is_dataclass(reading):
        return {"value": reading}
    return {f.name: getattr(reading, f.name) for f in dataclasses.fields(reading)} | {"type": type(reading)}


def _same(a, b) -> bool:
    fa, fb = _fields(a), _fields(b)
    if fa.keys() != fb.keys():
        return False
    for name in fa:
        x, y = fa[name], fb[name]
        if isinstance(x, np.ndarray) or isinstance(y, np.ndarray):
            if y is None or x is None or x.dtype != y.dtype or not np.array_equal(x, y, equal_nan=True):
                return False
        elif x != y:
            return False
    return True


@pytest.mark.parametrize("seed", SEEDS)
def test_batch_decoding_gives_feeds_counters_and_readings_bit_for_bit(seed: int) -> None:
    rng = np.random.default_rng(seed)
    one_by_one, batched, chunks = _fleet(rng, 9)
    expected = [d.feed(chunk) if chunk else [] for d, chunk in zip(one_by_one, chunks, strict=True)]
    result = decode_batch(batched, chunks)
    assert result is not None
    got, columns = result
    for want, have in zip(expected, got, strict=True):
        have = [columns.take(r.key, [r.index]) if isinstance(r, Row) else r for r in have]
        assert len(want) == len(have)
        assert all(_same(a, b) for a, b in zip(want, have, strict=True))
    for a, b in zip(one_by_one, batched, strict=True):
        assert vars(a.counters) == vars(b.counters)
    # merged over vehicles round by round, as the lockstep transport hands them to the estimators
    merged_expected = merge_by_round(expected)
    merged = merge_by_round(got, columns)
    assert len(merged) == len(merged_expected)
    assert all(_same(a, b) for a, b in zip(merged_expected, merged, strict=True))


def _random_housekeeping(rng: np.random.Generator, encoder: TelemetryEncoder, count: int) -> bytes:
    """`count` HEARTBEAT, SYS_STATUS and BATTERY_STATUS frames with raw field values drawn over their whole ranges
    and their edges (unknown voltages and charge, no cells, extension cells), which the batch decoder reads from
    their payloads without a message object."""
    out = bytearray()

    def cell() -> int:
        return int(rng.choice([0, UINT16_MAX, int(rng.integers(UINT16_MAX))]))

    for _ in range(count):
        kind = rng.integers(3)
        remaining = int(rng.choice([-1, -128, 0, 100, int(rng.integers(-128, 128))]))
        if kind == 0:
            fields = [int(v) for v in rng.integers(0, 256, 5)]
            fields[3] = int(rng.integers(2**32))  # custom_mode
            out += encoder.encoder.frame(mavlink.MAVLink_heartbeat_message, *fields)
        elif kind == 1:
            out += encoder.encoder.frame(mavlink.MAVLink_sys_status_message, 1, 2, 3, 0, cell(), -1, remaining, 0, 0,
                                         0, 0, 0, 0)  # fmt: skip
        else:
            cells = [cell() for _ in range(10)] if rng.random() < 0.7 else [UINT16_MAX] * 10
            ext = [cell() for _ in range(4)] if rng.random() < 0.3 else [0] * 4
            out += encoder.encoder.frame(mavlink.MAVLink_battery_status_message, 0, 0, 0, 32767, cells, -1, -1, -1,
                                         remaining, 0, 0, ext, 0, 0)  # fmt: skip
    return bytes(out)


@pytest.mark.parametrize("seed", range(5))
def test_housekeeping_read_from_payloads_is_feeds_bit_for_bit(seed: int) -> None:
    rng = np.random.default_rng(100 + seed)
    one_by_one, batched, _ = _fleet(rng, 9)
    chunks = [_random_housekeeping(rng, TelemetryEncoder(k + 1 if rng.random() < 0.9 else 40), 30) for k in range(9)]
    expected = [d.feed(chunk) for d, chunk in zip(one_by_one, chunks, strict=True)]
    got, _ = decode_batch(batched, chunks)
    for want, have in zip(expected, got, strict=True):
        assert len(want) == len(have) and not any(isinstance(r, Row) for r in have)
        assert all(_same(a, b) for a, b in zip(want, have, strict=True))
    for a, b in zip(one_by_one, batched, strict=True):
        assert vars(a.counters) == vars(b.counters)


def test_every_column_wise_kind_is_exercised() -> None:
    """The random telemetry above reaches every column-wise path, and its special cases, at least once."""
    rng = np.random.default_rng(0)
    kinds, no_fix, repeated, placed, sent = set(), 0, 0, 0, 0
    for _ in SEEDS:
        _, batched, chunks = _fleet(rng, 9)
        got, columns = decode_batch(batched, chunks)
        kinds |= {r.key for rows in got for r in rows if isinstance(r, Row)}
        no_fix += sum(d.counters.no_fix for d in batched)
        repeated += sum(d.counters.repeated_fix for d in batched)
        fixes = [
            columns.take(r.key, [r.index]) for rows in got for r in rows if isinstance(r, Row) and r.key[0] is GpsFix
        ]
        placed += sum(float(f.t_s[0]) != 12.5 for f in fixes)  # a fix dated before its arrival
        others = [columns.take(r.key, [r.index]) for rows in got for r in rows if isinstance(r, Row)]
        sent += sum(float(r.t_s[0]) < 12.5 for r in others if r.__class__ is not GpsFix)  # dated when sent
    assert no_fix > 0 and repeated > 0 and placed > 0 and sent > 0
    names = {(kind.__name__, present[-1]) for kind, present in kinds}
    assert names == {("GpsFix", True), ("GpsFix", False), ("CompassReading", True), ("ImuReading", True)}


@pytest.mark.parametrize(
    "spoil",
    [
        lambda c: b"\x00" + c,  # noise before a frame
        lambda c: c[:-1],  # a partial frame
        lambda c: c[:-1] + bytes([c[-1] ^ 0xFF]),  # a bad checksum
        lambda c: bytes([0xFE]) + c[1:],  # a MAVLink 1 marker
        lambda c: c[:2] + b"\x01" + c[3:],  # signed
    ],
)
def test_anything_off_the_fast_path_is_left_to_feed_and_touches_nothing(spoil) -> None:
    rng = np.random.default_rng(7)
    _, batched, chunks = _fleet(rng, 4)
    chunks[2] = spoil(TelemetryEncoder(3).attitude(1.0, 0.3)) + chunks[2]
    before = [dict(vars(d.counters), by_type=dict(d.counters.by_type)) for d in batched]
    assert decode_batch(batched, chunks) is None
    assert [vars(d.counters) for d in batched] == before


def test_a_decoder_with_bytes_pending_or_a_hook_is_left_to_feed() -> None:
    rng = np.random.default_rng(8)
    _, batched, _ = _fleet(rng, 3)
    frame = TelemetryEncoder(1).attitude(1.0, 0.3)
    batched[0].feed(frame[:5])  # half a frame waiting for the rest
    assert decode_batch(batched, [frame[5:], b"", b""]) is None
    _, batched, _ = _fleet(rng, 3)
    batched[1].message_hook = lambda msg: None
    assert decode_batch(batched, [b"", TelemetryEncoder(2).attitude(1.0, 0.3), b""]) is None


def test_links_receive_all_at_once_as_each_alone() -> None:
    """VehicleLink's own news (heartbeat, battery, acknowledgements) is kept as `receive` keeps it, on the fast
    path and on the fall-back alike."""
    for spoil in (False, True):
        alone = [VehicleLink(k + 1, "buoy", 50.0, lambda: 3.0, agent=k) for k in range(3)]
        together = [VehicleLink(k + 1, "buoy", 50.0, lambda: 3.0, agent=k) for k in range(3)]
        chunks = []
        for k in range(3):
            enc = TelemetryEncoder(k + 1)
            chunks.append(
                enc.heartbeat(mavlink.MAV_TYPE_SURFACE_BOAT, True, 0)
                + enc.sys_status(12.1, 80.0)
                + enc.command_ack(400, 0)
                + enc.attitude(1.0, 0.2 * k)
                + (b"\x55" if spoil and k == 1 else b"")
            )
        want = [link.receive(chunk) for link, chunk in zip(alone, chunks, strict=True)]
        got, columns = receive_all(together, chunks)
        assert (columns is None) == spoil
        for w, g, a, t in zip(want, got, alone, together, strict=True):
            g = [columns.take(r.key, [r.index]) if isinstance(r, Row) else r for r in g]
            assert all(_same(x, y) for x, y in zip(w, g, strict=True)) and len(w) == len(g)
            assert a.last_heartbeat == t.last_heartbeat and a.watch.last_beat_s == t.watch.last_beat_s
            assert _same(a.battery, t.battery) and a.acks == t.acks


def test_column_wise_heading_is_the_decoders_heading_to_the_last_bit() -> None:
    """The ATTITUDE column's heading (numpy remainder) against `heading_from_yaw` (Python's float modulo) on
    float32 yaws as they come off the wire, the edges included."""
    rng = np.random.default_rng(3)
    edges = [0.0, -0.0, math.pi, -math.pi, math.pi / 2, -math.pi / 2, 1e-45, -1e-45, 3.4e38, -3.4e38]
    yaws = np.concatenate((rng.uniform(-4, 4, 100_000), rng.normal(0, 1e3, 1000), edges)).astype(np.float32)
    enc = TelemetryEncoder(1)
    decoders = [TelemetryDecoder(lambda: 0.0, agent=0, source_system=1, source_component=1)]
    for start in range(0, len(yaws), 5000):
        frames = [
            enc.encoder.frame(mavlink.MAVLink_attitude_message, 0, 0.0, 0.0, float(y), 0.0, 0.0, 0.0)
            for y in yaws[start : start + 5000]
        ]
        chunk = b"".join(frames)
        per_decoder, columns = decode_batch(decoders, [chunk])
        rows = per_decoder[0]
        got = columns.take(rows[0].key, [r.index for r in rows]).heading_rad
        want = [heading_from_yaw(float(y)) for y in yaws[start : start + 5000]]
        assert np.array_equal(got, np.array(want))
