"""Issue 17, item 1 (vessel side): NaN, infinities and absurd numbers in every numeric field of every message the
ground-station component accepts, sent as real encoded MAVLink to a real GcsComponent, as an attacker would.

Each bad value must be refused the way its protocol refuses (COMMAND_ACK DENIED, the PARAM_VALUE in force,
MISSION_ACK with an error), change nothing, count one `out_of_range` and never raise. Where MAVLink lets NaN
mean "default" (a command parameter the command does not use, a waypoint's yaw), NaN is accepted; what is
then handed to the autopilot is still finite.
"""

from __future__ import annotations

import copy
import math
import struct

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from bob_autonomy.core.clock import ManualClock
from bob_autonomy.ground.gcs import AutopilotCommand, GcsComponent, MavlinkCodec
from bob_autonomy.ground.params import ParameterStore

SYSID = 3
LAT, LON = 45.0001, 7.0001
HUGE = 3.0e38  # about the largest float32
INT32_MAX, INT32_MIN = 2**31 - 1, -(2**31)
BAD_FLOATS = [math.nan, math.inf, -math.inf, HUGE, -HUGE]


class Gcs:
    """The ground station: packs real frames, decodes the component's answers."""

    def __init__(self, component: GcsComponent) -> None:
        self.component = component
        self.codec = MavlinkCodec(255, 190)
        self.mav = self.codec.mav

    def send(self, message) -> list:
        self.component.receive(self.codec.pack(message))
        out = []
        for data in self.component.outgoing():
            out.extend(self.codec.decode(data))
        return out


def of(messages, kind: str) -> list:
    return [m for m in messages if m.get_type() == kind]


def texts(messages) -> str:
    return "".join(m.text for m in of(messages, "STATUSTEXT"))  # chunks of a long text joined


def make_component() -> tuple[GcsComponent, Gcs]:
    component = GcsComponent(SYSID, ParameterStore(), clock=ManualClock(100.0).now)
    component.behavior_running = True
    component.params.set_goals([(45.5, 7.5)])
    component.params.set_fence([(45.0, 7.0), (45.0, 7.1), (45.1, 7.1)])
    component.outgoing()
    return component, Gcs(component)


def state(component: GcsComponent) -> tuple:
    """Everything a message could change."""
    return (
        component.params.values(),
        list(component.goals),
        list(component.fence),
        component.behavior_running,
        copy.deepcopy(component.pending_autopilot),
    )


def assert_finite_state(component: GcsComponent) -> None:
    assert all(math.isfinite(v) for v in component.params.values().values())
    for lat, lon in [*component.goals, *component.fence]:
        assert -90 <= lat <= 90 and -180 <= lon <= 180
    for command in component.pending_autopilot:
        assert isinstance(command, AutopilotCommand) and all(math.isfinite(v) for v in command.params)


# -- commands -----------------------------------------------------------------------------------------------

C = mavlink
# A good value for each of the seven parameters, and the parameters (1-based) the command really uses: written
# here from the MAVLink definitions, independently of the component's own table. A used parameter refuses NaN,
# except those in NAN_DEFAULT (arm's param2: NaN = not forced).
NAN_DEFAULT = {(C.MAV_CMD_COMPONENT_ARM_DISARM, 2)}
# Commands passed on to the autopilot: taken "in progress", the autopilot's own answer to follow.
TAKEN = {C.MAV_CMD_COMPONENT_ARM_DISARM: C.MAV_RESULT_IN_PROGRESS, C.MAV_CMD_DO_SET_MODE: C.MAV_RESULT_IN_PROGRESS}
COMMANDS = {
    C.MAV_CMD_MISSION_START: ([0, 0, 0, 0, 0, 0, 0], ()),
    C.MAV_CMD_DO_PAUSE_CONTINUE: ([0, 0, 0, 0, 0, 0, 0], (1,)),
    C.MAV_CMD_COMPONENT_ARM_DISARM: ([1, 0, 0, 0, 0, 0, 0], (1, 2)),
    C.MAV_CMD_DO_SET_MODE: ([1, 4, 0, 0, 0, 0, 0], (1, 2)),
    C.MAV_CMD_DO_REPOSITION: ([-1, 1, 0, 0, LAT, LON, 5], (5, 6, 7)),
    C.MAV_CMD_NAV_WAYPOINT: ([0, 0, 0, 0, LAT, LON, 5], (5, 6, 7)),
    C.MAV_CMD_DO_FOLLOW: ([4, 0, 0, 0, 0, 0, 0], (1,)),
    C.MAV_CMD_USER_1: ([3, 0, 0, 0, 0, 0, 0], (1,)),
    C.MAV_CMD_DO_FENCE_ENABLE: ([1, 0, 0, 0, 0, 0, 0], (1,)),
    C.MAV_CMD_REQUEST_MESSAGE: ([0, 0, 0, 0, 0, 0, 0], (1,)),
    C.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES: ([1, 0, 0, 0, 0, 0, 0], ()),
}
GOALS = (C.MAV_CMD_DO_REPOSITION, C.MAV_CMD_NAV_WAYPOINT)


def command_long(gcs: Gcs, command: int, params) -> object:
    return gcs.mav.command_long_encode(SYSID, 191, command, 0, *params)


def command_int(gcs: Gcs, command: int, params, frame: int = C.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT) -> object:
    """COMMAND_INT with params 5 and 6 as x, y (degrees * 1e7 for a goal)."""
    scale = 1e7 if command in GOALS else 1.0
    x, y = (int(max(INT32_MIN, min(INT32_MAX, round(v * scale)))) for v in params[4:6])
    return gcs.mav.command_int_encode(SYSID, 191, frame, command, 0, 0, *params[:4], x, y, params[6])


def ack_of(answers, command: int) -> int:
    (ack,) = of(answers, "COMMAND_ACK")
    assert ack.command == command
    return ack.result


def _command_cases():
    for command, (_, used) in COMMANDS.items():
        for k in range(7):
            for value in BAD_FLOATS:
                unused = (k + 1) not in used
                accepted = (unused and not math.isinf(value)) or ((command, k + 1) in NAN_DEFAULT and math.isnan(value))
                yield pytest.param(command, k, value, accepted, id=f"{command}-param{k + 1}-{value!r}")


@pytest.mark.parametrize(("command", "k", "value", "accepted"), list(_command_cases()))
@pytest.mark.parametrize("encoding", ["COMMAND_LONG", "COMMAND_INT"])
def test_every_command_parameter_refuses_nan_inf_and_huge(command, k, value, accepted, encoding) -> None:
    component, gcs = make_component()
    params = list(COMMANDS[command][0])
    params[k] = value
    before = state(component)
    if encoding == "COMMAND_INT" and k in (4, 5):  # x and y are integers: the worst they can be is the extremes
        x_or_y = INT32_MAX if value > 0 or math.isnan(value) else INT32_MIN
        message = command_int(gcs, command, [*params[:4], 0, 0, *params[6:]])
        setattr(message, "x" if k == 4 else "y", x_or_y)
        accepted = command not in GOALS
    elif encoding == "COMMAND_INT":
        message = command_int(gcs, command, params)
    else:
        message = command_long(gcs, command, params)
    answers = gcs.send(message)
    result = ack_of(answers, command)
    c = component.counters
    assert c.handler_errors == 0
    if accepted:
        assert result == TAKEN.get(command, C.MAV_RESULT_ACCEPTED), texts(answers)
        assert c.out_of_range == 0
    else:
        assert result == C.MAV_RESULT_DENIED
        assert state(component) == before
        assert c.out_of_range == 1 and f"param{k + 1}" in texts(answers)
    assert_finite_state(component)


def test_a_goal_by_command_int_must_be_in_a_global_frame() -> None:
    component, gcs = make_component()
    before = state(component)
    answers = gcs.send(command_int(gcs, C.MAV_CMD_DO_REPOSITION, COMMANDS[C.MAV_CMD_DO_REPOSITION][0], frame=1))
    assert ack_of(answers, C.MAV_CMD_DO_REPOSITION) == C.MAV_RESULT_DENIED and "frame 1" in texts(answers)
    assert state(component) == before and component.counters.out_of_range == 1


def test_nan_in_unused_arm_parameters_reaches_the_autopilot_as_zero() -> None:
    component, gcs = make_component()
    params = [1, 0, math.nan, math.nan, math.nan, math.nan, math.nan]  # as a GCS that means "default" sends them
    answers = gcs.send(command_long(gcs, C.MAV_CMD_COMPONENT_ARM_DISARM, params))
    assert ack_of(answers, 400) == C.MAV_RESULT_IN_PROGRESS  # the autopilot's own answer follows
    (command,) = component.take_autopilot_commands()
    assert command.kind == "arm" and command.params == (1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0) and not command.force
    with pytest.raises(ValueError, match="not finite"):
        AutopilotCommand("set_mode", 176, (1.0, math.nan), (255, 190), 0.0)


# 32-bit floats as they come off the wire: any bit pattern, NaNs and infinities included.
FLOAT32 = st.integers(0, 2**32 - 1).map(lambda bits: struct.unpack("<f", struct.pack("<I", bits))[0])
SPECIAL = st.sampled_from([math.nan, math.inf, -math.inf, 0.0, -0.0, 1.0, 21196.0, HUGE, 4.0, 2.0**32, LAT, LON])


@settings(max_examples=300, deadline=None, database=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    command=st.sampled_from([*COMMANDS, 0, 65535]),
    params=st.lists(st.one_of(FLOAT32, SPECIAL), min_size=7, max_size=7),
    as_int=st.booleans(),
    xy=st.tuples(st.integers(INT32_MIN, INT32_MAX), st.integers(INT32_MIN, INT32_MAX)),
    frame=st.sampled_from([0, 1, 3, 5, 6, 255]),
)
def test_any_command_is_answered_once_and_leaves_only_finite_state(command, params, as_int, xy, frame) -> None:
    component, gcs = make_component()
    before = state(component)
    if as_int:
        message = gcs.mav.command_int_encode(SYSID, 191, frame, command, 0, 0, *params[:4], *xy, params[6])
    else:
        message = command_long(gcs, command, params)
    result = ack_of(gcs.send(message), command)
    c = component.counters
    assert c.handler_errors == 0 and c.accepted == 1
    if result not in (C.MAV_RESULT_ACCEPTED, C.MAV_RESULT_IN_PROGRESS):
        assert state(component) == before
    if c.out_of_range:
        assert result == C.MAV_RESULT_DENIED and c.out_of_range == 1
    elif result == C.MAV_RESULT_DENIED:  # denied for another reason: a message it cannot send
        assert command == C.MAV_CMD_REQUEST_MESSAGE
    assert_finite_state(component)


# -- parameters ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("value", BAD_FLOATS)
def test_param_set_of_every_parameter_refuses_nan_inf_and_huge(value) -> None:
    component, gcs = make_component()
    for n, name in enumerate(component.params.names(), start=1):
        before = state(component)
        kept = component.params.get(name)
        answers = gcs.send(gcs.mav.param_set_encode(SYSID, 191, name.encode(), value, 9))
        (echo,) = of(answers, "PARAM_VALUE")
        assert (echo.param_id, echo.param_value) == (name, float(kept))  # the value in force, unchanged
        assert name in texts(answers)
        assert state(component) == before and component.counters.out_of_range == n
    assert component.counters.handler_errors == 0 and component.counters.params_set == 0


@settings(max_examples=200, deadline=None, database=None)
@given(index=st.integers(0, 100), value=st.one_of(FLOAT32, SPECIAL))
def test_any_param_set_answers_the_value_in_force_which_is_finite(index, value) -> None:
    component, gcs = make_component()
    name = component.params.name_at(index % len(component.params))
    (echo,) = of(gcs.send(gcs.mav.param_set_encode(SYSID, 191, name.encode(), value, 9)), "PARAM_VALUE")
    assert echo.param_value == float(component.params.get(name)) and math.isfinite(echo.param_value)
    assert_finite_state(component)
    c = component.counters
    assert c.params_set + c.out_of_range == 1 and c.handler_errors == 0


@pytest.mark.parametrize("index", [-2, -32768, 32767, "count"])
def test_param_request_read_outside_the_list_is_refused(index) -> None:
    component, gcs = make_component()
    index = len(component.params) if index == "count" else index
    answers = gcs.send(gcs.mav.param_request_read_encode(SYSID, 191, b"BOB_P0_M", index))
    assert of(answers, "PARAM_VALUE") == [] and "param_index" in texts(answers)
    assert component.counters.out_of_range == 1


# -- missions -----------------------------------------------------------------------------------------------

WAYPOINT, FENCE, RALLY = C.MAV_MISSION_TYPE_MISSION, C.MAV_MISSION_TYPE_FENCE, C.MAV_MISSION_TYPE_RALLY
ITEM = {  # mission type: (command, number of items, good param1)
    WAYPOINT: (C.MAV_CMD_NAV_WAYPOINT, 2, 0.0),
    FENCE: (C.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION, 3, 3.0),
    RALLY: (C.MAV_CMD_NAV_RALLY_POINT, 1, 0.0),
}
FIELDS = ("param1", "param2", "param3", "param4", "x", "y", "z")
RESULTS = dict(zip(FIELDS, range(C.MAV_MISSION_INVALID_PARAM1, C.MAV_MISSION_INVALID_PARAM7 + 1), strict=True))


def item(gcs: Gcs, mission_type: int, seq: int, *, legacy: bool, **bad) -> object:
    command, _, param1 = ITEM[mission_type]
    values = dict(param1=param1, param2=0.0, param3=0.0, param4=0.0, z=0.0)
    lat, lon = LAT + seq * 1e-4, LON + (seq == 2) * 1e-4
    if legacy:
        values |= dict(x=lat, y=lon)
        encode, frame = gcs.mav.mission_item_encode, C.MAV_FRAME_GLOBAL_RELATIVE_ALT
    else:
        values |= dict(x=round(lat * 1e7), y=round(lon * 1e7))
        encode, frame = gcs.mav.mission_item_int_encode, C.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT
    values |= bad
    return encode(SYSID, 191, seq, frame, command, 0, 1, *(values[f] for f in FIELDS), mission_type)


def _item_cases():
    for mission_type in ITEM:
        for legacy in (False, True):
            for name in FIELDS:
                integer = not legacy and name in ("x", "y")
                for value in [INT32_MAX, INT32_MIN] if integer else BAD_FLOATS:
                    finite = isinstance(value, int) or math.isfinite(value)
                    if name in ("x", "y", "z") or (name == "param1" and mission_type == FENCE):
                        accepted = False  # used: must be a number in range
                    elif name == "param4" and mission_type == WAYPOINT:
                        accepted = not math.isinf(value)  # yaw: NaN = keep the heading (ArduPilot's AP_Mission)
                    else:
                        accepted = finite  # unused: any number, but neither NaN nor infinite (AP_Mission)
                    kind = "MISSION_ITEM" if legacy else "MISSION_ITEM_INT"
                    yield pytest.param(mission_type, legacy, name, value, accepted,
                                       id=f"{kind}-type{mission_type}-{name}-{value!r}")  # fmt: skip


@pytest.mark.parametrize(("mission_type", "legacy", "name", "value", "accepted"), list(_item_cases()))
def test_every_mission_item_field_refuses_nan_inf_and_huge(mission_type, legacy, name, value, accepted) -> None:
    component, gcs = make_component()
    before = state(component)
    count = ITEM[mission_type][1]
    (request,) = of(gcs.send(gcs.mav.mission_count_encode(SYSID, 191, count, mission_type)), "MISSION_REQUEST_INT")
    assert request.seq == 0
    answers = gcs.send(item(gcs, mission_type, 0, legacy=legacy, **{name: value}))
    c = component.counters
    assert c.handler_errors == 0
    if accepted:
        for seq in range(1, count):
            answers = gcs.send(item(gcs, mission_type, seq, legacy=legacy))
        (ack,) = of(answers, "MISSION_ACK")
        assert ack.type == C.MAV_MISSION_ACCEPTED, texts(answers)
        assert c.out_of_range == 0
    else:
        (ack,) = of(answers, "MISSION_ACK")
        assert ack.type == RESULTS[name] and ack.mission_type == mission_type
        assert state(component) == before and c.out_of_range == 1 and "upload refused" in texts(answers)
        assert of(answers, "MISSION_REQUEST_INT") == []
        # the upload is over: the next item is not taken
        assert of(gcs.send(item(gcs, mission_type, 1, legacy=legacy)), "MISSION_REQUEST_INT") == []
        assert state(component) == before
    assert_finite_state(component)


def test_a_fence_vertex_count_that_is_not_a_whole_number_in_range_is_refused() -> None:
    for param1 in (2.0, 3.5, 101.0, -3.0):
        component, gcs = make_component()
        gcs.send(gcs.mav.mission_count_encode(SYSID, 191, 3, FENCE))
        (ack,) = of(gcs.send(item(gcs, FENCE, 0, legacy=False, param1=param1)), "MISSION_ACK")
        assert ack.type == C.MAV_MISSION_INVALID_PARAM1 and component.counters.out_of_range == 1


@pytest.mark.parametrize(("mission_type", "count", "result"), [
    (WAYPOINT, 65535, C.MAV_MISSION_NO_SPACE), (FENCE, 65535, C.MAV_MISSION_NO_SPACE),
    (RALLY, 2, C.MAV_MISSION_NO_SPACE), (FENCE, 1, C.MAV_MISSION_INVALID), (FENCE, 2, C.MAV_MISSION_INVALID),
])  # fmt: skip
def test_mission_counts_out_of_range_are_refused(mission_type, count, result) -> None:
    component, gcs = make_component()
    before = state(component)
    (ack,) = of(gcs.send(gcs.mav.mission_count_encode(SYSID, 191, count, mission_type)), "MISSION_ACK")
    assert ack.type == result and state(component) == before and component.counters.out_of_range == 1


@pytest.mark.parametrize("legacy", [False, True])
def test_mission_download_of_an_item_that_does_not_exist_is_refused(legacy) -> None:
    component, gcs = make_component()
    encode = gcs.mav.mission_request_encode if legacy else gcs.mav.mission_request_int_encode
    (ack,) = of(gcs.send(encode(SYSID, 191, 65535, WAYPOINT)), "MISSION_ACK")
    assert ack.type == C.MAV_MISSION_INVALID_SEQUENCE and component.counters.out_of_range == 1


@settings(max_examples=200, deadline=None, database=None)
@given(
    mission_type=st.sampled_from([WAYPOINT, FENCE, RALLY]),
    legacy=st.booleans(),
    values=st.lists(st.one_of(FLOAT32, SPECIAL), min_size=7, max_size=7),
    xy=st.tuples(st.integers(INT32_MIN, INT32_MAX), st.integers(INT32_MIN, INT32_MAX)),
)
def test_any_mission_item_leaves_only_finite_state(mission_type, legacy, values, xy) -> None:
    component, gcs = make_component()
    fields = dict(zip(FIELDS, values, strict=True))
    if not legacy:
        fields["x"], fields["y"] = xy
    gcs.send(gcs.mav.mission_count_encode(SYSID, 191, 1 if mission_type != FENCE else 3, mission_type))
    answers = gcs.send(item(gcs, mission_type, 0, legacy=legacy, **fields))
    assert component.counters.handler_errors == 0
    acks = of(answers, "MISSION_ACK")
    assert len(acks) + len(of(answers, "MISSION_REQUEST_INT")) == 1
    assert_finite_state(component)
