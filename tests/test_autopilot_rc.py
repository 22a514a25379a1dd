"""Parameters take effect as in ArduPilot Rover (item 3): RC scaling (RCx_MIN/TRIM/MAX/DZ/REVERSED), overrides only
from MAV_GCS_SYSID and only for RC_OVERRIDE_TIME, RCMAP_*, INITIAL_MODE, PILOT_STEER_TYPE, FRAME_TYPE (lateral only
on omni frames), MOT_SLEWRATE; what the vehicle applies is visible in RC_CHANNELS and SERVO_OUTPUT_RAW."""

from __future__ import annotations

import math

import numpy as np
import pytest
from autopilot_helpers import Gcs, of_type, parse
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_bridge.telemetry import TelemetryEncoder
from sitl.vehicles.autopilot_rc import OVERRIDE_CHANNELS, RcInput, scale_angle
from sitl.vehicles.mavlink_vehicle import SimulatedVehicle

m = mavlink
NO_SLEW = {"MOT_SLEWRATE": 0}


def _armed(kind: str = "buoy", **params) -> SimulatedVehicle:
    return SimulatedVehicle(1, kind, 10.0 if kind == "buoy" else 1.0, armed=True, params={**NO_SLEW, **params})


def _drive(v: SimulatedVehicle, channels: dict[int, int], t: float = 0.0, gcs: Gcs | None = None) -> np.ndarray:
    v.receive((gcs or Gcs()).override(channels), t)
    return v.actuator(t)


@pytest.mark.parametrize(
    ("pwm", "calib", "expected"),
    [
        (1900, (1100, 1500, 1900, 30, False), 1.0),
        (1530, (1100, 1500, 1900, 30, False), 0.0),  # inside the dead zone
        (1715, (1100, 1500, 1900, 30, False), 0.5),
        (1285, (1100, 1500, 1900, 30, False), -0.5),
        (1900, (1000, 1500, 2000, 30, False), (1900 - 1530) / (2000 - 1530)),  # SITL's 1000..2000: 78.7 %
        (1510, (1100, 1500, 1900, 0, False), 10 / 400),
        (1900, (1100, 1500, 1900, 30, True), -1.0),
        (2500, (1100, 1500, 1900, 30, False), 1.0),  # clipped to MAX
        (1600, (1100, 1600, 1900, 30, False), 0.0),  # TRIM moved
    ],
)
def test_scaling_is_rc_channels_pwm_to_angle(pwm, calib, expected) -> None:
    assert scale_angle(pwm, *calib) == pytest.approx(expected)


@pytest.mark.parametrize(
    ("pwm", "calib", "full_scale", "expected"),
    [
        (1900, (1000, 1500, 2000, 30, False), 100, 0.78),  # 78.7 % kept as the integer 78
        (1534, (1000, 1500, 2000, 30, False), 100, 0.0),  # 0.85 %: under 1 %, read as 0
        (1535, (1000, 1500, 2000, 30, False), 100, 0.01),
        (1466, (1000, 1500, 2000, 30, False), 100, 0.0),  # -0.85 %: not negative (truncated towards zero)
        (1465, (1000, 1500, 2000, 30, False), 100, -0.01),
        (1465, (1000, 1500, 2000, 30, True), 100, 0.01),
        (1715, (1100, 1500, 1900, 30, False), 4500, 0.5),  # steering in 1/4500
        (1716, (1100, 1500, 1900, 30, False), 4500, 2262 / 4500),  # 2262.16 truncated
        (1000, (1000, 1500, 2000, 30, False), 100, -1.0),
    ],
)
def test_ardupilot_keeps_what_it_reads_as_an_integer(pwm, calib, full_scale, expected) -> None:
    """RC_Channel::control_in is an int16_t: throttle and lateral in whole percent, steering in 1/4500."""
    assert scale_angle(pwm, *calib, full_scale) == pytest.approx(expected, abs=1e-12)


def test_a_buoy_scales_throttle_with_its_rc3_calibration() -> None:
    v = _armed(RC3_MIN=1000, RC3_MAX=2000)
    thrust = _drive(v, {3: 1900})
    # 370 / 470 = 78.7 %, kept by ArduPilot as the int16 78 (RC_Channel::control_in): 78 % of 10 N
    assert thrust[0] == pytest.approx(10.0 * 78 / 100) and thrust[1] == 0.0
    assert _drive(v, {3: 1520}, 0.1)[0] == 0.0, "dead zone"


def test_overrides_are_taken_only_from_mav_gcs_sysid() -> None:
    v = _armed()
    assert not _drive(v, {3: 1900}, gcs=Gcs(system=200)).any() and v.counters.refused == 1
    v.params.set("MAV_GCS_SYSID", 200)
    assert _drive(v, {3: 1900}, 0.1, gcs=Gcs(system=200))[0] == pytest.approx(10.0)
    assert v.counters.commands == 1


@pytest.mark.parametrize(("timeout", "alive_at", "gone_at"), [(3.0, 2.95, 3.05), (1.0, 0.95, 1.05), (-1.0, 500, None)])
def test_an_override_counts_for_rc_override_time(timeout, alive_at, gone_at) -> None:
    v = _armed(RC_OVERRIDE_TIME=timeout)
    _drive(v, {3: 1900})
    assert v.actuator(alive_at)[0] == pytest.approx(10.0)
    if gone_at is not None:
        assert v.actuator(gone_at)[0] == 0.0 and v.counters.failsafes == 1


def test_zero_override_time_disables_overrides() -> None:
    assert not _drive(_armed(RC_OVERRIDE_TIME=0), {3: 1900}).any()


def test_zero_releases_a_channel_and_max_leaves_it_alone() -> None:
    v = _armed()
    _drive(v, {3: 1900, 4: 1900})
    assert _drive(v, {3: 65535, 4: 0}, 0.1).tolist() == pytest.approx([10.0, 0.0])  # lateral back to the radio


def test_rcmap_decides_which_channel_is_which() -> None:
    v = _armed(RCMAP_THROTTLE=2, RCMAP_YAW=5, RC5_DZ=30)
    assert _drive(v, {3: 1900, 4: 1900}).tolist() == [0.0, 0.0]
    thrust = _drive(v, {2: 1900, 5: 1100}, 0.1)
    assert thrust.tolist() == pytest.approx([10.0, 10.0])  # forward; lateral left (positive y)


def test_lateral_moves_only_an_omni_frame() -> None:
    assert _drive(_armed(), {4: 1900})[1] == pytest.approx(-10.0)  # lateral right = thrust to -y
    assert _drive(_armed(FRAME_TYPE=0), {4: 1900}).tolist() == [0.0, 0.0]


@pytest.mark.parametrize(
    ("steer_type", "expected"),
    [(0, (-1.0, 0.0)), (2, (-1.0, 0.0)), (3, (0.0, -1.0))],  # 0 and 2 flip the steering when reversing
)
def test_pilot_steer_type_and_reverse(steer_type: int, expected) -> None:
    v = _armed("ebot", PILOT_STEER_TYPE=steer_type)
    # Throttle half back, steering half right: ArduPilot's default turns the other way when reversing.
    wheels = _drive(v, {3: 1500 - 30 - 185, 1: 1500 + 30 + 185})
    assert wheels.tolist() == pytest.approx(expected)


def test_two_paddles() -> None:
    v = _armed("ebot", PILOT_STEER_TYPE=1)
    assert _drive(v, {1: 1900, 3: 1900}).tolist() == pytest.approx([1.0, 1.0])
    assert _drive(v, {1: 1900, 3: 1500}, 0.1).tolist() == pytest.approx([1.0, 0.0])


def test_skid_steer_scales_steering_and_throttle_back_together() -> None:
    wheels = _drive(_armed("ebot"), {1: 1900, 3: 1900})
    assert wheels.tolist() == pytest.approx([1.0, 0.0])  # 0.5 + 0.5, 0.5 - 0.5


def test_initial_mode_is_the_boot_mode() -> None:
    v = SimulatedVehicle(1, "buoy", 10.0, armed=True, params={"INITIAL_MODE": 4})
    assert v.mode == 4
    assert not _drive(v, {3: 1900}).any(), "HOLD"
    (hb, *_) = of_type(parse(v.stream(0.0)), "HEARTBEAT")
    assert hb.custom_mode == 4 and hb.system_status == m.MAV_STATE_STANDBY


def test_mot_slewrate_ramps_the_throttle() -> None:
    v = SimulatedVehicle(1, "buoy", 10.0, armed=True)  # MOT_SLEWRATE 100 %/s
    v.actuator(0.0)
    v.receive(Gcs().override({3: 1900}), 0.0)
    assert [v.actuator(t)[0] for t in (0.25, 0.5, 1.0, 1.5)] == pytest.approx([2.5, 5.0, 10.0, 10.0])


def test_rc_channels_and_servo_output_raw_show_what_the_vehicle_applies() -> None:
    v, gcs = SimulatedVehicle(1, "ebot", 1.0, params=NO_SLEW), Gcs()
    v.receive(gcs.override({1: 1715, 3: 1900}), 0.0)
    v.actuator(0.0)
    messages = parse(v.stream(0.0))
    (rc,) = of_type(messages, "RC_CHANNELS")
    (servo,) = of_type(messages, "SERVO_OUTPUT_RAW")
    assert (rc.chan1_raw, rc.chan3_raw, rc.chan2_raw, rc.chancount) == (1715, 1900, 1500, 16)
    assert (servo.servo1_raw, servo.servo3_raw) == (1500, 1500), "disarmed: outputs at trim"
    v.receive(gcs.long(m.MAV_CMD_COMPONENT_ARM_DISARM, 1), 0.1)
    v.receive(gcs.override({1: 1715, 3: 1900}), 1.1)
    v.actuator(1.1)
    (servo,) = of_type(parse(v.stream(1.1)), "SERVO_OUTPUT_RAW")
    # throttle 1, steering 0.5 saturate to 1/1.5: left 1.0, right 1/3 (ThrottleLeft on SERVO1, Right on SERVO3)
    assert (servo.servo1_raw, servo.servo3_raw) == (1900, round(1500 + 400 / 3))
    v.receive(gcs.override({1: 0, 3: 0}), 1.2)  # release: the receiver's neutral sticks
    v.actuator(1.2)
    (rc,) = of_type(parse(v.stream(2.2)), "RC_CHANNELS")
    assert (rc.chan1_raw, rc.chan3_raw) == (1500, 1500)


def test_servo_output_raw_follows_a_servo_function_change_at_once() -> None:
    """The outputs are kept between sends only while the parameters stay: SERVO1_FUNCTION 0 (disabled) turns
    SERVO1 off in the very next SERVO_OUTPUT_RAW."""
    v, gcs = SimulatedVehicle(1, "ebot", 1.0, armed=True, params=NO_SLEW), Gcs()
    v.receive(gcs.override({1: 1715, 3: 1900}), 0.0)
    v.actuator(0.0)
    (servo,) = of_type(parse(v.stream(0.0)), "SERVO_OUTPUT_RAW")
    assert servo.servo1_raw == 1900
    assert v.params.set("SERVO1_FUNCTION", 0)
    (servo,) = of_type(parse(v.stream(1.0)), "SERVO_OUTPUT_RAW")
    assert (servo.servo1_raw, servo.servo3_raw) == (0, round(1500 + 400 / 3))


@pytest.mark.parametrize("pwm", [[1500] * 8, [-5, 70000, 1499.7, 65535, 0], [1100] * 20, []])
def test_rc_channels_clamp_each_value_into_its_uint16_field(pwm) -> None:
    (rc,) = parse(TelemetryEncoder(1).rc_channels(1.0, pwm, 16))
    fields = [getattr(rc, f"chan{i}_raw") for i in range(1, 19)]
    assert fields == [max(0, min(65535, int(p))) for p in pwm[:18]] + [0] * (18 - len(pwm[:18]))


def _update_channel_by_channel(rc: RcInput, t_s: float, timeout_s: float, trims: list[int]) -> list[int]:
    """RC_Channel::update as ArduPilot writes it, one channel at a time: the reference for RcInput.update."""
    radio_in = list(rc.radio_in)
    for i in range(OVERRIDE_CHANNELS):
        value = rc.override[i]
        live = bool(value) and (timeout_s < 0 or (timeout_s > 0 and t_s - rc.override_t[i] < timeout_s))
        if live:
            radio_in[i] = value
        elif rc.receiver:
            radio_in[i] = trims[i] if i < len(trims) else 1500
    return radio_in


@pytest.mark.parametrize("seed", range(5))
def test_rc_input_update_is_channel_by_channel_update(seed: int) -> None:
    rng = np.random.default_rng(seed)
    for _ in range(200):
        rc = RcInput(receiver=bool(rng.integers(2)))
        rc.override = [int(v) if rng.random() < 0.6 else 0 for v in rng.integers(800, 2200, OVERRIDE_CHANNELS)]
        rc.override_t = [float(v) for v in rng.uniform(0, 10, OVERRIDE_CHANNELS)]
        rc.radio_in = [int(v) for v in rng.integers(0, 2200, OVERRIDE_CHANNELS)]
        timeout = float(rng.choice([-1.0, 0.0, 0.5, 3.0, math.nan]))
        trims = [int(v) for v in rng.integers(1400, 1600, 8)]
        t = float(rng.uniform(0, 12))
        expected = _update_channel_by_channel(rc, t, timeout, trims)
        rc.update(t, timeout, trims)
        assert rc.radio_in == expected


@pytest.mark.parametrize("seed", range(5))
def test_rc_input_update_kept_between_changes_is_channel_by_channel_update(seed: int) -> None:
    """`update` and `any_override` skip the work while nothing they read has changed: over a run of calls at
    rising (sometimes equal, sometimes earlier) times, with overrides stored, cleared and expiring and the trims
    replaced now and then, each result is the reference's."""
    rng = np.random.default_rng(100 + seed)
    rc = RcInput(receiver=bool(rng.integers(2)))
    trims = [1500] * 8
    timeout = float(rng.choice([-1.0, 0.0, 0.3, 1.0, 3.0]))
    t = 0.0
    for _ in range(400):
        event = rng.random()
        if event < 0.15:
            raw = [int(v) if rng.random() < 0.5 else 65535 for v in rng.integers(800, 2200, OVERRIDE_CHANNELS)]
            rc.apply_override(raw, t)
        elif event < 0.18:
            rc.clear_overrides()
        elif event < 0.21:
            trims = [int(v) for v in rng.integers(1400, 1600, 8)]
        elif event < 0.24:
            timeout = float(rng.choice([-1.0, 0.0, 0.3, 1.0, 3.0]))
        t = max(0.0, t + float(rng.choice([0.0, 0.05, 0.1, 0.25, -0.1])))
        expected = _update_channel_by_channel(rc, t, timeout, trims)
        expected_any = any(rc.has_override(i, t, timeout) for i in range(OVERRIDE_CHANNELS))
        assert rc.update(t, timeout, trims) == expected_any
        assert rc.radio_in == expected
        assert rc.any_override(t, timeout) == expected_any


def test_a_calibration_change_acts_on_the_override_already_in_force() -> None:
    """The pilot input is kept between reads only while RC input and parameters stay: reversing the throttle
    channel turns the same override into thrust astern at the next motor output."""
    v = _armed()
    assert _drive(v, {3: 1900})[0] == pytest.approx(10.0)
    assert v.params.set("RC3_REVERSED", 1)
    assert v.actuator(0.1)[0] == pytest.approx(-10.0)
