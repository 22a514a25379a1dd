"""EbotEkfBank: N eBot EKFs ([x, y, heading] from wheel odometry, compass and position fixes) held in numpy arrays
(rows = agents), so that a fleet's readings of one kind are fused in one call instead of one filter at a time.

Each row follows `EbotEkf` (one filterpy ExtendedKalmanFilter per robot), the reference that tests/test_ebot_ekf_bank.py
holds it to reading by reading: the same odometry model, the same filterpy equations (kalman_rows), gate, resets
and replay of late readings (row_replay)."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from bob_autonomy.estimation.ebot_ekf import EbotEkfParams
from bob_autonomy.estimation.kalman_rows import _healthy_rows, kalman_predict_rows, wrap_angle
from bob_autonomy.estimation.row_fusion import _measurement, _RowFusion
from bob_autonomy.estimation.row_replay import _FAILED, _INIT, _PREDICTED, _REJECTED, _RowReplay, _scalars, _vectors
from bob_autonomy.estimation.simple_estimator import FloatArray, IntArray, PoseEstimate

_NX = 3  # [x, y, heading]
# Kinds of reading; the first two also index the counters of consecutive gated readings.
_COMPASS, _POSITION, _ENCODERS = range(3)
# Per-agent filter state (what a replay snapshot holds).
_FIELDS = ("x", "P", "t", "ticks", "has_ticks", "t_ticks", "velocity", "gate_run")
_POSITION_H = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
_POSITION_H.flags.writeable = False


class EbotEkfBank(_RowReplay, _RowFusion):
    """N eBot EKFs in arrays behind the batch API of OdometryEstimator (see the module docstring).

    position_m (n, 2), heading_rad (n,) or scalar: the known start poses; wheel_base_m: distance between the wheels
    (m); metres_per_tick: wheel travel per encoder tick (m). Arrays (row i = agent i): x (n, 3), P (n, 3, 3),
    t (n,) filter times (NaN before the first timed reading), ticks (n, 2) the last encoder counts (has_ticks: read
    yet) taken at t_ticks (n,), velocity (n, 2) over the last odometry interval (m/s).
    """

    def __init__(
        self,
        position_m: ArrayLike,
        heading_rad: ArrayLike,
        wheel_base_m: float,
        metres_per_tick: float,
        params: EbotEkfParams | None = None,
    ) -> None:
        self.params = p = EbotEkfParams() if params is None else params
        pos = np.asarray(position_m, dtype=float).reshape(-1, 2)
        self.n = n = pos.shape[0]
        self.wheel_base_m, self.metres_per_tick = float(wheel_base_m), float(metres_per_tick)
        head = np.broadcast_to(np.asarray(heading_rad, dtype=float), (n,))
        self.x = np.column_stack((pos, wrap_angle(head)))
        self.P = np.tile(np.diag([p.position_sigma_m**2, p.position_sigma_m**2, p.heading_sigma_rad**2]), (n, 1, 1))
        self.t = np.full(n, np.nan)
        self.ticks = np.zeros((n, 2), dtype=np.int64)
        self.has_ticks = np.zeros(n, dtype=bool)
        self.t_ticks = np.full(n, np.nan)
        self.velocity = np.zeros((n, 2))
        self.gate_run = np.zeros((n, 2), dtype=np.int64)
        self._init_replay(n, _FIELDS)

    # ------------------------------------------------------------ readings (the batch API)

    def update_encoders(
        self, agents: IntArray, t_s: ArrayLike, ticks: ArrayLike, gyro_z_radps: ArrayLike | None = None
    ) -> NDArray[np.int64]:
        """Dead-reckon from cumulative (left, right) ticks (k, 2) read at t_s; the heading change comes from the
        gyro yaw rates (rad/s) over the interval when given, else from the wheels. Returns outcome codes."""
        idx, t = self._batch(agents, t_s)
        raw = np.asarray(ticks).reshape(idx.size, 2)
        if raw.dtype.kind == "f":  # ticks given as floats: a non-finite count rejects its reading
            finite = np.isfinite(raw)
            t = np.where(finite.all(axis=1), t, np.nan)
            raw = np.where(finite, raw, 0.0)
        gyro = None if gyro_z_radps is None else _scalars(gyro_z_radps, idx.size)
        return self._submit(_ENCODERS, idx, t, (raw.astype(np.int64), gyro))

    def update_compass(
        self, agents: IntArray, heading_rad: ArrayLike, t_s: ArrayLike | None = None
    ) -> NDArray[np.int64]:
        """Fuse compass headings (rad) measured at t_s (None: at each filter's current time; a filter without a
        clock yet fuses it into its start pose, unlogged)."""
        if t_s is not None:
            idx, t = self._batch(agents, t_s)
            return self._submit(_COMPASS, idx, t, (_scalars(heading_rad, idx.size),))
        idx = np.asarray(agents, dtype=np.intp).reshape(-1)
        head = _scalars(heading_rad, idx.size)
        t = self.t[idx]
        clockless = np.isnan(t)
        codes = np.full(idx.size, _REJECTED)
        direct = clockless & np.isfinite(head)
        np.add.at(self._rejected, idx[clockless & ~direct], 1)
        if direct.any():
            codes[direct] = self._fuse_compass(idx[direct], head[direct])
        if not clockless.all():
            rows = np.flatnonzero(~clockless)
            codes[rows] = self._submit(_COMPASS, idx[rows], t[rows], (head[rows],))
        return codes

    def update_position(
        self, agents: IntArray, t_s: ArrayLike, xy_m: ArrayLike, sigma_m: ArrayLike
    ) -> NDArray[np.int64]:
        """Fuse position fixes (k, 2) (m) with per-axis std sigma_m (m; not positive: rejected), measured at t_s."""
        idx, t = self._batch(agents, t_s)
        sigma = _scalars(sigma_m, idx.size)
        sigma[~(sigma > 0.0)] = np.nan
        return self._submit(_POSITION, idx, t, (_vectors(xy_m, idx.size), sigma))

    def carry(self, agent: int, shift_m: FloatArray, variance_m2: float, velocity_mps: FloatArray) -> None:
        """Move an agent's position by shift_m (2,) and widen each axis' variance by variance_m2, outside the
        readings (a robot whose wheels say nothing follows its fixes: the pipeline carries it on between them)."""
        self.x[agent, 0:2] += shift_m
        self.P[agent, 0, 0] += variance_m2
        self.P[agent, 1, 1] += variance_m2
        self.velocity[agent] = velocity_mps

    # ------------------------------------------------------------ outputs

    def estimate(self, t_s: float | None = None) -> PoseEstimate:
        """Poses at the agents' last readings: positions (n, 2), velocities of the last odometry interval (n, 2),
        headings (n,)."""
        return PoseEstimate(self.x[:, 0:2].copy(), self.velocity.copy(), self.x[:, 2].copy())

    def covariance_trace(self) -> FloatArray:
        """(N,) trace of each agent's position covariance, m^2."""
        return self.P[:, 0, 0] + self.P[:, 1, 1]

    # ------------------------------------------------------------ readings, in time order

    def _handle(self, kind: int, idx: IntArray, t: FloatArray, data: tuple) -> IntArray:
        self.t[idx] = np.fmax(self.t[idx], t)
        if kind == _ENCODERS:
            return self._handle_encoders(idx, t, *data)
        if kind == _COMPASS:
            return self._fuse_compass(idx, data[0])
        if kind == _POSITION:
            xy, sigma = data
            r_cov = (sigma**2)[:, None, None] * np.eye(2)
            return self._fuse(idx, _POSITION, xy, self.x[idx, 0:2], _POSITION_H, r_cov, False, [0, 1])
        raise ValueError(f"unknown reading kind {kind!r}")

    def _fuse_compass(self, idx: IntArray, heading_rad: FloatArray) -> IntArray:
        _, h_jac, r_cov = _measurement(_NX, (2,), (self.params.compass_sigma_rad**2,))
        z = wrap_angle(heading_rad)[:, None]
        codes = self._fuse(idx, _COMPASS, z, self.x[idx, 2:3], h_jac, r_cov, True, [2])
        self.x[idx, 2] = wrap_angle(self.x[idx, 2])
        return codes

    def _handle_encoders(self, idx: IntArray, t: FloatArray, ticks: NDArray[np.int64], gyro: FloatArray | None):
        codes = np.full(idx.size, _INIT)
        first = ~self.has_ticks[idx]
        if first.any():  # the first count of each wheel: where odometry starts from
            rows = idx[first]
            self.ticks[rows], self.t_ticks[rows], self.has_ticks[rows] = ticks[first], t[first], True
        rest = np.flatnonzero(~first)
        if rest.size:
            codes[rest] = self._odometry(idx[rest], t[rest], ticks[rest], None if gyro is None else gyro[rest])
        return codes

    def _odometry(self, idx: IntArray, t: FloatArray, ticks: NDArray[np.int64], gyro: FloatArray | None) -> IntArray:
        """Predict rows idx by the wheels' travel since their last count: ds = (dl + dr) / 2 along the mid-interval
        heading, dpsi = (dr - dl) / b (or gyro dt); the input noise (slip as a fraction of travel, tick
        quantisation, gyro noise) enters through the Jacobian with respect to (ds, dpsi)."""
        p, b, mpt = self.params, self.wheel_base_m, self.metres_per_tick
        dt = t - self.t_ticks[idx]
        travel = (ticks - self.ticks[idx]).astype(float) * mpt
        dl, dr = travel[:, 0], travel[:, 1]
        self.ticks[idx], self.t_ticks[idx] = ticks, t
        ds = 0.5 * (dl + dr)
        quant = mpt**2 / 6.0  # two readings, each uniform over a tick
        var_l = (p.wheel_noise_fraction * dl) ** 2 + quant
        var_r = (p.wheel_noise_fraction * dr) ** 2 + quant
        x = self.x[idx]
        use_gyro = np.zeros(idx.size, dtype=bool) if gyro is None else dt > 0.0
        dpsi = (dr - dl) / b if gyro is None else np.where(use_gyro, gyro * dt, (dr - dl) / b)
        mid = x[:, 2] + 0.5 * dpsi
        c, s = np.cos(mid), np.sin(mid)
        x_next = np.column_stack((x[:, 0] + ds * c, x[:, 1] + ds * s, wrap_angle(x[:, 2] + dpsi)))
        f_jac = np.zeros((idx.size, 3, 3))
        f_jac[:, 0, 0] = f_jac[:, 1, 1] = f_jac[:, 2, 2] = 1.0
        f_jac[:, 0, 2], f_jac[:, 1, 2] = -ds * s, ds * c
        v_jac = np.zeros((idx.size, 3, 2))  # with respect to (ds, dpsi)
        v_jac[:, 0, 0], v_jac[:, 0, 1], v_jac[:, 1, 0], v_jac[:, 1, 1] = c, -0.5 * ds * s, s, 0.5 * ds * c
        v_jac[:, 2, 1] = 1.0
        m_cov = np.empty((idx.size, 2, 2))
        m_cov[:, 0, 0] = 0.25 * (var_l + var_r)
        cross = np.where(use_gyro, 0.0, 0.5 * (var_r - var_l) / b)
        m_cov[:, 0, 1] = m_cov[:, 1, 0] = cross
        m_cov[:, 1, 1] = np.where(use_gyro, (p.gyro_sigma_radps * dt) ** 2, (var_l + var_r) / b**2)
        p_next = kalman_predict_rows(self.P[idx], f_jac, v_jac @ m_cov @ np.swapaxes(v_jac, 1, 2))
        ok = _healthy_rows(x_next, p_next)
        self.x[idx[ok]], self.P[idx[ok]] = x_next[ok], p_next[ok]
        moving = dt > 0.0
        speed = np.column_stack((c, s)) * ds[:, None] / np.where(moving, dt, 1.0)[:, None]
        self.velocity[idx[moving]] = speed[moving]
        return np.where(ok, _PREDICTED, _FAILED)
