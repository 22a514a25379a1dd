"""Comparisons of 2-D lengths with a bound that give np.hypot's exact answer without paying for hypot everywhere.

np.hypot costs about 13-28 ns an element (the C library's careful algorithm), ten times a square root of
dx * dx + dy * dy. Whether a length exceeds a bound, and the factor min(1, bound / length) that limits a
vector to it, are settled by the squared length everywhere but in a thin band around the bound: hypot is
within one unit in the last place of the exact length and dx * dx + dy * dy within three of its square, so
outside a relative band of 1e-12 about bound ** 2 both give the same answer. hypot is evaluated only in
that band, and the results are the same bits as the plain hypot expressions.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

_BAND = 1e-12  # relative half-width about bound ** 2 where the squared length cannot settle the question
_SAFE_LOW, _SAFE_HIGH = 1e-100, 1e100  # bounds (m) whose squares neither underflow nor overflow


def exceeds(dx: FloatArray, dy: FloatArray, bound: FloatArray, bounds: FloatArray) -> NDArray[np.bool_]:
    """np.hypot(dx, dy) > bound (m; NaN: False), element by element, to the same result.

    `bound`: one per element, or one for all; `bounds`: every value it takes (outside [1e-100, 1e100] m hypot
    is used throughout).
    """
    finite = bounds[np.isfinite(bounds)]
    if finite.size == 0:
        return np.zeros(dx.size, dtype=bool)  # NaN bounds: no check
    if not (finite.min() >= _SAFE_LOW and finite.max() <= _SAFE_HIGH):
        return np.hypot(dx, dy) > bound
    length2 = dx * dx
    length2 += dy * dy
    bound2 = bound * bound
    out = length2 > bound2
    close = np.flatnonzero(np.abs(length2 - bound2) <= _BAND * bound2)
    if close.size:
        out[close] = np.hypot(dx[close], dy[close]) > np.broadcast_to(bound, out.shape)[close]
    return out


def limit_scale(vectors: FloatArray, bound: float, eps: float = 1e-12) -> FloatArray:
    """(n,) the factor min(1, bound / max(hypot(x, y), eps)) that scales each (n, 2) vector to at most `bound`.

    The same bits as that expression: where the length is surely at most `bound` the factor is exactly 1
    (bound / length >= 1 in floating point too), and hypot is taken only for the other rows. A vector with a
    NaN component gets NaN, as the expression gives. `bound` (m, m/s ...) must lie in [eps, 1e100].
    """
    if not (eps <= bound <= _SAFE_HIGH and eps >= _SAFE_LOW):
        raise ValueError(f"limit_scale: bound {bound!r} and eps {eps!r} must satisfy 1e-100 <= eps <= bound <= 1e100")
    x, y = vectors[:, 0], vectors[:, 1]
    length2 = x * x
    length2 += y * y
    scale = np.ones(length2.shape)
    # Not surely inside: at or above the band's lower edge, or NaN (which fails every comparison).
    check = np.flatnonzero(~(length2 < bound * bound * (1.0 - _BAND)))
    if check.size:
        scale[check] = np.minimum(1.0, bound / np.maximum(np.hypot(x[check], y[check]), eps))
    return scale
