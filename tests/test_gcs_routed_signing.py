"""The autopilot's frames that a keyed vessel routes to its ground station go out signed (MavlinkCodec.sign_routed),
checked with pymavlink's own signature check as the receiver, not only with ours."""

from __future__ import annotations

import hashlib
import itertools

import pytest
from pymavlink.dialects.v10 import ardupilotmega as mavlink_v1
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from bob_autonomy.ground.gcs_codec import MavlinkCodec, signing_timestamp

KEY = hashlib.sha256(b"fleet key").digest()
NOW_S = 1_790_000_000.0  # a wall-clock time (2026)


def _messages(mav: mavlink.MAVLink) -> list[mavlink.MAVLink_message]:
    """Messages as ArduPilot (system 1, component 1) sends them: some with a zero tail to cut in MAVLink 2."""
    return [
        mav.heartbeat_encode(mavlink.MAV_TYPE_SURFACE_BOAT, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, 129, 0, 4),
        mav.gps_raw_int_encode(123, 3, 473_977_000, 85_456_000, 0, 65535, 65535, 12, 0, 9),
        mav.param_value_encode(b"FRAME_CLASS", 2.0, mavlink.MAV_PARAM_TYPE_INT8, 111, 7),
        mav.rc_channels_encode(5, 18, *([1500] * 18), 0),
        mav.statustext_encode(mavlink.MAV_SEVERITY_INFO, b"ArduRover V4.7.0-dev", 0, 0),
    ]


def _autopilot_frames(mav: mavlink.MAVLink) -> list[bytes]:
    """The messages' MAVLink 2 frames."""
    return [bytes(m.pack(mav)) for m in _messages(mav)]


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
    already = vessel.sign_routed(frame)
    assert vessel.sign_routed(already) == already
    unknown = bytearray(frame)
    unknown[7:10] = (60_000).to_bytes(3, "little")  # a message id the dialect does not know: no CRC_EXTRA
    assert vessel.sign_routed(bytes(unknown)) == bytes(unknown)
    assert vessel.sign_routed(frame[:5]) == frame[:5]  # a fragment
    v1_fragment = _mavlink1_frames()[0][:-1]
    assert vessel.sign_routed(v1_fragment) == v1_fragment


def _mavlink1_frames() -> list[bytes]:
    """Frames as an autopilot port set to MAVLink 1 sends them (ArduPilot's SERIALn_PROTOCOL 1): the MAVLink 1
    dialect, base fields only, the whole payload (no zero tail cut)."""
    v1 = mavlink_v1.MAVLink(None, srcSystem=1, srcComponent=1)
    messages = [
        v1.heartbeat_encode(mavlink.MAV_TYPE_SURFACE_BOAT, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, 129, 0, 4),
        v1.gps_raw_int_encode(123, 3, 473_977_000, 85_456_000, 0, 65535, 65535, 12, 0, 0),
        v1.param_value_encode(b"FRAME_CLASS", 2.0, mavlink.MAV_PARAM_TYPE_INT8, 111, 7),
        v1.statustext_encode(mavlink.MAV_SEVERITY_INFO, b"ArduRover V4.7.0-dev"),
    ]
    frames = []
    for message in messages:
        frames.append(bytes(message.pack(v1)))
        v1.seq = (v1.seq + 1) % 256
    return frames


def test_mavlink1_frames_are_reframed_as_mavlink2_and_signed_so_a_strict_receiver_hears_them() -> None:
    """A MAVLink 1 frame has no room for a signature; routed unsigned, MAVProxy with allow_unsigned 0 drops it."""
    frames = _mavlink1_frames()
    assert all(frame[0] == mavlink.PROTOCOL_MARKER_V1 for frame in frames)
    vessel = MavlinkCodec(1, 191, signing_key=KEY, link_id=2, wall_clock=lambda: NOW_S)
    signed = [vessel.sign_routed(frame) for frame in frames]
    assert all(frame[0] == mavlink.PROTOCOL_MARKER_V2 and frame[2] & mavlink.MAVLINK_IFLAG_SIGNED for frame in signed)
    receiver = _receiver(KEY)
    originals = [mavlink.MAVLink(None).decode(bytearray(frame)) for frame in frames]
    for frame, original in zip(signed, originals, strict=True):
        got = receiver.decode(bytearray(frame))
        assert got.get_header().seq == original.get_header().seq
        assert (got.get_srcSystem(), got.get_srcComponent(), got.get_msgId()) == (1, 1, original.get_msgId())
        assert got.to_dict() == original.to_dict()
    assert receiver.signing.goodsig_count == len(frames) and receiver.signing.badsig_count == 0
    # the payload's zero tail is cut as MAVLink 2 does: the GPS frame's last field (satellites) is zero
    assert [len(frame) - 10 - 2 - 13 for frame in signed] == [9, 29, 25, 21]
    assert [frame[1] for frame in frames] == [9, 30, 25, 51]
    with pytest.raises(mavlink.MAVError, match="signature"):
        _receiver(hashlib.sha256(b"another key").digest()).decode(bytearray(signed[0]))
    assert MavlinkCodec(1, 191).sign_routed(frames[0]) == frames[0]  # no key: passed on as it came
