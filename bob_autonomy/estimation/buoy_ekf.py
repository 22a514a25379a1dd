"""BuoyEkf: the EKF of one buoy, a BuoyEkfBank of one (a vessel's own filter runs the fleet's code)."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike

from bob_autonomy.estimation.buoy_ekf_bank import BuoyEkfBank
from bob_autonomy.estimation.buoy_params import BuoyEkfParams
from bob_autonomy.estimation.row_replay import OUTCOMES
from bob_autonomy.estimation.simple_estimator import FloatArray


class BuoyEkf:
    """EKF of one buoy: [x, y, vx, vy, heading, yaw_rate, drift_x, drift_y, bias_x, bias_y] (see the docstring of
    bob_autonomy.estimation); a BuoyEkfBank of one, so a vessel's filter and a simulated fleet's run the same code.

    position_m, heading_rad: an initial pose if known (else the first GPS fix and compass reading set them).
    Each reading method returns the outcome of its reading (one of OUTCOMES): 'predicted', 'fused', 'init',
    'gated', 'reset', 'model_gated', 'model_reset', 'rejected' (non-finite), 'late' (older than the replay
    window) or 'failed'.
    """

    _ROW = np.zeros(1, dtype=np.intp)

    def __init__(
        self,
        position_m: ArrayLike | None = None,
        heading_rad: float | None = None,
        params: BuoyEkfParams | None = None,
    ) -> None:
        position = None if position_m is None else np.asarray(position_m, dtype=float).reshape(1, 2)
        heading = None if heading_rad is None else np.array([float(heading_rad)])
        self.bank = BuoyEkfBank(1, position, heading, params)
        self.params = self.bank.params

    # ------------------------------------------------------------ readings

    def predict(self, t_s: float, accel_body: ArrayLike | None = None, thrust_world_n: ArrayLike | None = None) -> str:
        """Predict to t_s (s) with the accelerometer reading accel_body (x forward, y left, m/s^2) taken at t_s,
        if any, and the thrust command (world frame, N) in force over the interval ending at t_s, if given (it
        stays in force for thrust_hold_s after t_s)."""
        accel = None if accel_body is None else np.reshape(accel_body, (1, 2))
        thrust = None if thrust_world_n is None else np.reshape(thrust_world_n, (1, 2))
        return OUTCOMES[self.bank._predict(self._ROW, t_s, accel, thrust)[0]]

    def update_gps(
        self,
        t_s: float,
        xy_m: ArrayLike,
        velocity_mps: ArrayLike | None = None,
        accuracy_m: float | None = None,
        speed_accuracy_mps: float | None = None,
    ) -> str:
        """Fuse a fix (local x east, y north, m) measured at t_s, and the ground velocity (m/s) if given; the
        receiver's horizontal (m) and speed (m/s) accuracies if it reports them (BuoyEkfBank.update_gps)."""
        vel = None if velocity_mps is None else np.reshape(velocity_mps, (1, 2))
        xy = np.reshape(xy_m, (1, 2))
        return OUTCOMES[self.bank._update_gps(self._ROW, t_s, xy, vel, accuracy_m, speed_accuracy_mps)[0]]

    def update_compass(self, t_s: float | None, heading_rad: float) -> str:
        """Fuse a compass heading (rad) measured at t_s (None: at the filter's current time)."""
        return OUTCOMES[self.bank._update_compass(self._ROW, heading_rad, t_s)[0]]

    def update_gyro(self, t_s: float, yaw_rate_radps: float) -> str:
        """Fuse a gyro yaw rate (rad/s, CCW positive) measured at t_s."""
        return OUTCOMES[self.bank._update_gyro(self._ROW, t_s, yaw_rate_radps)[0]]

    # ------------------------------------------------------------ outputs

    @property
    def state(self) -> FloatArray:
        """The state vector (10,) at the filter's time."""
        return self.bank.x[0].copy()

    @property
    def covariance(self) -> FloatArray:
        """The state covariance (10, 10)."""
        return self.bank.P[0].copy()

    @property
    def t_s(self) -> float | None:
        """The filter's time (that of its latest reading), s; None before the first reading."""
        t = float(self.bank.t[0])
        return None if math.isnan(t) else t

    @property
    def initialized(self) -> bool:
        """Whether position and heading have been set (by readings or at construction)."""
        return bool(self.bank.initialized()[0])

    def position_covariance_trace(self) -> float:
        """Trace of the position covariance, m^2."""
        return float(self.bank.covariance_trace()[0])

    def drift(self) -> FloatArray:
        """Estimated equivalent drift over ground (2,), m/s."""
        return self.bank.x[0, 6:8].copy()

    def estimate(self, t_s: float | None = None) -> tuple[FloatArray, FloatArray, float]:
        """(position (2,), velocity (2,), heading) extrapolated to t_s (never backwards; None: filter time)."""
        e = self.bank.estimate(self.bank.t[0] if t_s is None else t_s)
        return e.position[0], e.velocity[0], float(e.heading[0])

    def _count(self, outcome: str) -> int:
        return int(self.bank.outcome_counts(outcome)[0])

    @property
    def rejected(self) -> int:
        return self._count("rejected")

    @property
    def late(self) -> int:
        return self._count("late")

    @property
    def gated(self) -> int:
        return self._count("gated")

    @property
    def resets(self) -> int:
        return self._count("reset")

    @property
    def model_gated(self) -> int:
        return self._count("model_gated")

    @property
    def failures(self) -> int:
        return self._count("failed")
