"""What the autonomy's MAVLink component does so that ground stations we did not write (MAVSDK, MAVProxy) see a
vessel right, checked on the bytes (no sockets): tests/test_interop_mavsdk.py and tests/test_interop_mavproxy.py
found both against a running fleet (issue #11 item 4)."""

from __future__ import annotations

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from bob_autonomy.ground.gcs import GcsComponent
from bob_autonomy.ground.params import ParameterStore

VESSEL, AUTOPILOT, AUTONOMY = 7, 1, 191


def _component() -> GcsComponent:
    return GcsComponent(VESSEL, ParameterStore(None), clock=lambda: 0.0)


def _from_ground_station(message) -> bytes:
    sender = mavlink.MAVLink(None, srcSystem=255, srcComponent=230)  # MAVProxy's address
    return bytes(message.pack(sender))


def test_component_191_heartbeat_carries_no_mode_flag() -> None:
    """MAVSDK 4.1 reads the flight mode from any HEARTBEAT with MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    (SystemImpl::process_heartbeat); with the flag, a vessel in MANUAL showed as ACRO (our custom_mode 1 = behaviour
    running) every other second."""
    gcs = _component()
    gcs.behavior_running = True
    gcs.tick()
    parser = mavlink.MAVLink(None)
    beats = [m for f in gcs.outgoing() for m in parser.parse_buffer(f) or [] if m.get_type() == "HEARTBEAT"]
    assert beats, "the component sends a HEARTBEAT on its first tick"
    beat = beats[0]
    assert (beat.get_srcSystem(), beat.get_srcComponent()) == (VESSEL, AUTONOMY)
    assert beat.autopilot == mavlink.MAV_AUTOPILOT_INVALID and beat.type == mavlink.MAV_TYPE_ONBOARD_CONTROLLER
    assert beat.base_mode == 0
    assert beat.custom_mode & 1 == 1  # our own readers (MissionClient) still find the behaviour bits


@pytest.mark.parametrize("target", [(VESSEL, AUTOPILOT), (VESSEL, 0), (0, 0)])
def test_a_ground_stations_stream_request_never_reaches_the_autopilot(target) -> None:
    """MAVProxy asks every stream at 4 Hz (REQUEST_DATA_STREAM, MAV_DATA_STREAM_ALL) on connecting; passed on, it
    would reset the autopilot's ATTITUDE from the 20 Hz the process asked to 4 Hz, under the estimator's 5 Hz."""
    gcs = _component()
    request = mavlink.MAVLink_request_data_stream_message(*target, mavlink.MAV_DATA_STREAM_ALL, 4, 1)
    read = mavlink.MAVLink_param_request_read_message(*target, b"FRAME_CLASS", -1)
    interval = mavlink.MAVLink_command_long_message(
        *target, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0, mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE, 1e6, 0, 0, 0, 0, 0
    )
    gcs.receive(_from_ground_station(request) + _from_ground_station(read) + _from_ground_station(interval))
    routed = [mavlink.MAVLink(None).parse_buffer(frame)[0] for frame in gcs.take_for_autopilot()]
    assert [m.get_type() for m in routed] == ["PARAM_REQUEST_READ", "COMMAND_LONG"]
