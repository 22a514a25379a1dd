"""The filterpy-based EKF machinery (the eBot's filter): innovation gate, Joseph updates, symmetrisation and the
replay of late readings; filterpy itself is imported on first use."""

from __future__ import annotations

import bisect
import functools
import math
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from bob_autonomy.estimation.kalman_rows import CHI2_999, wrap_angle
from bob_autonomy.estimation.simple_estimator import FloatArray


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


@functools.cache
def _model_ekf_class() -> type:
    """filterpy's EKF with a nonlinear transition: the caller sets F (the Jacobian) and Q, then calls
    predict(u=x_next) with the mean propagated by the model; filterpy does P = F P F^T + Q.

    Built on first use: importing filterpy pulls in scipy.stats (about 0.5 s), which only the eBot filter needs;
    every `bob-autonomy` start and every buoy or motorboat vessel is spared it."""
    from filterpy.kalman import ExtendedKalmanFilter

    class _ModelEkf(ExtendedKalmanFilter):
        def predict_x(self, u: Any = 0) -> None:
            self.x = u

    return _ModelEkf


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
    replay log (see the docstring of bob_autonomy.estimation). Subclasses provide _handle, _snapshot and _restore."""

    def __init__(self, dim_x: int, replay_window_s: float, gate_reset_count: int) -> None:
        self.kf = _model_ekf_class()(dim_x=dim_x, dim_z=1)
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
