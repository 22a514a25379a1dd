"""firmware_bridge.frames against pymavlink itself: every message of the dialect packed byte for byte as pymavlink
packs it, and decoded into the same message as pymavlink's decode gives, over seeded random field values."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_bridge.commands import Encoder
from firmware_bridge.decoder import TelemetryDecoder, classify_frame
from firmware_bridge.frames import decode_unsigned, layout, pack_frame, renumber
from firmware_bridge.telemetry import TelemetryEncoder

INTEGER_RANGES = {
    "uint8_t": (0, 2**8), "int8_t": (-(2**7), 2**7), "uint16_t": (0, 2**16), "int16_t": (-(2**15), 2**15),
    "uint32_t": (0, 2**32), "int32_t": (-(2**31), 2**31), "uint64_t": (0, 2**64), "int64_t": (-(2**63), 2**63),
    "uint8_t_mavlink_version": (0, 2**8),
}  # fmt: skip
MESSAGES = sorted(mavlink.mavlink_map.values(), key=lambda c: c.id)


def _value(rng: np.random.Generator, field_type: str, zero_bias: float):
    """One random value of a MAVLink field type; often 0 so that payloads get trimmed."""
    if rng.random() < zero_bias:
        return 0.0 if field_type in ("float", "double") else 0
    if field_type in ("float", "double"):
        special = rng.integers(0, 10)
        if special == 0:
            return math.nan
        if special == 1:
            return -math.inf
        value = float(rng.normal(0.0, 10.0 ** rng.integers(-3, 8)))
        return float(np.float32(value)) if field_type == "float" else value
    low, high = INTEGER_RANGES[field_type]
    return int(rng.integers(low, high, dtype=np.uint64 if low == 0 and high == 2**64 else np.int64))


def random_args(message_class: type, rng: np.random.Generator, zero_bias: float) -> list:
    """Arguments for `message_class(...)` (declaration order) with random values of each field's type."""
    args = []
    wire_lengths = dict(zip(message_class.ordered_fieldnames, message_class.array_lengths, strict=True))
    for name, field_type in zip(message_class.fieldnames, message_class.fieldtypes, strict=True):
        length = wire_lengths[name]
        if field_type == "char":
            n = int(rng.integers(0, length + 1)) if length else 1
            text = bytes(rng.integers(33, 127, size=n).astype(np.uint8))
            args.append(text if length else (text or b"a"))
        elif length:
            args.append([_value(rng, field_type, zero_bias) for _ in range(length)])
        else:
            args.append(_value(rng, field_type, zero_bias))
    return args


def _same(a, b) -> bool:
    if isinstance(a, float) and isinstance(b, float):
        return (math.isnan(a) and math.isnan(b)) or a == b
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b, strict=True))
    return type(a) is type(b) and a == b


@pytest.mark.parametrize("zero_bias", [0.0, 0.6, 1.0])
@pytest.mark.parametrize("message_class", MESSAGES, ids=lambda c: c.msgname)
def test_frame_is_pymavlinks_frame_and_decodes_as_pymavlink_decodes(message_class: type, zero_bias: float) -> None:
    rng = np.random.default_rng(message_class.id * 10 + round(zero_bias * 10))
    for trial in range(8):
        args = random_args(message_class, rng, zero_bias)
        mav = mavlink.MAVLink(None, srcSystem=1 + trial * 31, srcComponent=1 + trial * 7)
        mav.seq = (trial * 37) % 256
        expected = bytes(message_class(*args).pack(mav))
        frame = pack_frame(message_class, args, mav.seq, mav.srcSystem, mav.srcComponent)
        assert frame == expected, (message_class.msgname, args)

        reference = mavlink.MAVLink(None).decode(bytearray(expected))
        crc = expected[-2] | (expected[-1] << 8)
        decoded = decode_unsigned(bytearray(expected), layout(message_class.id), crc)
        assert type(decoded) is type(reference)
        for name in message_class.fieldnames:
            assert _same(getattr(decoded, name), getattr(reference, name)), (message_class.msgname, name)
        assert vars(decoded._header) == vars(reference._header)
        assert (decoded._payload, decoded._msgbuf, decoded._crc) == (
            reference._payload,
            reference._msgbuf,
            reference._crc,
        )
        assert decoded.get_srcSystem() == mav.srcSystem and decoded.get_seq() == mav.seq


def test_encoder_frame_advances_the_sequence_as_pack_does_and_signed_links_take_pymavlinks_path() -> None:
    fast, slow = Encoder(7, 1), Encoder(7, 1)
    for k in range(300):
        args = (mavlink.MAV_TYPE_SURFACE_BOAT, 3, k % 256, k, 4)
        assert fast.frame(mavlink.MAVLink_heartbeat_message, *args) == slow.pack(slow.mav.heartbeat_encode(*args))
    signed, reference = Encoder(7, 1), Encoder(7, 1)
    for encoder in (signed, reference):
        encoder.mav.signing.secret_key = bytes(range(32))
        encoder.mav.signing.sign_outgoing = True
        encoder.mav.signing.timestamp = 1000
    data = signed.frame(mavlink.MAVLink_system_time_message, 5, 6)
    assert data == reference.pack(reference.mav.system_time_encode(5, 6))
    assert data[2] & mavlink.MAVLINK_IFLAG_SIGNED


def test_telemetry_encoder_frames_are_the_frames_pymavlink_builds_from_the_same_fields() -> None:
    telemetry = TelemetryEncoder(3)
    parser = mavlink.MAVLink(None)
    data = b"".join(
        [
            telemetry.heartbeat(mavlink.MAV_TYPE_SURFACE_BOAT, True, 15),
            telemetry.gps_raw_int(12.5, 45.1234567, 7.7654321, (0.3, -1.2)),
            telemetry.global_position_int(12.5, 45.1, 7.7, (0.3, -1.2), 0.4),
            telemetry.attitude(12.5, 1.0, 0.1),
            telemetry.scaled_imu(12.5, (0.1, -0.2), 0.05),
            telemetry.raw_imu(12.5, (0.1, -0.2), 0.05),
            telemetry.wheel_distance(12.5, (1.5, 2.5)),
            telemetry.rc_channels(12.5, [1500] * 8, 16),
            telemetry.servo_output_raw(12.5, [1100, 1900]),
            telemetry.statustext(4, "x" * 120),
            telemetry.battery_status(12.6, 90.0),
            telemetry.vfr_hud(1.2, 0.3, -50.0),
            telemetry.light(12.5, 300.0, 250.0),
        ]
    )
    messages = parser.parse_buffer(data)
    assert parser.total_receive_errors == 0
    assert [msg.get_seq() for msg in messages] == list(range(len(messages)))
    repacker = mavlink.MAVLink(None, srcSystem=3, srcComponent=1)
    for msg in messages:  # each frame is exactly what pymavlink packs from the fields it decoded
        repacker.seq = msg.get_seq()
        assert bytes(msg.pack(repacker)) == bytes(msg.get_msgbuf())
    assert [m.get_type() for m in messages].count("STATUSTEXT") == 3


def test_classify_frame_still_refuses_a_bad_checksum_and_signed_frames_go_through_pymavlink() -> None:
    frame = bytearray(TelemetryEncoder(2).attitude(1.0, 0.5))
    verdict, msg = classify_frame(bytearray(frame), mavlink.MAVLink(None), followed=True)
    assert verdict == "ok" and msg.get_type() == "ATTITUDE"
    frame[12] ^= 0x01
    assert classify_frame(frame, mavlink.MAVLink(None), followed=True) == ("bad_crc", None)

    sender = Encoder(2, 1)
    sender.mav.signing.secret_key = bytes(32)
    sender.mav.signing.sign_outgoing = True
    data = sender.frame(mavlink.MAVLink_attitude_message, 1, 0.0, 0.0, 0.5, 0.0, 0.0, 0.0)
    receiver = mavlink.MAVLink(None)
    receiver.signing.secret_key = bytes(32)
    verdict, msg = classify_frame(bytearray(data), receiver, followed=True)
    assert verdict == "ok" and msg._signed
    decoder = TelemetryDecoder(source_system=2)
    assert [type(r).__name__ for r in decoder.feed(TelemetryEncoder(2).attitude(1.0, 0.5))] == ["CompassReading"]


def test_renumber_gives_the_frames_pymavlink_packs_at_the_new_numbers_and_passes_on_what_it_cannot_number() -> None:
    """renumber against pymavlink's own pack at the new sequence numbers (MAVLink 2 and 1, across the wrap at
    255); a signed frame (its signature covers the number) and an unknown message id are passed on untouched and
    take no number; stray bytes and a cut-off frame are dropped."""
    rng = np.random.default_rng(11)
    classes = [mavlink.MAVLink_heartbeat_message, mavlink.MAVLink_gps_raw_int_message,
               mavlink.MAVLink_param_value_message, mavlink.MAVLink_statustext_message]  # fmt: skip
    mav = mavlink.MAVLink(None, srcSystem=4, srcComponent=1)
    messages = [(classes[k % 4](*random_args(classes[k % 4], rng, 0.3)), k % 3 == 0) for k in range(40)]

    def packed(numbers: list[int]) -> bytes:
        frames = []
        for (msg, v1), seq in zip(messages, numbers, strict=True):
            mav.seq = seq  # pymavlink's pack numbers with mav.seq; only send advances it
            frames.append(bytes(msg.pack(mav, force_mavlink1=v1)))
        return b"".join(frames)

    sent = packed([int(x) for x in rng.integers(0, 256, 40)])  # numbered as another link's frames would be
    expected = packed([(250 + k) % 256 for k in range(40)])
    assert sent != expected and sent[0] == 0xFE and expected[0] == 0xFE
    assert renumber(sent, 250) == (expected, (250 + 40) % 256)

    signer = mavlink.MAVLink(None, srcSystem=4, srcComponent=1)
    signer.signing.secret_key, signer.signing.sign_outgoing, signer.signing.timestamp = bytes(range(32)), True, 9
    signed = bytes(signer.heartbeat_encode(1, 2, 3, 4, 5).pack(signer))
    unknown = bytearray(pack_frame(mavlink.MAVLink_heartbeat_message, (1, 2, 3, 4, 5, 3), 0, 4, 1))
    unknown[7] = 0xEE  # message id 238: not in the dialect
    head = pack_frame(mavlink.MAVLink_heartbeat_message, (1, 2, 3, 4, 5, 3), 9, 4, 1)
    data = b"\x00\x11" + signed + bytes(unknown) + head + head[:7]
    out, after = renumber(data, 17)
    assert after == 18 and out == signed + bytes(unknown) + pack_frame(
        mavlink.MAVLink_heartbeat_message, (1, 2, 3, 4, 5, 3), 17, 4, 1)  # fmt: skip
