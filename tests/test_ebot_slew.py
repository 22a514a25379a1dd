"""The eBot MPC plans with the throttle slew of a skid-steer autopilot (MOT_SLEWRATE), as the motorboat's does.

A skid-steer rover behind ArduPilot gets throttle (l + r) / 2 and steering (l - r) / 2 and slews the throttle only
(AP_MotorsUGV::output). Over the lockstep MAVLink link, before this, 58 % of a `five-rooms` run's eBot actuator
updates were held back by the slew, 41 % by more than a tenth of full throttle (up to 1.27): the MPC planned wheel
speeds the autopilot did not let through.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from vessel_helpers import ORIGIN, SCALE, StandInVehicle

from bob_autonomy.control.ebot_mpc import DiffDriveMpc
from bob_autonomy.core.behavior_config import BehaviorChoice
from bob_autonomy.core.clock import ScaledWallClock
from bob_autonomy.onboard.vessel import Vessel, VesselConfig
from sitl.vehicles.autopilot_rc import slew_limited

RELAXED_BUDGET_S = 1.0  # solve-time budget for tests (the CI host may be loaded)
VMAX, DT = 0.2, 0.1


def throttle(wheels: np.ndarray) -> float:
    """The scaled throttle the autopilot reads from wheel speeds (m/s)."""
    return 0.5 * (wheels[0] + wheels[1]) / VMAX


def drive(mpc: DiffDriveMpc, seed: int, calls: int = 200) -> tuple[list[float], list[float], float]:
    """Random wishes, reversals among them, through an autopilot slewing the throttle at 100 %/s: (the change of
    each command's throttle from the autopilot's output before it, the largest change between planned steps, the
    largest gap between the controller's copy of the output and the autopilot's)."""
    rng = np.random.default_rng(seed)
    output, jumps, plan_changes, gap = 0.0, [], [], 0.0
    heading = 0.0
    for k in range(calls):
        wish = rng.uniform(-0.3, 0.3, 2) if k % 10 else -np.sign(rng.uniform(-1, 1)) * np.array([0.3, 0.0])
        result = mpc.solve(wish, heading, forward_only=bool(rng.random() < 0.3))
        assert result.ok, result.status
        jumps.append(abs(throttle(result.wheels_mps) - output))
        plan = 0.5 * (mpc._plan[0::2] + mpc._plan[1::2])
        plan_changes.append(float(np.abs(np.diff(plan)).max()))
        output = slew_limited(throttle(result.wheels_mps), output, 100.0, DT)  # the autopilot's output
        gap = max(gap, abs(mpc._output - output))
        heading += (result.wheels_mps[1] - result.wheels_mps[0]) / 0.1 * DT
    return jumps, plan_changes, gap


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_every_command_and_planned_step_is_within_the_slews_reach(seed: int) -> None:
    reach = 1.0 * DT
    jumps, plan_changes, gap = drive(DiffDriveMpc(time_budget_s=RELAXED_BUDGET_S, throttle_slew_per_s=1.0), seed)
    assert max(jumps) <= reach + 1e-9
    assert max(plan_changes) <= reach + 1e-9
    assert gap <= 1e-12  # the controller follows the autopilot's output as it moves
    # A controller that does not know the slew asks for far more than the autopilot lets through.
    unaware, _, _ = drive(DiffDriveMpc(time_budget_s=RELAXED_BUDGET_S), seed)
    assert max(unaware) > 5 * reach


def test_a_robot_backing_up_that_must_face_forward_ramps_up_at_the_slew() -> None:
    """forward_only asks every step to go forward; a robot still reversing cannot within one step: the plan takes
    what the slew reaches (it stays solvable) and the throttle climbs at the slew until forward."""
    mpc = DiffDriveMpc(time_budget_s=RELAXED_BUDGET_S, throttle_slew_per_s=1.0)
    for _ in range(20):
        mpc.solve(np.array([-0.2, 0.0]), 0.0)  # backing up at full speed
    assert mpc._output == pytest.approx(-1.0)
    levels = []
    for _ in range(12):
        result = mpc.solve(np.array([0.2, 0.0]), 0.0, forward_only=True)
        assert result.ok and not result.fallback
        levels.append(throttle(result.wheels_mps))
    np.testing.assert_allclose(levels[:10], np.arange(-0.9, 0.05, 0.1), atol=1e-6)
    assert levels[-1] > 0.15


def test_the_fallback_and_a_caller_s_command_are_followed_within_reach(monkeypatch) -> None:
    mpc = DiffDriveMpc(time_budget_s=RELAXED_BUDGET_S, throttle_slew_per_s=0.5)
    monkeypatch.setattr(mpc, "_solve_plan", lambda *args: (_ for _ in ()).throw(RuntimeError("forced")))
    result = mpc.solve(np.array([0.3, 0.0]), 0.0)
    assert result.fallback and throttle(result.wheels_mps) == pytest.approx(0.05)  # 0.5 /s x 0.1 s from rest
    assert result.wheels_mps[0] == pytest.approx(result.wheels_mps[1])  # shifted alike: the steering kept
    # A caller sent its own wheels instead (a robot turning on the spot): the copy follows those.
    mpc.sent(np.array([-0.2, 0.2]))
    assert mpc._output == pytest.approx(0.0)
    mpc.sent(np.array([0.2, 0.2]))
    assert mpc._output == pytest.approx(0.05)


@pytest.mark.parametrize("slew", [math.nan, math.inf, -0.1])
def test_a_bad_slew_is_refused(slew: float) -> None:
    with pytest.raises(ValueError, match="throttle_slew_per_s"):
        DiffDriveMpc(throttle_slew_per_s=slew)


@pytest.mark.xdist_group("realtime")  # real time and a UDP socket, as tests/test_vessel.py
@pytest.mark.parametrize(("slew_rate", "per_s"), [(None, 1.0), (40, 0.4), (0, 0.0)])
def test_an_ebot_vessel_plans_with_the_throttle_slew_its_autopilot_has(slew_rate: int | None, per_s: float) -> None:
    """A skid-steer vehicle's vessel reads MOT_SLEWRATE at start (ArduPilot's 100 %/s by default) and its MPCs plan
    with it."""
    robot = StandInVehicle(kind="ebot")
    if slew_rate is not None:
        assert robot.vehicle.params.set("MOT_SLEWRATE", slew_rate)
    robot.start()
    try:
        vessel = Vessel(_ebot_config(robot.port), clock=ScaledWallClock(SCALE))
        stats = vessel.run(duration_s=4.0)
    finally:
        robot.close()
    assert stats.commands > 5
    assert [mpc.throttle_slew_per_s for mpc in vessel.pipeline.mpcs] == [per_s]


def _ebot_config(port: int) -> VesselConfig:
    choice = BehaviorChoice(behavior="bob-rule", params={"goal": [3.0, 0.0], "H": 1, "p0": 0.5, "max_speed": 0.2})
    return VesselConfig(
        vehicle=f"udpout:127.0.0.1:{port}", system_id=1, behavior=choice, origin=ORIGIN, kind="ebot",
        controller="mpc", time_scale=SCALE, arm_timeout_s=5.0, heartbeat_timeout_s=3.0,
    )  # fmt: skip
