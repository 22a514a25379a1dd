"""Row-wise Kalman filter math: filterpy's EKF predict and Joseph update over a stack of filters, the innovation
gate's chi-square quantiles and angle wrapping."""

from __future__ import annotations

import functools

import numpy as np
from numpy.typing import ArrayLike, NDArray

from bob_autonomy.estimation.simple_estimator import FloatArray

# Chi-square 99.9 % quantiles by degrees of freedom (the innovation gate).
CHI2_999 = {1: 10.828, 2: 13.816, 3: 16.266, 4: 18.467}


def any_row(mask: NDArray[np.bool_]) -> bool:
    """Whether any entry of a boolean array is true (count_nonzero: a third of the cost of `.any()` on the few
    rows a bank's call holds, and these tests run several times per reading)."""
    return np.count_nonzero(mask) > 0


def every_row(mask: NDArray[np.bool_]) -> bool:
    """Whether every entry of a boolean array is true (see `any_row`)."""
    return np.count_nonzero(mask) == mask.size


def wrap_angle(angle_rad: ArrayLike) -> FloatArray:
    """Angles (rad) wrapped to (-pi, pi]."""
    return np.pi - np.mod(np.pi - np.asarray(angle_rad, dtype=float), 2.0 * np.pi)


def _transpose(a: FloatArray) -> FloatArray:
    """The matrices of a stack (..., r, c) transposed: (..., c, r)."""
    return np.swapaxes(a, -1, -2)


def kalman_predict_rows(p_cov: FloatArray, f_jac: FloatArray, q_cov: FloatArray) -> FloatArray:
    """Covariance prediction of filterpy's KalmanFilter/ExtendedKalmanFilter.predict, P = F P F^T + Q, for a
    stack of filters (m, n, n), then symmetrised."""
    p_new = f_jac @ p_cov @ _transpose(f_jac) + q_cov
    return 0.5 * (p_new + _transpose(p_new))


def kalman_update_rows(
    x: FloatArray,
    p_cov: FloatArray,
    y: FloatArray,
    h_jac: FloatArray,
    r_cov: FloatArray,
    selects: slice | None = None,
) -> tuple[FloatArray, FloatArray, FloatArray, NDArray[np.bool_]]:
    """The update of filterpy's ExtendedKalmanFilter.update (Joseph form) for a stack of m filters.

    x (m, n) states, p_cov (m, n, n), y (m, k) innovations z - h(x), h_jac (m, k, n) or (k, n), r_cov (m, k, k)
    or (k, k). Returns the updated states and covariances (symmetrised), the squared Mahalanobis distances
    y^T S^-1 y (m,) and which rows had a positive-definite innovation covariance S (the others are left as they
    were).

    selects: the states h_jac reads, when they are consecutive and each row of h_jac is a 1 at one of them (a
    sensor that measures states directly). P H^T and H P H^T are then P's columns and block: every sum of those
    products has one term that is not an exact zero, so the values are the same, without the matmuls.
    """
    if selects is not None and y.shape[1] == 1:
        return _update_one_state(x, p_cov, y, selects.start, r_cov)
    if selects is None:
        pht = p_cov @ _transpose(h_jac)
        s_cov = h_jac @ pht + r_cov
    else:  # (R's zeros off its diagonal make a -0.0 of the block +0.0, as the matmul's sum gives it)
        pht = p_cov[:, :, selects]
        s_cov = pht[:, selects, :] + r_cov
    s_inv, ok = _spd_inverse(s_cov)
    d2 = (y[:, None, :] @ s_inv @ y[:, :, None])[:, 0, 0]
    gain = pht @ s_inv
    x_new = x + (gain @ y[:, :, None])[:, :, 0]
    if selects is None:
        i_kh = _identity(x.shape[1]) - gain @ h_jac
    else:
        i_kh = _identity_stack(x.shape[0], x.shape[1])
        i_kh[:, :, selects] -= gain
    p_new = i_kh @ p_cov @ _transpose(i_kh) + gain @ r_cov @ _transpose(gain)
    return _updated(x, p_cov, x_new, p_new, d2, ok)


def _update_one_state(
    x: FloatArray, p_cov: FloatArray, y: FloatArray, col: int, r_cov: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray, NDArray[np.bool_]]:
    """kalman_update_rows for a reading of state `col` alone (H = e_col^T, k = 1). Every matmul of the general
    update but the Joseph product (I - K H) P (I - K H)^T then has one term per sum, so it is taken elementwise:
    the same products, in the same order. A matmul's sum starts at +0.0, which turns a product of -0.0 into
    +0.0; `+ 0.0` does the same here where a product can be -0.0 and the value is used on."""
    m, n = x.shape
    r = r_cov[..., 0, 0]  # () or (m,)
    pht = p_cov[:, :, col] + 0.0  # (m, n): P H^T
    s = pht[:, col] + r
    ok = s > 0.0
    s_inv = 1.0 / np.where(ok, s, 1.0)  # as _spd_inverse: positive
    y = y[:, 0]
    d2 = y * s_inv * y
    gain = pht * s_inv[:, None]  # (m, n); never -0.0 (pht is not, s_inv > 0)
    x_new = x + (gain * y[:, None] + 0.0)
    i_kh = _identity_stack(m, n)
    i_kh[:, :, col] -= gain
    gain_r = gain * (r[:, None] if np.ndim(r) else r)
    # K R K^T: a -0.0 in it is added to the Joseph product's matmul, never -0.0 itself, so it adds as +0.0 would.
    p_new = i_kh @ p_cov @ _transpose(i_kh) + gain_r[:, :, None] * gain[:, None, :]
    return _updated(x, p_cov, x_new, p_new, d2, ok)


def _updated(
    x: FloatArray, p_cov: FloatArray, x_new: FloatArray, p_new: FloatArray, d2: FloatArray, ok: NDArray[np.bool_]
) -> tuple[FloatArray, FloatArray, FloatArray, NDArray[np.bool_]]:
    """The end of kalman_update_rows: the covariances symmetrised, and the rows without a positive-definite S
    left as they were."""
    p_new = 0.5 * (p_new + _transpose(p_new))
    if every_row(ok):
        return x_new, p_new, d2, ok
    return np.where(ok[:, None], x_new, x), np.where(ok[:, None, None], p_new, p_cov), d2, ok


def _spd_inverse(s_cov: FloatArray) -> tuple[FloatArray, NDArray[np.bool_]]:
    """Inverses of a stack of symmetric matrices (m, k, k) (closed form for k <= 2) and which were positive
    definite (the others get the identity's inverse)."""
    k = s_cov.shape[-1]
    if k == 1:
        ok = s_cov[:, 0, 0] > 0.0
        return 1.0 / np.where(ok, s_cov[:, 0, 0], 1.0)[:, None, None], ok
    if k == 2:
        a, b, c, d = s_cov[:, 0, 0], s_cov[:, 0, 1], s_cov[:, 1, 0], s_cov[:, 1, 1]
        det = a * d - b * c
        ok = (a > 0.0) & (det > 0.0)
        if not every_row(ok):  # (every row positive definite: nothing to replace)
            a, b, c, d = (np.where(ok, v, w) for v, w in ((a, 1.0), (b, 0.0), (c, 0.0), (d, 1.0)))
            det = np.where(ok, det, 1.0)
        inv = np.empty_like(s_cov)
        inv[:, 0, 0], inv[:, 0, 1], inv[:, 1, 0], inv[:, 1, 1] = d / det, -b / det, -c / det, a / det
        return inv, ok
    ok = np.linalg.det(s_cov) > 0.0  # a symmetric S with a non-positive (or NaN) determinant is not SPD
    if not every_row(ok):
        s_cov = np.where(ok[:, None, None], s_cov, np.eye(k))
    return np.linalg.inv(s_cov), ok


@functools.cache
def _identity(n: int) -> FloatArray:
    """The n x n identity (shared, never written to)."""
    eye = np.eye(n)
    eye.flags.writeable = False
    return eye


def _identity_stack(m: int, n: int) -> FloatArray:
    """m copies of the n x n identity (m, n, n), to be written to."""
    return np.repeat(_identity(n)[None], m, axis=0)


def _healthy_rows(x: FloatArray, p_cov: FloatArray) -> NDArray[np.bool_]:
    """Rows whose state and covariance are finite with positive variances (a sum is finite only if every term is)."""
    finite = np.isfinite(x.sum(axis=1) + p_cov.sum(axis=(1, 2)))
    return finite & (np.diagonal(p_cov, axis1=1, axis2=2).min(axis=1) > 0.0)
