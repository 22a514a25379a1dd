"""The buoy bank's measurement updates: GPS, compass and gyro readings fused (or used to initialise the state) through
the gated fusion of row_fusion, which the drag balance shares."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from bob_autonomy.estimation.buoy_params import _COMPASS, _GPS, _GYRO, _NX, BuoyEkfParams
from bob_autonomy.estimation.kalman_rows import wrap_angle
from bob_autonomy.estimation.row_fusion import _measurement, _RowFusion
from bob_autonomy.estimation.row_replay import _INIT
from bob_autonomy.estimation.simple_estimator import FloatArray, IntArray


class _BuoyUpdates(_RowFusion):
    """The measurement updates of BuoyEkfBank (a base of the bank, which holds the arrays declared here)."""

    params: BuoyEkfParams
    x: FloatArray
    P: FloatArray
    pos_init: NDArray[np.bool_]
    heading_init: NDArray[np.bool_]
    gate_run: NDArray[np.int64]

    # ------------------------------------------------------------ readings

    def _handle_gps(self, idx: IntArray, xy: FloatArray, vel: FloatArray | None, acc: FloatArray | None) -> IntArray:
        """Fixes: the first sets each row's position (and velocity), later ones are fused; acc (k, 2): the receivers'
        horizontal and speed accuracies (m, m/s; 0 when not reported), each row's noise the larger of those and
        gps_sigma_m, gps_velocity_sigma_mps."""
        p = self.params
        cols, h_jac, r_cov = _measurement(
            _NX,
            (0, 1) if vel is None else (0, 1, 2, 3),
            tuple(np.square([p.gps_sigma_m] * 2 + ([] if vel is None else [p.gps_velocity_sigma_mps] * 2))),
        )
        if acc is not None:
            r_cov = np.repeat(r_cov[None], idx.size, axis=0)
            r_cov[:, 0, 0] = r_cov[:, 1, 1] = np.square(np.maximum(p.gps_sigma_m, acc[:, 0]))
            if vel is not None:
                r_cov[:, 2, 2] = r_cov[:, 3, 3] = np.square(np.maximum(p.gps_velocity_sigma_mps, acc[:, 1]))
        z = xy if vel is None else np.concatenate((xy, vel), axis=1)
        codes = np.full(idx.size, _INIT)
        first = ~self.pos_init[idx]
        if first.any():  # the first fix initialises position (and velocity), however far from the prior
            self._set_states(idx[first], cols, z[first], r_cov if acc is None else r_cov[first])
            self.pos_init[idx[first]] = True
        rows = np.flatnonzero(~first)
        if rows.size:
            agents = idx[rows]
            r_rows = r_cov if acc is None else r_cov[rows]
            reads = slice(0, len(cols))  # (the states cols: x, y and, with a velocity, vx, vy)
            codes[rows] = self._fuse(agents, _GPS, z[rows], self.x[agents][:, cols], h_jac, r_rows, False, cols, reads)
        return codes

    def _handle_compass(self, idx: IntArray, heading_rad: FloatArray) -> IntArray:
        """Compass headings: the first initialises each row's heading, later ones are fused (wrapped innovation)."""
        p = self.params
        codes = np.full(idx.size, _INIT)
        heading = wrap_angle(heading_rad)
        first = ~self.heading_init[idx]
        self._initial_heading(idx[first], heading[first])
        rows = np.flatnonzero(~first)
        if rows.size:
            agents = idx[rows]
            _, h_jac, r_cov = _measurement(_NX, (4,), (p.compass_sigma_rad**2,))
            z = heading[rows][:, None]
            codes[rows] = self._fuse(agents, _COMPASS, z, self.x[agents, 4:5], h_jac, r_cov, True, [4], slice(4, 5))
            self.x[agents, 4] = wrap_angle(self.x[agents, 4])
        return codes

    def _handle_gyro(self, idx: IntArray, yaw_rate_radps: FloatArray) -> IntArray:
        """Gyro yaw rates, fused into the yaw-rate state."""
        _, h_jac, r_cov = _measurement(_NX, (5,), (self.params.gyro_sigma_radps**2,))
        z = yaw_rate_radps[:, None]
        return self._fuse(idx, _GYRO, z, self.x[idx, 5:6], h_jac, r_cov, False, [5], slice(5, 6))

    def _initial_heading(self, idx: IntArray, heading: FloatArray) -> None:
        if idx.size:
            r_cov = np.array([[self.params.compass_sigma_rad**2]])
            self._set_states(idx, [4], wrap_angle(heading)[:, None], r_cov)
            self.heading_init[idx] = True

    def _reopen(self, idx: IntArray) -> None:
        """The drag balance's reset: the drift states of rows idx re-opened to their prior, uncorrelated."""
        p_cov = self.P[idx]
        p_cov[:, 6:8, :] = 0.0
        p_cov[:, :, 6:8] = 0.0
        p_cov[:, 6, 6] = p_cov[:, 7, 7] = self.params.initial_drift_sigma_mps**2
        self.P[idx] = p_cov
