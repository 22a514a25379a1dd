"""How a vessel builds its estimator-and-controller pipeline for its kind of vehicle (bob_autonomy.onboard.pipeline)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from bob_autonomy.control.motorboat_control import MotorboatModel
from bob_autonomy.control.velocity_control import BuoyModel
from bob_autonomy.core.geodesy import LocalFrame
from bob_autonomy.onboard.pipeline import BuoyPipeline, EbotPipeline, MotorboatPipeline

if TYPE_CHECKING:
    from bob_autonomy.onboard.vessel import VesselConfig


def ebot_pipeline(c: VesselConfig, max_wheel_speed_mps: float, throttle_slew_per_s: float = 0.0) -> EbotPipeline:
    """The eBot pipeline of a vessel: odometry or EKF from its start pose, wheel control at its top speed (m/s),
    planned with the autopilot's throttle slew (MOT_SLEWRATE / 100, per s; 0: none)."""
    e = c.ebot
    x, y, heading = c.start_pose
    return EbotPipeline(
        np.array([[x, y]]),
        np.array([heading]),
        e.wheel_base_m,
        max_wheel_speed_mps,
        e.metres_per_tick,
        estimator=c.estimator,
        controller=c.controller,
        dt_s=c.dt_s,
        frame=LocalFrame(*c.origin),
        throttle_slew_per_s=throttle_slew_per_s,
    )


def buoy_pipeline(c: VesselConfig, model: BuoyModel, *, on_ground: bool = False) -> BuoyPipeline:
    """The buoy pipeline of a vessel (on_ground: a ground rover that drives like a buoy, no water drift)."""
    return BuoyPipeline(
        1,
        LocalFrame(*c.origin),
        np.array([model.max_thrust_n * c.max_thrust_fraction]),
        estimator=c.estimator,
        controller=c.controller,
        dt_s=c.dt_s,
        model=model,
        on_ground=on_ground,
    )


def motorboat_pipeline(c: VesselConfig, model: MotorboatModel) -> MotorboatPipeline:
    """The motorboat pipeline of a vessel: its boat model and thrust fraction."""
    return MotorboatPipeline(
        1, LocalFrame(*c.origin), model, c.max_thrust_fraction, estimator=c.estimator, controller=c.controller,
        dt_s=c.dt_s,
    )  # fmt: skip
