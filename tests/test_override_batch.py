"""The lockstep fleet's batched RC overrides (firmware_bridge.override_batch, vehicle_link.command_frames,
SimulatedVehicle.receive_override) against the one-at-a-time path: the same units, bytes, counters and motors."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from bob_autonomy.onboard.vehicle_link import VehicleLink, command_frames
from firmware_bridge.commands import Encoder, rc_override
from firmware_bridge.decoder import TelemetryDecoder
from firmware_bridge.override_batch import carried_units, pwm_table, read_overrides
from firmware_bridge.rc_channels import STEERING_FULL_SCALE, THROTTLE_FULL_SCALE, RcChannelRange, ResolutionCarry
from sitl.vehicles.mavlink_vehicle import SimulatedVehicle

SPECIAL = [0.0, -0.0, math.nan, math.inf, -math.inf, 1.7, -3.0, 1e-4, 0.005, -0.005, 0.0049999, 1.0, -1.0, 1e300]


def _values(rng: np.random.Generator, n: int, scale: float = 0.5) -> np.ndarray:
    """n command values: mostly normal draws, one in four a special (zero, signed zero, NaN, inf, past full
    scale, under half a unit)."""
    values = rng.normal(0.0, scale, n)
    special = rng.random(n) < 0.25
    values[special] = rng.choice(SPECIAL, int(special.sum()))
    return values


@pytest.mark.parametrize("seed", range(4))
def test_carried_units_are_each_carrys_call(seed: int) -> None:
    rng = np.random.default_rng(seed)
    one, many = [ResolutionCarry() for _ in range(12)], [ResolutionCarry() for _ in range(12)]
    for _ in range(80):
        for channel in (3, 4):
            values = _values(rng, 12, scale=rng.choice([0.004, 0.3, 2.0]))
            expected = [carry(channel, v) for carry, v in zip(one, values, strict=True)]
            got = carried_units(many, channel, values) / THROTTLE_FULL_SCALE
            assert got.tolist() == expected
    assert [c._owed for c in many] == [c._owed for c in one]


def test_the_pwm_table_is_pwm_for_each_whole_unit() -> None:
    calibrations = (RcChannelRange(), RcChannelRange(1000, 1500, 2000, 30, True), RcChannelRange(982, 1491, 2006, 0))
    for calibration in calibrations:
        for full_scale in (THROTTLE_FULL_SCALE, STEERING_FULL_SCALE):
            table = pwm_table(calibration, full_scale)
            assert len(table) == 2 * full_scale + 1
            for k in (-full_scale, -full_scale + 1, -7, -1, 0, 1, 13, full_scale - 1, full_scale):
                assert table[k + full_scale] == calibration.pwm_for(k / full_scale, full_scale)


@pytest.mark.parametrize("kind", ["buoy", "ebot"])
@pytest.mark.parametrize("seed", range(3))
def test_command_frames_are_each_links_own_bytes(kind: str, seed: int) -> None:
    rng = np.random.default_rng(seed)
    scales = rng.uniform(0.2, 60.0, 9)

    def links() -> list[VehicleLink]:
        return [VehicleLink(k + 1, kind, s, clock=lambda: 0.0, agent=k) for k, s in enumerate(scales)]

    alone, together = links(), links()
    for _ in range(60):
        actuators = _values(rng, 18, scale=rng.choice([0.01, 0.5, 1.5])).reshape(9, 2) * scales[:, None]
        expected = [link.command(a) for link, a in zip(alone, actuators, strict=True)]
        assert command_frames(together, actuators) == expected
    assert [link.encoder.mav.seq for link in together] == [link.encoder.mav.seq for link in alone]
    assert [link.carry._owed for link in together] == [link.carry._owed for link in alone]


def test_command_frames_are_pymavlinks_own_bytes() -> None:
    """Each frame parsed by pymavlink and packed again by it (same sequence number and source) is the same
    bytes, and carries the PWMs the autopilot reads as the command (ArduPilot's default calibration)."""
    links = [VehicleLink(k + 1, "buoy", 40.0, clock=lambda: 0.0) for k in range(5)]
    actuators = np.array([[40.0, 0.0], [-20.0, 10.0], [0.0, 0.0], [4.0, -40.0], [math.nan, 100.0]])
    for frame, link in zip(command_frames(links, actuators), links, strict=True):
        parser = mavlink.MAVLink(None)
        (msg,) = parser.parse_buffer(frame)
        packer = mavlink.MAVLink(None, srcSystem=msg.get_srcSystem(), srcComponent=msg.get_srcComponent())
        packer.seq = msg.get_seq()
        assert bytes(msg.pack(packer)) == frame
        assert (msg.target_system, msg.target_component) == (link.target_system, 1)
    first = mavlink.MAVLink(None).parse_buffer(command_frames(links[:1], np.array([[40.0, -40.0]]))[0])[0]
    assert (first.chan3_raw, first.chan4_raw, first.chan1_raw, first.chan5_raw) == (1900, 1900, 1500, 65535)


def test_command_frames_of_mixed_kinds_take_each_links_own_path() -> None:
    links = [VehicleLink(1, "buoy", 40.0, clock=lambda: 0.0), VehicleLink(2, "ebot", 0.3, clock=lambda: 0.0)]
    twins = [VehicleLink(1, "buoy", 40.0, clock=lambda: 0.0), VehicleLink(2, "ebot", 0.3, clock=lambda: 0.0)]
    actuators = np.array([[10.0, -4.0], [0.1, 0.25]])
    assert command_frames(links, actuators) == [t.command(a) for t, a in zip(twins, actuators, strict=True)]
    assert command_frames([], np.zeros((0, 2))) == []


def _random_override(rng: np.random.Generator, encoder: Encoder) -> bytes:
    """An override from a random source to a random target: mostly PWMs, sometimes release, ignore or invalid."""
    channels = {}
    for channel in range(1, 19):
        if rng.random() < 0.5:
            channels[channel] = int(rng.choice([int(rng.integers(1000, 2001))] * 6 + [0, 65535, 65534]))
    if rng.random() < 0.05:
        channels[int(rng.integers(1, 19))] = int(rng.choice([700, 2300]))
    target = int(rng.choice([1, 1, 1, 0, 2]))
    component = int(rng.choice([1, 1, 0, 5]))
    return rc_override(channels, target, component, encoder=encoder)


def _decoder() -> TelemetryDecoder:
    return TelemetryDecoder(clock=lambda: 0.0, agent=0)


@pytest.mark.parametrize("seed", range(3))
def test_read_overrides_reads_and_counts_as_feed_messages(seed: int) -> None:
    rng = np.random.default_rng(seed)
    encoders = [Encoder(int(rng.choice([255, 255, 7])), int(rng.choice([190, 1]))) for _ in range(6)]
    fed, batched = [_decoder() for _ in encoders], [_decoder() for _ in encoders]
    for _ in range(40):
        chunks = [_random_override(rng, encoder) for encoder in encoders]
        found = read_overrides(batched, chunks)
        for decoder, chunk, read in zip(fed, chunks, found, strict=True):
            (msg,) = decoder.feed_messages(chunk)
            assert read == (msg.get_srcSystem(), msg.get_srcComponent(), [getattr(msg, f) for f in msg.fieldnames])
    assert [dataclasses.asdict(d.counters) for d in batched] == [dataclasses.asdict(d.counters) for d in fed]


def _spoiled(kind: str) -> bytes:
    good = rc_override({3: 1600}, 1, 1, encoder=Encoder())
    heartbeat = Encoder().pack(mavlink.MAVLink_heartbeat_message(6, 8, 0, 0, 4, 3))
    return {
        "two frames": good + good,
        "partial": good[:-3],
        "bad checksum": good[:-1] + bytes([good[-1] ^ 1]),
        "noise first": b"\x00" + good,
        "another message": heartbeat,
        "empty": b"",
        "mavlink 1": bytes([0xFE]) + good[1:],
        "signed flag": good[:2] + b"\x01" + good[3:],
    }[kind]


@pytest.mark.parametrize(
    "kind",
    ["two frames", "partial", "bad checksum", "noise first", "another message", "empty", "mavlink 1", "signed flag"],
)
def test_anything_but_one_good_override_is_left_to_feed_untouched(kind: str) -> None:
    decoder = _decoder()
    assert read_overrides([decoder], [_spoiled(kind)]) == [None]
    assert dataclasses.asdict(decoder.counters) == dataclasses.asdict(_decoder().counters)


def test_a_decoder_with_bytes_pending_or_a_hook_is_left_to_feed() -> None:
    good = rc_override({3: 1600}, 1, 1, encoder=Encoder())
    pending, hooked = _decoder(), _decoder()
    pending.feed_messages(good[:5])
    hooked.message_hook = lambda msg: None
    assert read_overrides([pending, hooked], [good, good]) == [None, None]
    assert hooked.counters.received == 0 and pending.counters.received == 0


def _state(vehicle: SimulatedVehicle) -> tuple:
    return (
        dataclasses.asdict(vehicle.counters),
        dataclasses.asdict(vehicle.reader.counters),
        list(vehicle.rc.override),
        list(vehicle.rc.radio_in),
        vehicle.failsafe.bits,
        vehicle.armed,
        vehicle.mode,
        vehicle._gcs_seen_s,
    )


@pytest.mark.parametrize("kind", ["buoy", "ebot", "motorboat"])
@pytest.mark.parametrize("seed", range(3))
def test_a_vehicle_takes_a_batch_read_override_as_its_bytes(kind: str, seed: int) -> None:
    """Random overrides (from the GCS and from others, to us and not, valid and not), at times with gaps past
    RC_OVERRIDE_TIME; one vehicle fed the bytes, its twin the batch reading: the same counters, RC state,
    failsafes and motors after every step, also with MAV_OPTIONS 1 (only the GCS heard)."""
    rng = np.random.default_rng(seed)
    params = {"MAV_OPTIONS": 1} if seed == 2 else {}
    fed, batched = (SimulatedVehicle(1, kind, 20.0, failsafe_s=1.0, armed=True, params=params) for _ in range(2))
    encoders = {255: Encoder(255, 190), 9: Encoder(9, 190)}
    t = 0.0
    for _ in range(150):
        t += float(rng.choice([0.1, 0.5, 1.5]))
        source = 255 if rng.random() < 0.85 else 9
        data = _random_override(rng, encoders[source])
        assert fed.receive(data, t) == b""
        (read,) = read_overrides([batched.reader], [data])
        batched.receive_override(read[0], read[2], t)
        assert fed.actuator(t).tolist() == batched.actuator(t).tolist()
        assert _state(fed) == _state(batched)
    assert fed.counters.commands > 20 and fed.counters.refused > 0 and fed.counters.other_target > 0
    assert fed.counters.rejected > 0 and fed.counters.failsafes > 0
