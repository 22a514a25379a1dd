"""MotorboatPipeline: the vessel's own estimation (buoy EKF, surge model) and motorboat control, closed around the
simulated boat and its simulated sensors (nothing from the simulator but readings reaches the pipeline)."""

from __future__ import annotations

import numpy as np
import pytest

from bob_autonomy.control.motorboat_control import MotorboatModel
from bob_autonomy.core.geodesy import LocalFrame
from bob_autonomy.onboard.pipeline import BuoyPipeline, MotorboatPipeline
from sitl.vehicles.motorboat import MotorboatDynamics, params_for
from sitl.vehicles.sensors import SensorSuite

FRAME = LocalFrame(1.3406, 103.9266)


def _loop(pipeline: MotorboatPipeline, goals: np.ndarray, current, seconds: float, dt: float = 0.2):
    n = len(goals)
    rng = np.random.default_rng(5)
    boats = MotorboatDynamics(params_for(2.0, 3.0), np.zeros((n, 2)), np.zeros(n), rng)
    sensors = SensorSuite(n, FRAME, rng, encoders=None, ranges=None, light=None)
    current = np.tile(current, (n, 1))
    t, distances = -2.0, []
    while t < seconds:
        idle = t < 0.0
        estimate = pipeline.estimate(t).position
        offset = goals - np.nan_to_num(estimate)
        distance = np.hypot(*offset.T)[:, None]
        wish = offset / np.maximum(distance, 1e-9) * np.minimum(1.0, 0.2 * distance)
        command = pipeline.thrust(wish, t, idle=idle)
        boats.step(command, dt, current_mps=current)
        t += dt
        pipeline.feed(sensors.sample(t, boats.position_m, boats.velocity_mps, boats.acceleration_mps2,
                                     boats.heading_rad, boats.yaw_rate_radps))  # fmt: skip
        distances.append(np.hypot(*(boats.position_m - goals).T))
    return np.array(distances), boats


@pytest.mark.parametrize("estimator", ["ekf", "simple"])
def test_estimated_and_controlled_boats_reach_their_goals_and_stay_near(estimator) -> None:
    goals = np.array([[40.0, 0.0], [-40.0, 10.0]])
    pipeline = MotorboatPipeline(2, FRAME, MotorboatModel.for_top_speed(2.0, 3.0), estimator=estimator, dt_s=0.2,
                                 mpc_time_budget_s=np.inf)  # fmt: skip
    distances, _ = _loop(pipeline, goals, (0.1, 0.05), 90.0)
    assert (distances[-75:] < 8.0).all()  # within a turning circle plus GPS error of each goal for the last 15 s
    assert pipeline.mpc_fallbacks == 0
    if estimator == "ekf":
        # The current, as a known disturbance: within 0.2 m/s (without the accelerometer, drift is seen only
        # through the thrust model, whose isotropic drag knows nothing of the sway in turns).
        assert np.hypot(*(pipeline.drift() - (0.1, 0.05)).T).max() < 0.2


def test_idle_boats_get_neutral_and_a_weak_battery_a_lower_throttle() -> None:
    pipeline = MotorboatPipeline(2, FRAME, max_throttle=np.array([1.0, 0.4]), estimator="ekf")
    assert isinstance(pipeline, BuoyPipeline)  # estimated as a buoy: the vessel loop's estimate checks apply
    wish = np.array([[2.0, 0.0], [2.0, 0.0]])
    assert pipeline.thrust(wish, 0.0, idle=True).tolist() == [[0.0, 0.0], [0.0, 0.0]]
    pipeline.feed([])
    command = pipeline.commands(wish, 0.0)
    assert 0.0 < command[1, 0] <= 0.4 < command[0, 0] <= 1.0
    with pytest.raises(ValueError, match="2 motorboat models for 3 boats"):
        MotorboatPipeline(3, FRAME, [MotorboatModel()] * 2)
