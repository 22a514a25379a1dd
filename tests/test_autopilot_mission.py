"""The simulated autopilot's mission protocol (item 4; libraries/GCS_MAVLink/MissionItemProtocol.cpp,
MissionItemProtocol_Waypoints.cpp, GCS_Common.cpp, libraries/AP_Mission/AP_Mission.cpp) on real frames."""

from __future__ import annotations

import math

import pytest
from autopilot_helpers import Gcs, of_type, parse, run, texts
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sitl.vehicles.mavlink_vehicle import SimulatedVehicle

m = mavlink
HOME = (13405000, 1039560000)


def _vehicle() -> SimulatedVehicle:
    v = SimulatedVehicle(1, "buoy", 45.0)
    run(v, 0.0, 1.0)  # a fix: home set
    v.stream(1.0)
    return v


def _item(gcs: Gcs, seq: int, *, lat=13406000, lon=1039561000, z=0.0, command=m.MAV_CMD_NAV_WAYPOINT,
          frame=m.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, params=(0.0, 0.0, 0.0, 0.0), mission_type=0) -> bytes:  # fmt: skip
    return gcs.pack(
        gcs.mav.mission_item_int_encode(1, 1, seq, frame, command, 0, 1, *params, lat, lon, z, mission_type)
    )


def _one(data: bytes, name: str):
    (msg,) = parse(data)
    assert msg.get_type() == name, msg
    return msg


def _upload(v: SimulatedVehicle, gcs: Gcs, items: list[bytes], t: float = 1.0):
    request = _one(v.receive(gcs.pack(gcs.mav.mission_count_encode(1, 1, len(items), 0)), t), "MISSION_REQUEST")
    assert (request.seq, request.target_system, request.target_component) == (0, 255, 190)
    for k, item in enumerate(items[:-1]):
        assert _one(v.receive(item, t), "MISSION_REQUEST").seq == k + 1
    return _one(v.receive(items[-1], t), "MISSION_ACK")


def test_upload_then_download_item_zero_is_home() -> None:
    v, gcs = _vehicle(), Gcs()
    items = [_item(gcs, 0, lat=1, lon=2), _item(gcs, 1, params=(5.0, 7.0, 0.0, math.nan), z=2.5),
             _item(gcs, 2, command=m.MAV_CMD_DO_CHANGE_SPEED, params=(1.0, 0.8, -1.0, 0.0), lat=0, lon=0)]  # fmt: skip
    ack = _upload(v, gcs, items)
    assert (ack.type, ack.mission_type) == (m.MAV_MISSION_ACCEPTED, 0)
    assert "Flight plan received" in texts(parse(v.stream(1.0)))
    count = _one(v.receive(gcs.pack(gcs.mav.mission_request_list_encode(1, 1, 0)), 1.0), "MISSION_COUNT")
    assert count.count == 3
    got = [_one(v.receive(gcs.pack(gcs.mav.mission_request_int_encode(1, 1, s, 0)), 1.0), "MISSION_ITEM_INT")
           for s in range(3)]  # fmt: skip
    assert (got[0].x, got[0].y, got[0].frame) == (*HOME, m.MAV_FRAME_GLOBAL), "home, not the uploaded item 0"
    wp = got[1]
    assert (wp.command, wp.x, wp.y, wp.z, wp.frame) == (16, 13406000, 1039561000, 2.5, m.MAV_FRAME_GLOBAL_RELATIVE_ALT)
    assert (wp.param1, wp.param2, wp.param4) == (5.0, 0.0, 0.0), "Rover keeps only the delay of a waypoint"
    assert (got[2].command, got[2].param1, got[2].param2, got[2].param3) == (178, 1.0, pytest.approx(0.8), -1.0)


def test_legacy_request_and_float_items() -> None:
    v, gcs = _vehicle(), Gcs()
    _one(v.receive(gcs.pack(gcs.mav.mission_count_encode(1, 1, 2, 0)), 1.0), "MISSION_REQUEST")
    v.receive(gcs.pack(gcs.mav.mission_item_encode(1, 1, 0, 0, 16, 0, 1, 0, 0, 0, 0, 0.0, 0.0, 0.0)), 1.0)
    ack = _one(v.receive(gcs.pack(gcs.mav.mission_item_encode(1, 1, 1, 3, 16, 0, 1, 0, 0, 0, 0, 1.25, 103.5, 0.0)),
                         1.0), "MISSION_ACK")  # fmt: skip
    assert ack.type == m.MAV_MISSION_ACCEPTED
    item = _one(v.receive(gcs.pack(gcs.mav.mission_request_encode(1, 1, 1, 0)), 1.0), "MISSION_ITEM")
    assert item.x == pytest.approx(1.25) and item.y == pytest.approx(103.5)
    said = texts(parse(v.stream(1.0)))
    assert "got MISSION_ITEM; GCS should send MISSION_ITEM_INT" in said
    assert "got MISSION_REQUEST; use MISSION_REQUEST_INT!" in said


@pytest.mark.parametrize(
    ("kw", "error"),
    [
        ({"params": (math.nan, 0, 0, 0)}, m.MAV_MISSION_INVALID_PARAM1),
        ({"params": (0, math.inf, 0, 0)}, m.MAV_MISSION_INVALID_PARAM2),
        ({"params": (0, 0, -math.inf, 0)}, m.MAV_MISSION_INVALID_PARAM3),
        ({"params": (0, 0, 0, math.inf)}, m.MAV_MISSION_INVALID_PARAM4),
        ({"command": m.MAV_CMD_DO_JUMP, "params": (0, 0, 0, math.nan)}, m.MAV_MISSION_INVALID_PARAM4),
        ({"lat": 910_000_000}, m.MAV_MISSION_INVALID_PARAM5_X),
        ({"lon": -1_800_000_001}, m.MAV_MISSION_INVALID_PARAM6_Y),
        ({"z": math.nan}, m.MAV_MISSION_INVALID_PARAM7),
        ({"z": 1e9}, m.MAV_MISSION_INVALID_PARAM7),
        ({"frame": m.MAV_FRAME_LOCAL_NED}, m.MAV_MISSION_UNSUPPORTED_FRAME),
        ({"command": 31999}, m.MAV_MISSION_UNSUPPORTED),
        ({"command": 1}, m.MAV_MISSION_INVALID),
    ],
)
def test_a_bad_item_is_refused_and_ends_the_upload(kw, error) -> None:
    v, gcs = _vehicle(), Gcs()
    v.receive(gcs.pack(gcs.mav.mission_count_encode(1, 1, 3, 0)), 1.0)
    v.receive(_item(gcs, 0), 1.0)
    ack = _one(v.receive(_item(gcs, 1, **kw), 1.0), "MISSION_ACK")
    assert ack.type == error and v.counters.rejected == 1
    assert _one(v.receive(_item(gcs, 2), 1.0), "MISSION_ACK").type == m.MAV_MISSION_ERROR, "no upload any more"


def test_wrong_sequence_and_other_senders_are_refused_without_ending_the_upload() -> None:
    v, gcs, other = _vehicle(), Gcs(), Gcs(system=254)
    v.receive(gcs.pack(gcs.mav.mission_count_encode(1, 1, 2, 0)), 1.0)
    assert _one(v.receive(_item(gcs, 1), 1.0), "MISSION_ACK").type == m.MAV_MISSION_INVALID_SEQUENCE
    assert _one(v.receive(_item(other, 0), 1.0), "MISSION_ACK").type == m.MAV_MISSION_DENIED
    count = other.pack(other.mav.mission_count_encode(1, 1, 5, 0))
    assert _one(v.receive(count, 1.0), "MISSION_ACK").type == m.MAV_MISSION_DENIED
    listing = gcs.pack(gcs.mav.mission_request_list_encode(1, 1, 0))
    assert _one(v.receive(listing, 1.0), "MISSION_ACK").type == m.MAV_MISSION_DENIED, "no download during upload"
    assert _one(v.receive(_item(gcs, 0), 1.0), "MISSION_REQUEST").seq == 1
    assert _one(v.receive(_item(gcs, 1), 1.0), "MISSION_ACK").type == m.MAV_MISSION_ACCEPTED


def test_the_vehicle_asks_again_after_a_second_and_gives_up_after_eight() -> None:
    v, gcs = _vehicle(), Gcs()
    v.receive(gcs.pack(gcs.mav.mission_count_encode(1, 1, 2, 0)), 1.0)
    assert of_type(parse(v.stream(1.9)), "MISSION_REQUEST") == []
    (again,) = of_type(parse(v.stream(2.1)), "MISSION_REQUEST")
    assert again.seq == 0
    messages = parse(b"".join(v.stream(2.1 + 0.5 * k) for k in range(1, 16)))
    (ack,) = of_type(messages, "MISSION_ACK")
    assert ack.type == m.MAV_MISSION_OPERATION_CANCELLED and (ack.target_system, ack.target_component) == (255, 190)
    assert "Mission upload timeout" in texts(messages)


def test_clear_all_count_zero_and_too_many() -> None:
    v, gcs = _vehicle(), Gcs()
    _upload(v, gcs, [_item(gcs, 0), _item(gcs, 1), _item(gcs, 2)])
    assert _one(v.receive(gcs.pack(gcs.mav.mission_clear_all_encode(1, 1, 0)), 1.0), "MISSION_ACK").type == 0
    assert _one(v.receive(gcs.pack(gcs.mav.mission_request_list_encode(1, 1, 0)), 1.0), "MISSION_COUNT").count == 1
    ack = _one(v.receive(gcs.pack(gcs.mav.mission_count_encode(1, 1, 0, 0)), 1.0), "MISSION_ACK")
    assert ack.type == m.MAV_MISSION_ACCEPTED
    ack = _one(v.receive(gcs.pack(gcs.mav.mission_count_encode(1, 1, 5000, 0)), 1.0), "MISSION_ACK")
    assert ack.type == m.MAV_MISSION_NO_SPACE and "Only 700 items are supported" in texts(parse(v.stream(1.0)))


def test_reading_past_the_end() -> None:
    v, gcs = _vehicle(), Gcs()
    count, ack = parse(v.receive(gcs.pack(gcs.mav.mission_request_int_encode(1, 1, 4, 0)), 1.0))
    assert (count.get_type(), count.count, ack.type) == ("MISSION_COUNT", 1, m.MAV_MISSION_INVALID_SEQUENCE)


@pytest.mark.parametrize("mission_type", [m.MAV_MISSION_TYPE_FENCE, m.MAV_MISSION_TYPE_RALLY])
def test_fence_and_rally_are_unsupported_here(mission_type: int) -> None:
    v, gcs = _vehicle(), Gcs()
    for message in (gcs.mav.mission_count_encode(1, 1, 3, mission_type),
                    gcs.mav.mission_request_list_encode(1, 1, mission_type),
                    gcs.mav.mission_clear_all_encode(1, 1, mission_type)):  # fmt: skip
        ack = _one(v.receive(gcs.pack(message), 1.0), "MISSION_ACK")
        assert (ack.type, ack.mission_type) == (m.MAV_MISSION_UNSUPPORTED, mission_type)
    assert _one(v.receive(_item(gcs, 0, mission_type=mission_type), 1.0), "MISSION_ACK").type == 3
    assert v.receive(gcs.pack(gcs.mav.mission_request_int_encode(1, 1, 0, mission_type)), 1.0) == b""


def test_no_home_no_mission() -> None:
    v, gcs = SimulatedVehicle(1, "buoy", 45.0), Gcs()
    assert _one(v.receive(gcs.pack(gcs.mav.mission_request_list_encode(1, 1, 0)), 0.0), "MISSION_COUNT").count == 0


def test_messages_for_another_vehicle_are_left_alone() -> None:
    v, gcs = _vehicle(), Gcs()
    assert v.receive(gcs.pack(gcs.mav.mission_request_list_encode(9, 1, 0)), 1.0) == b""
    assert v.counters.other_target == 1
