"""Extended Kalman filters for the BoB buoy and the eBot.

The buoy filter runs as a bank: `BuoyEkfBank` holds N independent buoy EKFs in
numpy arrays (rows = agents) and handles each call for all its rows at once;
`BuoyEkf` is a bank of one, so a vessel's own filter runs the same code as a
simulated fleet's. Its filter equations are those of filterpy's
`ExtendedKalmanFilter` (predict P = F P F^T + Q; update in Joseph form) written
over a stack of filters (`kalman_predict_rows`, `kalman_update_rows`;
tests/test_ekf.py checks them against filterpy row by row). The eBot filter
(`EbotEkf`) is one filterpy `ExtendedKalmanFilter` per robot, `EbotEkfBank`
holds N of them. Both banks have the batch API of
`bob_autonomy.simple_estimator` (update_gps, update_compass, update_encoders,
estimate -> PoseEstimate), which they replace. Frames: x east, y north (m);
headings in rad from east, counter-clockwise, wrapped to (-pi, pi]; the body
frame is x forward along the heading, y to the left.

Buoy (`BuoyEkfBank`, `BuoyEkf`)
-------------------------------
State s = [x, y, vx, vy, heading, yaw_rate, drift_x, drift_y, bias_x, bias_y]:
position (m), velocity over ground v (m/s), heading (rad), yaw rate r (rad/s),
the equivalent drift d (m/s, below) and the accelerometer bias b (body frame,
m/s^2).

What the drift is. The filter models the hull as the autonomy's nominal buoy
(velocity_control.BuoyModel, the MPC's model too): M dv/dt = T - f(v - d),
f(w) = (c1 + c2 |w|) w, with the thrust T known and d the velocity of "the
water" (M = 35 kg with added mass, c1 = 5 N s/m, c2 = 40 N s^2/m^2). On real
water a hull moving at v is pushed by E(v): drag from the surface water
(current plus wind-driven drift) and windage on the hull. The EQUIVALENT DRIFT
at v is the d for which the nominal law gives that same push, f(d - v) = E(v)
(`sitl.dynamics.equivalent_drift_mps` computes it from the simulator's force
balance). For an unpowered buoy it is the velocity over ground the buoy settles
to (there E = 0, so d = v); for a buoy holding station it is the water velocity
whose drag alone on a hull at rest equals water and wind together. The two
differ (by 0.02 to 0.09 m/s in a 5 m/s wind with a 0.1 m/s current): drag grows
with the square of the speed through the water, and a hull at one operating
velocity only ever feels E at that velocity, so where it would settle if
unpowered (which depends on how E splits into water and wind) is not observable
from it without a wind sensor. The filter therefore estimates d at the operating
velocity, which is what makes the nominal model, and the MPC that takes d as its
water, right where the buoy is. d is a slow random walk (PSD `drift_psd`,
0.003^2 m^2/s^3): it follows a change of operating point within tens of seconds.

Process model, integrated in sub-steps of at most `max_step_s` (0.25 s) with
p += v h + a h^2 / 2, v += a h, heading += r h; r, d and b are random walks. The
acceleration a over ground comes from, in order of preference:
  1. the accelerometer: a = R(heading) (a_body - b), the body-frame reading less
     the bias rotated by the ESTIMATED heading (the Jacobian carries how heading
     and bias errors feed velocity errors). The reading given to
     `predict(t, accel_body)` is the mean acceleration over the interval that
     ends at t (a sample describes the motion just past); it is then held for
     `accel_hold_s` (0.1 s) of predictions to later measurement times. Its white
     noise `accel_noise_mps2` (0.05 m/s^2) spreads over the interval H it covers:
     velocity PSD accel_noise^2 H + `accel_psd` (0.01^2 m^2/s^3, unmodelled
     motion). The bias (prior 0.05 m/s^2, random walk PSD `accel_bias_psd`
     1e-4^2 m^2/s^5) is observable through GPS: it is the gap between the
     integrated readings and the ground velocity;
  2. else, with a known thrust command, the nominal model M a = T - f(v - d),
     PSD `model_psd` (0.1^2 m^2/s^3, model error);
  3. else constant velocity, PSD `free_psd` (0.3^2 m^2/s^3: any manoeuvre).
Yaw rate: random walk, PSD `yaw_accel_psd` (0.05^2 rad^2/s^3). Position/velocity
and heading/yaw-rate noise use the exact piecewise-white blocks
q [[h^3/3, h^2/2], [h^2/2, h]].

The thrust and the nozzle. `predict(t, accel_body, thrust_world_n)` takes the
world-frame command (N) in force over the interval ending at t, the one that
produced the acceleration read at t; it stays in force for `thrust_hold_s` (1 s)
after t. The thrust on the hull lags the command: the vectored nozzle turns
relative to the hull at most `thrust_slew_radps` (3 rad/s; a reversal takes
~1 s, time enough for the real thrust to point 20 N away from a swinging
command). The filter turns a believed nozzle angle (forward at power-up) towards
each command's body-frame direction (its direction less the estimated heading)
at that rate, the magnitude following at once, and takes the mean body-frame
thrust T_b over the interval.

How the drift is observed: the drag balance. Each accelerometer reading that
comes with a command in force (once position and heading are known) is fused as
a pseudo-measurement a_body = T_b / M - R(heading)^T f(v_mid - d) / M + b at the
interval's midpoint velocity v_mid = v - R (a_body - b) H / 2 (the reading is a
mean over H), sigma `drag_balance_sigma_mps2` (0.1 m/s^2: sensor noise and
drag-model error), gated like a sensor (counted in `model_gated`);
`gate_reset_count` consecutive gated balances re-open the drift to its prior
(outcome 'model_reset'). GPS pins v (positions, Doppler velocity) and with it b;
the balance then gives d, to within M db / (c1 + 2 c2 |v - d|) for a bias error
db (7 db for an unpowered buoy, whose drag is softest). Without an
accelerometer, model (2) is what ties d to the velocity GPS sees: v relaxes
towards d + w_T, w_T the velocity through the water at which drag balances T.
With no thrust command the drift is not observable: it stays a random walk and
its variance grows (a caller that knows the buoy is idle passes zero thrust).

Measurement models (z = h(s) + noise):
  * GPS (`update_gps`): [x, y] (sigma `gps_sigma_m` 2 m per axis), plus
    [vx, vy] when the receiver's ground velocity is given (sigma
    `gps_velocity_sigma_mps` 0.1 m/s). The first fix initialises position (and
    velocity).
  * compass (`update_compass`): heading, sigma `compass_sigma_rad` (2 deg; the
    compass bias is not modelled), innovation wrapped to (-pi, pi]. The first
    reading initialises the heading; until then the accelerometer is ignored
    (it cannot be rotated into the world).
  * gyro (`update_gyro`): yaw rate, sigma `gyro_sigma_radps` (0.006 rad/s).

eBot (`EbotEkf`)
----------------
State [x, y, heading]. Prediction from wheel-encoder odometry: the cumulative
ticks give wheel travels dl, dr since the last reading; ds = (dl + dr) / 2,
dheading = (dr - dl) / wheel_base (or gyro_z * dt when a gyro reading comes
with the encoders); midpoint integration x += ds cos(heading + dheading / 2),
etc. Wheel-travel noise has a standard deviation proportional to the distance,
`wheel_noise_fraction` (0.05, as the simulator's per-step wheel slip) times |d|,
plus the tick quantisation (metres_per_tick^2 / 6 for the two readings), mapped
through the motion Jacobian; a gyro heading change has sigma
`gyro_sigma_radps` * dt. Corrections: compass (2 deg) and, when one exists, a
position fix `update_position(t, xy, sigma_m)`. Between encoder readings the
pose is held (an eBot's encoders are read every control step).

Robustness (both filters)
-------------------------
* Non-finite readings (NaN/inf in the time or any value) are never fused; they
  are counted in `rejected` and leave the filter untouched.
* Innovation gate: a reading whose squared Mahalanobis distance y^T S^-1 y
  exceeds the chi-square 99.9 % quantile for its dimension (10.83, 13.82,
  16.27, 18.47 for 1-4) is not fused and is counted in `gated` (a 100 m GPS
  jump is rejected). So that a filter that has lost track cannot lock itself
  out for ever, `gate_reset_count` (10) consecutive gated readings of one
  sensor re-initialise what it measures from the reading (counted in `resets`).
* Updates use the Joseph-form covariance update; P is symmetrised after every
  prediction and update; a step that would leave a non-finite state or a
  non-positive variance is undone (counted in `failures`). Estimates are never
  NaN: before its first fix a buoy reports its prior (the origin unless given;
  see `initialized`).
* Time. Each reading is fused at its own measurement time t_s: the filter
  first predicts to t_s. A reading older than the filter's time (out of order,
  e.g. a GPS fix delivered 0.1 s late after IMU predictions) is fused by
  stored-state replay: every call is logged with the filter state after it,
  for `replay_window_s` (1 s); the filter goes back to the state just before
  t_s, fuses the late reading there and re-runs the later calls, which gives
  exactly the result of an in-order arrival (the buoy bank re-runs the agents
  of one logged call together). Readings older than the window are rejected and
  counted in `late`.
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from bob_autonomy.estimation.buoy_params import (
    _AS_MODEL_OUTCOME,
    _COMPASS,
    _DRAG,
    _EYE2,
    _EYE_NX,
    _FAILED,
    _FIELDS,
    _FUSED,
    _GATED,
    _GPS,
    _GYRO,
    _IGNORED,
    _INIT,
    _LATE,
    _NX,
    _PREDICT,
    _PREDICTED,
    _REJECTED,
    _RESET,
    OUTCOMES,
    BuoyEkfParams,
)
from bob_autonomy.estimation.ebot_ekf import EbotEkf, EbotEkfBank, EbotEkfParams
from bob_autonomy.estimation.kalman_rows import (
    CHI2_999,
    _healthy_rows,
    _transpose,
    kalman_predict_rows,
    kalman_update_rows,
    wrap_angle,
)
from bob_autonomy.simple_estimator import FloatArray, IntArray, PoseEstimate
from bob_autonomy.velocity_control import BuoyModel

__all__ = [
    "CHI2_999",
    "OUTCOMES",
    "BuoyEkf",
    "BuoyEkfBank",
    "BuoyEkfParams",
    "EbotEkf",
    "EbotEkfBank",
    "EbotEkfParams",
    "kalman_predict_rows",
    "kalman_update_rows",
    "wrap_angle",
]

_TIME_EPS_S = 1e-12


# =========================================================================== buoy


def _drag_rows(w: FloatArray, model: BuoyModel) -> tuple[FloatArray, FloatArray]:
    """Nominal water drag f(w) = (c1 + c2 |w|) w (m, 2), N, at velocities through the water w (m, 2), m/s, and
    its Jacobian df/dw = (c1 + c2 |w|) I + c2 w w^T / |w| (m, 2, 2), N s/m."""
    c1, c2 = model.linear_drag_n_per_mps, model.quadratic_drag_n_per_mps2
    speed = np.hypot(w[:, 0], w[:, 1])
    coef = c1 + c2 * speed
    outer = w[:, :, None] * w[:, None, :]
    jac = coef[:, None, None] * _EYE2 + (c2 / np.maximum(speed, 1e-9))[:, None, None] * outer
    return coef[:, None] * w, jac


def _rotations(heading_rad: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """cos, sin (m,) and the body-to-world rotations R (m, 2, 2) of headings (m,) rad."""
    c, s = np.cos(heading_rad), np.sin(heading_rad)
    rot = np.empty((c.size, 2, 2))
    rot[:, 0, 0], rot[:, 0, 1], rot[:, 1, 0], rot[:, 1, 1] = c, -s, s, c
    return c, s, rot


def _process_templates(p: BuoyEkfParams, h: float | FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """See BuoyEkfBank._templates; h is a scalar or (m, 1, 1) sub-steps, s."""
    h2, h3 = 0.5 * h * h, h**3 / 3.0
    f_base = _EYE_NX + h * _F_STEP
    q_pattern = h3 * _Q_CUBE + h2 * _Q_SQUARE + h * _Q_LINE
    yaw = p.yaw_accel_psd * (h3 * _Q_YAW_CUBE + h2 * _Q_YAW_SQUARE + h * _Q_YAW_LINE)
    q_fixed = yaw + h * (p.drift_psd * _Q_DRIFT + p.accel_bias_psd * _Q_BIAS)
    return f_base, q_pattern, q_fixed


def _unit(*cells: tuple[int, int]) -> FloatArray:
    """A 10 x 10 matrix with ones at the cells given."""
    out = np.zeros((_NX, _NX))
    for i, j in cells:
        out[i, j] = 1.0
    return out


_F_STEP = _unit((0, 2), (1, 3), (4, 5))  # p += v h, heading += r h
_Q_CUBE, _Q_SQUARE, _Q_LINE = _unit((0, 0), (1, 1)), _unit((0, 2), (2, 0), (1, 3), (3, 1)), _unit((2, 2), (3, 3))
_Q_YAW_CUBE, _Q_YAW_SQUARE, _Q_YAW_LINE = _unit((4, 4)), _unit((4, 5), (5, 4)), _unit((5, 5))
_Q_DRIFT, _Q_BIAS = _unit((6, 6), (7, 7)), _unit((8, 8), (9, 9))


class BuoyEkfBank:
    """N buoy EKFs held in arrays, rows = agents, behind the batch API of AlphaBetaBuoyEstimator.

    n: number of buoys; position_m (n, 2), heading_rad (n,): initial poses if known (else the first GPS fix and
    compass reading set them); params: BuoyEkfParams. Each agent is an independent filter (see the module
    docstring); a call handles all its rows at once with numpy (an agent given twice in one call is handled
    row by row, in order).

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
        self.x = np.zeros((n, _NX))
        self.P = np.tile(np.diag(np.square(sig)), (n, 1, 1))
        self.t = np.full(n, np.nan)
        self.pos_init = np.zeros(n, dtype=bool)
        self.heading_init = np.zeros(n, dtype=bool)
        self.accel = np.full((n, 2), np.nan)  # the accelerometer reading in use (body frame), and its time
        self.t_accel = np.full(n, -np.inf)
        self.thrust = np.full((n, 2), np.nan)  # the thrust command in force (world frame), and its time
        self.t_thrust = np.full(n, -np.inf)
        self.nozzle = np.zeros(n)  # believed nozzle angle relative to the hull (rad), and when it was last slewed
        self.t_nozzle = np.full(n, np.nan)
        self.gate_run = np.zeros((n, 4), dtype=np.int64)  # consecutive gated readings of each kind
        self._template_cache: dict[float, tuple[FloatArray, FloatArray, FloatArray]] = {}
        self._rejected = np.zeros(n, dtype=np.int64)
        self._late = np.zeros(n, dtype=np.int64)
        self._pruned = np.zeros((n, len(OUTCOMES)), dtype=np.int64)  # outcomes of entries gone from the logs
        # Replay logs, one per agent: entries [t, call, row in call, snapshot block, row in block, outcome].
        self._logs: list[list[list]] = [[] for _ in range(n)]
        self._times: list[list[float]] = [[] for _ in range(n)]
        everyone = np.arange(n)
        if position_m is not None:
            pos = np.asarray(position_m, dtype=float).reshape(n, 2)
            self._set_states(everyone, [0, 1], pos, np.eye(2) * p.gps_sigma_m**2)
            self.pos_init[:] = True
        if heading_rad is not None:
            head = np.broadcast_to(np.asarray(heading_rad, dtype=float), (n,))
            self._set_states(everyone, [4], wrap_angle(head)[:, None], np.array([[p.compass_sigma_rad**2]]))
            self.heading_init[:] = True

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
        self, agents: IntArray, t_s: ArrayLike, xy_m: FloatArray, velocity_mps: FloatArray | None = None
    ) -> None:
        """Fuse fixes (k, 2) (local x east, y north, m) measured at t_s, and ground velocities (k, 2) m/s if given."""
        self._update_gps(agents, t_s, xy_m, velocity_mps)

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

    def _update_gps(self, agents: ArrayLike, t_s: ArrayLike, xy: ArrayLike, vel: ArrayLike | None) -> IntArray:
        idx, t = self._batch(agents, t_s)
        return self._submit(_GPS, idx, t, (_vectors(xy, idx.size), _vectors(vel, idx.size)))

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

    # ------------------------------------------------------------ outputs

    def estimate(self, t_s: ArrayLike) -> PoseEstimate:
        """Poses of the N agents, position and heading extrapolated to t_s (never backwards); never NaN."""
        dt = np.maximum(0.0, np.asarray(t_s, dtype=float) - self.t)
        dt = np.where(np.isnan(dt), 0.0, dt)
        x = self.x
        return PoseEstimate(x[:, 0:2] + x[:, 2:4] * dt[:, None], x[:, 2:4].copy(), wrap_angle(x[:, 4] + x[:, 5] * dt))

    def drift(self) -> FloatArray:
        """(N, 2) estimated equivalent drift over ground (see the module docstring), m/s."""
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

    def outcome_counts(self, outcome: str) -> NDArray[np.int64]:
        """(N,) how many readings of each agent had this outcome (one of OUTCOMES), replays accounted for."""
        code = OUTCOMES.index(outcome)
        if code == _REJECTED:
            return self._rejected.copy()
        if code == _LATE:
            return self._late.copy()
        live = np.array([sum(e[5] == code for e in log) for log in self._logs], dtype=np.int64)
        return self._pruned[:, code] + live

    @property
    def rejected(self) -> int:
        """Non-finite readings (never fused)."""
        return int(self._rejected.sum())

    @property
    def late(self) -> int:
        """Readings older than the replay window."""
        return int(self._late.sum())

    @property
    def gated(self) -> int:
        """Sensor readings rejected by the innovation gate."""
        return int(self.outcome_counts("gated").sum())

    @property
    def resets(self) -> int:
        """Re-initialisations after gate_reset_count consecutive gated readings of one sensor."""
        return int(self.outcome_counts("reset").sum())

    @property
    def model_gated(self) -> int:
        """Drag-balance pseudo-measurements rejected by the gate."""
        return int(self.outcome_counts("model_gated").sum())

    @property
    def failures(self) -> int:
        """Steps undone because they would have left a non-finite or non-positive-definite state."""
        return int(self.outcome_counts("failed").sum())

    # ------------------------------------------------------------ time, log and replay

    @staticmethod
    def _batch(agents: ArrayLike, t_s: ArrayLike) -> tuple[IntArray, FloatArray]:
        idx = np.asarray(agents, dtype=np.intp).reshape(-1)
        return idx, _scalars(t_s, idx.size)

    def _submit(self, kind: int, idx: IntArray, t: FloatArray, data: tuple) -> IntArray:
        """Handle a call's readings (rows idx at times t): in order, or by replay; returns the outcome codes."""
        k = idx.size
        if k > 1 and np.unique(idx).size < k:  # an agent twice in one call: one row at a time, in order
            return np.concatenate(
                [self._submit(kind, idx[i : i + 1], t[i : i + 1], _take(data, [i])) for i in range(k)]
            )
        codes = np.full(k, _REJECTED)
        good = np.isfinite(t)
        for values in data:
            if values is not None:
                good &= np.isfinite(values.reshape(k, -1)).all(axis=1)
        if not good.all():
            np.add.at(self._rejected, idx[~good], 1)
        clock = self.t[idx]
        in_order = good & ~(t < clock)  # NaN clock (no reading yet): in order
        late = good & (t < clock)
        if in_order.all():
            codes = self._run(kind, idx, t, data)
        elif in_order.any():
            rows = np.flatnonzero(in_order)
            codes[rows] = self._run(kind, idx[rows], t[rows], _take(data, rows))
        if late.any():
            rows = np.flatnonzero(late)
            codes[rows] = self._replay(kind, idx[rows], t[rows], _take(data, rows))
        return codes

    def _run(self, kind: int, idx: IntArray, t: FloatArray, data: tuple) -> IntArray:
        """In-order readings: handle, log with a snapshot, prune the logs."""
        codes = self._handle(kind, idx, t, data)
        call = (kind, data)
        block = self._snapshot(idx)
        window = self.params.replay_window_s
        pruned = self._pruned
        for r, (a, ta, code, now) in enumerate(
            zip(idx.tolist(), t.tolist(), codes.tolist(), self.t[idx].tolist(), strict=True)
        ):
            log, times = self._logs[a], self._times[a]
            log.append([ta, call, r, block, r, code])
            times.append(ta)
            cut = now - window  # keep the window's entries and the one before (the state to restart from)
            if len(times) > 1 and times[1] <= cut:
                j = bisect.bisect_right(times, cut) - 1
                for entry in log[:j]:
                    pruned[a, entry[5]] += 1
                del log[:j], times[:j]
        return codes

    def _replay(self, kind: int, idx: IntArray, t: FloatArray, data: tuple) -> IntArray:
        """Late readings: back to the state just before each, fuse it there, re-run the later entries."""
        codes = np.full(idx.size, _LATE)
        live: list[tuple[int, int, int]] = []  # (row in this call, agent, insertion index in its log)
        restore: dict[int, tuple[tuple, list[int], list[int]]] = {}
        for r, (a, ta) in enumerate(zip(idx.tolist(), t.tolist(), strict=True)):
            times = self._times[a]
            if not times or ta < times[0]:
                self._late[a] += 1
                continue
            j = bisect.bisect_right(times, ta)  # >= 1
            previous = self._logs[a][j - 1]
            group = restore.setdefault(id(previous[3]), (previous[3], [], []))
            group[1].append(a)
            group[2].append(previous[4])
            live.append((r, a, j))
        if not live:
            return codes
        for block, agents, rows in restore.values():
            self._restore(np.array(agents), block, np.array(rows))
        rows_in_call = np.array([r for r, _, _ in live])
        agents = idx[rows_in_call]
        sub = _take(data, rows_in_call)
        new_codes = self._handle(kind, agents, t[rows_in_call], sub)
        codes[rows_in_call] = new_codes
        call = (kind, sub)
        block = self._snapshot(agents)
        pending: list[tuple[int, list]] = []
        for n, ((r, a, j), code) in enumerate(zip(live, new_codes.tolist(), strict=True)):
            self._logs[a].insert(j, [float(t[r]), call, n, block, n, code])
            self._times[a].insert(j, float(t[r]))
            pending.append((a, self._logs[a][j + 1 :]))
        depth = 0
        while True:  # re-run the later entries, round by round; the agents of one logged call together
            groups: dict[int, list[tuple[int, list]]] = {}
            for a, entries in pending:
                if depth < len(entries):
                    groups.setdefault(id(entries[depth][1]), []).append((a, entries[depth]))
            if not groups:
                break
            for members in groups.values():
                kind_e, data_e = members[0][1][1]
                agents_e = np.array([a for a, _ in members])
                t_e = np.array([e[0] for _, e in members])
                redo = self._handle(kind_e, agents_e, t_e, _take(data_e, [e[2] for _, e in members]))
                block_e = self._snapshot(agents_e)
                for n, ((_, entry), code) in enumerate(zip(members, redo.tolist(), strict=True)):
                    entry[3], entry[4], entry[5] = block_e, n, code
            depth += 1
        return codes

    def _snapshot(self, idx: IntArray) -> tuple:
        return tuple(getattr(self, name)[idx] for name in _FIELDS)  # fancy indexing copies

    def _restore(self, idx: IntArray, block: tuple, rows: IntArray) -> None:
        for name, values in zip(_FIELDS, block, strict=True):
            getattr(self, name)[idx] = values[rows]

    # ------------------------------------------------------------ readings, in time order

    def _handle(self, kind: int, idx: IntArray, t: FloatArray, data: tuple) -> IntArray:
        clock = self.t[idx]
        self.t[idx] = np.where(np.isnan(clock), t, clock)
        if kind == _PREDICT:
            return self._handle_predict(idx, t, *data)
        self._propagate(idx, t)
        p = self.params
        if kind == _GPS:
            return self._handle_gps(idx, *data)
        if kind == _COMPASS:
            codes = np.full(idx.size, _INIT)
            heading = wrap_angle(data[0])
            first = ~self.heading_init[idx]
            self._initial_heading(idx[first], heading[first])
            rows = np.flatnonzero(~first)
            if rows.size:
                agents = idx[rows]
                h_jac = np.zeros((1, _NX))
                h_jac[0, 4] = 1.0
                r_cov = np.array([[p.compass_sigma_rad**2]])
                z = heading[rows][:, None]
                codes[rows] = self._fuse(agents, _COMPASS, z, self.x[agents, 4:5], h_jac, r_cov, True, [4])
                self.x[agents, 4] = wrap_angle(self.x[agents, 4])
            return codes
        if kind == _GYRO:
            h_jac = np.zeros((1, _NX))
            h_jac[0, 5] = 1.0
            r_cov = np.array([[p.gyro_sigma_radps**2]])
            return self._fuse(idx, _GYRO, data[0][:, None], self.x[idx, 5:6], h_jac, r_cov, False, [5])
        raise ValueError(f"unknown reading kind {kind!r}")

    def _handle_gps(self, idx: IntArray, xy: FloatArray, vel: FloatArray | None) -> IntArray:
        p = self.params
        cols = [0, 1] if vel is None else [0, 1, 2, 3]
        z = xy if vel is None else np.concatenate((xy, vel), axis=1)
        sig = [p.gps_sigma_m] * 2 + ([] if vel is None else [p.gps_velocity_sigma_mps] * 2)
        r_cov = np.diag(np.square(sig))
        codes = np.full(idx.size, _INIT)
        first = ~self.pos_init[idx]
        if first.any():  # the first fix initialises position (and velocity), however far from the prior
            self._set_states(idx[first], cols, z[first], r_cov)
            self.pos_init[idx[first]] = True
        rows = np.flatnonzero(~first)
        if rows.size:
            agents = idx[rows]
            h_jac = np.zeros((len(cols), _NX))
            h_jac[range(len(cols)), cols] = 1.0
            codes[rows] = self._fuse(agents, _GPS, z[rows], self.x[agents][:, cols], h_jac, r_cov, False, cols)
        return codes

    def _initial_heading(self, idx: IntArray, heading: FloatArray) -> None:
        if idx.size:
            r_cov = np.array([[self.params.compass_sigma_rad**2]])
            self._set_states(idx, [4], wrap_angle(heading)[:, None], r_cov)
            self.heading_init[idx] = True

    def _handle_predict(
        self, idx: IntArray, t: FloatArray, accel: FloatArray | None, thrust: FloatArray | None
    ) -> IntArray:
        """Slew the believed nozzle, propagate to t, keep the readings for later, fuse the drag balance."""
        p = self.params
        span = t - self.t[idx]  # the interval the accelerometer reading covers
        # The command in force: the one given (over the interval ending at t), else the held one.
        if thrust is not None:
            command = thrust
        else:
            held = t < self.t_thrust[idx] + p.thrust_hold_s
            command = np.where(held[:, None], self.thrust[idx], np.nan)
        commanded = ~np.isnan(command[:, 0]) & self.heading_init[idx]
        body_thrust = np.full((idx.size, 2), np.nan)
        if commanded.any():
            rows = np.flatnonzero(commanded)
            body_thrust[rows] = self._slew(idx[rows], t[rows], command[rows], span[rows])
        failed = self._propagate(idx, t, accel, thrust)
        if accel is not None:
            self.accel[idx], self.t_accel[idx] = accel, t
        if thrust is not None:
            self.thrust[idx], self.t_thrust[idx] = thrust, t
        codes = np.where(failed, _FAILED, _PREDICTED)
        if accel is not None:
            balance = commanded & self.pos_init[idx] & ~failed
            if balance.any():
                rows = np.flatnonzero(balance)
                codes[rows] = self._drag_balance(idx[rows], accel[rows], body_thrust[rows], span[rows])
        return codes

    def _slew(self, idx: IntArray, t: FloatArray, command: FloatArray, span: FloatArray) -> FloatArray:
        """Turn the believed nozzle towards the commands (world frame, N) at thrust_slew_radps since it was last
        turned; return the mean body-frame thrust over the interval `span` (s) that ends at t."""
        magnitude = np.hypot(command[:, 0], command[:, 1])
        nozzle = self.nozzle[idx]
        target = np.where(magnitude > 1e-9, np.arctan2(command[:, 1], command[:, 0]) - self.x[idx, 4], nozzle)
        turn = wrap_angle(target - nozzle)
        since = t - self.t_nozzle[idx]
        most = self.params.thrust_slew_radps * np.where(np.isnan(since), span, since)
        reached = np.abs(turn) <= most
        delta = np.where(reached, turn, np.copysign(most, turn))
        # Fraction of the interval spent turning (the rest at the end angle); mean direction along the arc.
        turning = np.where(reached, np.abs(turn) / np.maximum(most, 1e-12), 1.0)
        half = 0.5 * delta
        arc = np.where(np.abs(half) > 1e-9, np.sin(half) / np.where(np.abs(half) > 1e-9, half, 1.0), 1.0)
        mid, end = nozzle + half, nozzle + delta
        mean = turning[:, None] * arc[:, None] * np.column_stack((np.cos(mid), np.sin(mid)))
        mean += (1.0 - turning)[:, None] * np.column_stack((np.cos(end), np.sin(end)))
        self.nozzle[idx], self.t_nozzle[idx] = wrap_angle(end), t
        return magnitude[:, None] * mean

    def _propagate(
        self, idx: IntArray, t_to: FloatArray, accel: FloatArray | None = None, thrust: FloatArray | None = None
    ) -> NDArray[np.bool_]:
        """Predict rows idx from their filter times to t_to: with `accel` over the whole interval if given, else
        with the held accelerometer reading while it lasts; with `thrust` if given, else the held command while
        it lasts. Returns which rows had a sub-step undone (non-finite or not positive definite)."""
        p = self.params
        k = idx.size
        t_now = self.t[idx].copy()
        start = t_now.copy()
        failed = np.zeros(k, dtype=bool)
        no_heading = ~self.heading_init[idx]
        while True:
            active = t_to - t_now > _TIME_EPS_S
            if not active.any():
                break
            end = t_to.copy()
            if accel is not None:
                a, a_span = accel.copy(), t_to - start
            else:
                held = t_now < self.t_accel[idx] + p.accel_hold_s
                a = np.where(held[:, None], self.accel[idx], np.nan)
                end = np.where(held, np.minimum(end, self.t_accel[idx] + p.accel_hold_s), end)
                a_span = None
            if thrust is not None:
                force = thrust
            else:
                held = t_now < self.t_thrust[idx] + p.thrust_hold_s
                force = np.where(held[:, None], self.thrust[idx], np.nan)
                end = np.where(held, np.minimum(end, self.t_thrust[idx] + p.thrust_hold_s), end)
            a[no_heading] = np.nan  # a body-frame reading cannot be rotated into the world yet
            seg = np.where(active, end - t_now, 0.0)
            steps = np.where(active, np.maximum(1, np.ceil(seg / p.max_step_s - 1e-9)), 0).astype(np.int64)
            h = seg / np.maximum(steps, 1)
            noise_span = seg if a_span is None else a_span
            for j in range(int(steps.max())):
                rows = np.flatnonzero(steps > j)
                failed[rows] |= self._step(idx[rows], h[rows], a[rows], force[rows], noise_span[rows])
            t_now = np.where(active, end, t_now)
        self.t[idx] = np.maximum(self.t[idx], t_to)
        return failed

    def _step(
        self, idx: IntArray, h: FloatArray, accel_body: FloatArray, thrust: FloatArray, accel_span: FloatArray
    ) -> NDArray[np.bool_]:
        """One prediction sub-step of h (m,) s for rows idx; the velocity model of each row is the accelerometer
        (accel_body not NaN), else the thrust/drag model (thrust not NaN), else constant velocity. Returns
        which rows failed (left unchanged)."""
        p = self.params
        m = idx.size
        x, p_cov = self.x[idx], self.P[idx]
        with_accel = ~np.isnan(accel_body[:, 0])
        with_thrust = ~with_accel & ~np.isnan(thrust[:, 0])
        a = np.zeros((m, 2))
        da_dx = np.zeros((m, 2, _NX))  # Jacobian of the acceleration over ground with respect to the state
        if with_accel.any():  # a = R(heading) (a_body - bias)
            c, s, rot = _rotations(x[:, 4])
            body = accel_body - x[:, 8:10]
            a_accel = np.column_stack((c * body[:, 0] - s * body[:, 1], s * body[:, 0] + c * body[:, 1]))
            a_accel[~with_accel] = 0.0
            rot[~with_accel] = 0.0
            a += a_accel
            da_dx[:, 0, 4], da_dx[:, 1, 4] = -a_accel[:, 1], a_accel[:, 0]
            da_dx[:, :, 8:10] = -rot
        if with_thrust.any():  # M a = T - f(v - d)
            drag, jac = _drag_rows(x[:, 2:4] - x[:, 6:8], p.model)
            mask = with_thrust / p.model.mass_kg
            a += np.where(with_thrust[:, None], thrust - drag, 0.0) / p.model.mass_kg
            jac *= mask[:, None, None]
            da_dx[:, :, 2:4] = -jac
            da_dx[:, :, 6:8] = jac
        q = np.where(with_accel, p.accel_psd + p.accel_noise_mps2**2 * accel_span, p.free_psd)
        q = np.where(with_thrust, p.model_psd, q)
        f_base, q_pattern, q_fixed = self._templates(h)
        hh = 0.5 * h * h
        f_jac = f_base + np.zeros((m, 1, 1))
        f_jac[:, 0:2, :] += hh[:, None, None] * da_dx
        f_jac[:, 2:4, :] += h[:, None, None] * da_dx
        q_cov = q[:, None, None] * q_pattern + q_fixed
        x_next = x.copy()
        x_next[:, 0:2] += x[:, 2:4] * h[:, None] + a * hh[:, None]
        x_next[:, 2:4] += a * h[:, None]
        x_next[:, 4] = wrap_angle(x[:, 4] + x[:, 5] * h)
        p_next = kalman_predict_rows(p_cov, f_jac, q_cov)
        ok = _healthy_rows(x_next, p_next)
        if ok.all():
            self.x[idx], self.P[idx] = x_next, p_next
        else:
            self.x[idx[ok]], self.P[idx[ok]] = x_next[ok], p_next[ok]
        return ~ok

    def _templates(self, h: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        """For sub-steps h (m,) s: the transition's h-dependent identity part (F with p += v h, heading += r h),
        the pattern [[h^3/3, h^2/2], [h^2/2, h]] on (position, velocity) per axis that the velocity PSD scales,
        and the fixed process noise (yaw rate, drift and bias random walks). (10, 10) each, cached, when every
        row has the same h (a fleet in lockstep); else (m, 10, 10)."""
        if h.size and (h == h[0]).all():
            key = float(h[0])
            cached = self._template_cache.get(key)
            if cached is None:
                if len(self._template_cache) > 256:
                    self._template_cache.clear()
                cached = self._template_cache[key] = _process_templates(self.params, key)
            return cached
        return _process_templates(self.params, h[:, None, None])

    def _drag_balance(
        self, idx: IntArray, accel_body: FloatArray, thrust_body: FloatArray, span: FloatArray
    ) -> IntArray:
        """Fuse accelerometer readings against the drag model at the interval's midpoint velocity:
        a_body = T_body / M - R^T f(v_mid - d) / M + b, v_mid = v - R (a_body - b) span / 2."""
        p = self.params
        mass = p.model.mass_kg
        x = self.x[idx]
        c, s, rot = _rotations(x[:, 4])
        rot_t = _transpose(rot)
        body = accel_body - x[:, 8:10]
        a_world = (rot @ body[:, :, None])[:, :, 0]
        half = 0.5 * span
        drag, jac = _drag_rows(x[:, 2:4] - half[:, None] * a_world - x[:, 6:8], p.model)
        hx = thrust_body / mass - (rot_t @ drag[:, :, None])[:, :, 0] / mass + x[:, 8:10]
        dh_dw = -rot_t @ jac / mass  # d h / d v_mid
        drot_t = np.empty_like(rot_t)
        drot_t[:, 0, 0], drot_t[:, 0, 1], drot_t[:, 1, 0], drot_t[:, 1, 1] = -s, c, -c, -s
        dvmid_dpsi = -half[:, None] * np.column_stack((-a_world[:, 1], a_world[:, 0]))
        h_jac = np.zeros((idx.size, 2, _NX))
        h_jac[:, :, 2:4] = dh_dw
        h_jac[:, :, 6:8] = -dh_dw
        h_jac[:, :, 4] = (drot_t @ (-drag / mass)[:, :, None])[:, :, 0] + (dh_dw @ dvmid_dpsi[:, :, None])[:, :, 0]
        h_jac[:, :, 8:10] = _EYE2 + dh_dw @ (half[:, None, None] * rot)
        r_cov = _EYE2 * p.drag_balance_sigma_mps2**2
        codes = self._fuse(idx, _DRAG, accel_body, hx, h_jac, r_cov, False, None)
        return _AS_MODEL_OUTCOME[codes]

    # ------------------------------------------------------------ numerics

    def _set_states(self, idx: IntArray, cols: Sequence[int], z: FloatArray, r_cov: FloatArray) -> None:
        """Set states `cols` of rows idx to z (m, len(cols)) with covariance r_cov, uncorrelated with the rest."""
        cols = np.asarray(cols)
        x, p_cov = self.x[idx], self.P[idx]
        x[:, cols] = z
        p_cov[:, cols, :] = 0.0
        p_cov[:, :, cols] = 0.0
        p_cov[:, cols[:, None], cols[None, :]] = r_cov
        self.x[idx], self.P[idx] = x, p_cov

    def _fuse(
        self,
        idx: IntArray,
        kind: int,
        z: FloatArray,
        hx: FloatArray,
        h_jac: FloatArray,
        r_cov: FloatArray,
        angle: bool,
        reset_cols: Sequence[int] | None,
    ) -> IntArray:
        """Fuse z (m, k) into rows idx (Joseph form), each undone if its innovation fails the gate.

        Codes: fused, gated, failed, or reset (after gate_reset_count consecutive gated readings of this kind:
        states reset_cols re-initialised from z; for the drag balance (reset_cols None) the drift is re-opened
        to its prior instead)."""
        y = z - hx
        if angle:
            y = wrap_angle(y)
        x0, p0 = self.x[idx], self.P[idx]
        x1, p1, d2, inverted = kalman_update_rows(x0, p0, y, h_jac, r_cov)
        passed = inverted & (d2 <= CHI2_999[z.shape[1]])
        gated = inverted & ~passed
        healthy = passed & _healthy_rows(x1, p1)
        codes = np.where(healthy, _FUSED, np.where(gated, _GATED, _FAILED))
        run = np.where(passed, 0, self.gate_run[idx, kind] + gated)
        reset = gated & (run >= self.params.gate_reset_count)
        if reset.any():
            rows = idx[reset]
            if reset_cols is not None:
                self._set_states(rows, reset_cols, z[reset], r_cov)
            else:
                p_cov = self.P[rows]
                p_cov[:, 6:8, :] = 0.0
                p_cov[:, :, 6:8] = 0.0
                p_cov[:, 6, 6] = p_cov[:, 7, 7] = self.params.initial_drift_sigma_mps**2
                self.P[rows] = p_cov
            codes[reset], run[reset] = _RESET, 0
        self.gate_run[idx, kind] = run
        self.x[idx[healthy]], self.P[idx[healthy]] = x1[healthy], p1[healthy]
        return codes


def _vectors(values: ArrayLike | None, k: int) -> FloatArray | None:
    """(k, 2) float rows (a copy) of a batch argument, broadcast; None stays None."""
    if values is None:
        return None
    arr = np.array(values, dtype=float)
    return arr if arr.shape == (k, 2) else np.array(np.broadcast_to(arr, (k, 2)))


def _scalars(values: ArrayLike, k: int) -> FloatArray:
    """(k,) float values (a copy) of a batch argument, broadcast."""
    arr = np.array(values, dtype=float).reshape(-1)
    return arr if arr.size == k else np.array(np.broadcast_to(arr, (k,)))


def _take(data: tuple, rows: ArrayLike) -> tuple:
    """The given rows of each array of a call's data (None stays None)."""
    return tuple(None if values is None else values[rows] for values in data)


class BuoyEkf:
    """EKF of one buoy: [x, y, vx, vy, heading, yaw_rate, drift_x, drift_y, bias_x, bias_y] (see the module
    docstring); a BuoyEkfBank of one, so a vessel's filter and a simulated fleet's run the same code.

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

    def update_gps(self, t_s: float, xy_m: ArrayLike, velocity_mps: ArrayLike | None = None) -> str:
        """Fuse a fix (local x east, y north, m) measured at t_s, and the ground velocity (m/s) if given."""
        vel = None if velocity_mps is None else np.reshape(velocity_mps, (1, 2))
        return OUTCOMES[self.bank._update_gps(self._ROW, t_s, np.reshape(xy_m, (1, 2)), vel)[0]]

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
