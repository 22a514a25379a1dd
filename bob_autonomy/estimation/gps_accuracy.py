"""The GPS receiver's reported accuracies held at their peak and let decay, as ArduPilot's EKF3 does before it
weighs a fix with them.

Why: a receiver's accuracy estimate drops back as soon as it sees the sky again, while its position can stay off
for a few more fixes (multipath, a filter re-converging). ArduPilot's EKF3 therefore keeps a decaying envelope of
the reported accuracies (libraries/AP_NavEKF3/AP_NavEKF3_Measurements.cpp `readGpsData`: "a decaying envelope
filter with a 5 second time constant"), and so do we:

    alpha = clamp(0.2 dt, 0, 1)     (dt, s: the time between this fix and the previous one of the same receiver)
    envelope = max(envelope (1 - alpha), reported)

A fix without a report (NaN) clears the envelope, as ArduPilot sets it to zero. The caps (100 m, 50 m/s) and the
floor (the filter's own noise) are applied elsewhere (`firmware_bridge.decoder`, `BuoyEkfBank.update_gps`).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]
DECAY_PER_S = 0.2  # ArduPilot: alpha = 0.0002 per ms between fixes


class AccuracyEnvelope:
    """Per row of n: the held horizontal and speed accuracies (m, m/s; NaN: none) and the time of the last fix."""

    def __init__(self, n: int) -> None:
        self.held = np.full((n, 2), np.nan)
        self.last_t_s = np.full(n, np.nan)

    def apply(
        self,
        rows: NDArray[np.intp],
        t_s: FloatArray,
        accuracy_m: ArrayLike | None,
        speed_accuracy_mps: ArrayLike | None,
    ) -> tuple[FloatArray | None, FloatArray | None]:
        """The accuracies to weigh fixes of `rows` at times t_s (k,) with: the envelopes after these reports (each
        None or (k,), NaN where not reported). Rows are taken in order, so a row twice in one call decays between
        its fixes as it would over two calls."""
        if accuracy_m is None and speed_accuracy_mps is None:
            return None, None
        k = len(rows)
        columns = [np.full(k, np.nan) if v is None else np.asarray(v, dtype=float).reshape(k)
                   for v in (accuracy_m, speed_accuracy_mps)]  # fmt: skip
        reported = np.column_stack(columns)
        if np.isnan(reported).all() and np.isnan(self.held[rows]).all():
            self.last_t_s[rows] = t_s
            return accuracy_m, speed_accuracy_mps  # nothing reported and nothing held: as they came
        rows, t_s = np.asarray(rows), np.asarray(t_s, dtype=float).reshape(k)
        if np.unique(rows).size == k:  # each row once (a fleet's step): all rows at once, the same arithmetic
            out = self._step(rows, t_s, reported)
        else:
            out = np.empty((k, 2))
            for j in range(k):  # a row twice: in turn, so that it decays between its fixes
                out[j] = self._step(rows[j : j + 1], t_s[j : j + 1], reported[j : j + 1])[0]
        return (
            None if accuracy_m is None else out[:, 0],
            None if speed_accuracy_mps is None else out[:, 1],
        )

    def _step(self, rows: NDArray[np.intp], t_s: FloatArray, reported: FloatArray) -> FloatArray:
        """The envelopes (k, 2) of distinct `rows` after reports (k, 2) at t_s (k,), stored."""
        dt = t_s - self.last_t_s[rows]
        finite = np.isfinite(dt)
        alpha = np.where(finite, np.clip(DECAY_PER_S * np.where(finite, dt, 0.0), 0.0, 1.0), 1.0)
        decayed = self.held[rows] * (1.0 - alpha)[:, None]
        held = np.where(np.isnan(reported), np.nan, np.fmax(decayed, reported))
        self.held[rows], self.last_t_s[rows] = held, t_s
        return held
