"""The array types and the angle wrapping that estimation and control share."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]


def wrap(angle: FloatArray) -> FloatArray:
    """Wrap angles (rad) to [-pi, pi)."""
    return np.mod(angle + np.pi, 2.0 * np.pi) - np.pi
