"""The simulated autopilot over real UDP, with pymavlink's mavutil as the ground station: a VehicleServer with
ArduPilot streams answers parameters, missions, commands and stream requests as ArduPilot Rover does."""

from __future__ import annotations

import math
import threading
import time

import pytest
from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sitl.vehicles.vehicle_server import VehicleServer

m = mavlink


class _Served(threading.Thread):
    """A one-buoy VehicleServer in real time, its sensors at 5 Hz (GPS) and 10 Hz (compass, IMU)."""

    def __init__(self) -> None:
        super().__init__(daemon=True)
        self.server = VehicleServer(["buoy"], [45.0], base_port=0, streams="ardupilot")
        self.stop = threading.Event()

    def run(self) -> None:
        vehicle, endpoint = self.server.vehicles[0], self.server.endpoints[0]
        start, k = time.monotonic(), 0
        while not self.stop.is_set():
            self.server.serve(0.01, time.monotonic() - start)
            t = time.monotonic() - start
            if t >= k * 0.1:
                if k % 2 == 0:
                    vehicle.observe("gps", t, 1.3405, 103.956, (0.0, 0.0))
                vehicle.observe("compass", t, 0.2)
                vehicle.observe("imu", t, (0.0, 0.0), 0.0)
                vehicle.actuator(t)
                endpoint.send(vehicle.stream(t))
                k += 1


@pytest.fixture
def served():
    s = _Served()
    s.start()
    yield s
    s.stop.set()
    s.join(2.0)
    s.server.close()


def _wait(conn, kind, timeout: float = 3.0, **fields):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        msg = conn.recv_match(type=kind, blocking=True, timeout=0.2)
        if msg is not None and all(getattr(msg, k) == v for k, v in fields.items()):
            return msg
    raise AssertionError(f"no {kind} {fields} within {timeout} s")


@pytest.mark.xdist_group("realtime")
def test_a_ground_station_on_udp(served: _Served) -> None:
    conn = mavutil.mavlink_connection(f"udpout:127.0.0.1:{served.server.ports[0]}", source_system=255,
                                      source_component=190)  # fmt: skip
    try:
        conn.mav.heartbeat_send(m.MAV_TYPE_GCS, m.MAV_AUTOPILOT_INVALID, 0, 0, 0)
        hb = conn.wait_heartbeat(timeout=3)
        assert (hb.type, hb.autopilot, hb.custom_mode) == (m.MAV_TYPE_SURFACE_BOAT, m.MAV_AUTOPILOT_ARDUPILOTMEGA, 0)

        conn.mav.param_request_list_send(1, 1)
        first = _wait(conn, "PARAM_VALUE")
        names = {first.param_id}
        while len(names) < first.param_count:
            names.add(_wait(conn, "PARAM_VALUE").param_id)
        assert {"MAV_GCS_SYSID", "RC_OVERRIDE_TIME", "FS_ACTION", "MAV1_EXTRA1"} <= names
        conn.mav.param_set_send(1, 1, b"FS_TIMEOUT", 2.5, m.MAV_PARAM_TYPE_REAL32)
        assert _wait(conn, "PARAM_VALUE", param_id="FS_TIMEOUT").param_value == 2.5

        conn.mav.command_long_send(1, 1, m.MAV_CMD_REQUEST_MESSAGE, 0, m.MAVLINK_MSG_ID_AUTOPILOT_VERSION, 0, 0, 0,
                                   0, 0, 0)  # fmt: skip
        assert _wait(conn, "AUTOPILOT_VERSION").capabilities & m.MAV_PROTOCOL_CAPABILITY_MISSION_INT

        conn.mav.mission_count_send(1, 1, 2, 0)
        assert _wait(conn, "MISSION_REQUEST").seq == 0
        conn.mav.mission_item_int_send(1, 1, 0, 0, 16, 0, 1, 0, 0, 0, 0, 0, 0, 0, 0)
        assert _wait(conn, "MISSION_REQUEST").seq == 1
        conn.mav.mission_item_int_send(1, 1, 1, 6, 16, 0, 1, 0, 0, 0, math.nan, 13406000, 1039561000, 0.0, 0)
        assert _wait(conn, "MISSION_ACK").type == m.MAV_MISSION_ACCEPTED
        conn.mav.mission_request_list_send(1, 1, 0)
        assert _wait(conn, "MISSION_COUNT").count == 2
        conn.mav.mission_request_int_send(1, 1, 1, 0)
        assert _wait(conn, "MISSION_ITEM_INT").x == 13406000

        before = time.monotonic()
        _wait(conn, "GPS_RAW_INT")
        _wait(conn, "GPS_RAW_INT", timeout=2.0)
        assert time.monotonic() - before > 0.5, "1 Hz until asked"
        conn.mav.command_long_send(1, 1, m.MAV_CMD_SET_MESSAGE_INTERVAL, 0, m.MAVLINK_MSG_ID_GPS_RAW_INT, 200_000, 0,
                                   0, 0, 0, 0)  # fmt: skip
        assert _wait(conn, "COMMAND_ACK", command=m.MAV_CMD_SET_MESSAGE_INTERVAL).result == m.MAV_RESULT_ACCEPTED
        _wait(conn, "GPS_RAW_INT")
        start = time.monotonic()
        for _ in range(5):
            _wait(conn, "GPS_RAW_INT")
        assert time.monotonic() - start < 1.6, "5 Hz when asked"

        conn.mav.command_long_send(1, 1, m.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
        assert _wait(conn, "COMMAND_ACK", command=m.MAV_CMD_COMPONENT_ARM_DISARM).result == m.MAV_RESULT_ACCEPTED
        conn.mav.command_long_send(1, 1, m.MAV_CMD_DO_SET_MODE, 0, 1, math.nan, 0, 0, 0, 0, 0)
        assert _wait(conn, "COMMAND_ACK", command=m.MAV_CMD_DO_SET_MODE).result == m.MAV_RESULT_DENIED
        conn.mav.command_long_send(1, 1, m.MAV_CMD_DO_SET_MODE, 0, 1, 4, 0, 0, 0, 0, 0)
        assert _wait(conn, "COMMAND_ACK", command=m.MAV_CMD_DO_SET_MODE).result == m.MAV_RESULT_ACCEPTED
        hb = _wait(conn, "HEARTBEAT", custom_mode=4)
        assert hb.base_mode & m.MAV_MODE_FLAG_SAFETY_ARMED and hb.system_status == m.MAV_STATE_STANDBY
    finally:
        conn.close()


def _listen(conn, seconds: float) -> list:
    """Everything `conn` receives for `seconds`."""
    messages, end = [], time.monotonic() + seconds
    while time.monotonic() < end:
        if (msg := conn.recv_match(blocking=True, timeout=0.05)) is not None:
            messages.append(msg)
    return messages


@pytest.mark.xdist_group("realtime")
def test_each_ground_station_sees_an_unbroken_sequence_whatever_the_vehicle_answers_the_other(served: _Served) -> None:
    """Two ground stations on one vehicle's port: one fetches every parameter (all of them reach it, none the
    other) and sets streams, the other only listens. pymavlink counts a gap in a source's sequence numbers as
    lost frames (`mav_loss`, MAVProxy's link loss): each station's count stays 0, as with ArduPilot, whose every
    link numbers its own frames (before: 256 and 120)."""
    port = served.server.ports[0]
    asking = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=255, source_component=190)
    watching = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=254, source_component=190)
    try:
        for conn in (asking, watching):
            conn.mav.heartbeat_send(m.MAV_TYPE_GCS, m.MAV_AUTOPILOT_INVALID, 0, 0, 0)
            conn.wait_heartbeat(timeout=3)
        asking.mav.param_request_list_send(1, 1)
        for message_id in (m.MAVLINK_MSG_ID_ATTITUDE, m.MAVLINK_MSG_ID_SCALED_IMU):
            asking.mav.command_long_send(1, 1, m.MAV_CMD_SET_MESSAGE_INTERVAL, 0, message_id, 100_000, 0, 0, 0, 0, 0)
        heard: dict[str, list] = {"asking": [], "watching": []}
        for _ in range(4):  # both read in turn, 0.5 s each, so neither's socket buffer overflows
            heard["asking"] += _listen(asking, 0.5)
            heard["watching"] += _listen(watching, 0.5)
        params = [msg for msg in heard["asking"] if msg.get_type() == "PARAM_VALUE"]
        assert params and len({p.param_id for p in params}) == params[0].param_count
        assert not any(msg.get_type() == "PARAM_VALUE" for msg in heard["watching"])
        assert len(heard["watching"]) > 20
        assert (asking.mav_loss, watching.mav_loss) == (0, 0)
    finally:
        asking.close()
        watching.close()
