"""The array types, the angle wrapping and the finite-value guard that estimation and control share."""

from __future__ import annotations

import math
import sys

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]


def wrap(angle: FloatArray) -> FloatArray:
    """Wrap angles (rad) to [-pi, pi)."""
    return np.mod(angle + np.pi, 2.0 * np.pi) - np.pi


def finite_pair(value: object) -> tuple[float, float]:
    """The two entries of a (2,) vector as floats with numpy.nan_to_num's rule (NaN -> 0, +-inf -> the largest
    float of that sign), without its per-call cost (about 10 us on a 2-vector, paid per vessel per step)."""
    array = np.asarray(value, dtype=float).reshape(2)
    return _finite(float(array[0])), _finite(float(array[1]))


def _finite(x: float) -> float:
    if math.isfinite(x):
        return x
    return 0.0 if math.isnan(x) else math.copysign(sys.float_info.max, x)
