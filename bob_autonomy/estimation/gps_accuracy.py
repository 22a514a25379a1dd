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
        out = np.empty((k, 2))
        for j, row in enumerate(rows):
            dt = t_s[j] - self.last_t_s[row]
            alpha = 1.0 if not np.isfinite(dt) else min(max(DECAY_PER_S * dt, 0.0), 1.0)
            decayed = self.held[row] * (1.0 - alpha)
            self.held[row] = np.where(np.isnan(reported[j]), np.nan, np.fmax(decayed, reported[j]))
            self.last_t_s[row] = t_s[j]
            out[j] = self.held[row]
        return (
            None if accuracy_m is None else out[:, 0],
            None if speed_accuracy_mps is None else out[:, 1],
        )
