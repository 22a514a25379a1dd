"""BuoyEkfBank: N buoy EKFs held in numpy arrays (rows = agents) behind the batch estimator API."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from bob_autonomy.estimation.buoy_params import (
    _COMPASS,
    _FIELDS,
    _FLOAT_FIELDS,
    _GPS,
    _GYRO,
    _PREDICT,
    BuoyEkfParams,
)
from bob_autonomy.estimation.buoy_process import _BuoyProcess
from bob_autonomy.estimation.kalman_rows import any_row, wrap_angle
from bob_autonomy.estimation.row_replay import (
    _IGNORED,
    _INIT,
    _LATE,
    _REJECTED,
    _RowReplay,
    _scalars,
    _take,
    _vectors,
)
from bob_autonomy.estimation.simple_estimator import FloatArray, IntArray, PoseEstimate


def _finite_or_zero(values: FloatArray) -> FloatArray:
    """The values with 0.0 where they are not finite (np.nan_to_num's result, in two numpy calls)."""
    return np.where(np.isfinite(values), values, 0.0)


def _float_fields(bank: object, floats: FloatArray) -> None:
    """Set the float per-agent arrays of _FLOAT_FIELDS on the bank as views, (n, *shape), of the columns of
    `floats` (n, width), which holds them side by side."""
    n, start = floats.shape[0], 0
    for name, shape in _FLOAT_FIELDS:
        width = int(np.prod(shape))
        # (splitting the columns' contiguous axis: reshape gives a view)
        view = floats[:, start] if not shape else floats[:, start : start + width].reshape((n, *shape))
        setattr(bank, name, view)
        start += width


_FLOATS_WIDTH = sum(int(np.prod(shape)) for _, shape in _FLOAT_FIELDS)


class BuoyEkfBank(_RowReplay, _BuoyProcess):
    """N buoy EKFs held in arrays, rows = agents, behind the batch API of AlphaBetaBuoyEstimator.

    n: number of buoys; position_m (n, 2), heading_rad (n,): initial poses if known (else the first GPS fix and
    compass reading set them); params: BuoyEkfParams. Each agent is an independent filter (see the docstring of
    bob_autonomy.estimation); a call handles all its rows at once with numpy (an agent given twice in one call is
    handled row by row, in order).

    Its code is spread over bases by concern: _BuoyUpdates (measurement updates, on row_fusion's gated fusion),
    _BuoyProcess (prediction, drag balance) and row_replay's _RowReplay (time, log, replay and outcome counters).

    Arrays (row i = agent i): x (n, 10) states, P (n, 10, 10) covariances, t (n,) filter times (NaN before the
    first reading), pos_init / heading_init (n,) whether position / heading were set.
    """

    def __init__(
        self,
        n: int,
        position_m: ArrayLike | None = None,
        heading_rad: ArrayLike | None = None,
        params: BuoyEkfParams | None = None,
    ) -> None:
        self.params = p = BuoyEkfParams() if params is None else params
        self.n = n = int(n)
        sig = [p.initial_position_sigma_m] * 2 + [p.initial_velocity_sigma_mps] * 2
        sig += [p.initial_heading_sigma_rad, p.initial_yaw_rate_sigma_radps] + [p.initial_drift_sigma_mps] * 2
        sig += [p.initial_accel_bias_sigma_mps2] * 2
        self._floats = np.empty((n, _FLOATS_WIDTH))
        _float_fields(self, self._floats)  # x ... t_nozzle below are views of its columns
        self.x[:] = 0.0
        self.P[:] = np.diag(np.square(sig))
        self.t[:] = np.nan
        self.pos_init = np.zeros(n, dtype=bool)
        self.heading_init = np.zeros(n, dtype=bool)
        self.accel[:] = np.nan  # the accelerometer reading in use (body frame), and its time
        self.t_accel[:] = -np.inf
        self.thrust[:] = np.nan  # the thrust command in force (world frame), and its time
        self.t_thrust[:] = -np.inf
        self.nozzle[:] = 0.0  # believed nozzle angle relative to the hull (rad), and when it was last slewed
        self.t_nozzle[:] = np.nan
        self.gate_run = np.zeros((n, 4), dtype=np.int64)  # consecutive gated readings of each kind
        self._template_cache: dict[float, tuple[FloatArray, FloatArray, FloatArray]] = {}
        self._init_replay(n, _FIELDS)
        everyone = np.arange(n)
        if position_m is not None:
            pos = np.asarray(position_m, dtype=float).reshape(n, 2)
            self._set_states(everyone, [0, 1], pos, np.eye(2) * p.gps_sigma_m**2)
            self.pos_init[:] = True
        if heading_rad is not None:
            head = np.broadcast_to(np.asarray(heading_rad, dtype=float), (n,))
            self._set_states(everyone, [4], wrap_angle(head)[:, None], np.array([[p.compass_sigma_rad**2]]))
            self.heading_init[:] = True

    def __getstate__(self) -> dict:
        """The bank's attributes without the views of `_floats` (copied or pickled, they would come apart from
        it); __setstate__ makes them again."""
        views = {name for name, _ in _FLOAT_FIELDS}
        return {key: value for key, value in self.__dict__.items() if key not in views}

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        _float_fields(self, self._floats)

    # ------------------------------------------------------------ readings (the batch API)

    def predict(
        self,
        agents: IntArray,
        t_s: ArrayLike,
        accel_body: FloatArray | None = None,
        thrust_world_n: FloatArray | None = None,
    ) -> None:
        """Predict agents to t_s (s) with accelerometer readings (k, 2) (body frame: x forward, y left; m/s^2)
        taken at t_s, if any, and the thrust commands (k, 2) (world frame, N) in force over the interval that
        ends at t_s and for thrust_hold_s after it, if any."""
        self._predict(agents, t_s, accel_body, thrust_world_n)

    def update_imu(self, agents: IntArray, t_s: ArrayLike, accel_body: FloatArray, gyro_z_radps: FloatArray) -> None:
        """An IMU reading: predict with the accelerometer (held thrust), then fuse the gyro."""
        self._predict(agents, t_s, accel_body, None)
        self._update_gyro(agents, t_s, gyro_z_radps)

    def update_gps(
        self,
        agents: IntArray,
        t_s: ArrayLike,
        xy_m: FloatArray,
        velocity_mps: FloatArray | None = None,
        accuracy_m: ArrayLike | None = None,
        speed_accuracy_mps: ArrayLike | None = None,
    ) -> None:
        """Fuse fixes (k, 2) (local x east, y north, m) measured at t_s, and ground velocities (k, 2) m/s if given.
        accuracy_m, speed_accuracy_mps (k,): the receivers' own one-sigma horizontal and speed accuracies, m and
        m/s (0 or NaN: not reported). A fix is fused with the larger of each and the filter's own noise
        (`gps_sigma_m`, `gps_velocity_sigma_mps`), as ArduPilot's EKF3 does (max(gpsPosAccuracy, EK3_POSNE_M_NSE),
        max(gpsSpdAccuracy, EK3_VELNE_M_NSE): libraries/AP_NavEKF3)."""
        self._update_gps(agents, t_s, xy_m, velocity_mps, accuracy_m, speed_accuracy_mps)

    def update_compass(self, agents: IntArray, heading_rad: FloatArray, t_s: ArrayLike | None = None) -> None:
        """Compass headings (rad) measured at t_s (None: at each filter's current time)."""
        self._update_compass(agents, heading_rad, t_s)

    def update_gyro(self, agents: IntArray, t_s: ArrayLike, yaw_rate_radps: FloatArray) -> None:
        """Gyro yaw rates (rad/s, CCW positive) measured at t_s."""
        self._update_gyro(agents, t_s, yaw_rate_radps)

    def _predict(
        self, agents: ArrayLike, t_s: ArrayLike, accel: ArrayLike | None, thrust: ArrayLike | None
    ) -> IntArray:
        idx, t = self._batch(agents, t_s)
        return self._submit(_PREDICT, idx, t, (_vectors(accel, idx.size), _vectors(thrust, idx.size)))

    def _update_gps(
        self,
        agents: ArrayLike,
        t_s: ArrayLike,
        xy: ArrayLike,
        vel: ArrayLike | None,
        accuracy: ArrayLike | None = None,
        speed_accuracy: ArrayLike | None = None,
    ) -> IntArray:
        idx, t = self._batch(agents, t_s)
        vel = _vectors(vel, idx.size)
        return self._submit(
            _GPS, idx, t, (_vectors(xy, idx.size), vel, self._reported(idx.size, accuracy, speed_accuracy, vel))
        )

    def _reported(
        self, k: int, accuracy: ArrayLike | None, speed_accuracy: ArrayLike | None, vel: FloatArray | None
    ) -> FloatArray | None:
        """(k, 2) the receivers' accuracies (m, m/s; 0 where not reported), or None when none is worse than the
        filter's own noise, which then stands alone (the same arithmetic as without a report)."""
        p = self.params
        position, speed = (
            np.zeros(k) if values is None else _finite_or_zero(_scalars(values, k))
            for values in (accuracy, speed_accuracy)
        )
        worse = (position > p.gps_sigma_m).any() or (vel is not None and (speed > p.gps_velocity_sigma_mps).any())
        return np.column_stack((position, speed)) if worse else None

    def _update_gyro(self, agents: ArrayLike, t_s: ArrayLike, rate: ArrayLike) -> IntArray:
        idx, t = self._batch(agents, t_s)
        return self._submit(_GYRO, idx, t, (_scalars(rate, idx.size),))

    def _update_compass(self, agents: ArrayLike, heading: ArrayLike, t_s: ArrayLike | None) -> IntArray:
        if t_s is not None:
            idx, t = self._batch(agents, t_s)
            return self._submit(_COMPASS, idx, t, (_scalars(heading, idx.size),))
        idx = np.asarray(agents, dtype=np.intp).reshape(-1)
        head = _scalars(heading, idx.size)
        t = self.t[idx].copy()
        codes = np.full(idx.size, _REJECTED)
        clockless = np.isnan(t) & np.isfinite(head)
        if clockless.any():  # no clock yet: the reading can only initialise the heading (not logged)
            rows = idx[clockless]
            first = ~self.heading_init[rows]
            self._initial_heading(rows[first], head[clockless][first])
            codes[np.flatnonzero(clockless)] = np.where(first, _INIT, _IGNORED)
        rest = ~clockless
        if rest.any():
            codes[rest] = self._submit(_COMPASS, idx[rest], np.where(np.isnan(t[rest]), 0.0, t[rest]), (head[rest],))
        return codes

    def _older_than_log(self, kind: int, idx: IntArray, t: FloatArray, data: tuple) -> IntArray:
        """A vessel's first fix may be dated (when its autopilot read it, less the GPS's lag) before the first
        IMU round its filter logged, so there is no state to replay it from. Without a position there is nothing
        to keep either: such a fix sets the position at the filter's time, carried there at the fix's ground
        velocity when it has one (xy + v (t_filter - t_fix)). Dropped, a vessel would wait for a later fix, and
        an autopilot whose world stands still (a fleet before its start) sends none."""
        first = (kind == _GPS) & ~self.pos_init[idx]
        if not first.any():
            return super()._older_than_log(kind, idx, t, data)
        codes = np.full(idx.size, _LATE)
        rest = np.flatnonzero(~first)
        if rest.size:
            codes[rest] = super()._older_than_log(kind, idx[rest], t[rest], _take(data, rest))
        rows = np.flatnonzero(first)
        agents, clock = idx[rows], self.t[idx[rows]]
        xy, vel, acc = _take(data, rows)
        if vel is not None:
            xy = xy + vel * (clock - t[rows])[:, None]  # as ArduPilot's EKF3 ResetPosition carries its fix
        codes[rows] = self._run(_GPS, agents, clock, (xy, vel, acc))
        return codes

    # ------------------------------------------------------------ outputs

    def estimate(self, t_s: ArrayLike) -> PoseEstimate:
        """Poses of the N agents, position and heading extrapolated to t_s (never backwards); never NaN."""
        dt = np.maximum(0.0, np.asarray(t_s, dtype=float) - self.t)
        dt = np.where(np.isnan(dt), 0.0, dt)
        x = self.x
        return PoseEstimate(x[:, 0:2] + x[:, 2:4] * dt[:, None], x[:, 2:4].copy(), wrap_angle(x[:, 4] + x[:, 5] * dt))

    def drift(self) -> FloatArray:
        """(N, 2) estimated equivalent drift over ground (see bob_autonomy.estimation), m/s."""
        return self.x[:, 6:8].copy()

    def accel_bias(self) -> FloatArray:
        """(N, 2) estimated accelerometer bias (body frame), m/s^2."""
        return self.x[:, 8:10].copy()

    def initialized(self) -> NDArray[np.bool_]:
        """(N,) whether position and heading have been set (by readings or at construction)."""
        return self.pos_init & self.heading_init

    def covariance_trace(self) -> FloatArray:
        """(N,) trace of each agent's position covariance, m^2."""
        return self.P[:, 0, 0] + self.P[:, 1, 1]

    @property
    def model_gated(self) -> int:
        """Drag-balance pseudo-measurements rejected by the gate."""
        return int(self.outcome_counts("model_gated").sum())

    # ------------------------------------------------------------ readings, in time order

    def _handle(self, kind: int, idx: IntArray, t: FloatArray, data: tuple) -> IntArray:
        """Readings of one kind for rows idx at times t, in time order: predict to t, then fuse by kind."""
        unset = np.isnan(self.t[idx])  # no reading yet: the clock starts at this one's time
        if any_row(unset):
            self.t[idx[unset]] = t[unset]
        if kind == _PREDICT:
            return self._handle_predict(idx, t, *data)
        self._propagate(idx, t)
        if kind == _GPS:
            return self._handle_gps(idx, *data)
        if kind == _COMPASS:
            return self._handle_compass(idx, *data)
        if kind == _GYRO:
            return self._handle_gyro(idx, *data)
        raise ValueError(f"unknown reading kind {kind!r}")
