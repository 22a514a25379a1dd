"""Heading consensus at physics fidelity (issue 14 item 4b): what could slow the eBots' agreement to "about 11 s".

The issue asks for `heading-consensus` at physics fidelity agreeing within 5 degrees at 5.5 to 22 s (a factor of 2
of the paper's 11 s) and still following a leader turned 90 degrees at t = 22 s within 5 degrees by t = 40 s, at 9
of 10 seeds. tests/test_heading_fidelity_paper.py shows why no round length does it (eq. (2) agrees in one round on
a complete graph and needs about 30 rounds to follow) and that the paper's own software (marabunta: 1 Hz TDMA
broadcasts, turn gain 2.5/pi to 3/pi per rad) agrees in 3-5 s and is still 40-55 degrees off the leader at 40 s.
These tests measure, in the project's physics stack (eBot differential drive with slip, EKF on IMU and encoders,
the vessel's proportional turn controller, omega = 4 * error rad/s, wheels at most 0.20 m/s, 0.10 m apart), the
three candidates the issue names, each emulated here by wrapping the vessel's controller (test-only; nothing ships):

1. Physics fidelity as it is: agrees in about 1.3 s (seeds 1, 2), follows by t = 33-38 s. Too fast by 4x.

2. Latency in the turn loop (the eBot is driven over Bluetooth: each cycle is a `2P` pose round trip, then an `8w`
   wheel command after which the eBot API sleeps 0.05 s; marabunta's loop sleeps 0.1 s more). The controller turns
   on a heading estimate `latency` old. The disagreement mode then obeys e[k+1] = e[k] - K dt e[k-n], n = latency /
   dt, whose dominant root has modulus 0.88 (n = 2), 0.98 (n = 3), 1.02 (n = 4) at K dt = 0.4: there is no margin
   between "still fast" and "never settles". Measured (seeds 1-10 and 101-110, dt 0.1 s): 0.2 s agrees in 3.0-3.9 s;
   0.3 s never gets within 5 degrees (a limit cycle of 10-25 degrees; 0.4 s: 80-170 degrees). At dt 0.05 s and
   0.025 s (seeds 1-5): 0.25 s agrees in 4.1-4.8 s, 0.275 s in 4.3-5.4 s with the follow already failing at seed 4
   (5.1 degrees at 40 s), 0.3 s in 12-18 s but 5.4-11.5 degrees off the leader at 40 s. No latency gives both
   at this gain. With the authors' gain (1.06 rad/s per rad on the robot, below) and 0.3 s it agrees in 2.0-2.6 s
   and is 11-15 degrees off the leader at 40 s (the follow mode decays at K / 10). Halving our gain to 2 /s and
   delaying by 0.5 s (K tau = 1) does give both (agreement 8.6-12.4 s, the follow met, seeds 1-10 and 101-110),
   but 0.4 s agrees in 3.6-4.8 s and 0.6 s never, and a single eBot then overshoots a 90 degree turn by 52
   degrees: the oscillation marabunta's authors tuned their gain against ("too big and the robot oscillates before
   reaching the target heading", ebotBody.move_background), which their own gain and a 0.3 s delay do not show.

3. A cap on the yaw rate. Only a nonlinearity that slows large turns and not small ones can separate agreement (robots
   turn up to 180 degrees) from following (each update moves a follower about a tenth of its offset). Agreement
   then takes the largest initial deviation from the mean divided by the cap (measured 0.77 to 0.97 of that at
   seeds 1-10); a cap of 0.25 rad/s meets every criterion (seeds 1-10: agreement 6.4-11.4 s, follow at 9; seeds
   101-110: 6.3-11.0 s, 10), 0.30 and 0.35 rad/s do not (agreement under 5.5 s at seeds 8, 105 and 106). But the eBot
   turns in place at up to 2 x 0.20 m/s / 0.10 m = 4 rad/s (marabunta's rotate() assumes 3 rad/s at full wheel
   power): the cap is 16 times below the hardware, and nothing documented (eBot API, marabunta, the paper) says the
   robots turned at 14 deg/s. Shipping it would be an arbitrary knob, so the packaged scenario stays kinematic.
"""

from __future__ import annotations

import collections
import math

import numpy as np
import pytest

from behaviors.base import wrap_angle
from bob_autonomy.control.velocity_control import DiffDriveController
from bob_autonomy.onboard.pipeline import EbotPipeline
from sitl.experiments.runner import RunResult, simulate
from sitl.experiments.scenario import Scenario, load_scenario
from sitl.vehicles.dynamics import DiffDriveParams

TOLERANCE_DEG = 5.0
LEADER_T_S = 22.0
FOLLOW_BY_S = 40.0
EBOT = DiffDriveParams()
EBOT_MAX_YAW_RATE_RADPS = 2.0 * EBOT.max_wheel_speed_mps / EBOT.wheel_base_m  # turning in place at full wheel speed


def physics_result(seed: int) -> RunResult:
    """The packaged heading-consensus at physics fidelity (direct vehicle link: the same loop, faster)."""
    scenario = load_scenario("heading-consensus").with_overrides(seed=seed, fidelity="physics", link="direct")
    assert scenario.groups[0].params["cruise_speed"] == 0.0  # turning in place: the vessel's simple controller
    return simulate(scenario)


def physics_run(seed: int) -> dict:
    return physics_result(seed).metrics


def leader_overshoot_deg(result: RunResult) -> float:
    """How far (deg) the leader, robot 0, turns past the heading it holds from t = 22 s (90 deg counter-clockwise
    of its heading then): a single eBot's step response, since a leader no longer averages."""
    t, heading = result.recorder.agent_series(0, "heading")
    start = int(np.searchsorted(t, LEADER_T_S))
    held = heading[start] + math.pi / 2.0
    return float(np.degrees(wrap_angle(heading[start:] - held)).max())


def delay_turn_loop(
    monkeypatch: pytest.MonkeyPatch, latency_s: float, dt_s: float = 0.1, gain_per_s: float | None = None
) -> None:
    """The eBots' turn controller acts on the heading estimate of `latency_s` ago (the Bluetooth round trips),
    with a turn gain of `gain_per_s` rad/s per rad (None: the vessel's own, 4).

    Turning in place, EbotPipeline.wheels uses the simple proportional controller only; this replaces the heading
    it is given by the one `latency_s / dt_s` control steps older.
    """
    steps = round(latency_s / dt_s)

    def wheels(self, wish_mps, wish_heading_rad, t_s, *, idle=False):
        if gain_per_s is not None:
            self.simple.turn_gain_per_s = gain_per_s
        history = self.__dict__.setdefault("_test_heading_history", collections.deque(maxlen=steps + 1))
        history.append(self.estimate(t_s).heading.copy())
        return self.simple.wheels(wish_mps, wish_heading_rad, history[0])

    monkeypatch.setattr(EbotPipeline, "wheels", wheels)


def cap_yaw_rate(monkeypatch: pytest.MonkeyPatch, cap_radps: float) -> None:
    """The eBots turn at most `cap_radps`: the wheels' difference is clipped to cap * wheel base."""
    original = DiffDriveController.wheels

    def wheels(self, desired_mps, desired_heading_rad, heading_rad):
        w = original(self, desired_mps, desired_heading_rad, heading_rad)
        forward, half_difference = 0.5 * (w[:, 0] + w[:, 1]), 0.5 * (w[:, 1] - w[:, 0])
        limit = 0.5 * cap_radps * self.wheel_base_m
        half_difference = np.clip(half_difference, -limit, limit)
        return np.column_stack((forward - half_difference, forward + half_difference))

    monkeypatch.setattr(DiffDriveController, "wheels", wheels)


@pytest.mark.parametrize("seed", [1, 2])
def test_physics_fidelity_alone_agrees_about_four_times_too_fast(seed: int) -> None:
    m = physics_run(seed)
    assert m["consensus_time_s"] < 2.0 < 11.0 / 2.0
    assert m["deviation_from_leader_at_deadline_deg"] <= TOLERANCE_DEG
    assert m["passed"]  # the packaged (kinematic) criteria: agreed by 11 s, followed by 40 s


@pytest.mark.parametrize("seed", [1, 2])
def test_a_turn_loop_latency_of_0_2_s_still_agrees_before_5_5_s(seed: int, monkeypatch) -> None:
    delay_turn_loop(monkeypatch, 0.2, 0.1)
    m = physics_run(seed)
    assert 2.5 < m["consensus_time_s"] < 5.5  # slower than without latency, not slow enough
    assert m["deviation_from_leader_at_deadline_deg"] <= TOLERANCE_DEG


@pytest.mark.parametrize("seed", [1, 2])
def test_one_more_step_of_latency_never_settles(seed: int, monkeypatch) -> None:
    delay_turn_loop(monkeypatch, 0.3, 0.1)
    m = physics_run(seed)
    assert m["consensus_time_s"] is None  # never within 5 degrees before the leader appears
    assert m["spread_at_consensus_deadline_deg"] > TOLERANCE_DEG
    assert m["deviation_from_leader_at_deadline_deg"] > 2 * TOLERANCE_DEG  # a limit cycle, not a follow


# marabunta's ebotBody.move_background: omega = (2.5 / pi) * error, wheel speed 0.5 * omega * 0.10 m as a fraction of
# 0.15 m/s, a fraction 1 being the eBot's 0.20 m/s: 1.06 rad/s per rad on the robot.
AUTHORS_GAIN_PER_S = 2.5 / math.pi * 0.5 * 0.10 / 0.15 * 2.0 * EBOT.max_wheel_speed_mps / EBOT.wheel_base_m


def test_the_authors_turn_gain_and_latency_agree_fast_and_follow_too_slowly(monkeypatch) -> None:
    delay_turn_loop(monkeypatch, 0.3, gain_per_s=AUTHORS_GAIN_PER_S)
    result = physics_result(1)
    m = result.metrics
    assert m["consensus_time_s"] < 11.0 / 2.0  # 2.6 s
    assert m["deviation_from_leader_at_deadline_deg"] > 2 * TOLERANCE_DEG  # 11.4 deg: the follow mode is K / 10
    assert leader_overshoot_deg(result) < 2.0  # a single eBot does not oscillate: as the authors tuned it


def test_the_gain_and_latency_that_give_both_make_an_ebot_overshoot_a_90_degree_turn_by_50(monkeypatch) -> None:
    # Twice the authors' gain and a 0.5 s delay (a K tau of 1, whose step response overshoots by about half):
    # agreement 8.6-12.4 s and the follow met at seeds 1-10 and 101-110, but the leader alone rings.
    delay_turn_loop(monkeypatch, 0.5, gain_per_s=2.0)
    result = physics_result(1)
    m = result.metrics
    assert 11.0 / 2.0 <= m["consensus_time_s"] <= 2.0 * 11.0  # 11.3 s
    assert m["deviation_from_leader_at_deadline_deg"] <= TOLERANCE_DEG
    assert leader_overshoot_deg(result) > 40.0  # 52 deg: "too big and the robot oscillates" (move_background)


@pytest.mark.parametrize(("latency_s", "settles"), [(0.4, True), (0.6, False)])
def test_at_that_gain_0_1_s_less_latency_agrees_too_soon_and_0_1_s_more_never(latency_s, settles, monkeypatch) -> None:
    delay_turn_loop(monkeypatch, latency_s, gain_per_s=2.0)
    m = physics_run(1)
    if settles:
        assert m["consensus_time_s"] < 11.0 / 2.0  # 4.8 s
    else:
        assert m["consensus_time_s"] is None


def test_the_latency_model_has_no_margin_between_fast_and_unstable() -> None:
    # Dominant root of z^(n+1) - z^n + K dt = 0 (e[k+1] = e[k] - K dt e[k-n]), K = 4 /s, dt = 0.1 s.
    k_dt = DiffDriveController().turn_gain_per_s * 0.1
    modulus = {}
    for n in range(5):
        coefficients = np.zeros(n + 2)
        coefficients[0], coefficients[1] = 1.0, -1.0
        coefficients[-1] += k_dt
        modulus[n] = float(np.abs(np.roots(coefficients)).max())
    assert modulus[2] < 0.9 < modulus[3] < 1.0 < modulus[4]


CAP_RADPS = 0.25


@pytest.mark.parametrize("seed", [1, 8])  # initial spreads 158 and 96 degrees
def test_a_yaw_rate_cap_agrees_in_the_largest_deviation_over_the_cap(seed: int, monkeypatch) -> None:
    cap_yaw_rate(monkeypatch, CAP_RADPS)
    m = physics_run(seed)
    model_s = math.radians(m["initial_spread_deg"]) / CAP_RADPS
    assert 0.7 * model_s < m["consensus_time_s"] <= 1.05 * model_s
    assert 11.0 / 2.0 <= m["consensus_time_s"] <= 2.0 * 11.0
    assert m["deviation_from_leader_at_deadline_deg"] <= TOLERANCE_DEG
    # ... with a cap 16 times below the simulated (and the real) eBot's turn in place.
    assert math.isclose(EBOT_MAX_YAW_RATE_RADPS / CAP_RADPS, 16.0)


CRUISE_MPS = 0.15  # marabunta examples/dr3demo/heading.py: the eBots drive on at 0.15 while they align


def cruising_result(seed: int) -> RunResult:
    """The packaged heading-consensus at physics fidelity with the eBots cruising (the eBot MPC drives them)."""
    data = load_scenario("heading-consensus").with_overrides(seed=seed, fidelity="physics", link="direct").model_dump()
    data["groups"][0]["params"]["cruise_speed"] = CRUISE_MPS
    return simulate(Scenario.model_validate(data))


@pytest.mark.parametrize("seed", [1, 2])
def test_cruising_ebots_face_where_they_go_and_agree(seed: int) -> None:
    # The eBot MPC used to back a robot up to a wish behind it: its body heading, which is what heading consensus
    # broadcasts, then pointed the other way and the swarm split into two groups 180 degrees apart (spread 179
    # degrees at 11 s). A robot wished a heading now turns to face it and only drives forward.
    result = cruising_result(seed)
    along = [
        np.cos(f.heading) * f.velocity[:, 0] + np.sin(f.heading) * f.velocity[:, 1] for f in result.recorder.frames
    ]
    assert float(np.min(np.concatenate(along))) > -0.2 * CRUISE_MPS  # measured -0.013 and -0.014 m/s: slip in a pivot
    m = result.metrics
    assert m["spread_at_consensus_deadline_deg"] <= TOLERANCE_DEG
    assert m["deviation_from_leader_at_deadline_deg"] <= TOLERANCE_DEG
