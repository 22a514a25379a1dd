"""The eBot's EKF ([x, y, heading] from wheel odometry, compass and position fixes) on filterpy, one robot per
filter: the reference that EbotEkfBank (the fleet's and the vessel's filter, in arrays) is held to."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from bob_autonomy.estimation.kalman_rows import wrap_angle
from bob_autonomy.estimation.simple_estimator import FloatArray
from bob_autonomy.estimation.timed_ekf import _finite, _TimedEkf


@dataclass(frozen=True)
class EbotEkfParams:
    """Noise and tuning of `EbotEkf` (SI units; see the docstring of bob_autonomy.estimation).

    wheel_noise_fraction: std of each wheel's travel error as a fraction of its travel (slip).
    compass_sigma_rad, gyro_sigma_radps: measurement noise std. position_sigma_m, heading_sigma_rad: prior std
    of the initial pose. gate_reset_count, replay_window_s: as for the buoy.
    """

    wheel_noise_fraction: float = 0.05
    compass_sigma_rad: float = math.radians(2.0)
    gyro_sigma_radps: float = 0.01
    position_sigma_m: float = 0.05
    heading_sigma_rad: float = 0.1
    gate_reset_count: int = 10
    replay_window_s: float = 1.0


class EbotEkf(_TimedEkf):
    """EKF of one eBot: [x, y, heading] from wheel odometry, compass and position fixes.

    position_m (2,), heading_rad: the known start pose; wheel_base_m: distance between the wheels;
    metres_per_tick: wheel travel per encoder tick. Methods return outcomes as BuoyEkf's do.
    """

    def __init__(
        self,
        position_m: ArrayLike,
        heading_rad: float,
        wheel_base_m: float,
        metres_per_tick: float,
        params: EbotEkfParams | None = None,
    ) -> None:
        self.params = p = EbotEkfParams() if params is None else params
        super().__init__(3, p.replay_window_s, p.gate_reset_count)
        self.wheel_base_m, self.metres_per_tick = float(wheel_base_m), float(metres_per_tick)
        pos = np.asarray(position_m, dtype=float).reshape(2)
        self.kf.x = np.array([[pos[0]], [pos[1]], [float(wrap_angle(heading_rad))]])
        self.kf.P = np.diag([p.position_sigma_m**2, p.position_sigma_m**2, p.heading_sigma_rad**2])
        self._ticks: NDArray[np.int64] | None = None
        self._t_ticks = math.nan
        self._velocity = np.zeros(2)

    # ------------------------------------------------------------ readings

    def update_encoders(self, t_s: float, ticks: ArrayLike, gyro_z_radps: float | None = None) -> str:
        """Dead-reckon from cumulative (left, right) ticks read at t_s; the heading change comes from the
        gyro yaw rate (rad/s) over the interval when given, else from the wheels."""
        k = np.asarray(ticks).reshape(2)
        if not _finite(t_s, gyro_z_radps, k):
            return self._reject()
        return self._submit(float(t_s), "encoders", (k.astype(np.int64), gyro_z_radps))

    def update_compass(self, t_s: float | None, heading_rad: float) -> str:
        """Fuse a compass heading (rad) measured at t_s (None: at the filter's current time)."""
        if not _finite(t_s, heading_rad):
            return self._reject()
        if t_s is None:
            t_s = self.t_s if self.t_s is not None else -math.inf
            if self.t_s is None:  # no clock yet: fuse into the start pose directly
                return self._handle("compass", t_s, (float(heading_rad),))
        return self._submit(float(t_s), "compass", (float(heading_rad),))

    def update_position(self, t_s: float, xy_m: ArrayLike, sigma_m: float) -> str:
        """Fuse a position fix (m) with per-axis std sigma_m (m), measured at t_s."""
        xy = np.asarray(xy_m, dtype=float).reshape(2)
        if not _finite(t_s, xy, sigma_m) or sigma_m <= 0.0:
            return self._reject()
        return self._submit(float(t_s), "position", (xy, float(sigma_m)))

    # ------------------------------------------------------------ outputs

    @property
    def state(self) -> FloatArray:
        return self.kf.x[:, 0].copy()

    def position_covariance_trace(self) -> float:
        return float(self.kf.P[0, 0] + self.kf.P[1, 1])

    def estimate(self, t_s: float | None = None) -> tuple[FloatArray, FloatArray, float]:
        """(position (2,), velocity (2,) of the last odometry interval, heading) at the last reading."""
        x = self.kf.x[:, 0]
        return x[0:2].copy(), self._velocity.copy(), float(x[2])

    # ------------------------------------------------------------ internals

    def _snapshot(self) -> tuple:
        return (self.t_s, self.kf.x.copy(), self.kf.P.copy(), self._ticks, self._t_ticks, self._velocity.copy(),
                dict(self._gate_run))  # fmt: skip

    def _restore(self, s: tuple) -> None:
        self.t_s, x, p, self._ticks, self._t_ticks, velocity, gate_run = s
        self.kf.x, self.kf.P, self._velocity, self._gate_run = x.copy(), p.copy(), velocity.copy(), dict(gate_run)

    def _handle(self, kind: str, t: float, data: tuple) -> str:
        p = self.params
        if math.isfinite(t):
            self.t_s = t if self.t_s is None else max(self.t_s, t)
        if kind == "encoders":
            return self._odometry(t, *data)
        if kind == "compass":
            h_jac = np.array([[0.0, 0.0, 1.0]])
            z = np.array([[float(wrap_angle(data[0]))]])
            r_cov = np.array([[p.compass_sigma_rad**2]])
            outcome = self._fuse("compass", z, self.kf.x[[2]], h_jac, r_cov, angle_rows=[0], reset_rows=[2])
            self.kf.x[2, 0] = wrap_angle(self.kf.x[2, 0])
            return outcome
        if kind == "position":
            xy, sigma = data
            h_jac = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
            r_cov = np.eye(2) * sigma**2
            return self._fuse("position", xy[:, None], self.kf.x[[0, 1]], h_jac, r_cov, reset_rows=[0, 1])
        raise ValueError(f"unknown reading kind {kind!r}")

    def _odometry(self, t: float, ticks: NDArray[np.int64], gyro: float | None) -> str:
        p = self.params
        if self._ticks is None:
            self._ticks, self._t_ticks = ticks, t
            return "init"
        dt = t - self._t_ticks
        dl, dr = (ticks - self._ticks).astype(float) * self.metres_per_tick
        self._ticks, self._t_ticks = ticks, t
        b = self.wheel_base_m
        ds = 0.5 * (dl + dr)
        quant = self.metres_per_tick**2 / 6.0  # two readings, each uniform over a tick
        var_l = (p.wheel_noise_fraction * dl) ** 2 + quant
        var_r = (p.wheel_noise_fraction * dr) ** 2 + quant
        x = self.kf.x[:, 0]
        use_gyro = gyro is not None and dt > 0.0
        dpsi = gyro * dt if use_gyro else (dr - dl) / b
        mid = x[2] + 0.5 * dpsi
        c, s = math.cos(mid), math.sin(mid)
        x_next = np.array([x[0] + ds * c, x[1] + ds * s, float(wrap_angle(x[2] + dpsi))])
        f_jac = np.array([[1.0, 0.0, -ds * s], [0.0, 1.0, ds * c], [0.0, 0.0, 1.0]])
        # Input Jacobian with respect to (ds, dpsi), and the input covariance.
        v_jac = np.array([[c, -0.5 * ds * s], [s, 0.5 * ds * c], [0.0, 1.0]])
        if use_gyro:
            m_cov = np.diag([0.25 * (var_l + var_r), (p.gyro_sigma_radps * dt) ** 2])
        else:
            cov_ds = 0.25 * (var_l + var_r)
            cov_dpsi = (var_l + var_r) / b**2
            cov_x = 0.5 * (var_r - var_l) / b
            m_cov = np.array([[cov_ds, cov_x], [cov_x, cov_dpsi]])
        ok = self._predict_with(x_next[:, None], f_jac, v_jac @ m_cov @ v_jac.T)
        if dt > 0.0:
            self._velocity = np.array([c, s]) * ds / dt
        return "predicted" if ok else "failed"
