"""GcsComponent against real encoded MAVLink bytes: parameters, commands, missions, signing, robustness."""

from __future__ import annotations

import hashlib
import math
import random

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from bob_autonomy.core.clock import ManualClock
from bob_autonomy.ground.gcs import (
    GcsComponent,
    MavlinkCodec,
    SigningKeyError,
    load_signing_key,
    passphrase_to_key,
    signing_timestamp,
)
from bob_autonomy.ground.params import BEHAVIOR_NAMES, ParameterStore

SYSID = 3
KEY = hashlib.sha256(b"fleet key").digest()
OTHER_KEY = hashlib.sha256(b"another key").digest()
WALL_T0 = 1.75e9  # a fixed Unix time for signing timestamps


class Wall:
    """A settable Unix clock for signing timestamps."""

    def __init__(self, t: float = WALL_T0) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t


class Gcs:
    """The ground-station side of a test: packs requests and decodes the component's answers."""

    def __init__(self, component: GcsComponent, *, key: bytes | None = None, system_id: int = 255, wall=None):
        self.component = component
        self.codec = MavlinkCodec(system_id, 190, signing_key=key, wall_clock=wall or Wall())
        self.mav = self.codec.mav

    def frame(self, message) -> bytes:
        return self.codec.pack(message)

    def send(self, message) -> list:
        self.component.receive(self.frame(message))
        return self.answers()

    def answers(self) -> list:
        out = []
        for data in self.component.outgoing():
            out.extend(self.codec.decode(data))
        return out


def of(messages, kind: str) -> list:
    return [m for m in messages if m.get_type() == kind]


def texts(messages) -> str:
    """The STATUSTEXTs among messages, chunks of one text (same non-zero id) joined."""
    out: list[str] = []
    last_id = 0
    for m in of(messages, "STATUSTEXT"):
        if m.id and m.id == last_id:
            out[-1] += m.text
        else:
            out.append(m.text)
        last_id = m.id
    return " | ".join(out)


@pytest.fixture
def clock() -> ManualClock:
    return ManualClock(100.0)


@pytest.fixture
def component(tmp_path, clock) -> GcsComponent:
    return GcsComponent(SYSID, ParameterStore(tmp_path / "params.json"), clock=clock.now, mission_timeout_s=1.0)


@pytest.fixture
def gcs(component) -> Gcs:
    return Gcs(component)


# -- heartbeat and telemetry --------------------------------------------------------------------------------


def test_heartbeat_once_a_second(component, gcs, clock) -> None:
    component.tick()
    (beat,) = of(gcs.answers(), "HEARTBEAT")
    assert beat.type == mavlink.MAV_TYPE_ONBOARD_CONTROLLER and beat.autopilot == mavlink.MAV_AUTOPILOT_INVALID
    assert (beat.get_srcSystem(), beat.get_srcComponent()) == (SYSID, 191)
    assert beat.custom_mode & 1 == 0 and beat.system_status == mavlink.MAV_STATE_STANDBY
    clock.advance(0.5)
    component.tick()
    assert gcs.answers() == []
    clock.advance(0.5)
    component.tick()
    assert len(of(gcs.answers(), "HEARTBEAT")) == 1


def test_position_reports_at_bob_pos_hz(component, gcs, clock) -> None:
    component.tick()
    assert of(gcs.answers(), "GLOBAL_POSITION_INT") == []  # nothing until the process reports a position
    component.params.set("BOB_POS_HZ", 2.0)
    component.report_position(45.1234567, -7.5, v_east_mps=1.0, v_north_mps=-0.5, heading_rad=0.0)
    component.tick()
    (pos,) = of(gcs.answers(), "GLOBAL_POSITION_INT")
    assert (pos.lat, pos.lon) == (451234567, -75000000)
    assert (pos.vx, pos.vy) == (-50, 100)  # north, east in cm/s
    assert pos.hdg == 9000  # heading 0 = east = 90 deg from north
    clock.advance(0.3)
    component.tick()
    assert of(gcs.answers(), "GLOBAL_POSITION_INT") == []
    clock.advance(0.25)
    component.report_position(45.0, 7.0, heading_rad=None)
    component.tick()
    (pos,) = of(gcs.answers(), "GLOBAL_POSITION_INT")
    assert pos.hdg == 65535


def test_long_statustext_is_chunked(component, gcs) -> None:
    component.notify(mavlink.MAV_SEVERITY_WARNING, "x" * 60 + "y" * 60)
    chunks = of(gcs.answers(), "STATUSTEXT")
    assert [c.chunk_seq for c in chunks] == [0, 1, 2] and len({c.id for c in chunks}) == 1 and chunks[0].id != 0
    assert "".join(c.text for c in chunks) == "x" * 60 + "y" * 60


def test_gcs_failsafe(component, gcs, clock) -> None:
    component.params.set("BOB_GCS_FS_S", 5.0)
    component.tick()
    clock.advance(60)
    component.tick()
    assert not component.gcs_lost  # no ground station ever heard: nothing to lose
    gcs.send(gcs.mav.heartbeat_encode(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0))
    clock.advance(4.0)
    component.tick()
    assert not component.gcs_lost
    clock.advance(2.0)
    component.tick()
    assert component.gcs_lost and "ground station lost" in texts(gcs.answers())
    gcs.send(gcs.mav.heartbeat_encode(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0))
    assert not component.gcs_lost


# -- parameters ---------------------------------------------------------------------------------------------


def test_param_request_list(component, gcs) -> None:
    values = of(gcs.send(gcs.mav.param_request_list_encode(SYSID, 191)), "PARAM_VALUE")
    names = component.params.names()
    assert [v.param_id for v in values] == names
    assert [v.param_index for v in values] == list(range(len(names)))
    assert {v.param_count for v in values} == {len(names)}
    by_name = {v.param_id: v for v in values}
    assert by_name["BOB_P0_M"].param_value == 10.0 and by_name["BOB_P0_M"].param_type == 9
    assert by_name["BOB_BEHAVIOR"].param_type == 6


def test_param_read_by_id_and_by_index(component, gcs) -> None:
    (v,) = gcs.send(gcs.mav.param_request_read_encode(SYSID, 191, b"BOB_GCS_FS_S", -1))
    assert (v.param_id, v.param_value, v.param_index) == ("BOB_GCS_FS_S", 30.0, component.params.index("BOB_GCS_FS_S"))
    (v,) = gcs.send(gcs.mav.param_request_read_encode(SYSID, 191, b"", 2))
    assert v.param_id == component.params.name_at(2)
    answers = gcs.send(gcs.mav.param_request_read_encode(SYSID, 191, b"BOB_NOPE", -1))
    assert of(answers, "PARAM_VALUE") == [] and "BOB_NOPE" in texts(answers)


def test_param_set_round_trip_and_persistence(tmp_path, component, gcs, clock) -> None:
    (v,) = gcs.send(gcs.mav.param_set_encode(SYSID, 191, b"BOB_P0_M", 5.5, 9))
    assert (v.param_id, v.param_value) == ("BOB_P0_M", 5.5)
    (v,) = gcs.send(gcs.mav.param_set_encode(SYSID, 191, b"BOB_BEHAVIOR", 3.0, 6))
    assert v.param_value == 3.0 and component.params.behavior_name == BEHAVIOR_NAMES[3]
    restarted = GcsComponent(SYSID, ParameterStore(tmp_path / "params.json"), clock=clock.now)
    assert restarted.params.get("BOB_P0_M") == 5.5 and restarted.params.get("BOB_BEHAVIOR") == 3
    assert component.counters.params_set == 2


def test_invalid_param_set_answers_the_old_value_and_why(component, gcs) -> None:
    answers = gcs.send(gcs.mav.param_set_encode(SYSID, 191, b"BOB_MAX_SPD_MPS", 50.0, 9))
    (v,) = of(answers, "PARAM_VALUE")
    assert (v.param_id, v.param_value) == ("BOB_MAX_SPD_MPS", 1.0)
    assert "BOB_MAX_SPD_MPS" in texts(answers) and "out of range" in texts(answers)
    assert answers[0].get_type() == "STATUSTEXT"  # the reason comes first
    answers = gcs.send(gcs.mav.param_set_encode(SYSID, 191, b"BOB_NOPE", 1.0, 9))
    assert of(answers, "PARAM_VALUE") == [] and "unknown parameter" in texts(answers)
    assert component.counters.params_rejected == 2 and component.params.get("BOB_MAX_SPD_MPS") == 1.0


def test_corrupt_parameter_file_is_reported_over_mavlink(tmp_path, clock) -> None:
    path = tmp_path / "params.json"
    path.write_text("{broken")
    component = GcsComponent(SYSID, ParameterStore(path), clock=clock.now)
    assert "corrupt" in texts(Gcs(component).answers())
    assert (tmp_path / "params.json.corrupt-1").exists()


# -- commands -----------------------------------------------------------------------------------------------


def command(gcs: Gcs, cmd: int, *params: float, target: int = SYSID, component: int = 191) -> list:
    p = [float(v) for v in params] + [0.0] * (7 - len(params))
    return gcs.send(gcs.mav.command_long_encode(target, component, cmd, 0, *p))


def ack_of(answers, cmd: int) -> int:
    (ack,) = of(answers, "COMMAND_ACK")
    assert ack.command == cmd and (ack.target_system, ack.target_component) == (255, 190)
    return ack.result


def test_start_and_stop_the_behaviour(component, gcs, clock) -> None:
    assert ack_of(command(gcs, mavlink.MAV_CMD_MISSION_START), mavlink.MAV_CMD_MISSION_START) == 0
    assert component.behavior_running
    component.tick()
    (beat,) = of(gcs.answers(), "HEARTBEAT")
    assert beat.custom_mode & 1 == 1 and beat.system_status == mavlink.MAV_STATE_ACTIVE
    answers = command(gcs, mavlink.MAV_CMD_DO_PAUSE_CONTINUE, 0)
    assert ack_of(answers, mavlink.MAV_CMD_DO_PAUSE_CONTINUE) == 0 and not component.behavior_running
    assert "stopped" in texts(answers)
    command(gcs, mavlink.MAV_CMD_DO_PAUSE_CONTINUE, 1)
    assert component.behavior_running
    answers = command(gcs, mavlink.MAV_CMD_DO_PAUSE_CONTINUE, 5)
    assert ack_of(answers, mavlink.MAV_CMD_DO_PAUSE_CONTINUE) == mavlink.MAV_RESULT_DENIED


def test_unknown_command_is_unsupported(component, gcs) -> None:
    answers = command(gcs, mavlink.MAV_CMD_DO_SET_SERVO, 1, 1500)
    assert ack_of(answers, mavlink.MAV_CMD_DO_SET_SERVO) == mavlink.MAV_RESULT_UNSUPPORTED
    assert component.counters.commands_unsupported == 1


def test_arm_disarm_and_mode_are_handed_to_the_process(component, gcs) -> None:
    """Answered "in progress" at once; the final answer is the autopilot's, which the process passes back."""
    assert ack_of(command(gcs, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1), 400) == mavlink.MAV_RESULT_IN_PROGRESS
    command(gcs, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 21196)
    command(gcs, mavlink.MAV_CMD_DO_SET_MODE, mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 15)
    taken = component.take_autopilot_commands()
    assert [(c.kind, c.force) for c in taken] == [("arm", False), ("disarm", True), ("set_mode", False)]
    assert taken[2].custom_mode == 15 and taken[0].source == (255, 190)
    assert component.pending_autopilot == []
    component.answer_autopilot_command(taken[0], mavlink.MAV_RESULT_FAILED)  # its pre-arm checks failed
    component.answer_autopilot_command(taken[2], mavlink.MAV_RESULT_ACCEPTED)
    (refused, accepted) = of(gcs.answers(), "COMMAND_ACK")
    assert (refused.command, refused.result) == (400, mavlink.MAV_RESULT_FAILED)
    assert (accepted.command, accepted.result) == (mavlink.MAV_CMD_DO_SET_MODE, mavlink.MAV_RESULT_ACCEPTED)
    assert (refused.target_system, refused.target_component) == (255, 190)
    assert component.counters.autopilot_refused == 1
    answers = command(gcs, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0.5)
    assert ack_of(answers, 400) == mavlink.MAV_RESULT_DENIED and component.pending_autopilot == []


def test_set_goal_by_command_long_and_command_int(component, gcs) -> None:
    answers = command(gcs, mavlink.MAV_CMD_NAV_WAYPOINT, 0, 0, 0, 0, 45.5, 7.25)
    assert ack_of(answers, mavlink.MAV_CMD_NAV_WAYPOINT) == 0
    assert component.goals == [(45.5, 7.25)]
    message = gcs.mav.command_int_encode(
        SYSID, 191, mavlink.MAV_FRAME_GLOBAL_INT, mavlink.MAV_CMD_DO_REPOSITION, 0, 0,
        -1, 0, 0, math.nan, 451234567, -71234567, 0,
    )  # fmt: skip
    assert ack_of(gcs.send(message), mavlink.MAV_CMD_DO_REPOSITION) == 0
    assert component.goals == [(45.1234567, -7.1234567)]
    assert component.params.get("BOB_GOAL_LAT") == 45.1234567
    answers = command(gcs, mavlink.MAV_CMD_DO_REPOSITION, -1, 0, 0, 0, math.nan, math.nan)
    assert ack_of(answers, mavlink.MAV_CMD_DO_REPOSITION) == mavlink.MAV_RESULT_DENIED
    assert component.goals == [(45.1234567, -7.1234567)]


def test_leader_behaviour_fence_and_capabilities(component, gcs) -> None:
    assert ack_of(command(gcs, mavlink.MAV_CMD_DO_FOLLOW, 12), mavlink.MAV_CMD_DO_FOLLOW) == 0
    assert component.params.get("BOB_LEADER_ID") == 12
    assert ack_of(command(gcs, mavlink.MAV_CMD_USER_1, 2), mavlink.MAV_CMD_USER_1) == 0
    assert component.params.behavior_name == BEHAVIOR_NAMES[2]
    answers = command(gcs, mavlink.MAV_CMD_USER_1, 99)
    assert ack_of(answers, mavlink.MAV_CMD_USER_1) == mavlink.MAV_RESULT_DENIED and "BOB_BEHAVIOR" in texts(answers)
    assert ack_of(command(gcs, mavlink.MAV_CMD_DO_FENCE_ENABLE, 1), mavlink.MAV_CMD_DO_FENCE_ENABLE) == 0
    assert component.params.get("BOB_FENCE_EN") == 1
    answers = command(gcs, mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION)
    (version,) = of(answers, "AUTOPILOT_VERSION")
    assert version.capabilities & mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_C_CAST
    assert version.capabilities & mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_FENCE


def test_targets_ours_and_broadcast_only(component, gcs) -> None:
    assert command(gcs, mavlink.MAV_CMD_MISSION_START, target=SYSID + 1) == []
    assert command(gcs, mavlink.MAV_CMD_MISSION_START, component=1) == []  # for the autopilot, not us
    assert component.counters.ignored_other_target == 2 and not component.behavior_running
    assert ack_of(command(gcs, mavlink.MAV_CMD_MISSION_START, target=0, component=0), 300) == 0
    assert component.behavior_running


def test_system_zero_reaches_every_vessel(tmp_path, clock) -> None:
    fleet = [GcsComponent(s, ParameterStore(), clock=clock.now) for s in (1, 2, 5)]
    sender = Gcs(fleet[0])
    frame = sender.frame(sender.mav.command_long_encode(0, 0, mavlink.MAV_CMD_MISSION_START, 0, 0, 0, 0, 0, 0, 0, 0))
    setp = sender.frame(sender.mav.param_set_encode(0, 0, b"BOB_P0_M", 25.0, 9))
    for vessel in fleet:
        vessel.receive(frame)
        vessel.receive(setp)
    assert all(v.behavior_running and v.params.get("BOB_P0_M") == 25.0 for v in fleet)
    acks = [Gcs(v).answers() for v in fleet]
    assert [{m.get_srcSystem() for m in a} for a in acks] == [{1}, {2}, {5}]
    assert all(len(of(a, "COMMAND_ACK")) == 1 and len(of(a, "PARAM_VALUE")) == 1 for a in acks)


# -- missions -----------------------------------------------------------------------------------------------

GOALS = [(45.0001, 7.0001), (45.0002, 7.0003), (45.0004, 7.0005)]
FENCE = [(45.0, 7.0), (45.0, 7.01), (45.01, 7.01), (45.01, 7.0)]


def item_int(gcs: Gcs, seq: int, lat: float, lon: float, mission_type=0, command=16, param1=0.0, frame=6):
    return gcs.mav.mission_item_int_encode(
        SYSID, 191, seq, frame, command, 0, 1, param1, 0, 0, 0, round(lat * 1e7), round(lon * 1e7), 0, mission_type
    )


def upload(gcs: Gcs, points, mission_type=0, command=16, *, legacy=False) -> list:
    """Answer the component's requests until its MISSION_ACK; return every message it sent."""
    seen = []
    answers = gcs.send(gcs.mav.mission_count_encode(SYSID, 191, len(points), mission_type))
    param1 = float(len(points)) if mission_type == 1 else 0.0
    for _ in range(len(points) + 1):
        seen += answers
        requests = of(answers, "MISSION_REQUEST_INT") + of(answers, "MISSION_REQUEST")
        if not requests:
            break
        seq = requests[-1].seq
        lat, lon = points[seq]
        if legacy:
            message = gcs.mav.mission_item_encode(SYSID, 191, seq, 3, command, 0, 1, param1, 0, 0, 0, lat, lon, 0,
                                                  mission_type)  # fmt: skip
        else:
            message = item_int(gcs, seq, lat, lon, mission_type, command, param1)
        answers = gcs.send(message)
    return seen


def same_points(a, b, tol: float = 1e-7) -> bool:
    """Equal lists of (lat, lon) within tol degrees (1e-7 = the degE7 resolution)."""
    return len(a) == len(b) and all(
        abs(p[0] - q[0]) <= tol and abs(p[1] - q[1]) <= tol for p, q in zip(a, b, strict=True)
    )


def mission_ack(messages) -> int:
    (ack,) = of(messages, "MISSION_ACK")
    return ack.type


def test_upload_three_waypoints_and_download_them(component, gcs) -> None:
    seen = upload(gcs, GOALS)
    assert [m.seq for m in of(seen, "MISSION_REQUEST_INT")] == [0, 1, 2]
    assert mission_ack(seen) == mavlink.MAV_MISSION_ACCEPTED
    assert same_points(component.goals, GOALS)
    assert component.params.get("BOB_GOAL_LAT") == pytest.approx(GOALS[0][0])
    (count,) = of(gcs.send(gcs.mav.mission_request_list_encode(SYSID, 191, 0)), "MISSION_COUNT")
    assert count.count == 3
    downloaded = []
    for seq in range(3):
        (item,) = gcs.send(gcs.mav.mission_request_int_encode(SYSID, 191, seq, 0))
        assert item.get_type() == "MISSION_ITEM_INT" and item.command == 16
        downloaded.append((item.x / 1e7, item.y / 1e7))
    (item,) = gcs.send(gcs.mav.mission_request_encode(SYSID, 191, 1, 0))  # legacy request, legacy item
    assert item.get_type() == "MISSION_ITEM" and same_points([(item.x, item.y)], GOALS[1:2], tol=1e-5)
    assert same_points(downloaded, GOALS)


def test_upload_with_legacy_items(component, gcs) -> None:
    assert mission_ack(upload(gcs, GOALS, legacy=True)) == mavlink.MAV_MISSION_ACCEPTED
    assert same_points(component.goals, GOALS, tol=1e-5)  # MISSION_ITEM carries float32 degrees


def test_upload_a_fence_polygon(component, gcs) -> None:
    seen = upload(gcs, FENCE, 1, mavlink.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION)
    assert mission_ack(seen) == mavlink.MAV_MISSION_ACCEPTED
    assert same_points(component.fence, FENCE) and component.goals == []
    assert component.fence_contains(45.005, 7.005) is True
    assert component.fence_contains(45.02, 7.005) is False
    (count,) = gcs.send(gcs.mav.mission_request_list_encode(SYSID, 191, 1))
    assert count.count == 4 and count.mission_type == 1
    (item,) = gcs.send(gcs.mav.mission_request_int_encode(SYSID, 191, 3, 1))
    assert item.command == mavlink.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION and item.param1 == 4


def test_a_fence_with_a_return_point_sets_the_rally_point(component, gcs) -> None:
    """MAVProxy's fence files may start with a return point (MAV_CMD_NAV_FENCE_RETURN_POINT)."""
    gcs.send(gcs.mav.mission_count_encode(SYSID, 191, 5, 1))
    answers = gcs.send(item_int(gcs, 0, 45.005, 7.005, 1, mavlink.MAV_CMD_NAV_FENCE_RETURN_POINT))
    for seq, (lat, lon) in enumerate(FENCE, start=1):
        answers = gcs.send(item_int(gcs, seq, lat, lon, 1, mavlink.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION, 4.0))
    assert mission_ack(answers) == mavlink.MAV_MISSION_ACCEPTED
    assert same_points(component.fence, FENCE)
    assert (component.params.get("BOB_RALLY_LAT"), component.params.get("BOB_RALLY_LON")) == (45.005, 7.005)


def test_a_dropped_request_is_repeated_and_a_silent_peer_cancelled(component, gcs, clock) -> None:
    answers = gcs.send(gcs.mav.mission_count_encode(SYSID, 191, 3, 0))
    assert of(answers, "MISSION_REQUEST_INT")[0].seq == 0
    gcs.send(item_int(gcs, 0, *GOALS[0]))  # the request for item 1 is "lost": we do not answer it
    clock.advance(0.5)
    component.tick()
    assert of(gcs.answers(), "MISSION_REQUEST_INT") == []
    clock.advance(0.6)
    component.tick()
    answers = gcs.answers()
    again = of(answers, "MISSION_REQUEST_INT") + of(answers, "MISSION_REQUEST")
    assert [r.seq for r in again] == [1] and component.counters.mission_retries == 1
    gcs.send(item_int(gcs, 1, *GOALS[1]))
    assert mission_ack(gcs.send(item_int(gcs, 2, *GOALS[2]))) == mavlink.MAV_MISSION_ACCEPTED
    assert same_points(component.goals, GOALS)
    # Our MISSION_ACK lost: the ground station repeats the last item and is acknowledged again.
    assert mission_ack(gcs.send(item_int(gcs, 2, *GOALS[2]))) == mavlink.MAV_MISSION_ACCEPTED
    # A ground station that goes silent: requests repeated, then the upload is cancelled.
    gcs.send(gcs.mav.mission_count_encode(SYSID, 191, 2, 0))
    for _ in range(component.mission_retries + 1):
        clock.advance(1.1)
        component.tick()
    answers = gcs.answers()
    assert mission_ack(answers) == mavlink.MAV_MISSION_OPERATION_CANCELLED and "upload refused" in texts(answers)
    assert same_points(component.goals, GOALS)  # the old mission is kept


@pytest.mark.parametrize(
    ("mission_type", "items", "result"),
    [
        (0, [dict(command=mavlink.MAV_CMD_DO_SET_SERVO)], mavlink.MAV_MISSION_UNSUPPORTED),
        (0, [dict(frame=mavlink.MAV_FRAME_LOCAL_NED)], mavlink.MAV_MISSION_UNSUPPORTED_FRAME),
        (0, [dict(lat=95.0)], mavlink.MAV_MISSION_INVALID_PARAM5_X),
        (1, [dict(command=5001, param1=3.0)] * 3 + [dict(command=5001, param1=3.0)], mavlink.MAV_MISSION_UNSUPPORTED),
    ],
)
def test_bad_items_are_refused_with_the_right_code(component, gcs, mission_type, items, result) -> None:
    answers = gcs.send(gcs.mav.mission_count_encode(SYSID, 191, len(items), mission_type))
    for seq, fields in enumerate(items):
        kw = dict(lat=45.0 + seq * 1e-4, lon=7.0, command=16, param1=0.0, frame=6) | fields
        answers = gcs.send(item_int(gcs, seq, kw["lat"], kw["lon"], mission_type, kw["command"], kw["param1"],
                                    kw["frame"]))  # fmt: skip
        if of(answers, "MISSION_ACK"):
            break
    assert mission_ack(answers) == result and "refused" in texts(answers)
    assert component.goals == [] and component.fence == [] and component.counters.mission_errors == 1


def test_counts_refused_up_front(component, gcs) -> None:
    assert mission_ack(gcs.send(gcs.mav.mission_count_encode(SYSID, 191, 2, 1))) == mavlink.MAV_MISSION_INVALID
    assert mission_ack(gcs.send(gcs.mav.mission_count_encode(SYSID, 191, 9999, 0))) == mavlink.MAV_MISSION_NO_SPACE
    assert mission_ack(gcs.send(gcs.mav.mission_count_encode(SYSID, 191, 1, 7))) == mavlink.MAV_MISSION_UNSUPPORTED


def test_a_second_uploader_is_told_to_wait(component, gcs) -> None:
    gcs.send(gcs.mav.mission_count_encode(SYSID, 191, 3, 0))
    other = Gcs(component, system_id=250)
    assert mission_ack(other.send(other.mav.mission_count_encode(SYSID, 191, 1, 0))) == mavlink.MAV_MISSION_DENIED


def test_rally_point_and_clear_all(component, gcs) -> None:
    upload(gcs, GOALS)
    upload(gcs, FENCE, 1, mavlink.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION)
    assert mission_ack(upload(gcs, [(45.002, 7.002)], 2, mavlink.MAV_CMD_NAV_RALLY_POINT)) == 0
    assert (component.params.get("BOB_RALLY_LAT"), component.params.get("BOB_RALLY_LON")) == (45.002, 7.002)
    assert mission_ack(gcs.send(gcs.mav.mission_clear_all_encode(SYSID, 191, 1))) == 0
    assert component.fence == [] and same_points(component.goals, GOALS)
    assert mission_ack(gcs.send(gcs.mav.mission_clear_all_encode(SYSID, 191, 255))) == 0
    assert component.goals == [] and component.params.get("BOB_RALLY_LAT") == 0.0


# -- signing ------------------------------------------------------------------------------------------------


def signed_component(clock, wall) -> GcsComponent:
    return GcsComponent(SYSID, ParameterStore(), signing_key=KEY, clock=clock.now, wall_clock=wall)


def test_signing_accepts_signed_and_rejects_the_rest(clock) -> None:
    wall = Wall()
    component = signed_component(clock, wall)
    good = Gcs(component, key=KEY, wall=wall)
    start = good.frame(good.mav.command_long_encode(SYSID, 191, 300, 0, 0, 0, 0, 0, 0, 0, 0))
    assert start[2] & mavlink.MAVLINK_IFLAG_SIGNED
    component.receive(start)
    assert component.behavior_running and ack_of(good.answers(), 300) == 0  # our answer verified with the key

    stop = [0.0] * 7
    unsigned = Gcs(component)  # no key: sends unsigned frames
    assert unsigned.send(unsigned.mav.command_long_encode(SYSID, 191, 193, 0, *stop)) == []
    wrong = Gcs(component, key=OTHER_KEY, wall=wall)
    assert wrong.send(wrong.mav.command_long_encode(SYSID, 191, 193, 0, *stop)) == []
    component.receive(start)  # a replay of a frame already accepted
    tampered = bytearray(good.frame(good.mav.command_long_encode(SYSID, 191, 193, 0, *stop)))
    tampered[-1] ^= 0x01
    component.receive(bytes(tampered))
    assert component.behavior_running and component.outgoing() == []

    c = component.counters
    assert (c.unsigned_rejected, c.bad_signature, c.replay_rejected, c.accepted) == (1, 2, 1, 1)
    assert c.malformed == 0


def test_a_stale_new_stream_is_a_replay(clock) -> None:
    wall = Wall()
    component = signed_component(clock, wall)
    old = Gcs(component, key=KEY, wall=Wall(WALL_T0 - 120))  # signed two minutes ago, never seen before
    assert old.send(old.mav.param_request_list_encode(SYSID, 191)) == []
    assert component.counters.replay_rejected == 1
    recent = Gcs(component, key=KEY, wall=Wall(WALL_T0 - 30), system_id=254)
    assert len(recent.send(recent.mav.param_request_list_encode(SYSID, 191))) == len(component.params)


def test_signing_interoperates_with_pymavlink(clock) -> None:
    """Frames signed by pymavlink (as MAVProxy signs) are accepted; ours pass pymavlink's own check."""
    component = signed_component(clock, time_now := Wall(1.76e9))
    theirs = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
    theirs.signing.secret_key = KEY
    theirs.signing.sign_outgoing = True
    theirs.signing.link_id = 1
    theirs.signing.timestamp = signing_timestamp(time_now())
    component.receive(theirs.command_long_encode(SYSID, 191, 300, 0, 0, 0, 0, 0, 0, 0, 0).pack(theirs))
    assert component.behavior_running
    checker = mavlink.MAVLink(None)
    checker.signing.secret_key = KEY
    (ack,) = [checker.decode(bytearray(f)) for f in component.outgoing() if f[7] == 77]  # COMMAND_ACK id 77
    assert ack.command == 300 and checker.signing.goodsig_count == 1


def test_key_files(tmp_path) -> None:
    raw = tmp_path / "raw.key"
    raw.write_bytes(bytes(range(32)))
    assert load_signing_key(raw) == bytes(range(32))
    phrase = tmp_path / "phrase.key"
    phrase.write_text("correct horse battery staple\n")
    assert load_signing_key(phrase) == hashlib.sha256(b"correct horse battery staple").digest()
    assert passphrase_to_key("correct horse battery staple") == load_signing_key(phrase)
    empty = tmp_path / "empty.key"
    empty.write_text("\n")
    with pytest.raises(SigningKeyError, match="empty"):
        load_signing_key(empty)
    with pytest.raises(SigningKeyError, match=r"missing\.key"):
        load_signing_key(tmp_path / "missing.key")
    with pytest.raises(SigningKeyError, match="32 bytes"):
        GcsComponent(1, ParameterStore(), signing_key=b"short")


# -- robustness ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("key", [None, KEY], ids=["unsigned", "signed"])
def test_noise_and_mutated_frames_never_raise(clock, key) -> None:
    component = GcsComponent(SYSID, ParameterStore(), signing_key=key, clock=clock.now, wall_clock=Wall())
    gcs = Gcs(component, key=key)
    rng = random.Random(7)
    frames = [
        gcs.frame(gcs.mav.param_request_list_encode(SYSID, 191)),
        gcs.frame(gcs.mav.command_long_encode(SYSID, 191, 300, 0, 0, 0, 0, 0, 0, 0, 0)),
        gcs.frame(gcs.mav.mission_count_encode(SYSID, 191, 3, 0)),
        gcs.frame(item_int(gcs, 0, 45.0, 7.0)),
        gcs.frame(gcs.mav.param_set_encode(SYSID, 191, b"BOB_P0_M", 12.0, 9)),
        gcs.frame(gcs.mav.mission_request_int_encode(SYSID, 191, 0, 1)),
    ]
    for _ in range(3000):
        choice = rng.random()
        if choice < 0.3:
            data = bytes(rng.getrandbits(8) for _ in range(rng.randint(0, 300)))
        elif choice < 0.4:
            data = bytes([0xFD]) + bytes(rng.getrandbits(8) for _ in range(rng.randint(0, 60)))
        else:
            data = bytearray(rng.choice(frames))
            for _ in range(rng.randint(1, 4)):
                data[rng.randrange(len(data))] = rng.getrandbits(8)
            cut = rng.randint(1, len(data))
            data = bytes(data[:cut]) if rng.random() < 0.3 else bytes(data)
        component.receive(data, datagram=rng.random() < 0.5)
        component.outgoing()
    c = component.counters
    assert c.malformed > 0 and c.handler_errors == 0
    rejected = c.unsigned_rejected + c.bad_signature + c.replay_rejected
    assert c.frames == c.accepted + c.malformed + c.unknown_id + rejected
    assert (rejected > 0) == (key is not None)
    # Still healthy: good frames after all that are answered, even behind a false start marker.
    component.receive(b"", datagram=True)  # end whatever partial frame the noise left
    component.receive(b"\x00\xfd\x09" + gcs.frame(gcs.mav.param_request_read_encode(SYSID, 191, b"BOB_H", -1)))
    component.receive(gcs.frame(gcs.mav.param_request_read_encode(SYSID, 191, b"BOB_H", -1)), datagram=True)
    assert [m.param_id for m in of(gcs.answers(), "PARAM_VALUE")] == ["BOB_H", "BOB_H"]


def test_frames_split_across_chunks(component, gcs) -> None:
    data = gcs.frame(gcs.mav.param_request_read_encode(SYSID, 191, b"BOB_H", -1)) * 2
    for i in range(len(data)):
        component.receive(data[i : i + 1])
    assert len(of(gcs.answers(), "PARAM_VALUE")) == 2
