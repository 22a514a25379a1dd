"""ArduPilot reads an RC input as an integer (RC_Channel::control_in, int16_t: whole percent of throttle); in reverse
it flips the steering stick (Rover/mode.cpp get_pilot_input, PILOT_STEER_TYPE 0, when that integer is negative)
and flips the steering output back (AP_MotorsUGV::output_regular, a frame with a steering output). Against
ArduPilot's own SITL motorboat: the rudder it puts out (SERVO1, ground steering) for our overrides is on the side
the vessel meant, ahead, 5 % astern and 0.4 % astern. Before, the vessel pre-flipped the steering for any
negative wish, which put the rudder on the other side at 5 % astern (and at 0.4 %, read as 0, on the side meant
except on the overrides that carried -1 %) (docs/ardupilot.md).

Four settings a boat owner may have changed, also read from the autopilot: MANUAL_STR_EXPO (ArduPilot shapes the
steering in MANUAL; the vessel sends the inverse, so the rudder is the one asked for), MOT_THR_MAX (the throttle is
clipped to it; the vessel plans within it), MOT_SLEWRATE (the throttle output ramps at that rate; a motorboat's
MPC plans with it) and throttle left / right on outputs other than SERVO1 / SERVO3 (still skid steering:
AP_MotorsUGV::have_skid_steering looks at every output).

Skipped unless ARDUPILOT_SITL names a built `ardurover`. Judged by SERVO_OUTPUT_RAW on the autopilot's SERIAL1.
"""

from __future__ import annotations

import time

import pytest
from pymavlink import mavutil
from sitl_harness import BINARY, NEEDS_SITL, RoverSitl

from bob_autonomy.onboard.autopilot import CORE_PARAMS, EBOT, LEGACY_PARAMS, MOTORBOAT, AutopilotSession
from firmware_bridge.commands import Encoder

pytestmark = NEEDS_SITL
PARAMS = ["FRAME_CLASS", "FRAME_TYPE", "PILOT_STEER_TYPE", "MAV_GCS_SYSID", "RCMAP_ROLL", "RCMAP_THROTTLE"]
PARAMS += [f"RC{ch}_{what}" for ch in (1, 3) for what in ("MIN", "TRIM", "MAX", "DZ", "REVERSED")]


def _read_params(link, names: list[str], timeout_s: float = 20.0) -> dict[str, float]:
    values: dict[str, float] = {}
    deadline = time.monotonic() + timeout_s
    for name in names:
        while name not in values and time.monotonic() < deadline:
            link.mav.param_request_read_send(1, 1, name.encode(), -1)
            msg = link.recv_match(type="PARAM_VALUE", blocking=True, timeout=1.0)
            if msg is not None:
                values[msg.param_id] = msg.param_value
    missing = [n for n in names if n not in values]
    assert not missing, f"the autopilot did not answer for {missing}"
    return values


def _session_on(sitl: RoverSitl, kind: str, extra: list[str]) -> tuple:
    """A link to SERIAL0 and a session that has read the start-up parameters (CORE_PARAMS, those that exist) and
    `extra`, armed in MANUAL."""
    link = mavutil.mavlink_connection(f"tcp:127.0.0.1:{sitl.serial0}", source_system=255, source_component=190)
    session = AutopilotSession(1, kind, Encoder(), clock=time.monotonic)
    session.params.update(_read_params(link, [n for n in CORE_PARAMS if n not in LEGACY_PARAMS] + PARAMS + extra))
    session.learn()
    link.write(session.set_mode("MANUAL"))
    deadline = time.monotonic() + 30
    while not (sitl.seen.modes and sitl.seen.modes[-1][2]) and time.monotonic() < deadline:
        link.write(session.arm(force=True))
        time.sleep(1.0)
    assert sitl.seen.modes and sitl.seen.modes[-1][2], f"not armed: {sitl.seen.texts[-5:]}"
    return link, session


def _outputs_while(sitl: RoverSitl, link, session: AutopilotSession, steering: float, throttle: float) -> list:
    """SERVO1..8 (us) while overrides go out at 10 Hz for 3 s, from 1 s on."""
    start = time.monotonic()
    while time.monotonic() - start < 3.0:
        link.write(session.override(steering, throttle))
        time.sleep(0.1)
    link.write(session.override(0.0, 0.0))
    return [servos for t, servos in sitl.seen.servos if t > start + 1.0]


def test_the_rudder_is_the_one_asked_for_under_a_steering_expo(tmp_path) -> None:
    """MANUAL_STR_EXPO 0.4: a stick at 0.5 would give a rudder of 0.375 (Rover/mode_manual.cpp input_expo)."""
    with RoverSitl(BINARY, "motorboat", tmp_path, params={"MANUAL_STR_EXPO": 0.4}) as sitl:
        sitl.wait_initialised()
        link, session = _session_on(sitl, MOTORBOAT, ["SERVO1_MIN", "SERVO1_TRIM", "SERVO1_MAX"])
        assert session.profile.steering_expo == pytest.approx(0.4)
        low, trim, high = (session.params[f"SERVO1_{f}"] for f in ("MIN", "TRIM", "MAX"))
        for steering in (0.5, -0.25):
            rudder = [servos[0] for servos in _outputs_while(sitl, link, session, steering, 0.05)]
            assert len(rudder) >= 1, "no SERVO_OUTPUT_RAW from the autopilot"
            fractions = [(r - trim) / ((high - trim) if r >= trim else (trim - low)) for r in rudder]
            assert all(f == pytest.approx(steering, abs=0.01) for f in fractions), (steering, rudder)


def test_the_throttle_is_clipped_to_mot_thr_max_which_the_vessel_reads(tmp_path) -> None:
    """MOT_THR_MAX 50: asked for 80 %, ArduPilot's throttle output (SERVO3) stays at 50 % of its throw; the vessel
    reads the limit at start (and then plans with it: tests/test_vessel.py)."""
    with RoverSitl(BINARY, "motorboat", tmp_path, params={"MOT_THR_MAX": 50}) as sitl:
        sitl.wait_initialised()
        link, session = _session_on(sitl, MOTORBOAT, ["SERVO3_MIN", "SERVO3_TRIM", "SERVO3_MAX"])
        assert session.profile.throttle_ceiling == 0.5
        trim, high = session.params["SERVO3_TRIM"], session.params["SERVO3_MAX"]
        outputs = _outputs_while(sitl, link, session, 0.0, 0.8)
        assert outputs, "no SERVO_OUTPUT_RAW from the autopilot"
        assert all((servos[2] - trim) / (high - trim) == pytest.approx(0.5, abs=0.01) for servos in outputs[-5:]), [
            servos[2] for servos in outputs
        ]


def test_the_throttle_output_ramps_at_mot_slewrate_which_the_vessel_reads(tmp_path) -> None:
    """MOT_SLEWRATE 50 (%/s): asked for full throttle from none, ArduPilot's throttle output (SERVO3) takes 2 s to
    get there (AP_MotorsUGV::slew_limit_throttle, in MANUAL too). The vessel reads the rate, and its motorboat MPC
    plans its speed changes, braking above all, with it (tests/test_motorboat_control.py)."""
    with RoverSitl(BINARY, "motorboat", tmp_path, params={"MOT_SLEWRATE": 50}) as sitl:
        sitl.wait_initialised()
        link, session = _session_on(sitl, MOTORBOAT, ["SERVO3_MIN", "SERVO3_TRIM", "SERVO3_MAX"])
        assert session.profile.throttle_slew_per_s == 0.5
        trim, high = session.params["SERVO3_TRIM"], session.params["SERVO3_MAX"]
        _outputs_while(sitl, link, session, 0.0, 0.0)  # at rest
        start = time.monotonic()
        while time.monotonic() - start < 4.0:
            link.write(session.override(0.0, 1.0))
            time.sleep(0.1)
        link.write(session.override(0.0, 0.0))
        ramp = [(t - start, (servos[2] - trim) / (high - trim)) for t, servos in sitl.seen.servos if t > start]
        assert len(ramp) >= 10, "no SERVO_OUTPUT_RAW from the autopilot"
        at_full = [t for t, fraction in ramp if fraction > 0.98]
        assert at_full and 1.9 <= at_full[0] <= 2.8, ramp  # 0.5 of full throttle per s, plus the link's delays
        assert all(fraction <= 0.5 * t + 0.03 for t, fraction in ramp), ramp  # never faster than the slew
        assert any(0.2 <= fraction <= 0.8 for _, fraction in ramp), ramp  # a ramp, not a step


def _ramp(sitl: RoverSitl, link, session: AutopilotSession, steering: float, throttle: float, seconds: float) -> list:
    """(s since the first override, SERVO1..8 us) while overrides go out at 10 Hz for `seconds`, then neutral."""
    start = time.monotonic()
    while time.monotonic() - start < seconds:
        link.write(session.override(steering, throttle))
        time.sleep(0.1)
    link.write(session.override(0.0, 0.0))
    return [(t - start, servos) for t, servos in sitl.seen.servos if t > start]


def test_a_skid_steer_rover_slews_its_throttle_and_not_its_steering(tmp_path) -> None:
    """What the eBot MPC plans with (bob_autonomy/control/ebot_mpc.py): AP_MotorsUGV::output slews the throttle
    (MOT_SLEWRATE, here 25 %/s) before the skid-steer mix, and not the steering. A pivot (steering alone) reaches
    both sides at once; full throttle from none takes 4 s on both sides."""
    with RoverSitl(BINARY, "skid", tmp_path, params={"MOT_SLEWRATE": 25}) as sitl:
        sitl.wait_initialised()
        link, session = _session_on(sitl, EBOT, ["SERVO1_TRIM", "SERVO1_MAX", "SERVO3_TRIM", "SERVO3_MAX"])
        assert session.profile.skid_steering and session.profile.throttle_slew_per_s == 0.25
        p = session.params

        def left(servos: list) -> float:  # SERVO1, throttle left (73), as a fraction of full
            return (servos[0] - p["SERVO1_TRIM"]) / (p["SERVO1_MAX"] - p["SERVO1_TRIM"])

        def right(servos: list) -> float:  # SERVO3, throttle right (74)
            return (servos[2] - p["SERVO3_TRIM"]) / (p["SERVO3_MAX"] - p["SERVO3_TRIM"])

        _ramp(sitl, link, session, 0.0, 0.0, 1.0)  # at rest
        pivot = _ramp(sitl, link, session, 0.5, 0.0, 2.0)
        turned = [t for t, servos in pivot if abs(left(servos)) > 0.45 and abs(right(servos)) > 0.45]
        assert turned and turned[0] < 1.0, pivot  # the slewed throttle would take 1.8 s to 0.45
        _ramp(sitl, link, session, 0.0, 0.0, 1.0)
        ramp = _ramp(sitl, link, session, 0.0, 1.0, 6.0)
        assert len(ramp) >= 10, "no SERVO_OUTPUT_RAW from the autopilot"
        at_full = [t for t, servos in ramp if left(servos) > 0.98 and right(servos) > 0.98]
        assert at_full and 3.9 <= at_full[0] <= 4.8, ramp  # 0.25 of full throttle per s, plus the link's delays
        assert all(left(servos) <= 0.25 * t + 0.03 for t, servos in ramp), ramp  # never faster than the slew


def test_throttle_left_and_right_on_other_outputs_still_turn_the_way_meant_astern(tmp_path) -> None:
    """A skid-steer rover with its throttles on SERVO5 (left) and SERVO6 (right): ArduPilot flips the steering
    once astern (get_pilot_input; output_skid_steering keeps it), so the vessel must pre-flip it. Asked to turn
    clockwise (steering 0.5) at 30 % astern, the left side must run faster than the right."""
    moved = {"SERVO1_FUNCTION": 0, "SERVO3_FUNCTION": 0, "SERVO5_FUNCTION": 73, "SERVO6_FUNCTION": 74}
    with RoverSitl(BINARY, "skid", tmp_path, params=moved) as sitl:
        sitl.wait_initialised()
        link, session = _session_on(sitl, EBOT, [])
        assert session.profile.skid_steering and session.profile.steering_flips_in_reverse
        outputs = _outputs_while(sitl, link, session, 0.5, -0.3)
        assert outputs, "no SERVO_OUTPUT_RAW from the autopilot"
        assert all(servos[4] > 1500 > servos[5] for servos in outputs), [s[4:6] for s in outputs]


def test_the_rudder_is_on_the_side_meant_ahead_astern_and_under_a_percent_astern(tmp_path) -> None:
    with RoverSitl(BINARY, "motorboat", tmp_path) as sitl:
        sitl.wait_initialised()
        link, session = _session_on(sitl, MOTORBOAT, [])
        # PILOT_STEER_TYPE 0 on a frame with a steering output: flipped by get_pilot_input, back by output_regular
        assert session.params["PILOT_STEER_TYPE"] == 0 and not session.profile.steering_flips_in_reverse
        sides = {}
        for throttle in (0.05, -0.05, -0.004):  # ahead; 5 % astern; 0.4 % astern (0, or -1 % now and then)
            session.carry = type(session.carry)()
            rudder = [servos[0] for servos in _outputs_while(sitl, link, session, 0.5, throttle)]
            assert len(rudder) >= 5, "no SERVO_OUTPUT_RAW from the autopilot"
            sides[throttle] = {(r > 1500) - (r < 1500) for r in rudder}
        ahead = sides[0.05]
        assert len(ahead) == 1 and ahead != {0}, sides
        assert sides[-0.05] == ahead and sides[-0.004] == ahead, sides
