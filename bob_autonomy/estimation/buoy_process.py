"""The buoy bank's process model: the believed nozzle's slew, the prediction in sub-steps (accelerometer,
thrust/drag model or constant velocity) and the drag-balance pseudo-measurement that makes the drift observable."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from bob_autonomy.control.velocity_control import BuoyModel
from bob_autonomy.estimation.buoy_params import _AS_MODEL_OUTCOME, _DRAG, _EYE2, _EYE_NX, _NX, BuoyEkfParams
from bob_autonomy.estimation.buoy_updates import _BuoyUpdates
from bob_autonomy.estimation.kalman_rows import (
    _healthy_rows,
    _transpose,
    any_row,
    every_row,
    kalman_predict_rows,
    wrap_angle,
)
from bob_autonomy.estimation.row_replay import _FAILED, _PREDICTED
from bob_autonomy.estimation.simple_estimator import FloatArray, IntArray

_TIME_EPS_S = 1e-12


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


class _BuoyProcess(_BuoyUpdates):
    """The prediction of BuoyEkfBank (a base of the bank, which holds the arrays declared here)."""

    t: FloatArray
    accel: FloatArray
    t_accel: FloatArray
    thrust: FloatArray
    t_thrust: FloatArray
    nozzle: FloatArray
    t_nozzle: FloatArray
    _template_cache: dict[float, tuple[FloatArray, FloatArray, FloatArray]]

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
        if every_row(commanded):  # (the usual case: every row driven, no rows to pick)
            body_thrust = self._slew(idx, t, command, span)
        else:
            body_thrust = np.full((idx.size, 2), np.nan)
            if any_row(commanded):
                rows = commanded.nonzero()[0]
                body_thrust[rows] = self._slew(idx[rows], t[rows], command[rows], span[rows])
        failed = self._propagate(idx, t, accel, thrust)
        if accel is not None:
            self.accel[idx], self.t_accel[idx] = accel, t
        if thrust is not None:
            self.thrust[idx], self.t_thrust[idx] = thrust, t
        codes = np.where(failed, _FAILED, _PREDICTED)
        if accel is not None:
            balance = commanded & self.pos_init[idx] & ~failed
            if every_row(balance):
                codes = self._drag_balance(idx, accel, body_thrust, span)
            elif any_row(balance):
                rows = balance.nonzero()[0]
                codes[rows] = self._drag_balance(idx[rows], accel[rows], body_thrust[rows], span[rows])
        return codes

    def _slew(self, idx: IntArray, t: FloatArray, command: FloatArray, span: FloatArray) -> FloatArray:
        """Turn the believed nozzle towards the commands (world frame, N) at thrust_slew_radps since it was last
        turned; return the mean body-frame thrust over the interval `span` (s) that ends at t."""
        cx, cy = command[:, 0], command[:, 1]
        magnitude = np.hypot(cx, cy)
        nozzle = self.nozzle[idx]
        target = np.where(magnitude > 1e-9, np.arctan2(cy, cx) - self.x[idx, 4], nozzle)
        turn = wrap_angle(target - nozzle)
        since = t - self.t_nozzle[idx]
        most = self.params.thrust_slew_radps * np.where(np.isnan(since), span, since)
        size = np.abs(turn)
        reached = size <= most
        delta = np.where(reached, turn, np.copysign(most, turn))
        # Fraction of the interval spent turning (the rest at the end angle); mean direction along the arc.
        turning = np.where(reached, size / np.maximum(most, 1e-12), 1.0)
        half = 0.5 * delta
        curved = np.abs(half) > 1e-9
        arc = np.where(curved, np.sin(half) / np.where(curved, half, 1.0), 1.0)
        angles = np.empty((idx.size, 2))
        angles[:, 0], angles[:, 1] = nozzle + half, nozzle + delta  # the arc's middle and its end
        cos, sin = np.cos(angles), np.sin(angles)
        along, rest = turning * arc, 1.0 - turning
        mean = np.empty((idx.size, 2))
        mean[:, 0] = along * cos[:, 0] + rest * cos[:, 1]
        mean[:, 1] = along * sin[:, 0] + rest * sin[:, 1]
        self.nozzle[idx], self.t_nozzle[idx] = wrap_angle(angles[:, 1]), t
        return magnitude[:, None] * mean

    def _propagate(
        self, idx: IntArray, t_to: FloatArray, accel: FloatArray | None = None, thrust: FloatArray | None = None
    ) -> NDArray[np.bool_]:
        """Predict rows idx from their filter times to t_to: with `accel` over the whole interval if given, else
        with the held accelerometer reading while it lasts; with `thrust` if given, else the held command while
        it lasts. Returns which rows had a sub-step undone (non-finite or not positive definite)."""
        p = self.params
        k = idx.size
        if not any_row(t_to - self.t[idx] > _TIME_EPS_S):  # every row already there (a reading at the filter's time)
            self.t[idx] = np.maximum(self.t[idx], t_to)
            return np.zeros(k, dtype=bool)
        t_now = self.t[idx].copy()
        start = t_now.copy()
        failed = np.zeros(k, dtype=bool)
        no_heading = ~self.heading_init[idx]
        while True:
            active = t_to - t_now > _TIME_EPS_S
            if not any_row(active):
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
                stepping = steps > j
                if every_row(stepping):  # (the usual case: one sub-step for every row)
                    failed |= self._step(idx, h, a, force, noise_span)
                    continue
                rows = stepping.nonzero()[0]
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
        every_accel = every_row(with_accel)  # (the usual case: no row on the drag model or constant velocity)
        with_thrust = None if every_accel else ~with_accel & ~np.isnan(thrust[:, 0])
        a = np.zeros((m, 2))
        da_dx = np.zeros((m, 2, _NX))  # Jacobian of the acceleration over ground with respect to the state
        if any_row(with_accel):  # a = R(heading) (a_body - bias)
            c, s, rot = _rotations(x[:, 4])
            body = accel_body - x[:, 8:10]
            bx, by = body[:, 0], body[:, 1]
            a_accel = np.empty((m, 2))
            a_accel[:, 0], a_accel[:, 1] = c * bx - s * by, s * bx + c * by
            if not every_accel:
                a_accel[~with_accel] = 0.0
                rot[~with_accel] = 0.0
            a += a_accel
            da_dx[:, 0, 4], da_dx[:, 1, 4] = -a_accel[:, 1], a_accel[:, 0]
            da_dx[:, :, 8:10] = -rot
        if with_thrust is not None and any_row(with_thrust):  # M a = T - f(v - d)
            drag, jac = _drag_rows(x[:, 2:4] - x[:, 6:8], p.model)
            mask = with_thrust / p.model.mass_kg
            a += np.where(with_thrust[:, None], thrust - drag, 0.0) / p.model.mass_kg
            jac *= mask[:, None, None]
            da_dx[:, :, 2:4] = -jac
            da_dx[:, :, 6:8] = jac
        q = p.accel_psd + p.accel_noise_mps2**2 * accel_span
        if with_thrust is not None:
            q = np.where(with_thrust, p.model_psd, np.where(with_accel, q, p.free_psd))
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
        if every_row(ok):
            self.x[idx], self.P[idx] = x_next, p_next
        else:
            self.x[idx[ok]], self.P[idx[ok]] = x_next[ok], p_next[ok]
        return ~ok

    def _templates(self, h: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        """For sub-steps h (m,) s: the transition's h-dependent identity part (F with p += v h, heading += r h),
        the pattern [[h^3/3, h^2/2], [h^2/2, h]] on (position, velocity) per axis that the velocity PSD scales,
        and the fixed process noise (yaw rate, drift and bias random walks). (10, 10) each, cached, when every
        row has the same h (a fleet in lockstep); else (m, 10, 10)."""
        if h.size and every_row(h == h[0]):
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
        across = np.empty_like(a_world)  # a_world a quarter turn counter-clockwise: d(R (a_body - b)) / d heading
        across[:, 0], across[:, 1] = -a_world[:, 1], a_world[:, 0]
        dvmid_dpsi = -half[:, None] * across
        h_jac = np.zeros((idx.size, 2, _NX))
        h_jac[:, :, 2:4] = dh_dw
        h_jac[:, :, 6:8] = -dh_dw
        h_jac[:, :, 4] = (drot_t @ (-drag / mass)[:, :, None])[:, :, 0] + (dh_dw @ dvmid_dpsi[:, :, None])[:, :, 0]
        h_jac[:, :, 8:10] = _EYE2 + dh_dw @ (half[:, None, None] * rot)
        r_cov = _EYE2 * p.drag_balance_sigma_mps2**2
        codes = self._fuse(idx, _DRAG, accel_body, hx, h_jac, r_cov, False, None)
        return _AS_MODEL_OUTCOME[codes]

    # ------------------------------------------------------------ numerics
