"""Arming, modes and failsafes of the simulated autopilot as ArduPilot Rover does them (item 5;
sitl/vehicles/autopilot_safety.py has the source files), on real frames read back by pymavlink."""

from __future__ import annotations

import math

import pytest
from autopilot_helpers import Gcs, acks, of_type, parse, run, texts
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sitl.vehicles.mavlink_vehicle import SimulatedVehicle

m = mavlink
ARM, MODE = m.MAV_CMD_COMPONENT_ARM_DISARM, m.MAV_CMD_DO_SET_MODE
MANUAL, ACRO, STEERING, HOLD, LOITER, GUIDED = 0, 1, 3, 4, 5, 15
NO_SLEW = {"MOT_SLEWRATE": 0}


def _arm(v: SimulatedVehicle, t: float, *extra: float) -> tuple[int, list[str]]:
    (ack,) = acks(v.receive(Gcs().long(ARM, 1, *extra), t))
    return ack.result, texts(parse(v.stream(t)))


def _mode(v: SimulatedVehicle, mode: int, t: float) -> int:
    (ack,) = acks(v.receive(Gcs().long(MODE, m.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, mode), t))
    return ack.result


def test_without_a_fix_arming_is_refused_with_ardupilots_text_when_a_location_is_needed() -> None:
    v = SimulatedVehicle(1, "buoy", 45.0, params={"ARMING_NEED_LOC": 1})
    result, said = _arm(v, 0.0)
    assert result == m.MAV_RESULT_FAILED and not v.armed
    assert "Arm: GPS 1: Bad fix" in said
    run(v, 0.0, 1.0)
    result, said = _arm(v, 1.0)
    assert result == m.MAV_RESULT_ACCEPTED and v.armed and "Throttle armed" in said


def test_rover_arms_in_manual_without_gps_but_not_in_a_position_mode() -> None:
    # AP_Arming_Rover::gps_checks: no location needed by MANUAL unless ARMING_NEED_LOC (default 0).
    assert _arm(SimulatedVehicle(1, "buoy", 45.0), 0.0)[0] == m.MAV_RESULT_ACCEPTED
    v = SimulatedVehicle(1, "buoy", 45.0)
    assert _mode(v, GUIDED, 0.0) == m.MAV_RESULT_ACCEPTED, "disarmed, any mode"
    result, said = _arm(v, 0.0)
    assert result == m.MAV_RESULT_FAILED and "Arm: GPS 1: Bad fix" in said
    assert _arm(v, 0.0, 2989)[0] == m.MAV_RESULT_ACCEPTED and v.armed, "forced"


def test_arm_disarm_answers() -> None:
    v, gcs = SimulatedVehicle(1, "ebot", 0.2), Gcs()
    assert _arm(v, 0.0)[0] == m.MAV_RESULT_ACCEPTED
    assert _arm(v, 0.1)[0] == m.MAV_RESULT_ACCEPTED, "already armed"
    for bad in (2.0, math.nan, -1.0):
        (ack,) = acks(v.receive(gcs.long(ARM, bad), 0.2))
        assert ack.result == m.MAV_RESULT_UNSUPPORTED and v.armed
    (ack,) = acks(v.receive(gcs.long(ARM, 0), 0.3))
    assert ack.result == m.MAV_RESULT_ACCEPTED and not v.armed
    assert "Throttle disarmed" in texts(parse(v.stream(0.3)))


def test_rc_calibration_checks() -> None:
    v = SimulatedVehicle(1, "buoy", 45.0, params={"RC3_MIN": 1400})
    result, said = _arm(v, 0.0)
    assert result == m.MAV_RESULT_FAILED and "Arm: Throttle radio min too high" in said
    v = SimulatedVehicle(1, "buoy", 45.0, params={"RC6_TRIM": 1000, "RC6_MIN": 1100})
    result, said = _arm(v, 0.0)
    assert result == m.MAV_RESULT_FAILED and "Arm: RC6_MIN is greater than RC6_TRIM" in said
    v = SimulatedVehicle(1, "buoy", 45.0, params={"RC3_MIN": 1400, "ARMING_CHECK": 0})
    assert _arm(v, 0.0)[0] == m.MAV_RESULT_ACCEPTED


def _neutral(t: float) -> bytes:
    return Gcs().override({1: 1500, 3: 1500, 4: 1500})


def test_no_rc_receiver_boots_into_hold_and_arms_after_overrides_arrive() -> None:
    v = SimulatedVehicle(1, "buoy", 45.0, rc_receiver=False, params=NO_SLEW)
    messages = run(v, 0.0, 2.5)
    assert "Radio Failsafe" in texts(messages) and v.mode == HOLD
    assert of_type(messages, "HEARTBEAT")[-1].system_status == m.MAV_STATE_CRITICAL
    result, said = _arm(v, 2.5)
    assert result == m.MAV_RESULT_FAILED and "Arm: Radio failsafe on" in said  # issue 18 item 8
    messages = run(v, 2.5, 4.5, every_step=_neutral)  # two seconds of neutral overrides first
    assert "Radio Failsafe Cleared" in texts(messages)
    assert _arm(v, 4.5)[0] == m.MAV_RESULT_ACCEPTED
    full = Gcs().override({3: 1900})
    v.receive(full, 4.5)
    assert not v.actuator(4.5).any(), "still in HOLD: the overrides do nothing"
    assert _mode(v, MANUAL, 4.6) == m.MAV_RESULT_ACCEPTED
    v.receive(full, 4.6)
    assert v.actuator(4.6)[0] == pytest.approx(45.0)
    # The overrides stop: no new RC input for 0.5 s is a radio failsafe (zero input); FS_TIMEOUT later, HOLD.
    assert v.actuator(5.05)[0] == pytest.approx(45.0)
    assert not v.actuator(5.2).any() and v.mode == MANUAL
    messages = run(v, 5.2, 7.0, gps=False)
    assert v.mode == HOLD and "Radio Failsafe" in texts(messages) and v.armed


def test_fs_action_terminate_disarms_and_nothing_keeps_the_mode() -> None:
    v = SimulatedVehicle(1, "buoy", 45.0, rc_receiver=False, params={"FS_ACTION": 5})
    run(v, 0.0, 1.0, every_step=_neutral)
    _arm(v, 1.0)
    run(v, 1.0, 4.0)
    assert not v.armed
    v = SimulatedVehicle(1, "buoy", 45.0, rc_receiver=False, params={"FS_ACTION": 0})
    run(v, 0.0, 4.0)
    assert v.mode == MANUAL


def test_without_radio_failsafe_and_receiver_the_last_override_sticks() -> None:
    # A boat with no receiver and FS_THR_ENABLE = 0: ArduPilot keeps the last RC input (RC_Channel::update returns
    # early) after RC_OVERRIDE_TIME; shown here so that nobody relies on the override timeout in that setup.
    v = SimulatedVehicle(1, "buoy", 45.0, rc_receiver=False, armed=True, params={"FS_THR_ENABLE": 0, **NO_SLEW})
    v.receive(Gcs().override({3: 1900}), 0.0)
    assert v.actuator(10.0)[0] == pytest.approx(45.0)
    v = SimulatedVehicle(1, "buoy", 45.0, armed=True, params=NO_SLEW)  # with a receiver: its neutral sticks
    v.receive(Gcs().override({3: 1900}), 0.0)
    assert v.actuator(10.0)[0] == 0.0


def test_gcs_failsafe_after_silence_from_mav_gcs_sysid() -> None:
    v = SimulatedVehicle(1, "buoy", 45.0, params={"FS_GCS_ENABLE": 1})
    run(v, 0.0, 10.0)
    assert v.mode == MANUAL, "a GCS never heard cannot be lost"
    messages = run(v, 10.0, 12.0, every_step=lambda t: Gcs().heartbeat())
    messages += run(v, 12.0, 18.0)
    assert v.mode == MANUAL
    messages += run(v, 18.0, 19.0)  # 5 s silence + FS_TIMEOUT 1.5 s
    # Rover's radio check runs first each loop and names the failsafe it finds due (Rover/failsafe.cpp).
    assert v.mode == HOLD and "Radio Failsafe" in texts(messages)
    messages = run(v, 19.0, 20.0, every_step=lambda t: Gcs().heartbeat())
    assert "GCS Failsafe Cleared" in texts(messages) and v.mode == HOLD
    v = SimulatedVehicle(1, "buoy", 45.0, params={"FS_GCS_ENABLE": 1, "FS_THR_ENABLE": 0})
    run(v, 0.0, 1.0, every_step=lambda t: Gcs().heartbeat())
    assert "GCS Failsafe" in texts(run(v, 1.0, 8.0)) and v.mode == HOLD


@pytest.mark.parametrize("mode", [MANUAL, ACRO, STEERING, HOLD, LOITER, GUIDED])
def test_modes_are_accepted_and_reported(mode: int) -> None:
    v = SimulatedVehicle(1, "buoy", 45.0, params={"INITIAL_MODE": HOLD if mode == MANUAL else MANUAL})
    assert _mode(v, mode, 0.0) == m.MAV_RESULT_ACCEPTED
    (hb, *_) = of_type(parse(v.stream(0.0)), "HEARTBEAT")
    assert hb.custom_mode == mode and hb.base_mode & m.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    assert bool(hb.base_mode & m.MAV_MODE_FLAG_MANUAL_INPUT_ENABLED) == (mode in (MANUAL, ACRO, STEERING))
    assert bool(hb.base_mode & m.MAV_MODE_FLAG_GUIDED_ENABLED) == (mode in (LOITER, GUIDED))


@pytest.mark.parametrize(("mode", "drives"), [(MANUAL, True), (ACRO, True), (STEERING, True), (HOLD, False),
                                              (LOITER, False), (GUIDED, False)])  # fmt: skip
def test_only_the_pilot_modes_drive(mode: int, drives: bool) -> None:
    v = SimulatedVehicle(1, "buoy", 45.0, params=NO_SLEW)
    run(v, 0.0, 1.0)
    _arm(v, 1.0)
    assert _mode(v, mode, 1.0) == m.MAV_RESULT_ACCEPTED
    v.receive(Gcs().override({3: 1900}), 1.0)
    assert bool(v.actuator(1.0).any()) == drives


def test_position_modes_need_a_fix_when_armed() -> None:
    v = SimulatedVehicle(1, "buoy", 45.0)
    _arm(v, 0.0)
    assert _mode(v, LOITER, 0.0) == m.MAV_RESULT_FAILED and v.mode == MANUAL
    assert "Flight mode change failed" in texts(parse(v.stream(0.0)))
    run(v, 0.0, 1.0)
    assert _mode(v, LOITER, 1.0) == m.MAV_RESULT_ACCEPTED


@pytest.mark.parametrize(
    ("mode", "text"),
    [
        (2, "No such mode 2"),
        (99, "No such mode 99"),
        (10, "Flight mode change failed"),
        (11, "Flight mode change failed"),
    ],
)
def test_unknown_and_unsimulated_modes(mode: int, text: str) -> None:
    v = SimulatedVehicle(1, "buoy", 45.0)
    assert _mode(v, mode, 0.0) == m.MAV_RESULT_FAILED and v.mode == MANUAL
    assert text in texts(parse(v.stream(0.0)))


def test_set_mode_needs_the_custom_flag_and_the_message_works_too() -> None:
    v, gcs = SimulatedVehicle(1, "buoy", 45.0), Gcs()
    (ack,) = acks(v.receive(gcs.long(MODE, 0, HOLD), 0.0))
    assert ack.result == m.MAV_RESULT_DENIED and v.mode == MANUAL
    assert v.receive(gcs.pack(gcs.mav.set_mode_encode(1, m.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, HOLD)), 0.0) == b""
    assert v.mode == HOLD


def test_prearm_reports_on_request_and_every_30_s() -> None:
    v, gcs = SimulatedVehicle(1, "buoy", 45.0, params={"ARMING_NEED_LOC": 1}), Gcs()
    (ack,) = acks(v.receive(gcs.long(m.MAV_CMD_RUN_PREARM_CHECKS), 0.0))
    said = texts(parse(v.stream(0.0)))
    assert ack.result == m.MAV_RESULT_ACCEPTED and said.count("PreArm: GPS 1: Bad fix") == 2  # boot + request
    reminders = texts(run(v, 0.0, 65.0, gps=False, dt=0.5))
    assert reminders.count("PreArm: GPS 1: Bad fix") == 2  # at 30 s and 60 s
    v.armed = True
    (ack,) = acks(v.receive(gcs.long(m.MAV_CMD_RUN_PREARM_CHECKS), 65.0))
    assert ack.result == m.MAV_RESULT_TEMPORARILY_REJECTED


# SYS_STATUS (present, enabled, health) of ArduPilot's rover-omni3mecanum SITL, disarmed, its EKF settled on GPS
# and its pre-arm checks passing (read on its SERIAL0, 2026-11-27); armed, LOGGING is enabled too.
SETTLED_ROVER_SITL = (0x1331DC2F, 0x1221802F, 0x1331812F)


def _sensors(messages: list) -> tuple[int, int, int]:
    status = of_type(messages, "SYS_STATUS")[-1]
    return (
        status.onboard_control_sensors_present,
        status.onboard_control_sensors_enabled,
        status.onboard_control_sensors_health,
    )


def test_sys_status_reports_sensors_as_rover_sitl_and_the_pre_arm_check_as_arming_would_go() -> None:
    v = SimulatedVehicle(1, "buoy", 45.0)
    assert _sensors(run(v, 0.0, 2.0)) == SETTLED_ROVER_SITL
    assert _arm(v, 2.0)[0] == m.MAV_RESULT_ACCEPTED
    _present, enabled, health = _sensors(run(v, 2.0, 4.0))
    assert enabled == SETTLED_ROVER_SITL[1] | m.MAV_SYS_STATUS_LOGGING and health == SETTLED_ROVER_SITL[2]

    refused = SimulatedVehicle(1, "buoy", 45.0, params={"RC3_MIN": 1400})  # "Throttle radio min too high"
    _present, _enabled, health = _sensors(run(refused, 0.0, 2.0))
    assert health == SETTLED_ROVER_SITL[2] & ~m.MAV_SYS_STATUS_PREARM_CHECK
    assert _arm(refused, 2.0)[0] == m.MAV_RESULT_FAILED

    lost = SimulatedVehicle(1, "buoy", 45.0, params={"ARMING_NEED_LOC": 1})
    _present, enabled, health = _sensors(run(lost, 0.0, 2.0, gps=False))
    assert not enabled & m.MAV_SYS_STATUS_AHRS
    assert not health & (m.MAV_SYS_STATUS_SENSOR_GPS | m.MAV_SYS_STATUS_AHRS | m.MAV_SYS_STATUS_PREARM_CHECK)

    deaf = SimulatedVehicle(1, "buoy", 45.0, rc_receiver=False)  # radio failsafe from boot
    _present, _enabled, health = _sensors(run(deaf, 0.0, 2.0))
    assert not health & (m.MAV_SYS_STATUS_SENSOR_RC_RECEIVER | m.MAV_SYS_STATUS_PREARM_CHECK)
