"""Gated measurement updates of a bank of EKFs held as rows (the buoy's and the eBot's): filterpy's Joseph-form
update over the rows a call names, the innovation gate, the reset after a run of gated readings, and setting states
from a reading."""

from __future__ import annotations

import functools
from collections.abc import Sequence
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from bob_autonomy.estimation.kalman_rows import (
    CHI2_999,
    _healthy_rows,
    any_row,
    every_row,
    kalman_update_rows,
    wrap_angle,
)
from bob_autonomy.estimation.row_replay import _FAILED, _FUSED, _GATED, _RESET
from bob_autonomy.estimation.simple_estimator import FloatArray, IntArray


@functools.lru_cache(maxsize=64)
def _measurement(
    nx: int, cols: tuple[int, ...], variances: tuple[float, ...]
) -> tuple[list[int], FloatArray, FloatArray]:
    """A reading of the states `cols` with independent noise `variances`: the columns, H (k, nx) selecting them
    and R = diag(variances) (k, k); built once per kind and noise (H and R read-only)."""
    h_jac = np.zeros((len(cols), nx))
    h_jac[range(len(cols)), cols] = 1.0
    r_cov = np.diag(variances)
    h_jac.flags.writeable = r_cov.flags.writeable = False
    return list(cols), h_jac, r_cov


class _GateParams(Protocol):
    gate_reset_count: int


class _RowFusion:
    """The fusion of a bank (a base of the bank, which holds the arrays declared here: states x (n, nx),
    covariances P (n, nx, nx) and gate_run (n, kinds), each agent's consecutive gated readings of each kind)."""

    params: _GateParams
    x: FloatArray
    P: FloatArray
    gate_run: NDArray[np.int64]

    def _set_states(self, idx: IntArray, cols: Sequence[int], z: FloatArray, r_cov: FloatArray) -> None:
        """Set states `cols` of rows idx to z (m, len(cols)) with covariance r_cov (k, k) or (m, k, k),
        uncorrelated with the rest."""
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
        selects: slice | None = None,
    ) -> IntArray:
        """Fuse z (m, k) into rows idx (Joseph form), each undone if its innovation fails the gate; selects: the
        states h_jac reads directly, if it does (see kalman_update_rows).

        Codes: fused, gated, failed, or reset (after gate_reset_count consecutive gated readings of this kind:
        states reset_cols re-initialised from z; with reset_cols None, _reopen(rows) instead)."""
        y = z - hx
        if angle:
            y = wrap_angle(y)
        x0, p0 = self.x[idx], self.P[idx]
        x1, p1, d2, inverted = kalman_update_rows(x0, p0, y, h_jac, r_cov, selects)
        passed = inverted & (d2 <= CHI2_999[z.shape[1]])
        healthy = passed & _healthy_rows(x1, p1)
        if every_row(healthy):  # the usual case: every reading fused, no gate run left
            self.gate_run[idx, kind] = 0
            self.x[idx], self.P[idx] = x1, p1
            return np.full(idx.size, _FUSED)
        gated = inverted & ~passed
        codes = np.where(healthy, _FUSED, np.where(gated, _GATED, _FAILED))
        run = np.where(passed, 0, self.gate_run[idx, kind] + gated)
        reset = gated & (run >= self.params.gate_reset_count)
        if any_row(reset):
            rows = idx[reset]
            if reset_cols is not None:
                self._set_states(rows, reset_cols, z[reset], r_cov[reset] if r_cov.ndim == 3 else r_cov)
            else:
                self._reopen(rows)
            codes[reset], run[reset] = _RESET, 0
        self.gate_run[idx, kind] = run
        self.x[idx[healthy]], self.P[idx[healthy]] = x1[healthy], p1[healthy]
        return codes

    def _reopen(self, idx: IntArray) -> None:
        """The reset of a kind without reset_cols (the buoy's drag balance)."""
        raise NotImplementedError
