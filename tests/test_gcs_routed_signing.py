"""The autopilot's frames that a keyed vessel routes to its ground station go out signed (MavlinkCodec.sign_routed),
checked with pymavlink's own signature check as the receiver, not only with ours."""

from __future__ import annotations

import hashlib
import itertools

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from bob_autonomy.ground.gcs_codec import MavlinkCodec, signing_timestamp

KEY = hashlib.sha256(b"fleet key").digest()
NOW_S = 1_790_000_000.0  # a wall-clock time (2026)


def _autopilot_frames(mav: mavlink.MAVLink) -> list[bytes]:
    """Frames as ArduPilot (system 1, component 1) sends them: some with a payload cut short of its zero tail."""
    messages = [
        mav.heartbeat_encode(mavlink.MAV_TYPE_SURFACE_BOAT, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, 129, 0, 4),
        mav.gps_raw_int_encode(123, 3, 473_977_000, 85_456_000, 0, 65535, 65535, 12, 0, 9),
        mav.param_value_encode(b"FRAME_CLASS", 2.0, mavlink.MAV_PARAM_TYPE_INT8, 111, 7),
        mav.rc_channels_encode(5, 18, *([1500] * 18), 0),
        mav.statustext_encode(mavlink.MAV_SEVERITY_INFO, b"ArduRover V4.7.0-dev", 0, 0),
    ]
    return [bytes(m.pack(mav)) for m in messages]


def _receiver(key: bytes) -> mavlink.MAVLink:
    """pymavlink taking signed frames only (no unsigned callback: an unsigned frame is refused)."""
    receiver = mavlink.MAVLink(None)
    receiver.signing.secret_key = key
    return receiver


def test_routed_frames_pass_pymavlinks_signature_check_with_the_key_and_fail_it_without() -> None:
    sender = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    frames = _autopilot_frames(sender)
    vessel = MavlinkCodec(1, 191, signing_key=KEY, link_id=3, wall_clock=lambda: NOW_S)
    signed = [vessel.sign_routed(frame) for frame in frames]

    receiver = _receiver(KEY)
    decoded = [receiver.decode(bytearray(frame)) for frame in signed]
    assert receiver.signing.goodsig_count == len(frames) and receiver.signing.badsig_count == 0
    originals = [mavlink.MAVLink(None).decode(bytearray(frame)) for frame in frames]
    for got, original in zip(decoded, originals, strict=True):
        assert (got.get_srcSystem(), got.get_srcComponent()) == (1, 1)
        assert got.to_dict() == original.to_dict()
    link_ids = {frame[-13] for frame in signed}
    timestamps = [int.from_bytes(frame[-12:-6], "little") for frame in signed]
    assert link_ids == {3} and timestamps[0] >= signing_timestamp(NOW_S)
    assert all(b > a for a, b in itertools.pairwise(timestamps))

    stranger = _receiver(hashlib.sha256(b"another key").digest())
    for frame in signed:
        with pytest.raises(mavlink.MAVError, match="signature"):
            stranger.decode(bytearray(frame))
    with pytest.raises(mavlink.MAVError, match="signature"):  # and the frame as the autopilot sent it
        _receiver(KEY).decode(bytearray(frames[0]))


def test_a_ground_codec_with_the_key_authenticates_the_routed_frames_and_the_vessels_own() -> None:
    sender = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    vessel = MavlinkCodec(1, 191, signing_key=KEY, wall_clock=lambda: NOW_S)
    data = b"".join(vessel.sign_routed(frame) for frame in _autopilot_frames(sender))
    data += vessel.pack(vessel.mav.heartbeat_encode(18, 8, 0, 0, 3))
    ground = MavlinkCodec(255, 190, signing_key=KEY, wall_clock=lambda: NOW_S)
    messages = ground.decode(data)
    assert len(messages) == 6 and ground.counters.authenticated == 6
    assert ground.counters.unsigned_rejected == ground.counters.bad_signature == ground.counters.replay_rejected == 0


def test_frames_that_cannot_or_need_not_be_signed_pass_unchanged() -> None:
    v2 = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    frame = _autopilot_frames(v2)[0]
    assert MavlinkCodec(1, 191).sign_routed(frame) == frame  # no key: nothing to sign with
    vessel = MavlinkCodec(1, 191, signing_key=KEY, wall_clock=lambda: NOW_S)
    v1 = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    v1.WIRE_PROTOCOL_VERSION = "1.0"  # MAVLink 1: no room for a signature
    v1_frame = bytes(v1.heartbeat_encode(10, 3, 0, 0, 4).pack(v1, force_mavlink1=True))
    assert v1_frame[0] == mavlink.PROTOCOL_MARKER_V1 and vessel.sign_routed(v1_frame) == v1_frame
    already = vessel.sign_routed(frame)
    assert vessel.sign_routed(already) == already
    unknown = bytearray(frame)
    unknown[7:10] = (60_000).to_bytes(3, "little")  # a message id the dialect does not know: no CRC_EXTRA
    assert vessel.sign_routed(bytes(unknown)) == bytes(unknown)
    assert vessel.sign_routed(frame[:5]) == frame[:5]  # a fragment
