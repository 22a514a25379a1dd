"""The buoy bank's measurement updates: GPS, compass and gyro readings fused (or used to initialise the state), and
the gated Joseph-form fusion that they and the drag balance share."""

from __future__ import annotations

import functools
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from bob_autonomy.estimation.buoy_params import (
    _COMPASS,
    _FAILED,
    _FUSED,
    _GATED,
    _GPS,
    _GYRO,
    _INIT,
    _NX,
    _RESET,
    BuoyEkfParams,
)
from bob_autonomy.estimation.kalman_rows import CHI2_999, _healthy_rows, kalman_update_rows, wrap_angle
from bob_autonomy.estimation.simple_estimator import FloatArray, IntArray


@functools.lru_cache(maxsize=64)
def _measurement(cols: tuple[int, ...], variances: tuple[float, ...]) -> tuple[list[int], FloatArray, FloatArray]:
    """A reading of the states `cols` with independent noise `variances`: the columns, H (k, 10) selecting them
    and R = diag(variances) (k, k); built once per kind and noise (H and R read-only)."""
    h_jac = np.zeros((len(cols), _NX))
    h_jac[range(len(cols)), cols] = 1.0
    r_cov = np.diag(variances)
    h_jac.flags.writeable = r_cov.flags.writeable = False
    return list(cols), h_jac, r_cov


class _BuoyUpdates:
    """The measurement updates of BuoyEkfBank (a base of the bank, which holds the arrays declared here)."""

    params: BuoyEkfParams
    x: FloatArray
    P: FloatArray
    pos_init: NDArray[np.bool_]
    heading_init: NDArray[np.bool_]
    gate_run: NDArray[np.int64]

    # ------------------------------------------------------------ readings

    def _handle_gps(self, idx: IntArray, xy: FloatArray, vel: FloatArray | None) -> IntArray:
        p = self.params
        cols, h_jac, r_cov = _measurement(
            (0, 1) if vel is None else (0, 1, 2, 3),
            tuple(np.square([p.gps_sigma_m] * 2 + ([] if vel is None else [p.gps_velocity_sigma_mps] * 2))),
        )
        z = xy if vel is None else np.concatenate((xy, vel), axis=1)
        codes = np.full(idx.size, _INIT)
        first = ~self.pos_init[idx]
        if first.any():  # the first fix initialises position (and velocity), however far from the prior
            self._set_states(idx[first], cols, z[first], r_cov)
            self.pos_init[idx[first]] = True
        rows = np.flatnonzero(~first)
        if rows.size:
            agents = idx[rows]
            codes[rows] = self._fuse(agents, _GPS, z[rows], self.x[agents][:, cols], h_jac, r_cov, False, cols)
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
            _, h_jac, r_cov = _measurement((4,), (p.compass_sigma_rad**2,))
            z = heading[rows][:, None]
            codes[rows] = self._fuse(agents, _COMPASS, z, self.x[agents, 4:5], h_jac, r_cov, True, [4])
            self.x[agents, 4] = wrap_angle(self.x[agents, 4])
        return codes

    def _handle_gyro(self, idx: IntArray, yaw_rate_radps: FloatArray) -> IntArray:
        """Gyro yaw rates, fused into the yaw-rate state."""
        _, h_jac, r_cov = _measurement((5,), (self.params.gyro_sigma_radps**2,))
        return self._fuse(idx, _GYRO, yaw_rate_radps[:, None], self.x[idx, 5:6], h_jac, r_cov, False, [5])

    def _initial_heading(self, idx: IntArray, heading: FloatArray) -> None:
        if idx.size:
            r_cov = np.array([[self.params.compass_sigma_rad**2]])
            self._set_states(idx, [4], wrap_angle(heading)[:, None], r_cov)
            self.heading_init[idx] = True

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
