"""The autonomy's side of an ArduPilot autopilot: RC scaling, the profile read from parameters, requests and the
start-up, checked on real encoded bytes (pymavlink's parser on the other end)."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from bob_autonomy.control.velocity_control import BuoyModel
from bob_autonomy.onboard.autopilot import BUOY, EBOT, MOTORBOAT, AutopilotProfile, AutopilotSession
from bob_autonomy.onboard.autopilot_start import AutopilotStarter, AutopilotStartError, StartOptions
from firmware_bridge.commands import Encoder
from firmware_bridge.rc_channels import RcChannelRange, RcMap, ResolutionCarry
from sitl.vehicles.mavlink_vehicle import SimulatedVehicle


def _parse(data: bytes) -> list:
    parser = mavlink.MAVLink(None)
    parser.robust_parsing = True
    return [m for m in parser.parse_buffer(data) or []]


# -- RC scaling ------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "calibration",
    [
        RcChannelRange(),
        RcChannelRange(1000, 1500, 2000, 30),  # SITL's rover.parm
        RcChannelRange(982, 1494, 2006, 10, reversed=True),
        RcChannelRange(1100, 1520, 1900, 0),
    ],
)
def test_pwm_for_is_the_inverse_of_ardupilot_scaling(calibration: RcChannelRange) -> None:
    for u in np.linspace(-1.0, 1.0, 401):
        pwm = calibration.pwm_for(u)
        assert calibration.min_us <= pwm <= calibration.max_us
        # one microsecond is the resolution: the read-back is within one step of the wish
        step = 1.0 / min(calibration.max_us - calibration.trim_us, calibration.trim_us - calibration.min_us) * 1.2
        assert calibration.value_of(pwm) == pytest.approx(u, abs=step + 0.02)
    assert calibration.pwm_for(0.0) == calibration.trim_us
    assert calibration.pwm_for(math.nan) == calibration.trim_us
    assert calibration.value_of(calibration.trim_us) == 0.0


def test_full_throttle_is_full_scale_on_a_1000_2000_channel() -> None:
    # Issue #18: a fixed 1900 us was read by SITL's 1000-2000 calibration as 78 % throttle.
    sitl = RcChannelRange(1000, 1500, 2000, 30)
    assert sitl.pwm_for(1.0) == 2000 and sitl.value_of(2000) == 1.0
    assert sitl.value_of(1900) == pytest.approx((1900 - 1530) / (2000 - 1530))
    assert sitl.pwm_for(0.01) > 1530  # just past the dead zone: a small wish is not swallowed by it


def test_rc_map_problems_name_the_parameter() -> None:
    assert RcMap().problem() is None
    assert "share a channel" in RcMap(1, 1, 4).problem()
    assert "channels 1-8" in RcMap(1, 3, 12).problem()
    bad = RcMap(1, 3, 4, ((3, RcChannelRange(1500, 1500, 2000)),))
    assert "throttle (RCMAP_THROTTLE) channel 3" in bad.problem()


# -- the profile -------------------------------------------------------------------------------------------


def test_a_buoy_on_a_motorboat_frame_is_refused_with_what_to_change() -> None:
    motorboat = AutopilotProfile({"FRAME_CLASS": 2, "FRAME_TYPE": 0})
    (problem,) = motorboat.problems(BUOY)
    assert "cannot move sideways" in problem and "FRAME_CLASS=2 (boat)" in problem
    assert motorboat.problems(EBOT) == []
    assert AutopilotProfile({"FRAME_CLASS": 1, "FRAME_TYPE": 4}).problems(BUOY) == []


def test_override_time_and_steer_type_problems_and_warnings() -> None:
    assert any("RC_OVERRIDE_TIME is 0" in p for p in AutopilotProfile({"RC_OVERRIDE_TIME": 0}).problems(EBOT))
    assert any("two paddles" in p for p in AutopilotProfile({"PILOT_STEER_TYPE": 1}).problems(EBOT))
    never = AutopilotProfile({"RC_OVERRIDE_TIME": -1})
    assert any("never lapse" in w for w in never.warnings(0.1))
    assert AutopilotProfile({"RC_OVERRIDE_TIME": 3}).warnings(0.1) == []


def test_the_gps_lag_from_gps1_delay_ms_or_its_older_name() -> None:
    assert AutopilotProfile({"GPS1_DELAY_MS": 120, "GPS_DELAY_MS": 50}).gps_lag_s == pytest.approx(0.12)
    assert AutopilotProfile({"GPS_DELAY_MS": 50}).gps_lag_s == pytest.approx(0.05)  # before ArduPilot 4.6
    for unknown in ({}, {"GPS1_DELAY_MS": 0}, {"GPS1_DELAY_MS": math.nan}):  # 0: the GPS type's default, unsaid
        assert AutopilotProfile(unknown).gps_lag_s is None
    assert AutopilotProfile({"GPS1_DELAY_MS": 5000}).gps_lag_s == 1.0  # MAX_GPS_LAG_S


def test_the_gps_antenna_offset_is_gps1_pos_less_ins_pos1_as_ardupilots_ekf_takes_it() -> None:
    mast = {"GPS1_POS_X": 0.5, "GPS1_POS_Y": 0.0, "GPS1_POS_Z": -1.5, "INS_POS1_X": 0.1, "INS_POS1_Z": 0.25}
    assert AutopilotProfile(mast).gps_antenna_m == pytest.approx((0.4, 0.0, -1.75))
    older = {"GPS_POS1_X": 0.2, "GPS_POS1_Y": -0.1, "GPS_POS1_Z": 0.0}  # before ArduPilot 4.6
    assert AutopilotProfile(older).gps_antenna_m == pytest.approx((0.2, -0.1, 0.0))
    level = {f"GPS1_POS_{a}": 0.0 for a in "XYZ"}
    for none in ({}, level, {"GPS1_POS_X": 1.0}, {**level, "GPS1_POS_Z": math.nan}):  # unread, zero, partial, NaN
        assert AutopilotProfile(none).gps_antenna_m is None
    far = AutopilotProfile({**level, "GPS1_POS_Z": -25.0})  # centimetres typed as metres, say
    assert far.gps_antenna_m is None
    assert any("GPS1_POS_X/Y/Z or INS_POS1_X/Y/Z is over 5 m" in w for w in far.warnings(0.1))
    assert not any("GPS1_POS" in w for w in AutopilotProfile(mast).warnings(0.1))


def test_gcs_id_top_speed_and_rc_map_from_parameters() -> None:
    p = AutopilotProfile(
        {
            "MAV_GCS_SYSID": 250,
            "SYSID_MYGCS": 7,
            "CRUISE_SPEED": 2.0,
            "CRUISE_THROTTLE": 25,
            "RCMAP_ROLL": 2,
            "RCMAP_THROTTLE": 1,
            "RCMAP_YAW": 5,
            "RC1_MIN": 1000,
            "RC1_MAX": 2000,
        }
    )
    assert p.gcs_system_id == 250  # the current name wins; SYSID_MYGCS is for older firmware
    assert AutopilotProfile({"SYSID_MYGCS": 7}).gcs_system_id == 7
    assert p.top_speed_mps == pytest.approx(8.0)  # CRUISE_SPEED / CRUISE_THROTTLE %
    assert AutopilotProfile({"SPEED_MAX": 3.5, "CRUISE_SPEED": 2}).top_speed_mps == 3.5
    m = p.rc_map
    assert (m.steering, m.throttle, m.lateral) == (2, 1, 5)
    assert m.range_of(1) == RcChannelRange(1000, 1500, 2000, 30)


# -- bytes out -------------------------------------------------------------------------------------------


def _session(kind: str = BUOY, **params: float) -> AutopilotSession:
    s = AutopilotSession(3, kind, Encoder(), clock=lambda: 10.0)
    s.params.update(params)
    s.learn()
    return s


def test_override_goes_to_the_mapped_channels_from_the_gcs_id() -> None:
    s = _session(MAV_GCS_SYSID=250, RCMAP_ROLL=1, RCMAP_THROTTLE=3, RCMAP_YAW=4, FRAME_CLASS=2, FRAME_TYPE=1)
    (msg,) = _parse(s.override(0.5, 1.0, -1.0))
    assert msg.get_type() == "RC_CHANNELS_OVERRIDE" and msg.get_srcSystem() == 250
    assert (msg.chan1_raw, msg.chan3_raw, msg.chan4_raw) == (1715, 1900, 1100)
    assert msg.chan2_raw == 65535  # untouched channels are left to the receiver


def test_a_parameter_a_ground_station_changes_while_driving_is_followed_by_the_next_override() -> None:
    """ArduPilot sends a parameter's new value to every link when anyone sets it (GCS::send_parameter_value): the
    session learns its profile again, so the next override is made with the new calibration and GCS id, and
    the change is listed for the vessel to say. A repeat of a value, or a parameter never read, changes nothing;
    nor do the statistics ArduPilot itself sets and sends every 30 s (STAT_RUNTIME, heard before the profile was
    learned: found on ArduPilot's SITL, where the vessel said "STAT_RUNTIME changed (by a ground station?)").
    Before, the profile was learned once: overrides kept the old trim (the boat drove at neutral stick)."""
    s = _session(
        MAV_GCS_SYSID=250, RC3_MIN=1100, RC3_TRIM=1500, RC3_MAX=1900, FRAME_CLASS=2, FRAME_TYPE=1, STAT_RUNTIME=30
    )
    autopilot = mavlink.MAVLink(None, srcSystem=3, srcComponent=1)
    changes = (("RC3_MIN", 1100.0), ("RC3_TRIM", 1600.0), ("STAT_RUNTIME", 61.0), ("MAV_GCS_SYSID", 251.0))
    for name, value in (*changes, ("NOT_READ", 2.0)):
        for decoded in _parse(autopilot.param_value_encode(name.encode(), value, 9, 900, 0).pack(autopilot)):
            s.handle(decoded)
    assert s.param_changes == [("RC3_TRIM", 1500.0, 1600.0), ("MAV_GCS_SYSID", 250.0, 251.0)]
    (msg,) = _parse(s.override(0.0, 0.0, 0.0))
    assert msg.chan3_raw == 1600 and msg.get_srcSystem() == 251
    (msg,) = _parse(s.override(0.0, 1.0, 0.0))
    assert msg.chan3_raw == 1900


@pytest.mark.parametrize(
    ("frame", "steer_type", "sent"),
    [
        ({"FRAME_TYPE": 0}, 0, 0.5),  # steering output: get_pilot_input and output_regular both flip it
        ({"FRAME_TYPE": 0}, 2, 0.5),
        ({"FRAME_TYPE": 0}, 3, -0.5),  # output_regular alone flips it
        ({"FRAME_TYPE": 0, "SERVO1_FUNCTION": 73, "SERVO3_FUNCTION": 74}, 0, -0.5),  # skid-steer: the first alone
        ({"FRAME_TYPE": 0, "SERVO1_FUNCTION": 73, "SERVO3_FUNCTION": 74}, 3, 0.5),
        ({"FRAME_TYPE": 1}, 0, -0.5),  # omni: get_pilot_input alone
        ({"FRAME_TYPE": 0, "SERVO5_FUNCTION": 73, "SERVO6_FUNCTION": 74}, 0, -0.5),  # skid-steer on any outputs
        ({"FRAME_TYPE": 0, "SERVO30_FUNCTION": 74, "SERVO2_FUNCTION": 73}, 0, -0.5),
        ({"FRAME_TYPE": 0, "SERVO1_FUNCTION": 73}, 0, 0.5),  # throttle left alone is no skid steering
    ],
)
def test_steering_is_flipped_in_reverse_where_ardupilot_flips_it_once(frame: dict, steer_type: int, sent: float):
    """Astern (throttle -50 %), a steering of 0.5 is sent so that the frame's steering comes out as 0.5."""
    session = _session(MOTORBOAT, PILOT_STEER_TYPE=steer_type, FRAME_CLASS=2, **frame)
    (msg,) = _parse(session.override(0.5, -0.5))
    assert session.profile.rc_map.range_of(1).value_of(msg.chan1_raw) == pytest.approx(sent, abs=0.01)


SITL_RC = {"RC1_MIN": 1000, "RC1_MAX": 2000, "RC3_MIN": 1000, "RC3_MAX": 2000}  # SITL's rover.parm


@pytest.mark.parametrize("throttle", [-0.004, -0.0064, -0.009, -0.012, -0.3, 0.004, 0.0064, 0.3, -1.0])
def test_a_small_astern_throttle_keeps_the_rudder_the_vessel_meant(throttle: float) -> None:
    """ArduPilot keeps the throttle it reads as an integer percent, truncated (RC_Channel::control_in, int16_t), and
    flips the steering in reverse only when that integer is negative (Rover/mode.cpp get_pilot_input). ArduPilot's
    own SITL motorboat, sent -0.64 % (1467 us) with the steering negated, read 0 %, did not negate it back, steered
    the other way and sat still for a whole leg. Through real bytes, the simulated autopilot (its own model of
    control_in) applies the rudder the vessel meant and the throttle to the nearest whole percent."""
    session = _session(MOTORBOAT, FRAME_CLASS=2, FRAME_TYPE=0, PILOT_STEER_TYPE=0, **SITL_RC)
    vehicle = SimulatedVehicle(3, MOTORBOAT, 1.0, armed=True, params={"MOT_SLEWRATE": 0, **SITL_RC})
    vehicle.receive(session.override(0.5, throttle), 0.0)
    applied_throttle, rudder = vehicle.actuator(0.0)
    assert rudder == pytest.approx(0.5, abs=1e-3)
    assert applied_throttle == pytest.approx(math.copysign(math.floor(abs(throttle) * 100 + 0.5), throttle) / 100)


@pytest.mark.parametrize("expo", [0.0, 0.4, 0.9, -0.5])
@pytest.mark.parametrize("throttle", [0.3, -0.3])
def test_the_rudder_is_the_one_asked_for_under_the_autopilots_steering_expo(expo: float, throttle: float) -> None:
    """In MANUAL ArduPilot shapes the steering with MANUAL_STR_EXPO (Rover/mode_manual.cpp, input_expo): at 0.4 a
    stick at 0.5 turns the rudder 0.375. The vessel sends the inverse, so through real bytes the simulated
    autopilot's rudder is the one asked for, ahead and astern; a vessel that ignored the expo would not be."""
    params = {"MANUAL_STR_EXPO": expo, **SITL_RC}
    session = _session(MOTORBOAT, FRAME_CLASS=2, FRAME_TYPE=0, PILOT_STEER_TYPE=0, **params)
    vehicle = SimulatedVehicle(3, MOTORBOAT, 1.0, armed=True, params={"MOT_SLEWRATE": 0, **params})
    unaware = _session(MOTORBOAT, FRAME_CLASS=2, FRAME_TYPE=0, PILOT_STEER_TYPE=0, **SITL_RC)
    pwm_step = 0.002 * max(1.0 / (1.0 - expo), 1.0 - expo)  # 1 us of 500, times the expo's steepest slope
    for steering in (-1.0, -0.5, -0.1, 0.02, 0.25, 0.5, 0.8, 1.0):
        vehicle.receive(session.override(steering, throttle), 0.0)
        assert vehicle.actuator(0.0)[1] == pytest.approx(steering, abs=pwm_step)
        vehicle.receive(unaware.override(steering, throttle), 0.0)
        if expo != 0.0 and 0.0 < abs(steering) < 1.0:
            assert abs(vehicle.actuator(0.0)[1] - steering) > 0.05 * abs(steering)


def test_steering_speed_scaling_in_manual_is_a_warning_with_what_to_change() -> None:
    """MANUAL_OPTIONS bit 0 scales the steering with the autopilot's speed and flips it on that speed's sign
    (AP_MotorsUGV::output_regular with _scale_steering): not what the vessel asks for, so it says so."""
    quiet = AutopilotProfile({"FRAME_CLASS": 2, "FRAME_TYPE": 0, "FS_GCS_ENABLE": 1, "MANUAL_OPTIONS": 0})
    scaled = AutopilotProfile({"FRAME_CLASS": 2, "FRAME_TYPE": 0, "FS_GCS_ENABLE": 1, "MANUAL_OPTIONS": 3})
    assert quiet.warnings(0.1) == []
    (text,) = scaled.warnings(0.1)
    assert "MANUAL_OPTIONS" in text and "clear bit 0" in text


SLEW_RATES = [(None, 1.0), (math.nan, 1.0), (100, 1.0), (250, 2.5), (0, 0.0), (-5, 0.0)]


@pytest.mark.parametrize(("slew_rate", "per_s"), SLEW_RATES)
def test_the_throttle_slew_is_mot_slewrate_per_second(slew_rate: float | None, per_s: float) -> None:
    """AP_MotorsUGV::get_slew_limited_throttle moves the output at most MOT_SLEWRATE % of full throttle per s (0 or
    less: no limit); ArduPilot's default, 100, when the parameter was not read."""
    values = {} if slew_rate is None else {"MOT_SLEWRATE": slew_rate}
    assert AutopilotProfile(values).throttle_slew_per_s == per_s


@pytest.mark.parametrize(("thr_max", "ceiling"), [(None, 1.0), (100, 1.0), (50, 0.5), (10, 0.3), (150, 1.0)])
def test_the_throttle_ceiling_is_mot_thr_max_as_ardupilot_keeps_it(thr_max: float | None, ceiling: float) -> None:
    """AP_MotorsUGV::sanity_check_parameters keeps MOT_THR_MAX within 30-100 %; the demand is clipped to it."""
    values = {} if thr_max is None else {"MOT_THR_MAX": thr_max}
    assert AutopilotProfile(values).throttle_ceiling == ceiling


def test_a_full_scale_unit_is_the_nearest_whole_unit_the_autopilot_reads() -> None:
    """pwm_for(value, full_scale) is read back (control_in) as value x full_scale rounded to the nearest unit, on
    every calibration, both ways, for throttle (100) and steering (4500: the nearer of the PWMs about it)."""
    for calibration in (
        RcChannelRange(),
        RcChannelRange(1000, 1500, 2000, 30),
        RcChannelRange(982, 1494, 2006, 10, reversed=True),
    ):
        for value in np.linspace(-1.0, 1.0, 801):
            pwm = calibration.pwm_for(value, 100)
            assert calibration.control_in(pwm, 100) == math.copysign(math.floor(abs(value) * 100 + 0.5), value)
            steer = calibration.pwm_for(value, 4500)
            best = min(abs(calibration.control_in(p, 4500) - value * 4500) for p in range(steer - 3, steer + 4))
            assert abs(calibration.control_in(steer, 4500) - value * 4500) == best


def test_lateral_stays_at_trim_on_a_frame_that_cannot_use_it() -> None:
    s = _session(EBOT, FRAME_CLASS=1, FRAME_TYPE=0)
    (msg,) = _parse(s.override(0.0, 0.2, 1.0))
    assert msg.chan4_raw == 1500


def test_stream_requests_ask_each_message_at_its_rate() -> None:
    s = _session()
    asked = {}
    for msg in _parse(b"".join(s.stream_requests())):
        assert msg.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL and msg.target_component == 1
        asked[int(msg.param1)] = msg.param2
    assert asked[mavlink.MAVLINK_MSG_ID_GPS_RAW_INT] == pytest.approx(1e5)  # 10 Hz
    assert asked[mavlink.MAVLINK_MSG_ID_SCALED_IMU] == pytest.approx(4e4)  # 25 Hz: ArduPilot refuses 50 Hz
    groups = {m.req_stream_id: m.req_message_rate for m in _parse(b"".join(s.stream_fallback_requests()))}
    assert groups[mavlink.MAV_DATA_STREAM_EXTENDED_STATUS] == 10 and groups[mavlink.MAV_DATA_STREAM_RAW_SENSORS] == 25


def test_slow_streams_are_reported_once_until_they_recover() -> None:
    now = [0.0]
    s = AutopilotSession(1, BUOY, Encoder(), clock=lambda: now[0])
    s.stream_requests()
    autopilot = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    for k in range(60):  # 1 Hz GPS for 60 s, as Rover's default SRn rates give
        now[0] = float(k)
        s.handle(_parse(autopilot.gps_raw_int_encode(0, 3, 0, 0, 0, 0, 0, 0, 0, 10).pack(autopilot))[0])
    warnings = s.slow_streams(now[0])
    assert any(w.startswith("GPS_RAW_INT arrives at 1.0 Hz") for w in warnings)
    assert not any("GPS_RAW_INT" in w for w in s.slow_streams(now[0]))


def test_overrides_the_autopilot_does_not_apply_are_noticed() -> None:
    s = _session()
    sent = _parse(s.override(0.0, 0.5, 0.0))[0]
    autopilot = mavlink.MAVLink(None, srcSystem=3, srcComponent=1)
    applied = [sent.chan1_raw, 1500, sent.chan3_raw, sent.chan4_raw] + [1500] * 14
    s.handle(_parse(autopilot.rc_channels_encode(0, 8, *applied, 255).pack(autopilot))[0])
    assert not s.ignoring_overrides(10.0)
    neutral = [1500] * 18
    s.handle(_parse(autopilot.rc_channels_encode(0, 8, *neutral, 255).pack(autopilot))[0])
    assert s.ignoring_overrides(10.0)


def test_an_override_echoed_late_by_a_slow_link_is_still_taken_for_applied() -> None:
    """Over a link that delivers 2.2 s late, the RC_CHANNELS the autopilot sends shows the override we sent 2.2 s
    ago, while we have sent others since: that is an autopilot taking our overrides. One showing none of them, or
    only one older than the look-back, is not."""
    now = [0.0]
    s = AutopilotSession(3, BUOY, Encoder(), clock=lambda: now[0])
    s.learn()
    sent = []
    for k in range(40):  # 4 s of commands at 10 Hz, each throttle a little different
        now[0] = 0.1 * k
        sent.append(_parse(s.override(0.0, 0.2 + 0.01 * k, 0.0))[0])
    autopilot = mavlink.MAVLink(None, srcSystem=3, srcComponent=1)

    def report(msg) -> None:
        applied = [msg.chan1_raw, 1500, msg.chan3_raw, msg.chan4_raw] + [1500] * 14
        s.handle(_parse(autopilot.rc_channels_encode(0, 8, *applied, 255).pack(autopilot))[0])

    report(sent[17])  # at t = 3.9 s, the override of t = 1.7 s
    assert not s.ignoring_overrides(now[0])
    assert s.ignoring_overrides(now[0], lag_s=0.0)  # the look-back of old: an autopilot that ignores us
    s.handle(_parse(autopilot.rc_channels_encode(0, 8, *([1500] * 18), 255).pack(autopilot))[0])
    assert s.ignoring_overrides(now[0])  # neutral, which we never sent
    now[0] = 8.0
    for _ in range(3):
        _parse(s.override(0.0, 0.9, 0.0))
    report(sent[5])  # the override of t = 0.5 s, 7.5 s ago: older than 1.5 + 5 s
    assert s.ignoring_overrides(now[0])


def test_messages_from_another_component_are_not_the_autopilots() -> None:
    s = _session()
    other = mavlink.MAVLink(None, srcSystem=3, srcComponent=191)
    s.handle(_parse(other.heartbeat_encode(10, 3, 0, 4, 4).pack(other))[0])
    assert s.custom_mode is None


def test_model_for_a_faster_vehicle_reaches_its_top_speed() -> None:
    m = BuoyModel.for_top_speed(9.0)
    drag = m.linear_drag_n_per_mps * 9.0 + m.quadratic_drag_n_per_mps2 * 81.0
    assert drag == pytest.approx(m.max_thrust_n)
    with pytest.raises(ValueError, match="top speed"):
        BuoyModel.for_top_speed(math.nan)


# -- the start-up against a scripted autopilot -------------------------------------------------------------


class ScriptedAutopilot:
    """Just enough of an autopilot to walk the start-up: heartbeats, parameters, a mode, a GPS fix, and arming
    refused `refusals` times with a PreArm text before it is accepted."""

    def __init__(self, session: AutopilotSession, params: dict[str, float], refusals: int, fix_type: int = 3):
        self.session, self.params, self.refusals, self.fix_type = session, params, refusals, fix_type
        self.mav = mavlink.MAVLink(None, srcSystem=session.target_system, srcComponent=1)
        self.mode, self.armed, self.inbox = 0, False, bytearray()
        self.overrides = 0
        self.arm_commands = 0
        self.arm_lag_s = 0.0  # wall s before an arming (its ACK and the armed HEARTBEAT) is heard: a slow link
        self.delayed: list[tuple[float, object]] = []
        self.lose: dict[str, int] = {}  # how many of the first messages of each name a noisy line loses
        self.intervals: dict[int, float] = {}  # message id: interval (us) set by SET_MESSAGE_INTERVAL
        self.group_requests = 0  # REQUEST_DATA_STREAMs heard
        self.ground_station_arming = False  # a ground station on the same link (a router) arms it: every pump

    def send(self, data: bytes) -> None:
        self.inbox += data

    def _out(self, msg) -> None:
        for decoded in _parse(msg.pack(self.mav)):
            self.session.handle(decoded)

    def pump(self, _wait_s: float) -> None:
        due = [msg for at, msg in self.delayed if at <= time.monotonic()]
        self.delayed = [(at, msg) for at, msg in self.delayed if at > time.monotonic()]
        for msg in due:
            self.armed = True
            self._out(msg)
        flags = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (mavlink.MAV_MODE_FLAG_SAFETY_ARMED if self.armed else 0)
        self._out(self.mav.heartbeat_encode(10, 3, flags, self.mode, 4))
        self._out(self.mav.gps_raw_int_encode(0, self.fix_type, 0, 0, 0, 0, 0, 0, 0, 9))
        if self.ground_station_arming:  # its answer, to (255, 190), as a router passes it to every output
            arm = mavlink.MAV_CMD_COMPONENT_ARM_DISARM
            self._out(self.mav.command_ack_encode(arm, mavlink.MAV_RESULT_ACCEPTED, 0, 0, 255, 190))
        for msg in _parse(bytes(self.inbox)):
            name = msg.get_type()
            sender = (msg.get_srcSystem(), msg.get_srcComponent())  # ArduPilot addresses its COMMAND_ACK to it
            if name == "COMMAND_LONG" and msg.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
                name = "SET_MESSAGE_INTERVAL"
            if self.lose.get(name, 0) > 0:
                self.lose[name] -= 1
                continue
            if name == "SET_MESSAGE_INTERVAL":
                self.intervals[int(msg.param1)] = msg.param2
                self._out(self.mav.command_ack_encode(msg.command, 0, 0, 0, *sender))
            elif name == "REQUEST_DATA_STREAM":
                self.group_requests += 1
            elif name == "PARAM_REQUEST_READ":
                pid = msg.param_id
                if pid in self.params:
                    self._out(self.mav.param_value_encode(pid.encode(), self.params[pid], 9, 1, 0))
            elif name == "RC_CHANNELS_OVERRIDE":
                self.overrides += 1
            elif name == "COMMAND_LONG" and msg.command == mavlink.MAV_CMD_DO_SET_MODE:
                self.mode = int(msg.param2)
                self._out(self.mav.command_ack_encode(msg.command, 0, 0, 0, *sender))
            elif name == "COMMAND_LONG" and msg.command == mavlink.MAV_CMD_COMPONENT_ARM_DISARM:
                self.arm_commands += 1
                if self.arm_lag_s and not self.refusals:
                    ack = self.mav.command_ack_encode(msg.command, 0, 0, 0, *sender)
                    self.delayed.append((time.monotonic() + self.arm_lag_s, ack))
                elif self.refusals > 0:
                    self.refusals -= 1
                    self._out(self.mav.command_ack_encode(msg.command, mavlink.MAV_RESULT_FAILED, 0, 0, *sender))
                    self._out(self.mav.statustext_encode(3, b"PreArm: GPS not healthy"))
                else:
                    self.armed = True
                    self._out(self.mav.command_ack_encode(msg.command, 0, 0, 0, *sender))
            elif name == "COMMAND_LONG":
                self._out(self.mav.command_ack_encode(msg.command, 0))  # unaddressed, as MAVLink 1 firmware
        self.inbox.clear()


def _start(params: dict[str, float], refusals: int = 0, kind: str = BUOY, arm_lag_s: float = 0.0, **options) -> tuple:
    session = AutopilotSession(1, kind, Encoder(), clock=time.monotonic)
    autopilot = ScriptedAutopilot(session, params, refusals)
    autopilot.arm_lag_s = arm_lag_s
    said: list[str] = []
    opts = StartOptions(**{"neutral_lead_s": 0.05, "param_timeout_s": 0.3, "arm_timeout_s": 6.0, **options})
    notify = lambda _severity, text: said.append(text)  # noqa: E731
    starter = AutopilotStarter(session, autopilot.send, autopilot.pump, lambda: False, notify, opts)
    return starter, autopilot, said


OMNI = {"FRAME_CLASS": 2.0, "FRAME_TYPE": 1.0, "RC_OVERRIDE_TIME": 3.0, "FS_GCS_ENABLE": 1.0, "MAV_GCS_SYSID": 254.0}


def test_start_up_reads_the_profile_sets_manual_and_arms_after_refusals() -> None:
    starter, autopilot, said = _start(OMNI, refusals=2)
    profile = starter.run()
    assert profile.lateral_capable and profile.gcs_system_id == 254
    assert autopilot.armed and autopilot.mode == 0 and autopilot.overrides > 0
    refusals = [t for t in said if t.startswith("autopilot refused to arm")]
    assert refusals == ["autopilot refused to arm (failed (its checks did not pass)): PreArm: GPS not healthy"] * 2


def test_start_up_gives_up_with_the_autopilots_reasons() -> None:
    starter, autopilot, _said = _start(OMNI, refusals=99)
    with pytest.raises(AutopilotStartError, match=r"would not arm within 6 s: PreArm: GPS not healthy"):
        starter.run()
    assert not autopilot.armed


@pytest.mark.parametrize(
    "answer_s, lag_s, commands, complaints", [(3.0, 1.5, 1, 0), (0.5, 1.3, 1, 1), (1.0, 2.8, 2, 1)]
)
def test_start_up_arms_over_a_link_that_answers_late(answer_s: float, lag_s: float, commands: int, complaints: int):
    """An arming heard 1.5 s later is waited for (the 45-vessel process fleet on 2 cores lagged 3 s, and five
    vessels gave up after 60 s of "no answer" when each attempt waited 1 s); one heard after an attempt's wait
    still counts when it comes during the 1 s back-off (1.3 s, the back-off runs 0.8-1.8 s) or the next attempt
    (2.8 s, which waits 2.3-3.3 s), and is not asked for again. Each lag sits 0.5 s from either edge of its
    window, so a loaded CI machine's late wake-ups do not move it into the next one."""
    starter, autopilot, said = _start(OMNI, arm_lag_s=lag_s, arm_answer_s=answer_s)
    assert starter.run() is not None
    assert autopilot.armed and autopilot.arm_commands == commands
    expected = f"autopilot refused to arm (no answer within {answer_s:g} s)"
    assert [t for t in said if "refused to arm" in t] == [expected] * complaints


def test_a_ground_stations_arming_answered_on_a_shared_link_is_not_taken_for_ours() -> None:
    """A router (MAVProxy, mavlink-router) passes every autopilot frame to every output, so the vessel hears the
    COMMAND_ACKs ArduPilot addresses to a ground station (target_system, target_component: the sender,
    GCS_Common.cpp handle_command_long). While the autopilot refuses the vessel, a ground station's accepted
    arming must not end the vessel's start-up as armed (the old session took any ARM_DISARM ack)."""
    starter, autopilot, said = _start(OMNI, refusals=99, arm_timeout_s=2.5)
    autopilot.ground_station_arming = True
    with pytest.raises(AutopilotStartError, match=r"would not arm within 2.5 s: PreArm: GPS not healthy"):
        starter.run()
    assert not autopilot.armed and autopilot.arm_commands >= 2
    assert starter.session.acks_for_others > 0
    refusals = [t for t in said if "refused to arm" in t]
    assert refusals and all(t.startswith("autopilot refused to arm (failed") for t in refusals)


def test_start_up_asks_again_for_what_a_noisy_line_lost() -> None:
    """Requests lost on the way (a noisy serial line) are sent again: every message rate and every parameter
    arrive, and no stream group is asked for (ArduPilot would set every message of the group to its rate)."""
    starter, autopilot, said = _start(OMNI)
    autopilot.lose = {"SET_MESSAGE_INTERVAL": 2, "PARAM_REQUEST_READ": 3}
    profile = starter.run()
    assert set(autopilot.intervals) == set(starter.session.streams)
    assert autopilot.group_requests == 0
    assert profile.gcs_system_id == 254 and not any("did not report" in t for t in said), said


def test_a_lost_interval_is_asked_again_by_id_and_a_message_without_one_by_its_group() -> None:
    s = _session()
    gps, imu, wheels = (
        mavlink.MAVLINK_MSG_ID_GPS_RAW_INT,
        mavlink.MAVLINK_MSG_ID_SCALED_IMU,
        mavlink.MAVLINK_MSG_ID_WHEEL_DISTANCE,
    )
    s.streams[wheels] = (20.0, 0.0)
    before = _parse(b"".join(s.requests_again([gps, imu, wheels])))  # nothing accepted yet: firmware without it
    groups = {
        mavlink.MAV_DATA_STREAM_EXTENDED_STATUS,
        mavlink.MAV_DATA_STREAM_RAW_SENSORS,
        mavlink.MAV_DATA_STREAM_EXTRA1,
    }
    assert {m.req_stream_id for m in before} == groups
    autopilot = mavlink.MAVLink(None, srcSystem=3, srcComponent=1)
    s.handle(_parse(autopilot.command_ack_encode(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0).pack(autopilot))[0])
    after = _parse(b"".join(s.requests_again([gps, imu, wheels])))
    by_id = {int(m.param1): m.param2 for m in after if m.get_type() == "COMMAND_LONG"}
    assert by_id == {gps: pytest.approx(1e5), imu: pytest.approx(4e4)}
    assert [m.req_stream_id for m in after if m.get_type() == "REQUEST_DATA_STREAM"] == [mavlink.MAV_DATA_STREAM_EXTRA1]


def test_a_stream_slow_while_driving_is_asked_again_by_id_every_5_s() -> None:
    now = [0.0]
    s = AutopilotSession(1, BUOY, Encoder(), clock=lambda: now[0])
    s.stream_requests()
    autopilot = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    s.handle(_parse(autopilot.command_ack_encode(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0).pack(autopilot))[0])
    asked = []
    for k in range(200):  # 20 s of ATTITUDE at 20 Hz; no SCALED_IMU, no GPS_RAW_INT
        now[0] = 0.1 * k
        for _ in range(2):
            s.handle(_parse(autopilot.attitude_encode(0, 0, 0, 0.1, 0, 0, 0).pack(autopilot))[0])
        asked += [(round(now[0], 1), int(m.param1)) for m in _parse(b"".join(s.slow_stream_requests(now[0])))]
    slow = {mavlink.MAVLINK_MSG_ID_GPS_RAW_INT, mavlink.MAVLINK_MSG_ID_SCALED_IMU, mavlink.MAVLINK_MSG_ID_SYS_STATUS}
    assert {m for _t, m in asked} == slow  # those the estimator needs at a rate; not ATTITUDE, which comes
    assert sorted({t for t, _m in asked}) == [5.0, 10.0, 15.0]  # after the 5 s grace, then every 5 s


def test_start_up_refuses_a_buoy_on_a_motorboat() -> None:
    starter, autopilot, _ = _start({**OMNI, "FRAME_TYPE": 0.0})
    with pytest.raises(AutopilotStartError, match="cannot move sideways"):
        starter.run()
    assert not autopilot.armed


# -- the command line --------------------------------------------------------------------------------------


def test_command_line_takes_a_southern_origin_and_the_autopilot_options() -> None:
    from bob_autonomy.cli import _apply_config_file, _join_negative_values, _parser, config_from_args

    argv = ["run", "--vehicle", "tcp:127.0.0.1:5760", "--system-id", "1", "--origin", "-35.36,149.16"]
    argv += ["--behavior", "bob-rule", "--on-stop", "hold", "--force-arm", "--top-speed", "9", "--arm-timeout", "45"]
    config = config_from_args(_apply_config_file(_parser(), _join_negative_values(argv)))
    assert config.origin == (-35.36, 149.16)
    assert config.on_stop == "hold" and config.autopilot.force_arm and config.top_speed_mps == 9.0
    assert config.arm_timeout_s == 45.0
    with pytest.raises(SystemExit):
        _apply_config_file(_parser(), [*argv[:-4], "--on-stop", "sink"])


def test_an_ebot_pipeline_with_a_frame_fuses_gps_fixes() -> None:
    # A rover outdoors without wheel encoders (ArduPilot sends WHEEL_DISTANCE only with WENC_TYPE set): the
    # estimate follows the GPS instead of staying at the start pose (issue #18).
    from bob_autonomy.core.geodesy import LocalFrame
    from bob_autonomy.onboard.pipeline import EbotPipeline
    from firmware_bridge.readings import GpsFix

    frame = LocalFrame(-35.363261, 149.165230)
    pipeline = EbotPipeline(np.zeros((1, 2)), np.zeros(1), 0.3, 1.0, 0.001, estimator="ekf", frame=frame)
    for k in range(40):
        lat, lon = frame.to_geodetic(30.0, -20.0)
        fix = GpsFix(np.array([0]), np.array([0.2 * k]), np.array([lat]), np.array([lon]))
        pipeline.feed([fix])
    np.testing.assert_allclose(pipeline.estimate(8.0).position[0], [30.0, -20.0], atol=1.0)


@pytest.mark.parametrize(("wheel_every", "asked_again"), [(20, True), (1, False)])
def test_messages_the_autopilot_will_not_schedule_are_asked_by_their_stream_group(wheel_every, asked_again) -> None:
    now = [0.0]
    s = AutopilotSession(1, EBOT, Encoder(), clock=lambda: now[0])
    s.stream_requests()
    autopilot = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    for k in range(40):  # 2 s of ATTITUDE at the compass's 10 Hz, WHEEL_DISTANCE at 1 Hz (Rover's default) or 20 Hz
        now[0] = k * 0.05
        if k % 2 == 0:
            s.handle(_parse(autopilot.attitude_encode(0, 0, 0, 0.1, 0, 0, 0).pack(autopilot))[0])
        if k % wheel_every == 0:
            s.handle(_parse(autopilot.wheel_distance_encode(0, 2, [0.0] * 16).pack(autopilot))[0])
    asked = {m.req_stream_id: m.req_message_rate for m in _parse(b"".join(s.lagging_stream_requests(now[0], 2.0)))}
    # WHEEL_DISTANCE is in ArduPilot's EXTRA1 group with ATTITUDE; ATTITUDE limited by its sensor alone is not slow
    assert (asked.get(mavlink.MAV_DATA_STREAM_EXTRA1) == 20) is asked_again


def test_a_diverged_estimate_is_noticed_and_reset() -> None:
    # Issue #18: on a 9 m/s boat the filter lagged, diverged to 2e34 m and the process died. The pipeline now
    # tells a diverged estimate (far from a fresh fix, or non-finite) and starts afresh.
    from bob_autonomy.core.geodesy import LocalFrame
    from bob_autonomy.onboard.pipeline import BuoyPipeline
    from firmware_bridge.readings import GpsFix

    frame = LocalFrame(-35.363261, 149.165230)
    pipeline = BuoyPipeline(1, frame, np.array([45.0]), estimator="ekf")
    lat, lon = frame.to_geodetic(0.0, 0.0)
    pipeline.feed([GpsFix(np.array([0]), np.array([1.0]), np.array([lat]), np.array([lon]))])
    assert not pipeline.diverged(1.0).any()
    pipeline.estimator.x[0, 0:2] = [2e34, -1e30]  # what the field saw
    assert pipeline.diverged(1.5).all()
    pipeline.reset()
    assert pipeline.resets == 1 and not pipeline.diverged(1.5).any()
    pipeline.feed([GpsFix(np.array([0]), np.array([2.0]), np.array([lat]), np.array([lon]))])
    assert np.hypot(*pipeline.estimate(2.0).position[0]) < 1.0


def test_an_ebot_without_wheel_readings_follows_a_moving_gps_fix() -> None:
    # Without encoders nothing predicts the motion: the position variance must grow between fixes, or the
    # filter grows sure of an old position and lags (3.3 m median on ArduPilot's skid-steer SITL before).
    from bob_autonomy.core.geodesy import LocalFrame
    from bob_autonomy.onboard.pipeline import EbotPipeline
    from firmware_bridge.readings import GpsFix

    frame = LocalFrame(-35.363261, 149.165230)
    pipeline = EbotPipeline(np.zeros((1, 2)), np.zeros(1), 0.3, 2.0, 0.001, estimator="ekf", frame=frame)
    errors = []
    for k in range(100):  # 1.5 m/s east, fixes at 5 Hz
        t = 0.2 * k
        lat, lon = frame.to_geodetic(1.5 * t, 0.0)
        pipeline.feed([GpsFix(np.array([0]), np.array([t]), np.array([lat]), np.array([lon]))])
        errors.append(abs(pipeline.estimate(t).position[0, 0] - 1.5 * t))
    assert np.median(errors[20:]) < 1.0


@pytest.mark.parametrize("seed", range(3))
def test_an_ebot_without_wheel_readings_follows_fixes_dated_before_its_compass_readings(seed: int) -> None:
    """As above, as a vessel reads ArduPilot: compass readings (ATTITUDE, 20 Hz) fused at their arrival, each fix
    dated when ArduPilot read it, 77-100 ms before it arrives (firmware_bridge.autopilot_clock). Fused at its own
    time by replay, a fix undid the carry between fixes and the robot was estimated metres behind (on ArduPilot's
    skid-steer SITL it hunted about its goal); taken at the filter's time, carried there at the fixes' velocity,
    it is not."""
    from bob_autonomy.core.geodesy import LocalFrame
    from bob_autonomy.onboard.pipeline import EbotPipeline
    from firmware_bridge.readings import CompassReading, GpsFix

    rng = np.random.default_rng(seed)
    frame = LocalFrame(-35.363261, 149.165230)
    pipeline = EbotPipeline(np.zeros((1, 2)), np.zeros(1), 0.3, 2.0, 0.001, estimator="ekf", frame=frame)
    errors = []
    for k in range(1, 400):  # 1.5 m/s east for 20 s
        t = 0.05 * k
        readings: list[object] = [CompassReading(np.array([0]), np.array([t]), np.array([0.0]))]
        if k % 4 == 0:  # a 5 Hz GPS
            read = t - float(rng.uniform(0.077, 0.1))
            lat, lon = frame.to_geodetic(1.5 * read + 0.3 * rng.standard_normal(), 0.3 * rng.standard_normal())
            readings.append(GpsFix(np.array([0]), np.array([read]), np.array([lat]), np.array([lon])))
        pipeline.feed(readings)
        errors.append(abs(pipeline.estimate(t).position[0, 0] - 1.5 * t))
    assert np.median(errors[100:]) < 0.5, np.median(errors[100:])


def test_a_wish_finer_than_a_percent_is_met_on_average() -> None:
    """ResolutionCarry (error diffusion over whole percent): a steady 0.3 % is 1 % in 3 overrides of 10, where
    rounding alone sends nothing; each value sent is a whole percent; a stop sends 0 and forgets what was owed;
    beyond full scale nothing winds up."""
    carry = ResolutionCarry()
    sent = [carry("throttle", 0.003) for _ in range(1000)]
    assert all(round(v * 100) == v * 100 for v in sent) and set(sent) == {0.0, 0.01}
    assert np.mean(sent) == pytest.approx(0.003, abs=1e-5)
    assert np.mean([carry("lateral", -0.0449) for _ in range(1000)]) == pytest.approx(-0.0449, abs=1e-5)
    assert carry("throttle", 0.0) == 0.0 and carry("throttle", 0.003) == 0.0  # nothing owed after a stop
    saturated = [carry("throttle", 5.0) for _ in range(50)]
    assert set(saturated) == {1.0} and carry("throttle", 0.5) == 0.5  # owed at most half a unit
    session = _session(MOTORBOAT, FRAME_CLASS=2, FRAME_TYPE=0, **SITL_RC)
    vehicle = SimulatedVehicle(3, MOTORBOAT, 1.0, armed=True, params={"MOT_SLEWRATE": 0, **SITL_RC})
    applied = []
    for k in range(200):  # through real bytes: the autopilot applies 0.4 % astern on average, and the rudder meant
        vehicle.receive(session.override(0.5, -0.004), 0.1 * k)
        applied.append(vehicle.actuator(0.1 * k))
    throttle, rudder = np.array(applied).T
    assert np.mean(throttle) == pytest.approx(-0.004, abs=1e-4) and np.allclose(rudder, 0.5, atol=1e-3)


def test_frames_lost_on_the_line_are_counted_from_the_autopilots_sequence_numbers() -> None:
    s = _session()
    autopilot = mavlink.MAVLink(None, srcSystem=3, srcComponent=1)
    frames = []
    for k in range(600):  # the sequence number wraps at 256
        autopilot.seq = k % 256  # as MAVLink.send sets it (pack alone keeps it)
        frames.append(autopilot.heartbeat_encode(10, 3, 0, 0, 4).pack(autopilot))
    for k, frame in enumerate(frames):
        if k % 10 != 3 and k not in (250, 251, 252, 253, 254, 255, 256, 257):  # one in ten lost; 8 across a wrap
            s.handle(_parse(frame)[0])
    assert s.frames_lost == 60 + 8 - 1  # k = 253 is both
    late = _session()
    for k in (0, 1, 3, 2, 4, 5, 7, 9, 8, 10):  # 2 and 8 late, 6 lost
        autopilot.seq = k
        late.handle(_parse(autopilot.heartbeat_encode(10, 3, 0, 0, 4).pack(autopilot))[0])
    assert late.frames_lost == 1
