"""AUTOPILOT_VERSION and HOME_POSITION of the simulated autopilot (item 2): home set on the first fix and moved
with the vehicle while disarmed (Rover/commands.cpp update_home), MAV_CMD_DO_SET_HOME with the current or a given
position (GCS_Common.cpp handle_command_do_set_home), MAV_CMD_GET_HOME_POSITION."""

from __future__ import annotations

import math

import pytest
from autopilot_helpers import ORIGIN, Gcs, acks, of_type, parse, run, texts
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sitl.vehicles.mavlink_vehicle import SimulatedVehicle

m = mavlink


def _fixed() -> SimulatedVehicle:
    v = SimulatedVehicle(1, "buoy", 45.0)
    run(v, 0.0, 1.0)
    return v


def test_home_is_set_on_the_first_fix_and_follows_the_vehicle_while_disarmed() -> None:
    v = SimulatedVehicle(1, "buoy", 45.0)
    assert v.home is None
    run(v, 0.0, 1.0, gps=False)
    assert v.home is None, "no fix, no home"
    messages = run(v, 1.0, 2.0)
    (home,) = of_type(messages, "HOME_POSITION")
    assert (home.latitude, home.longitude) == (round(ORIGIN[0] * 1e7), round(ORIGIN[1] * 1e7))
    assert all(math.isnan(q) for q in home.q)
    moved = (ORIGIN[0] + 2e-5, ORIGIN[1])  # 2.2 m north
    messages = run(v, 2.0, 4.0, position=moved)
    assert of_type(messages, "HOME_POSITION")[-1].latitude == round(moved[0] * 1e7)
    small = (moved[0] + 2e-6, moved[1])  # 0.2 m: under DISTANCE_HOME_MINCHANGE
    assert of_type(run(v, 4.0, 6.0, position=small), "HOME_POSITION") == []
    v.receive(Gcs().long(m.MAV_CMD_COMPONENT_ARM_DISARM, 1), 6.0)
    assert v.armed
    assert of_type(run(v, 6.0, 9.0, position=ORIGIN), "HOME_POSITION") == [], "armed: home stays"


def test_do_set_home_to_the_current_position_locks_it() -> None:
    v, gcs = SimulatedVehicle(1, "buoy", 45.0), Gcs()
    (ack,) = acks(v.receive(gcs.long(m.MAV_CMD_DO_SET_HOME, 1), 0.0))
    assert ack.result == m.MAV_RESULT_FAILED, "no position yet"
    run(v, 0.0, 1.0)
    (ack,) = acks(v.receive(gcs.long(m.MAV_CMD_DO_SET_HOME, 1), 1.0))
    assert ack.result == m.MAV_RESULT_ACCEPTED
    said = parse(v.stream(1.0))
    assert "Set HOME to 1.340500 103.956000 at 0.00m" in texts(said) and of_type(said, "HOME_POSITION")
    assert of_type(run(v, 1.0, 4.0, position=(ORIGIN[0] + 1e-4, ORIGIN[1])), "HOME_POSITION") == [], "locked"


def test_do_set_home_to_a_given_position_long_and_int() -> None:
    v, gcs = _fixed(), Gcs()
    (ack,) = acks(v.receive(gcs.long(m.MAV_CMD_DO_SET_HOME, 0, 0, 0, 0, 1.25, 103.5, 3.0), 1.0))
    assert ack.result == m.MAV_RESULT_ACCEPTED
    lat, lon, alt = v.home
    assert abs(lat - 12_500_000) <= 1 and abs(lon - 1_035_000_000) <= 64 and alt == 3.0  # COMMAND_LONG is float32
    message = gcs.mav.command_int_encode(
        1, 1, m.MAV_FRAME_GLOBAL_INT, m.MAV_CMD_DO_SET_HOME, 0, 0, 0, 0, 0, 0, 13_400_001, 1_039_000_002, 0.0
    )
    (ack,) = acks(v.receive(gcs.pack(message), 1.0))
    assert ack.result == m.MAV_RESULT_ACCEPTED and v.home[:2] == (13_400_001, 1_039_000_002)
    messages = parse(v.receive(gcs.long(m.MAV_CMD_GET_HOME_POSITION), 1.0))
    assert [x.get_type() for x in messages] == ["COMMAND_ACK", "HOME_POSITION"]
    assert (messages[1].latitude, messages[1].longitude, messages[1].altitude) == (13_400_001, 1_039_000_002, 0)


@pytest.mark.parametrize(
    ("params", "result"),
    [
        ((2, 0, 0, 0, 1.25, 103.5, 0.0), m.MAV_RESULT_FAILED),  # param1 must be 0 or 1
        ((0, 0, 0, 0, 1.25, 103.5, math.nan), m.MAV_RESULT_DENIED),  # no altitude
        ((0, 0, 0, 0, 1.25, 103.5, 1e6), m.MAV_RESULT_DENIED),  # beyond LOCATION_ALT_MAX_M
        ((0, 0, 0, 0, 95.0, 103.5, 0.0), m.MAV_RESULT_FAILED),  # no such latitude
        ((math.inf, 0, 0, 0, 1.25, 103.5, 0.0), m.MAV_RESULT_FAILED),
    ],
)
def test_do_set_home_refusals(params, result) -> None:
    v = _fixed()
    before = v.home
    (ack,) = acks(v.receive(Gcs().long(m.MAV_CMD_DO_SET_HOME, *params), 1.0))
    assert ack.result == result and v.home == before


def test_get_home_position_before_home_fails() -> None:
    (ack,) = acks(SimulatedVehicle(1, "buoy", 45.0).receive(Gcs().long(m.MAV_CMD_GET_HOME_POSITION), 0.0))
    assert ack.result == m.MAV_RESULT_FAILED


def test_autopilot_version_by_the_old_command_too() -> None:
    v, gcs = SimulatedVehicle(3, "ebot", 0.2), Gcs()
    messages = parse(v.receive(gcs.long(m.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES, 1, target=3), 0.0))
    assert [x.get_type() for x in messages] == ["COMMAND_ACK", "AUTOPILOT_VERSION"]
    assert bytes(messages[1].flight_custom_version) == b"90700977" and messages[1].uid != 0
    (ack,) = acks(v.receive(gcs.long(m.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES, 0, target=3), 0.0))
    assert ack.result == m.MAV_RESULT_FAILED
