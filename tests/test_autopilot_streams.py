"""The simulated autopilot's telemetry streams against ArduPilot Rover's rules (sitl/vehicles/autopilot_streams.py),
read
back with pymavlink's own parser."""

from __future__ import annotations

import math

import pytest
from autopilot_helpers import Gcs, acks, count, of_type, parse, run
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sitl.vehicles.mavlink_vehicle import CAPABILITIES, FLIGHT_SW_VERSION, SimulatedVehicle

m = mavlink
GROUP_MESSAGES_AT_1HZ = ["HEARTBEAT", "SYS_STATUS", "GPS_RAW_INT", "GLOBAL_POSITION_INT", "ATTITUDE", "RAW_IMU",
                         "RC_CHANNELS", "SERVO_OUTPUT_RAW", "VFR_HUD", "BATTERY_STATUS", "SYSTEM_TIME"]  # fmt: skip


def _buoy(**kw) -> SimulatedVehicle:
    return SimulatedVehicle(1, "buoy", 45.0, **kw)


def test_until_asked_every_message_goes_at_rovers_1hz_default() -> None:
    messages = run(_buoy(), 0.0, 10.0)  # sensors at 5, 10, 20 Hz
    for name in GROUP_MESSAGES_AT_1HZ:
        assert count(messages, name) == 10, name
    # SCALED_IMU is in no stream group, WHEEL_DISTANCE needs WENC_TYPE, a buoy has no range finders.
    assert count(messages, "SCALED_IMU") == count(messages, "WHEEL_DISTANCE") == count(messages, "DISTANCE_SENSOR") == 0


def test_set_message_interval_speeds_a_message_up_but_never_past_its_sensor() -> None:
    v, gcs = _buoy(), Gcs()
    (ack,) = acks(v.receive(gcs.long(m.MAV_CMD_SET_MESSAGE_INTERVAL, m.MAVLINK_MSG_ID_ATTITUDE, 100_000), 0.0))
    assert (ack.command, ack.result) == (m.MAV_CMD_SET_MESSAGE_INTERVAL, m.MAV_RESULT_ACCEPTED)
    assert (ack.target_system, ack.target_component) == (255, 190)
    (ack,) = acks(v.receive(gcs.long(m.MAV_CMD_SET_MESSAGE_INTERVAL, m.MAVLINK_MSG_ID_GPS_RAW_INT, 50_000), 0.0))
    assert ack.result == m.MAV_RESULT_ACCEPTED
    messages = run(v, 0.0, 10.0)
    assert count(messages, "ATTITUDE") == 100  # 10 Hz from a 10 Hz compass
    # 20 Hz asked of a 5 Hz GPS: as ArduPilot, every fix four times, each copy stamped with the fix's time
    gps = of_type(messages, "GPS_RAW_INT")
    assert len(gps) == 200
    assert len({g.time_usec for g in gps}) == 50
    assert all(g.time_usec % 200_000 == 0 for g in gps)  # the GPS's times, 0.2 s apart
    assert count(messages, "RAW_IMU") == 10  # untouched


def test_gps_raw_int_after_the_gps_timeout_is_ardupilots_cleared_state() -> None:
    """AP_GPS::update_instance: no GPS message for GPS_TIMEOUT_MS (4 s) clears the state: NO_GPS, no position,
    HDOP unknown; send_mavlink_gps_raw still stamps it with the last fix's time."""
    v, gcs = _buoy(), Gcs()
    v.receive(gcs.long(m.MAV_CMD_SET_MESSAGE_INTERVAL, m.MAVLINK_MSG_ID_GPS_RAW_INT, 100_000), 0.0)
    run(v, 0.0, 2.0)
    last_fix_usec = round(1.8 * 1e6)
    quiet = of_type(run(v, 2.0, 8.0, gps=False), "GPS_RAW_INT")
    assert len(quiet) == 60  # still at 10 Hz
    held = [g for g in quiet if g.fix_type == m.GPS_FIX_TYPE_3D_FIX]
    cleared = [g for g in quiet if g.fix_type == m.GPS_FIX_TYPE_NO_GPS]
    assert len(held) + len(cleared) == 60 and 38 <= len(held) <= 42  # the fix of t = 1.8 s kept until 5.8 s
    assert {g.time_usec for g in quiet} == {last_fix_usec}
    assert all((g.lat, g.lon, g.eph, g.vel, g.satellites_visible) == (0, 0, 65535, 0, 0) for g in cleared)


@pytest.mark.parametrize(
    ("message_id", "interval_us", "result", "text"),
    [
        (m.MAVLINK_MSG_ID_ATTITUDE, -1, m.MAV_RESULT_ACCEPTED, None),
        (m.MAVLINK_MSG_ID_ATTITUDE, 0, m.MAV_RESULT_ACCEPTED, None),
        (m.MAVLINK_MSG_ID_ATTITUDE, -2, m.MAV_RESULT_DENIED, None),
        (
            m.MAVLINK_MSG_ID_ATTITUDE,
            10_000,
            m.MAV_RESULT_DENIED,
            "Requested rate for message ID 30 too fast. Increase SCHED_LOOP_RATE",
        ),
        (m.MAVLINK_MSG_ID_WHEEL_DISTANCE, 100_000, m.MAV_RESULT_DENIED, "No ap_message for mavlink id (9000)"),
        (m.MAVLINK_MSG_ID_NAMED_VALUE_FLOAT, 100_000, m.MAV_RESULT_DENIED, "No ap_message for mavlink id (251)"),
        (m.MAVLINK_MSG_ID_SCALED_IMU, 50_000, m.MAV_RESULT_ACCEPTED, None),
    ],
)
def test_set_message_interval_answers_as_ardupilot(message_id, interval_us, result, text) -> None:
    v, gcs = _buoy(), Gcs()
    data = v.receive(gcs.long(m.MAV_CMD_SET_MESSAGE_INTERVAL, message_id, interval_us), 0.0)
    (ack,) = acks(data)
    assert ack.result == result
    said = of_type(parse(v.stream(0.0)), "STATUSTEXT")
    if text is None:
        assert not said
        return
    if len(text) > 50:  # ArduPilot cuts a long text into chunks of 50 with one id
        assert [x.chunk_seq for x in said] == [0, 1] and said[0].id == said[1].id != 0
    assert "".join(x.text for x in said).startswith(text)


def test_minus_one_stops_and_zero_restores_the_default() -> None:
    v, gcs = _buoy(), Gcs()
    v.receive(gcs.long(m.MAV_CMD_SET_MESSAGE_INTERVAL, m.MAVLINK_MSG_ID_ATTITUDE, -1), 0.0)
    assert count(run(v, 0.0, 5.0), "ATTITUDE") == 0
    v.receive(gcs.long(m.MAV_CMD_SET_MESSAGE_INTERVAL, m.MAVLINK_MSG_ID_ATTITUDE, 0), 5.0)
    assert count(run(v, 5.0, 10.0), "ATTITUDE") == 5


def test_param3_must_be_zero() -> None:
    (ack,) = acks(_buoy().receive(Gcs().long(m.MAV_CMD_SET_MESSAGE_INTERVAL, 30, 100_000, 1), 0.0))
    assert ack.result == m.MAV_RESULT_DENIED


@pytest.mark.parametrize(
    ("message_id", "result", "interval_us"),
    [
        (m.MAVLINK_MSG_ID_ATTITUDE, m.MAV_RESULT_ACCEPTED, 1_000_000),
        (m.MAVLINK_MSG_ID_SCALED_IMU, m.MAV_RESULT_ACCEPTED, -1),
        (m.MAVLINK_MSG_ID_HEARTBEAT, m.MAV_RESULT_ACCEPTED, 1_000_000),
        (m.MAVLINK_MSG_ID_WHEEL_DISTANCE, m.MAV_RESULT_FAILED, 0),
    ],
)
def test_get_message_interval(message_id, result, interval_us) -> None:
    messages = parse(_buoy().receive(Gcs().long(m.MAV_CMD_GET_MESSAGE_INTERVAL, message_id), 0.0))
    reply, ack = messages  # ArduPilot answers before it acknowledges
    assert ack.result == result and (reply.message_id, reply.interval_us) == (message_id, interval_us)


def test_request_data_stream_sets_a_group_and_its_parameter() -> None:
    v, gcs = _buoy(), Gcs()
    assert v.receive(gcs.pack(gcs.mav.request_data_stream_encode(1, 1, m.MAV_DATA_STREAM_EXTRA1, 10, 1)), 0.0) == b""
    assert v.params["MAV1_EXTRA1"] == 10
    messages = run(v, 0.0, 5.0)
    assert count(messages, "ATTITUDE") == 50 and count(messages, "RAW_IMU") == 5
    v.receive(gcs.pack(gcs.mav.request_data_stream_encode(1, 1, m.MAV_DATA_STREAM_ALL, 4, 1)), 5.0)
    assert all(v.params[f"MAV1_{g}"] == 4 for g in ("RAW_SENS", "EXT_STAT", "POSITION", "EXTRA1", "EXTRA3"))
    assert v.params["MAV1_PARAMS"] == 10  # ArduPilot never touches the parameter stream here
    messages = run(v, 5.0, 10.0)
    assert count(messages, "RAW_IMU") == 20 and count(messages, "GPS_RAW_INT") == 20
    v.receive(gcs.pack(gcs.mav.request_data_stream_encode(1, 1, m.MAV_DATA_STREAM_EXTENDED_STATUS, 7, 0)), 10.0)
    messages = run(v, 10.0, 12.0)
    assert count(messages, "GPS_RAW_INT") == count(messages, "SYS_STATUS") == 0 and count(messages, "RAW_IMU") == 8


def test_request_message_sends_autopilot_version_and_home_once() -> None:
    v, gcs = _buoy(), Gcs()
    messages = parse(v.receive(gcs.long(m.MAV_CMD_REQUEST_MESSAGE, m.MAVLINK_MSG_ID_AUTOPILOT_VERSION), 0.0))
    assert [x.get_type() for x in messages] == ["COMMAND_ACK", "AUTOPILOT_VERSION"]
    version = messages[1]
    assert version.flight_sw_version == FLIGHT_SW_VERSION and version.flight_sw_version >> 24 == 4
    for bit in (m.MAV_PROTOCOL_CAPABILITY_MAVLINK2, m.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT,
                m.MAV_PROTOCOL_CAPABILITY_MISSION_INT, m.MAV_PROTOCOL_CAPABILITY_COMMAND_INT,
                m.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED):  # fmt: skip
        assert version.capabilities & bit
    assert version.capabilities == CAPABILITIES and not version.capabilities & m.MAV_PROTOCOL_CAPABILITY_MISSION_FENCE
    # No home before the first GPS fix: accepted, nothing sent (GCS_Common.cpp send_home_position).
    messages = parse(v.receive(gcs.long(m.MAV_CMD_REQUEST_MESSAGE, m.MAVLINK_MSG_ID_HOME_POSITION), 0.0))
    assert [x.get_type() for x in messages] == ["COMMAND_ACK"] and messages[0].result == m.MAV_RESULT_ACCEPTED
    first = run(v, 0.0, 1.0)
    (home,) = of_type(first, "HOME_POSITION")  # announced when set, on the first fix
    assert (home.latitude, home.longitude) == (13405000, 1039560000)
    messages = parse(v.receive(gcs.long(m.MAV_CMD_REQUEST_MESSAGE, m.MAVLINK_MSG_ID_HOME_POSITION), 1.0))
    assert [x.get_type() for x in messages] == ["COMMAND_ACK", "HOME_POSITION"]
    (ack,) = acks(v.receive(gcs.long(m.MAV_CMD_REQUEST_MESSAGE, 9000), 1.0))
    assert ack.result == m.MAV_RESULT_FAILED


def test_global_position_int_carries_the_compass_heading() -> None:
    (msg, *_) = of_type(run(_buoy(), 0.0, 2.0), "GLOBAL_POSITION_INT")
    assert msg.hdg != 65535
    # our heading 0.5 rad from east, counter-clockwise = 90 - 28.6479 deg from north
    assert msg.hdg == round((90.0 - math.degrees(0.5)) * 100)


def test_wheel_distance_only_with_wheel_encoders_configured() -> None:
    def feed(v):
        out = bytearray()
        for k in range(40):
            t = k * 0.05
            v.observe("wheels", t, (0.01 * k, 0.02 * k))
            out += v.stream(t)
        return of_type(parse(bytes(out)), "WHEEL_DISTANCE")

    ebot = feed(SimulatedVehicle(1, "ebot", 0.2))  # the eBot kind has WENC_TYPE = WENC2_TYPE = 10
    assert len(ebot) == 2 and ebot[0].count == 2
    assert feed(SimulatedVehicle(1, "ebot", 0.2, params={"WENC_TYPE": 0, "WENC2_TYPE": 0})) == []
    (one, _) = feed(SimulatedVehicle(1, "ebot", 0.2, params={"WENC2_TYPE": 0}))
    assert one.count == 1
    assert feed(_buoy()) == []


def test_sensor_rate_streams_keep_the_old_behaviour() -> None:
    v = _buoy(streams="sensor-rate")
    out = bytearray(v.housekeeping(0.0))
    for k in range(1, 20):
        out += v.housekeeping(k * 0.1)
    kinds = [x.get_type() for x in parse(bytes(out))]
    assert kinds == ["HEARTBEAT", "SYS_STATUS", "HEARTBEAT", "SYS_STATUS"]


def test_vfr_hud_reports_reverse_throttle_as_rover_does() -> None:
    v = _buoy(armed=True, params={"MOT_SLEWRATE": 0})
    v.receive(Gcs().override({3: 1100}), 0.0)  # full astern
    (hud,) = of_type(run(v, 0.0, 1.0, every_step=lambda t: Gcs().override({3: 1100})), "VFR_HUD")
    assert hud.throttle == (-100) & 0xFFFF and v.counters.errors == 0  # an int16 in the uint16 field
