"""Hardening of the simulated autopilot (#17 item 1, vehicle side), written as an attacker would: every numeric field
of every message it accepts, set to NaN, infinities and out-of-range values, is refused (the protocol's failure
answer, or no effect), counted, and never raises; and the UDP vehicle server never dies on a datagram."""

from __future__ import annotations

import math
import socket
import time

import numpy as np
import pytest
from autopilot_helpers import Gcs, acks, of_type, parse, run
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sitl.vehicles.mavlink_vehicle import SimulatedVehicle
from sitl.vehicles.vehicle_server import VehicleServer

m = mavlink
BAD_FLOATS = [math.nan, math.inf, -math.inf, 3.0e38, -3.0e38]
REFUSALS = {m.MAV_RESULT_DENIED, m.MAV_RESULT_FAILED, m.MAV_RESULT_UNSUPPORTED}
HOLD = 4

# Commands the vehicle acts on: a valid request, and the params it reads (others are ignored, as ArduPilot does).
COMMANDS = {
    m.MAV_CMD_COMPONENT_ARM_DISARM: ((1, 0, 0, 0, 0, 0, 0), {1}),
    m.MAV_CMD_DO_SET_MODE: ((1, HOLD, 0, 0, 0, 0, 0), {1, 2}),
    m.MAV_CMD_SET_MESSAGE_INTERVAL: ((30, 100_000, 0, 0, 0, 0, 0), {1, 2, 3}),
    m.MAV_CMD_GET_MESSAGE_INTERVAL: ((30, 0, 0, 0, 0, 0, 0), {1}),
    m.MAV_CMD_REQUEST_MESSAGE: ((148, 0, 0, 0, 0, 0, 0), {1}),
    m.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES: ((1, 0, 0, 0, 0, 0, 0), {1}),
    m.MAV_CMD_DO_SET_HOME: ((0, 0, 0, 0, 1.25, 103.5, 2.0), {1, 5, 6, 7}),
}


def _state(v: SimulatedVehicle) -> tuple:
    return (v.armed, v.mode, v.home, dict(v.params.values), dict(v.schedule.interval_ms), len(v.mission.items))


def _fixed() -> SimulatedVehicle:
    v = SimulatedVehicle(1, "buoy", 45.0)
    run(v, 0.0, 1.0)
    v.stream(1.0)
    return v


@pytest.mark.parametrize("command", sorted(COMMANDS))
@pytest.mark.parametrize("index", range(1, 8))
@pytest.mark.parametrize("bad", BAD_FLOATS)
def test_every_command_param(command: int, index: int, bad: float) -> None:
    params, used = COMMANDS[command]
    baseline = _fixed()
    (good,) = acks(baseline.receive(Gcs().long(command, *params), 1.0))
    v = _fixed()
    before = _state(v)
    values = list(params)
    values[index - 1] = bad
    (ack,) = acks(v.receive(Gcs().long(command, *values), 1.0))
    assert v.counters.errors == 0
    if index in used and not (command == m.MAV_CMD_COMPONENT_ARM_DISARM and index == 2):
        assert ack.result in REFUSALS, (command, index, bad)
        assert _state(v) == before, "a refused command changed nothing"
    else:
        assert ack.result == good.result, "an unused param is ignored, as ArduPilot does"


@pytest.mark.parametrize("field", ["param1", "param2", "param3", "param4", "z"])
@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_command_int_float_fields(field: str, bad: float) -> None:
    v, gcs = _fixed(), Gcs()
    values = {"param1": 0.0, "param2": 0.0, "param3": 0.0, "param4": 0.0, "z": 2.0, field: bad}
    message = gcs.mav.command_int_encode(1, 1, m.MAV_FRAME_GLOBAL_INT, m.MAV_CMD_DO_SET_HOME, 0, 0, values["param1"],
                                         values["param2"], values["param3"], values["param4"], 12_500_000,
                                         1_035_000_000, values["z"])  # fmt: skip
    before = v.home
    (ack,) = acks(v.receive(gcs.pack(message), 1.0))
    if field in ("param2", "param3", "param4"):
        assert ack.result == m.MAV_RESULT_ACCEPTED  # unused by DO_SET_HOME
    else:
        assert ack.result in REFUSALS and v.home == before


@pytest.mark.parametrize(("x", "y"), [(2**31 - 1, 0), (-(2**31), 5), (5, 2**31 - 1), (910_000_000, 10)])
def test_command_int_locations_out_of_range(x: int, y: int) -> None:
    v, gcs = _fixed(), Gcs()
    message = gcs.mav.command_int_encode(1, 1, m.MAV_FRAME_GLOBAL_INT, m.MAV_CMD_DO_SET_HOME, 0, 0, 0, 0, 0, 0, x, y, 0)
    before = v.home
    (ack,) = acks(v.receive(gcs.pack(message), 1.0))
    assert ack.result in REFUSALS and v.home == before


def test_the_issue_17_datagram_nan_mode_is_denied_and_counted() -> None:
    v = SimulatedVehicle(1, "buoy", 45.0)
    for bad in (math.nan, math.inf, -1.0, 2.0**33):
        (ack,) = acks(v.receive(Gcs().long(m.MAV_CMD_DO_SET_MODE, 1, bad), 0.0))
        assert ack.result == m.MAV_RESULT_DENIED and v.mode == 0
    assert v.counters.rejected == 4 and v.counters.errors == 0


def test_every_parameter_refuses_every_bad_value() -> None:
    v, gcs = SimulatedVehicle(1, "buoy", 45.0), Gcs()
    before = dict(v.params.values)
    for name in v.params.index:
        for bad in BAD_FLOATS:
            v.receive(gcs.pack(gcs.mav.param_set_encode(1, 1, name.encode(), bad, m.MAV_PARAM_TYPE_REAL32)), 0.0)
        echoes = of_type(parse(v.stream(0.0)), "PARAM_VALUE")
        assert [e.param_value for e in echoes] == [pytest.approx(before[name])] * 2, name  # the two huge values
    assert v.params.values == before and v.counters.rejected == 5 * len(before) and v.counters.errors == 0


@pytest.mark.parametrize("field", ["param1", "param2", "param3", "param4", "x", "y", "z"])
@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf, 1e30])
def test_every_mission_item_field(field: str, bad: float) -> None:
    v, gcs = _fixed(), Gcs()
    v.receive(gcs.pack(gcs.mav.mission_count_encode(1, 1, 2, 0)), 1.0)
    v.receive(gcs.pack(gcs.mav.mission_item_encode(1, 1, 0, 0, 16, 0, 1, 0, 0, 0, 0, 0, 0, 0)), 1.0)
    values = {"param1": 0.0, "param2": 0.0, "param3": 0.0, "param4": 0.0, "x": 1.25, "y": 103.5, "z": 0.0, field: bad}
    if field == "param4" and math.isnan(bad):
        values["param4"] = math.inf  # NaN is allowed in a waypoint's param4 (AP_Mission::sanity_check_params)
    if field.startswith("param") and abs(bad) == 1e30:
        return  # a finite param: stored as ArduPilot stores it (cast), not an error
    item = gcs.mav.mission_item_encode(1, 1, 1, m.MAV_FRAME_GLOBAL_RELATIVE_ALT, 16, 0, 1, values["param1"],
                                       values["param2"], values["param3"], values["param4"], values["x"],
                                       values["y"], values["z"])  # fmt: skip
    (ack,) = of_type(parse(v.receive(gcs.pack(item), 1.0)), "MISSION_ACK")
    assert ack.type != m.MAV_MISSION_ACCEPTED and v.mission.items == [] and v.counters.errors == 0


@pytest.mark.parametrize("channel", range(1, 19))
@pytest.mark.parametrize("bad", [1, 799, 2201, 40000, 65533])
def test_every_override_channel(channel: int, bad: int) -> None:
    v, gcs = SimulatedVehicle(1, "buoy", 45.0, armed=True), Gcs()
    raw = [1900] * 8 + [0] * 10
    raw[channel - 1] = bad
    v.receive(gcs.pack(gcs.mav.rc_channels_override_encode(1, 1, *raw)), 0.0)
    assert v.counters.rejected == 1 and v.counters.commands == 0 and not v.actuator(0.5).any()


@pytest.mark.parametrize(("y", "z"), [(32000, 0), (0, -32000), (-1001, 0), (0, 1001)])
def test_manual_control_axes_out_of_range(y: int, z: int) -> None:
    v, gcs = SimulatedVehicle(1, "ebot", 0.2, armed=True), Gcs()
    v.receive(gcs.pack(gcs.mav.manual_control_encode(1, 32767, y, z, 32767, 0)), 0.0)
    assert v.counters.rejected == 1 and not v.actuator(0.5).any()


def test_request_data_stream_nonsense_is_ignored() -> None:
    v, gcs = SimulatedVehicle(1, "buoy", 45.0), Gcs()
    before = _state(v)
    for stream, rate, start in ((200, 5, 1), (m.MAV_DATA_STREAM_EXTRA1, 5, 7)):
        assert v.receive(gcs.pack(gcs.mav.request_data_stream_encode(1, 1, stream, rate, start)), 0.0) == b""
    assert _state(v) == before and v.counters.rejected == 2
    v.receive(gcs.pack(gcs.mav.request_data_stream_encode(1, 1, m.MAV_DATA_STREAM_EXTRA1, 65535, 1)), 0.0)
    assert v.params["MAV1_EXTRA1"] == 50 and v.schedule.interval_ms[m.MAVLINK_MSG_ID_ATTITUDE] == 25


# -- property: any values in any field of any message the vehicle reads ------------------------------------------

ACCEPTED = ["COMMAND_LONG", "COMMAND_INT", "PARAM_SET", "PARAM_REQUEST_READ", "PARAM_REQUEST_LIST", "MISSION_COUNT",
            "MISSION_ITEM_INT", "MISSION_ITEM", "MISSION_REQUEST_INT", "MISSION_REQUEST", "MISSION_REQUEST_LIST",
            "MISSION_CLEAR_ALL", "RC_CHANNELS_OVERRIDE", "MANUAL_CONTROL", "SET_MODE", "REQUEST_DATA_STREAM",
            "HEARTBEAT"]  # fmt: skip
_INT_RANGES = {"uint8_t": (0, 255), "int8_t": (-128, 127), "uint16_t": (0, 65535), "int16_t": (-32768, 32767),
               "uint32_t": (0, 2**32 - 1), "int32_t": (-(2**31), 2**31 - 1), "uint64_t": (0, 2**64 - 1)}  # fmt: skip


def _field(ftype: str, length: int, name: str):
    if name in ("target_system", "target"):
        return st.sampled_from([1, 1, 1, 0, 2])
    if name == "target_component":
        return st.sampled_from([1, 0, 5])
    if ftype == "char":
        return st.text(alphabet=st.characters(min_codepoint=32, max_codepoint=126), max_size=length).map(str.encode)
    if ftype in ("float", "double"):
        one = st.floats(width=32, allow_nan=True, allow_infinity=True)
    else:
        low, high = _INT_RANGES[ftype]
        one = st.one_of(st.integers(low, high), st.sampled_from([low, high, 0, 1]))
    return st.lists(one, min_size=length, max_size=length) if length else one


@st.composite
def _message(draw):
    name = draw(st.sampled_from(ACCEPTED))
    cls = getattr(mavlink, f"MAVLink_{name.lower()}_message")
    types = dict(zip(cls.fieldnames, cls.fieldtypes, strict=True))
    lengths = dict(zip(cls.ordered_fieldnames, cls.array_lengths, strict=True))
    values = [draw(_field(types[f], lengths[f], f)) for f in cls.fieldnames]
    if name in ("COMMAND_LONG", "COMMAND_INT"):
        values[cls.fieldnames.index("command")] = draw(st.sampled_from([*sorted(COMMANDS), 0, 42428, 401, 65535]))
    return cls(*values)


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(_message(), min_size=1, max_size=6), st.sampled_from(["buoy", "ebot"]), st.integers(200, 255))
def test_any_message_any_values_never_raises_and_keeps_the_vehicle_sane(messages, kind, source) -> None:
    v = SimulatedVehicle(1, kind, 1.0, armed=True)
    run(v, 0.0, 0.2)
    gcs = Gcs(system=source)
    for k, message in enumerate(messages):
        try:
            data = gcs.pack(message)
        except Exception:  # pymavlink cannot pack it (e.g. a value its struct format refuses): nothing to send
            continue
        t = 0.2 + 0.4 * k  # long enough apart that every 1 Hz message goes out with the state the message left
        reply = v.receive(data, t)
        assert np.isfinite(v.actuator(t)).all()
        parse(reply + v.stream(t))  # whatever the vehicle says is a valid frame
    assert v.counters.errors == 0, "a handler raised"
    for spec in v.params.specs:
        value = v.params[spec.name]
        assert math.isfinite(value) and spec.low <= value <= spec.high, spec.name


# -- the UDP server never dies -----------------------------------------------------------------------------------


@pytest.mark.xdist_group("realtime")
def test_the_vehicle_server_survives_a_handler_that_raises_and_answers_the_next_datagram() -> None:
    server = VehicleServer(["buoy"], [45.0], base_port=0, streams="ardupilot")
    client = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    client.settimeout(2.0)
    try:
        vehicle = server.vehicles[0]
        calls = []

        def broken(data: bytes, t_s: float) -> bytes:
            calls.append(data)
            if len(calls) == 1:
                raise RuntimeError("boom")
            return SimulatedVehicle.receive(vehicle, data, t_s)

        vehicle.receive = broken
        port = server.ports[0]
        client.sendto(Gcs().long(m.MAV_CMD_DO_SET_MODE, 1, math.nan), ("127.0.0.1", port))
        client.sendto(b"junk without a start marker " * 8, ("127.0.0.1", port))
        client.sendto(Gcs().long(m.MAV_CMD_DO_SET_MODE, 1, math.nan), ("127.0.0.1", port))
        deadline = time.monotonic() + 2.0
        while len(calls) < 3 and time.monotonic() < deadline:
            server.serve(0.05, 0.0)
        data, _ = client.recvfrom(65535)
        (ack,) = of_type(parse(data), "COMMAND_ACK")
        assert ack.result == m.MAV_RESULT_DENIED
        assert server.counters()["datagram_errors"] == 1 and vehicle.mode == 0
    finally:
        client.close()
        server.close()
