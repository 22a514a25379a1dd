"""The buoy filter's tuning (BuoyEkfParams), state layout and kinds of reading."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from bob_autonomy.control.velocity_control import BuoyModel
from bob_autonomy.estimation.row_replay import (
    _FUSED,
    _GATED,
    _MODEL_GATED,
    _MODEL_RESET,
    _PREDICTED,
    _RESET,
    OUTCOMES,
)

_NX = 10  # [x, y, vx, vy, heading, yaw_rate, drift_x, drift_y, bias_x, bias_y]
_EYE2 = np.eye(2)
_EYE_NX = np.eye(_NX)

# The outcome of a prediction whose drag balance had this outcome.
_AS_MODEL_OUTCOME = np.arange(len(OUTCOMES))
_AS_MODEL_OUTCOME[[_FUSED, _GATED, _RESET]] = _PREDICTED, _MODEL_GATED, _MODEL_RESET
# Kinds of reading; the first four also index the counters of consecutive gated readings.
_GPS, _COMPASS, _GYRO, _DRAG, _PREDICT = range(5)
# Per-agent filter state, in the arrays of a BuoyEkfBank (what a replay snapshot holds): the float arrays are views
# of columns of one array, `_floats`, in this order and of these shapes per agent, so that a snapshot copies one
# array where it would copy nine (a numpy call each, for every call's rows).
_FLOAT_FIELDS = (
    ("x", (_NX,)), ("P", (_NX, _NX)), ("t", ()), ("accel", (2,)), ("t_accel", ()), ("thrust", (2,)),
    ("t_thrust", ()), ("nozzle", ()), ("t_nozzle", ()),
)  # fmt: skip
_FIELDS = ("_floats", "pos_init", "heading_init", "gate_run")


@dataclass(frozen=True)
class BuoyEkfParams:
    """Noise and tuning of the buoy filter (SI units; see the docstring of bob_autonomy.estimation for the models).

    model: the nominal mass and water drag (velocity_control.BuoyModel).
    thrust_slew_radps: the thruster's nozzle slew limit relative to the hull, rad/s.
    gps_sigma_m, gps_velocity_sigma_mps, compass_sigma_rad, gyro_sigma_radps: measurement noise std.
    accel_noise_mps2: white noise std of one accelerometer reading, m/s^2 (it spreads over the interval the
        reading covers). accel_bias_psd: random-walk PSD of the accelerometer bias states, m^2/s^5.
    drag_balance_sigma_mps2: std of the drag-balance pseudo-measurement (accelerometer vs drag model), m/s^2.
    accel_psd, model_psd, free_psd: velocity process noise PSD (m^2/s^3) with the accelerometer (on top of its
        reading noise), with the thrust/drag model, with neither (constant velocity).
    yaw_accel_psd: yaw-rate random walk PSD (rad^2/s^3). drift_psd: drift random walk PSD (m^2/s^3).
    accel_hold_s, thrust_hold_s: how long an accelerometer reading / thrust command stays in use after its time.
    max_step_s: longest prediction sub-step. gate_reset_count: consecutive gated readings that re-initialise.
    replay_window_s: how far back an out-of-order reading is fused by replay.
    initial_*: prior std of the states before readings set them.
    """

    model: BuoyModel = field(default_factory=BuoyModel)
    thrust_slew_radps: float = 3.0
    gps_sigma_m: float = 2.0
    gps_velocity_sigma_mps: float = 0.1
    compass_sigma_rad: float = math.radians(2.0)
    gyro_sigma_radps: float = 0.006
    accel_noise_mps2: float = 0.05
    accel_bias_psd: float = 1e-4**2
    drag_balance_sigma_mps2: float = 0.1
    accel_psd: float = 0.01**2
    model_psd: float = 0.1**2
    free_psd: float = 0.3**2
    yaw_accel_psd: float = 0.05**2
    drift_psd: float = 0.003**2
    accel_hold_s: float = 0.1
    thrust_hold_s: float = 1.0
    max_step_s: float = 0.25
    gate_reset_count: int = 10
    replay_window_s: float = 1.0
    initial_position_sigma_m: float = 100.0
    initial_velocity_sigma_mps: float = 1.0
    initial_heading_sigma_rad: float = math.pi
    initial_yaw_rate_sigma_radps: float = 0.2
    initial_drift_sigma_mps: float = 0.3
    initial_accel_bias_sigma_mps2: float = 0.05
