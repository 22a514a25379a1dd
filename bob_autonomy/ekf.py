"""Extended Kalman filters for the BoB buoy and the eBot, built on filterpy.

One filterpy `ExtendedKalmanFilter` per vessel (a vessel runs one filter); the
`BuoyEkfBank` and `EbotEkfBank` wrappers hold N of them behind the batch API of
`bob_autonomy.simple_estimator` (update_gps, update_compass, update_encoders,
estimate -> PoseEstimate), which they replace. Frames: x east, y north (m);
headings in rad from east, counter-clockwise, wrapped to (-pi, pi]; the body
frame is x forward along the heading, y to the left.

Buoy (`BuoyEkf`)
----------------
State s = [x, y, vx, vy, heading, yaw_rate, drift_x, drift_y]: position (m),
velocity over ground v (m/s), heading (rad), yaw rate r (rad/s), and the drift
d of the surface water over ground (current + wind drift, m/s).

Process model, integrated in sub-steps of at most `max_step_s` (0.1 s) with
p += v h + a h^2 / 2, v += a h, heading += r h; r and d are random walks. The
acceleration a over ground comes from, in order of preference:
  1. the accelerometer (control input): a = R(heading) a_body, the body-frame
     reading rotated by the ESTIMATED heading (so heading errors feed velocity
     errors, and the Jacobian carries that coupling). The reading given to
     `predict(t, accel_body)` acts over the interval that ends at t (an IMU
     sample describes the motion just past) and is then held for the next
     `accel_hold_s` (0.1 s) of internal predictions (to measurement times);
     velocity process noise: white acceleration of PSD `accel_psd`
     (0.03^2 m^2/s^3: covers the 0.05 m/s^2 noise and ~0.02 m/s^2 bias);
  2. else, with a known thrust command T (world frame, N), the nominal drag
     model of `velocity_control.BuoyModel`: M a = T - (c1 + c2 |w|) w with
     w = v - d the velocity through the water (M = 35 kg with added mass,
     c1 = 5 N s/m, c2 = 40 N s^2/m^2); PSD `model_psd` (0.1^2 m^2/s^3, model
     error). A thrust command is held from its time for `thrust_hold_s` (1 s);
  3. else constant velocity, PSD `free_psd` (0.3^2 m^2/s^3: any manoeuvre).
Yaw rate: random walk, PSD `yaw_accel_psd` (0.05^2 rad^2/s^3). Drift: random
walk, PSD `drift_psd` (0.003^2 m^2/s^3, i.e. 0.023 m/s per minute).
Position/velocity and heading/yaw-rate noise use the exact piecewise-white
blocks q [[h^3/3, h^2/2], [h^2/2, h]].

How the drift is observable. GPS sees v (positions, Doppler velocity), never d
directly; v = w + d ties them through the water: the velocity through the water
is set by the thrust via the drag model (with zero thrust the buoy moves at the
drift). Without an accelerometer this is the process model (2): v relaxes
towards d + w_T, where w_T solves c1 w + c2 |w| w = T, with time constant
M / (c1 + 2 c2 |w|) ~ 1-7 s, so d is whatever lets the model explain the
velocity GPS sees. With an accelerometer (which then drives v), each IMU
reading that comes with a known thrust is also fused as a "drag balance"
pseudo-measurement: the body-frame reading must equal R(heading)^T (T - (c1 +
c2 |w|) w) / M, sigma `drag_balance_sigma_mps2` (0.1 m/s^2: sensor noise, bias
and drag-model error), gated like a sensor (count `model_gated`). Either way the
drift estimate is only as good as the nominal drag model and the thrust
command: an accelerometer bias b shifts it by ~ M b / (c1 + 2 c2 |w|) (about
0.03 m/s for 0.02 m/s^2), a 20 % drag error at 0.5 m/s through water by ~0.04
m/s. With no thrust command the drift is not observable: it stays a random walk
and its variance grows (a caller that knows the buoy is idle passes zero thrust).

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
* Updates use filterpy's Joseph-form covariance update; P is symmetrised after
  every prediction and update; a step that would leave a non-finite state or a
  non-positive variance is undone (counted in `failures`). Estimates are never
  NaN: before its first fix a buoy reports its prior (the origin unless given;
  see `initialized`).
* Time. Each reading is fused at its own measurement time t_s: the filter
  first predicts to t_s. A reading older than the filter's time (out of order,
  e.g. a GPS fix delivered 0.1 s late after IMU predictions) is fused by
  stored-state replay: every call is logged with the full filter state after
  it, for `replay_window_s` (1 s); the filter goes back to the state just
  before t_s, fuses the late reading there and re-runs the later calls, which
  gives exactly the result of an in-order arrival. Readings older than the
  window are rejected and counted in `late`.
"""

from __future__ import annotations

import bisect
import math
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from filterpy.kalman import ExtendedKalmanFilter
from numpy.typing import ArrayLike, NDArray

from bob_autonomy.simple_estimator import FloatArray, IntArray, PoseEstimate
from bob_autonomy.velocity_control import BuoyModel

# Chi-square 99.9 % quantiles by degrees of freedom (the innovation gate).
CHI2_999 = {1: 10.828, 2: 13.816, 3: 16.266, 4: 18.467}

_TIME_EPS_S = 1e-12


def wrap_angle(angle_rad: ArrayLike) -> FloatArray:
    """Angles (rad) wrapped to (-pi, pi]."""
    return np.pi - np.mod(np.pi - np.asarray(angle_rad, dtype=float), 2.0 * np.pi)


def _finite(*values: Any) -> bool:
    """Whether every value given (scalars or arrays; None is skipped) is finite."""
    for v in values:
        if v is None:
            continue
        if isinstance(v, float | int):
            if not math.isfinite(v):
                return False
        elif not np.isfinite(np.asarray(v, dtype=float)).all():
            return False
    return True


class _ModelEkf(ExtendedKalmanFilter):
    """filterpy's EKF with a nonlinear transition: the caller sets F (the Jacobian) and Q, then calls
    predict(u=x_next) with the mean propagated by the model; filterpy does P = F P F^T + Q."""

    def predict_x(self, u: Any = 0) -> None:
        self.x = u


@dataclass
class _Entry:
    """One logged call: time, kind, data; the full filter state after it and what came of it."""

    t: float
    kind: str
    data: tuple
    snapshot: Any = None
    outcome: str = ""


class _TimedEkf:
    """Shared machinery: gating, Joseph updates through filterpy, symmetrisation, and time handling with a
    replay log (see the module docstring). Subclasses provide _handle, _snapshot and _restore."""

    def __init__(self, dim_x: int, replay_window_s: float, gate_reset_count: int) -> None:
        self.kf = _ModelEkf(dim_x=dim_x, dim_z=1)
        self.t_s: float | None = None  # the filter's time: that of its latest reading
        self.rejected = 0  # non-finite readings
        self.late = 0  # readings older than the replay window
        self.replay_window_s = replay_window_s
        self.gate_reset_count = gate_reset_count
        self._gate_run: dict[str, int] = {}
        self._log: list[_Entry] = []
        self._pruned: Counter[str] = Counter()

    # ------------------------------------------------------------ counters

    def _count(self, outcome: str) -> int:
        return self._pruned[outcome] + sum(e.outcome == outcome for e in self._log)

    @property
    def gated(self) -> int:
        """Sensor readings rejected by the innovation gate."""
        return self._count("gated")

    @property
    def resets(self) -> int:
        """Re-initialisations after gate_reset_count consecutive gated readings of one sensor."""
        return self._count("reset")

    @property
    def model_gated(self) -> int:
        """Drag-balance pseudo-measurements rejected by the gate (buoy)."""
        return self._count("model_gated")

    @property
    def failures(self) -> int:
        """Steps undone because they would have left a non-finite or non-positive-definite state."""
        return self._count("failed")

    @property
    def covariance(self) -> FloatArray:
        return self.kf.P.copy()

    # ------------------------------------------------------------ time and replay

    def _reject(self) -> str:
        self.rejected += 1
        return "rejected"

    def _submit(self, t: float, kind: str, data: tuple) -> str:
        """Process a reading at time t, in order or by replay; returns its outcome."""
        if self.t_s is None or t >= self.t_s:
            outcome = self._handle(kind, t, data)
            self._log.append(_Entry(t, kind, data, self._snapshot(), outcome))
            self._prune()
            return outcome
        if not self._log or t < self._log[0].t:
            self.late += 1
            return "late"
        i = bisect.bisect_right(self._log, t, key=lambda e: e.t)  # >= 1: log[0].t <= t
        self._restore(self._log[i - 1].snapshot)
        self._log.insert(i, _Entry(t, kind, data))
        for entry in self._log[i:]:
            entry.outcome = self._handle(entry.kind, entry.t, entry.data)
            entry.snapshot = self._snapshot()
        return self._log[i].outcome

    def _prune(self) -> None:
        """Keep the entries of the replay window and one before it (the state to restart from)."""
        cut = self.t_s - self.replay_window_s
        k = 0
        while k + 1 < len(self._log) and self._log[k + 1].t <= cut:
            k += 1
        if k:
            self._pruned.update(e.outcome for e in self._log[:k])
            del self._log[:k]

    # ------------------------------------------------------------ numerics

    def _symmetrize(self) -> None:
        self.kf.P = 0.5 * (self.kf.P + self.kf.P.T)

    def _healthy(self) -> bool:
        # A sum is finite only if every term is (inf - inf is NaN).
        return math.isfinite(float(self.kf.x.sum() + self.kf.P.sum())) and float(self.kf.P.diagonal().min()) > 0.0

    def _predict_with(self, x_next: FloatArray, f_jac: FloatArray, q_cov: FloatArray) -> bool:
        """filterpy predict with the model mean x_next, Jacobian f_jac and process noise q_cov."""
        kf = self.kf
        x0, p0 = kf.x, kf.P
        kf.F, kf.Q = f_jac, q_cov
        kf.predict(u=x_next)
        self._symmetrize()
        if not self._healthy():
            kf.x, kf.P = x0, p0
            return False
        return True

    def _set_states(self, rows: Sequence[int], z: FloatArray, r_cov: FloatArray) -> None:
        """Set states `rows` to the measurement z (column) with covariance r_cov, uncorrelated with the rest."""
        kf = self.kf
        idx = np.asarray(rows)
        x = kf.x.copy()
        x[idx] = z
        p = kf.P.copy()
        p[idx, :] = 0.0
        p[:, idx] = 0.0
        p[np.ix_(idx, idx)] = r_cov
        kf.x, kf.P = x, p

    def _fuse(
        self,
        kind: str,
        z: FloatArray,
        hx: FloatArray,
        h_jac: FloatArray,
        r_cov: FloatArray,
        angle_rows: Sequence[int] = (),
        reset_rows: Sequence[int] | None = None,
    ) -> str:
        """Fuse z (m, 1) with filterpy's EKF update (Joseph form), undone if the innovation fails the gate.

        Returns 'fused', 'gated', 'reset' (rows reset_rows re-initialised from z after gate_reset_count
        consecutive gated readings of this kind) or 'failed'."""
        kf = self.kf
        y = z - hx
        for i in angle_rows:
            y[i] = wrap_angle(y[i])
        x0, p0 = kf.x, kf.P  # filterpy's update binds new arrays: these stay the prior
        try:
            kf.update(z, lambda _x: h_jac, lambda _x: hx, R=r_cov, residual=lambda _z, _hx: y)
        except np.linalg.LinAlgError:
            kf.x, kf.P = x0, p0
            return "failed"
        d2 = float((y.T @ kf.SI @ y).item())  # squared Mahalanobis distance of the innovation
        if not math.isfinite(d2) or d2 > CHI2_999[z.shape[0]]:
            kf.x, kf.P = x0, p0
            run = self._gate_run.get(kind, 0) + 1
            if reset_rows is not None and run >= self.gate_reset_count:
                self._gate_run[kind] = 0
                self._set_states(reset_rows, z, r_cov)
                return "reset"
            self._gate_run[kind] = run
            return "gated"
        self._gate_run[kind] = 0
        self._symmetrize()
        if not self._healthy():
            kf.x, kf.P = x0, p0
            return "failed"
        return "fused"

    # ------------------------------------------------------------ subclass hooks

    def _handle(self, kind: str, t: float, data: tuple) -> str:
        raise NotImplementedError

    def _snapshot(self) -> Any:
        raise NotImplementedError

    def _restore(self, snapshot: Any) -> None:
        raise NotImplementedError


# =========================================================================== buoy


@dataclass(frozen=True)
class BuoyEkfParams:
    """Noise and tuning of `BuoyEkf` (SI units; see the module docstring for the models).

    model: the nominal mass and drag (velocity_control.BuoyModel).
    gps_sigma_m, gps_velocity_sigma_mps, compass_sigma_rad, gyro_sigma_radps: measurement noise std.
    drag_balance_sigma_mps2: std of the drag-balance pseudo-measurement (accelerometer vs drag model).
    accel_psd, model_psd, free_psd: velocity process noise PSD (m^2/s^3) with the accelerometer, with the
        thrust/drag model, with neither (constant velocity).
    yaw_accel_psd: yaw-rate random walk PSD (rad^2/s^3). drift_psd: drift random walk PSD (m^2/s^3).
    accel_hold_s, thrust_hold_s: how long an accelerometer reading / thrust command stays in use.
    max_step_s: longest prediction sub-step. gate_reset_count: consecutive gated readings that re-initialise.
    replay_window_s: how far back an out-of-order reading is fused by replay.
    initial_*: prior std of the states before the first readings set them.
    """

    model: BuoyModel = field(default_factory=BuoyModel)
    gps_sigma_m: float = 2.0
    gps_velocity_sigma_mps: float = 0.1
    compass_sigma_rad: float = math.radians(2.0)
    gyro_sigma_radps: float = 0.006
    drag_balance_sigma_mps2: float = 0.1
    accel_psd: float = 0.03**2
    model_psd: float = 0.1**2
    free_psd: float = 0.3**2
    yaw_accel_psd: float = 0.05**2
    drift_psd: float = 0.003**2
    accel_hold_s: float = 0.1
    thrust_hold_s: float = 1.0
    max_step_s: float = 0.1
    gate_reset_count: int = 10
    replay_window_s: float = 1.0
    initial_position_sigma_m: float = 100.0
    initial_velocity_sigma_mps: float = 1.0
    initial_heading_sigma_rad: float = math.pi
    initial_yaw_rate_sigma_radps: float = 0.2
    initial_drift_sigma_mps: float = 0.3


def _drag(w: FloatArray, model: BuoyModel) -> tuple[FloatArray, FloatArray]:
    """Nominal water drag force magnitude law f(w) = (c1 + c2 |w|) w (N) and its Jacobian df/dw (2x2)."""
    c1, c2 = model.linear_drag_n_per_mps, model.quadratic_drag_n_per_mps2
    speed = math.hypot(w[0], w[1])
    jac = (c1 + c2 * speed) * np.eye(2)
    if speed > 1e-9:
        jac += c2 * np.outer(w, w) / speed
    return (c1 + c2 * speed) * w, jac


class BuoyEkf(_TimedEkf):
    """EKF of one buoy: [x, y, vx, vy, heading, yaw_rate, drift_x, drift_y] (see the module docstring).

    position_m, heading_rad: an initial pose if known (else the first GPS fix and compass reading set them).
    Each reading method returns the outcome of its reading: 'predicted', 'fused', 'init', 'gated', 'reset',
    'model_gated', 'rejected' (non-finite), 'late' (older than the replay window) or 'failed'.
    """

    def __init__(
        self,
        position_m: ArrayLike | None = None,
        heading_rad: float | None = None,
        params: BuoyEkfParams | None = None,
    ) -> None:
        self.params = p = BuoyEkfParams() if params is None else params
        super().__init__(8, p.replay_window_s, p.gate_reset_count)
        self.kf.x = np.zeros((8, 1))
        sig = [p.initial_position_sigma_m] * 2 + [p.initial_velocity_sigma_mps] * 2
        sig += [p.initial_heading_sigma_rad, p.initial_yaw_rate_sigma_radps] + [p.initial_drift_sigma_mps] * 2
        self.kf.P = np.diag(np.square(sig))
        self._pos_init = position_m is not None
        self._heading_init = heading_rad is not None
        if position_m is not None:
            pos = np.asarray(position_m, dtype=float).reshape(2, 1)
            self._set_states([0, 1], pos, np.eye(2) * p.gps_sigma_m**2)
        if heading_rad is not None:
            self._set_states([4], np.array([[float(wrap_angle(heading_rad))]]), np.array([[p.compass_sigma_rad**2]]))
        self._accel: FloatArray | None = None  # the accelerometer reading in use, and its time
        self._t_accel = -math.inf
        self._thrust: FloatArray | None = None  # the thrust command in force, and its time
        self._t_thrust = -math.inf

    # ------------------------------------------------------------ readings

    def predict(self, t_s: float, accel_body: ArrayLike | None = None, thrust_world_n: ArrayLike | None = None) -> str:
        """Predict to t_s (s) with the accelerometer reading accel_body (x forward, y left, m/s^2) taken at
        t_s, if any, and set the thrust command (world frame, N) in force from t_s, if given."""
        accel = None if accel_body is None else np.asarray(accel_body, dtype=float).reshape(2)
        thrust = None if thrust_world_n is None else np.asarray(thrust_world_n, dtype=float).reshape(2)
        if not _finite(t_s, accel, thrust):
            return self._reject()
        return self._submit(float(t_s), "predict", (accel, thrust))

    def update_gps(self, t_s: float, xy_m: ArrayLike, velocity_mps: ArrayLike | None = None) -> str:
        """Fuse a fix (local x east, y north, m) measured at t_s, and the ground velocity (m/s) if given."""
        xy = np.asarray(xy_m, dtype=float).reshape(2)
        vel = None if velocity_mps is None else np.asarray(velocity_mps, dtype=float).reshape(2)
        if not _finite(t_s, xy, vel):
            return self._reject()
        return self._submit(float(t_s), "gps", (xy, vel))

    def update_compass(self, t_s: float | None, heading_rad: float) -> str:
        """Fuse a compass heading (rad) measured at t_s (None: at the filter's current time)."""
        if not _finite(t_s, heading_rad):
            return self._reject()
        if t_s is None:
            if self.t_s is None:  # no clock yet: the reading can only initialise the heading
                return self._initial_heading(float(heading_rad))
            t_s = self.t_s
        return self._submit(float(t_s), "compass", (float(heading_rad),))

    def update_gyro(self, t_s: float, yaw_rate_radps: float) -> str:
        """Fuse a gyro yaw rate (rad/s, CCW positive) measured at t_s."""
        if not _finite(t_s, yaw_rate_radps):
            return self._reject()
        return self._submit(float(t_s), "gyro", (float(yaw_rate_radps),))

    # ------------------------------------------------------------ outputs

    @property
    def state(self) -> FloatArray:
        """The state vector (8,) at the filter's time."""
        return self.kf.x[:, 0].copy()

    @property
    def initialized(self) -> bool:
        """Whether position and heading have been set (by readings or at construction)."""
        return self._pos_init and self._heading_init

    def position_covariance_trace(self) -> float:
        """Trace of the position covariance, m^2."""
        return float(self.kf.P[0, 0] + self.kf.P[1, 1])

    def drift(self) -> FloatArray:
        """Estimated water drift over ground (2,), m/s."""
        return self.kf.x[6:8, 0].copy()

    def estimate(self, t_s: float | None = None) -> tuple[FloatArray, FloatArray, float]:
        """(position (2,), velocity (2,), heading) extrapolated to t_s (never backwards; None: filter time)."""
        x = self.kf.x[:, 0]
        dt = 0.0 if t_s is None or self.t_s is None else max(0.0, t_s - self.t_s)
        return x[0:2] + x[2:4] * dt, x[2:4].copy(), float(wrap_angle(x[4] + x[5] * dt))

    # ------------------------------------------------------------ state for the replay log

    def _snapshot(self) -> tuple:
        return (self.t_s, self.kf.x.copy(), self.kf.P.copy(), self._pos_init, self._heading_init,
                self._accel, self._t_accel, self._thrust, self._t_thrust, dict(self._gate_run))  # fmt: skip

    def _restore(self, s: tuple) -> None:
        self.t_s, x, p, self._pos_init, self._heading_init = s[:5]
        self._accel, self._t_accel, self._thrust, self._t_thrust, gate_run = s[5:]
        self.kf.x, self.kf.P, self._gate_run = x.copy(), p.copy(), dict(gate_run)

    # ------------------------------------------------------------ process model

    def _propagate(self, t_to: float, accel: FloatArray | None = None) -> None:
        """Predict from the filter's time to t_to: with `accel` over the whole interval if given, else with
        the held accelerometer reading while it lasts; with the thrust command while it lasts."""
        p = self.params
        t = self.t_s
        while t_to - t > _TIME_EPS_S:
            end = t_to
            a = accel
            if a is None and self._accel is not None and t < self._t_accel + p.accel_hold_s:
                a, end = self._accel, min(end, self._t_accel + p.accel_hold_s)
            thrust = None
            if self._thrust is not None and t < self._t_thrust + p.thrust_hold_s:
                thrust, end = self._thrust, min(end, self._t_thrust + p.thrust_hold_s)
            if not self._heading_init:
                a = None  # the body-frame reading cannot be rotated into the world yet
            n = max(1, math.ceil((end - t) / p.max_step_s - 1e-9))
            h = (end - t) / n
            for _ in range(n):
                self._step(h, a, thrust)
            t = end
        self.t_s = max(self.t_s, t_to)

    def _step(self, h: float, accel_body: FloatArray | None, thrust: FloatArray | None) -> None:
        """One prediction sub-step of h seconds (see the module docstring for the three velocity models)."""
        p = self.params
        x = self.kf.x[:, 0]
        f_jac = np.eye(8)
        f_jac[0, 2] = f_jac[1, 3] = h
        f_jac[4, 5] = h
        if accel_body is not None:
            c, s = math.cos(x[4]), math.sin(x[4])
            a = np.array([c * accel_body[0] - s * accel_body[1], s * accel_body[0] + c * accel_body[1]])
            da_dpsi = np.array([-a[1], a[0]])
            f_jac[0:2, 4] = 0.5 * h * h * da_dpsi
            f_jac[2:4, 4] = h * da_dpsi
            q = p.accel_psd
        elif thrust is not None:
            force, dforce = _drag(x[2:4] - x[6:8], p.model)
            a = (thrust - force) / p.model.mass_kg
            jac = dforce / p.model.mass_kg  # da/dv = -jac, da/d(drift) = +jac
            f_jac[0:2, 2:4] -= 0.5 * h * h * jac
            f_jac[0:2, 6:8] = 0.5 * h * h * jac
            f_jac[2:4, 2:4] -= h * jac
            f_jac[2:4, 6:8] = h * jac
            q = p.model_psd
        else:
            a = np.zeros(2)
            q = p.free_psd
        x_next = x.copy()
        x_next[0:2] += x[2:4] * h + 0.5 * a * h * h
        x_next[2:4] += a * h
        x_next[4] = wrap_angle(x[4] + x[5] * h)
        # Piecewise-white noise blocks q [[h^3/3, h^2/2], [h^2/2, h]] on (position, velocity) per axis and on
        # (heading, yaw rate); random walk on the drift.
        h2, h3 = h * h / 2.0, h**3 / 3.0
        q_cov = np.zeros((8, 8))
        q_cov[0, 0] = q_cov[1, 1] = q * h3
        q_cov[0, 2] = q_cov[2, 0] = q_cov[1, 3] = q_cov[3, 1] = q * h2
        q_cov[2, 2] = q_cov[3, 3] = q * h
        q_cov[4, 4], q_cov[4, 5], q_cov[5, 4], q_cov[5, 5] = (p.yaw_accel_psd * v for v in (h3, h2, h2, h))
        q_cov[6, 6] = q_cov[7, 7] = p.drift_psd * h
        self._predict_with(x_next[:, None], f_jac, q_cov)

    def _drag_balance(self, accel_body: FloatArray, thrust: FloatArray) -> str:
        """Fuse the accelerometer reading against the drag model: a_body = R(heading)^T (T - f(v - d)) / M."""
        p = self.params
        x = self.kf.x[:, 0]
        force, dforce = _drag(x[2:4] - x[6:8], p.model)
        g = (thrust - force) / p.model.mass_kg
        jac = dforce / p.model.mass_kg
        c, s = math.cos(x[4]), math.sin(x[4])
        rot_t = np.array([[c, s], [-s, c]])  # world -> body
        drot_t = np.array([[-s, c], [-c, -s]])
        h_jac = np.zeros((2, 8))
        h_jac[:, 2:4] = -rot_t @ jac
        h_jac[:, 6:8] = rot_t @ jac
        h_jac[:, 4] = drot_t @ g
        r_cov = np.eye(2) * p.drag_balance_sigma_mps2**2
        outcome = self._fuse("drag", accel_body[:, None], (rot_t @ g)[:, None], h_jac, r_cov)
        return {"gated": "model_gated", "fused": "predicted"}.get(outcome, outcome)

    # ------------------------------------------------------------ readings, in time order

    def _initial_heading(self, heading_rad: float) -> str:
        if self._heading_init:
            return "ignored"
        z = np.array([[float(wrap_angle(heading_rad))]])
        self._set_states([4], z, np.array([[self.params.compass_sigma_rad**2]]))
        self._heading_init = True
        return "init"

    def _handle(self, kind: str, t: float, data: tuple) -> str:
        p = self.params
        if self.t_s is None:
            self.t_s = t
        if kind == "predict":
            accel, thrust = data
            self._propagate(t, accel)
            if accel is not None:
                self._accel, self._t_accel = accel, t
            if thrust is not None:
                self._thrust, self._t_thrust = thrust, t
            thrust_known = self._thrust is not None and t < self._t_thrust + p.thrust_hold_s
            if accel is not None and thrust_known and self._heading_init:
                return self._drag_balance(accel, self._thrust)
            return "predicted"
        self._propagate(t)
        if kind == "gps":
            xy, vel = data
            rows = [0, 1] if vel is None else [0, 1, 2, 3]
            z = (xy if vel is None else np.concatenate((xy, vel)))[:, None]
            sig = [p.gps_sigma_m] * 2 + ([] if vel is None else [p.gps_velocity_sigma_mps] * 2)
            r_cov = np.diag(np.square(sig))
            if not self._pos_init:
                self._set_states(rows, z, r_cov)
                self._pos_init = True
                return "init"
            h_jac = np.zeros((len(rows), 8))
            h_jac[range(len(rows)), rows] = 1.0
            return self._fuse("gps", z, self.kf.x[rows], h_jac, r_cov, reset_rows=rows)
        if kind == "compass":
            if not self._heading_init:
                return self._initial_heading(data[0])
            z = np.array([[float(wrap_angle(data[0]))]])
            r_cov = np.array([[p.compass_sigma_rad**2]])
            h_jac = np.zeros((1, 8))
            h_jac[0, 4] = 1.0
            outcome = self._fuse("compass", z, self.kf.x[[4]], h_jac, r_cov, angle_rows=[0], reset_rows=[4])
            self.kf.x[4, 0] = wrap_angle(self.kf.x[4, 0])
            return outcome
        if kind == "gyro":
            h_jac = np.zeros((1, 8))
            h_jac[0, 5] = 1.0
            r_cov = np.array([[p.gyro_sigma_radps**2]])
            return self._fuse("gyro", np.array([[data[0]]]), self.kf.x[[5]], h_jac, r_cov, reset_rows=[5])
        raise ValueError(f"unknown reading kind {kind!r}")


# =========================================================================== eBot


@dataclass(frozen=True)
class EbotEkfParams:
    """Noise and tuning of `EbotEkf` (SI units; see the module docstring).

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


# =========================================================================== banks


def _rows(agents: IntArray, *arrays: ArrayLike | None) -> list:
    """Per-row values of batch arrays: each broadcast to len(agents) rows (None stays None)."""
    k = len(agents)
    out = []
    for a in arrays:
        if a is None:
            out.append([None] * k)
        else:
            arr = np.asarray(a, dtype=float)
            out.append(list(np.broadcast_to(arr, (k, *arr.shape[1:])) if arr.ndim else np.full(k, float(arr))))
    return out


class _Bank:
    filters: list

    @property
    def rejected(self) -> int:
        return sum(f.rejected for f in self.filters)

    @property
    def late(self) -> int:
        return sum(f.late for f in self.filters)

    @property
    def gated(self) -> int:
        return sum(f.gated for f in self.filters)

    @property
    def resets(self) -> int:
        return sum(f.resets for f in self.filters)

    def covariance_trace(self) -> FloatArray:
        """(N,) trace of each agent's position covariance, m^2."""
        return np.array([f.position_covariance_trace() for f in self.filters])

    def estimate(self, t_s: float) -> PoseEstimate:
        """Poses of the N agents (position extrapolated to t_s for buoys); never NaN."""
        rows = [f.estimate(t_s) for f in self.filters]
        n = len(rows)
        return PoseEstimate(
            np.array([r[0] for r in rows]).reshape(n, 2),
            np.array([r[1] for r in rows]).reshape(n, 2),
            np.array([r[2] for r in rows], dtype=float).reshape(n),
        )


class BuoyEkfBank(_Bank):
    """N independent BuoyEkf behind the batch API of AlphaBetaBuoyEstimator (rows: agent indices)."""

    def __init__(
        self,
        n: int,
        position_m: ArrayLike | None = None,
        heading_rad: ArrayLike | None = None,
        params: BuoyEkfParams | None = None,
    ) -> None:
        pos = None if position_m is None else np.asarray(position_m, dtype=float).reshape(n, 2)
        head = None if heading_rad is None else np.broadcast_to(np.asarray(heading_rad, dtype=float), (n,))
        self.filters = [
            BuoyEkf(None if pos is None else pos[i], None if head is None else float(head[i]), params) for i in range(n)
        ]

    def predict(
        self,
        agents: IntArray,
        t_s: ArrayLike,
        accel_body: FloatArray | None = None,
        thrust_world_n: FloatArray | None = None,
    ) -> None:
        for i, t, a, f in zip(agents, *_rows(agents, t_s, accel_body, thrust_world_n), strict=True):
            self.filters[i].predict(t, a, f)

    def update_imu(self, agents: IntArray, t_s: ArrayLike, accel_body: FloatArray, gyro_z_radps: FloatArray) -> None:
        """An IMU reading: predict with the accelerometer (held thrust), then fuse the gyro."""
        for i, t, a, g in zip(agents, *_rows(agents, t_s, accel_body, gyro_z_radps), strict=True):
            self.filters[i].predict(t, a)
            self.filters[i].update_gyro(t, g)

    def update_gps(
        self, agents: IntArray, t_s: ArrayLike, xy_m: FloatArray, velocity_mps: FloatArray | None = None
    ) -> None:
        for i, t, xy, v in zip(agents, *_rows(agents, t_s, xy_m, velocity_mps), strict=True):
            self.filters[i].update_gps(t, xy, v)

    def update_compass(self, agents: IntArray, heading_rad: FloatArray, t_s: ArrayLike | None = None) -> None:
        """Compass headings (rad) measured at t_s (None: at each filter's current time)."""
        for i, h, t in zip(agents, *_rows(agents, heading_rad, t_s), strict=True):
            self.filters[i].update_compass(t, h)

    def update_gyro(self, agents: IntArray, t_s: ArrayLike, yaw_rate_radps: FloatArray) -> None:
        for i, t, g in zip(agents, *_rows(agents, t_s, yaw_rate_radps), strict=True):
            self.filters[i].update_gyro(t, g)

    def drift(self) -> FloatArray:
        """(N, 2) estimated water drift over ground, m/s."""
        return np.array([f.drift() for f in self.filters]).reshape(len(self.filters), 2)

    def initialized(self) -> NDArray[np.bool_]:
        return np.array([f.initialized for f in self.filters], dtype=bool)


class EbotEkfBank(_Bank):
    """N independent EbotEkf behind the batch API of OdometryEstimator."""

    def __init__(
        self,
        position_m: FloatArray,
        heading_rad: FloatArray,
        wheel_base_m: float,
        metres_per_tick: float,
        params: EbotEkfParams | None = None,
    ) -> None:
        pos = np.asarray(position_m, dtype=float).reshape(-1, 2)
        head = np.broadcast_to(np.asarray(heading_rad, dtype=float), (pos.shape[0],))
        self.filters = [
            EbotEkf(pos[i], float(head[i]), wheel_base_m, metres_per_tick, params) for i in range(pos.shape[0])
        ]

    def update_encoders(
        self,
        agents: IntArray,
        t_s: ArrayLike,
        ticks: NDArray[np.int64],
        gyro_z_radps: FloatArray | None = None,
    ) -> None:
        ticks = np.asarray(ticks).reshape(len(agents), 2)
        (times, gyros) = _rows(agents, t_s, gyro_z_radps)
        for i, t, k, g in zip(agents, times, ticks, gyros, strict=True):
            self.filters[i].update_encoders(t, k, g)

    def update_compass(self, agents: IntArray, heading_rad: FloatArray, t_s: ArrayLike | None = None) -> None:
        for i, h, t in zip(agents, *_rows(agents, heading_rad, t_s), strict=True):
            self.filters[i].update_compass(t, h)

    def update_position(self, agents: IntArray, t_s: ArrayLike, xy_m: FloatArray, sigma_m: ArrayLike) -> None:
        for i, t, xy, s in zip(agents, *_rows(agents, t_s, xy_m, sigma_m), strict=True):
            self.filters[i].update_position(t, xy, s)
