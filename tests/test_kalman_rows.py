"""The buoy bank's row arithmetic: kalman_update_rows' path for sensors that read states directly gives the general
path's bytes; the float state a snapshot copies in one array."""

from __future__ import annotations

import numpy as np
import pytest

from bob_autonomy.estimation.kalman_rows import kalman_update_rows
from bob_autonomy.estimation.row_fusion import _measurement


def _covariances(rng: np.random.Generator, m: int, n: int) -> np.ndarray:
    """Random covariances (m, n, n), some with the exact zeros of states set apart (as a reading sets them)."""
    a = rng.normal(size=(m, n, n))
    p_cov = a @ np.swapaxes(a, 1, 2) + 0.1 * np.eye(n)
    p_cov[::3, 4, :] = p_cov[::3, :, 4] = 0.0
    p_cov[::3, 4, 4] = 0.5
    p_cov[1::4, 0:2, 2:] = p_cov[1::4, 2:, 0:2] = 0.0
    return p_cov


@pytest.mark.parametrize("cols", [(5,), (4,), (0, 1), (0, 1, 2, 3)])
@pytest.mark.parametrize("per_row_noise", [False, True])
def test_reading_states_directly_gives_the_general_updates_bytes(cols: tuple[int, ...], per_row_noise: bool) -> None:
    rng = np.random.default_rng(len(cols) + 10 * per_row_noise)
    m, n, k = 45, 10, len(cols)
    for _ in range(20):
        x = rng.normal(size=(m, n))
        x[::5, 2] = 0.0
        p_cov = _covariances(rng, m, n)
        y = rng.normal(size=(m, k)) * rng.choice([0.01, 1.0, 100.0])
        y[::7] = 0.0
        _, h_jac, r_cov = _measurement(n, cols, tuple(rng.uniform(0.01, 2.0, size=k)))
        if per_row_noise:
            r_cov = np.repeat(r_cov[None], m, axis=0) * rng.uniform(0.5, 4.0, size=(m, 1, 1))
        p_cov[-1, cols[0], cols[0]] = -r_cov[..., 0, 0].max() - 1.0  # a row whose S is not positive definite
        plain = kalman_update_rows(x, p_cov, y, h_jac, r_cov)
        direct = kalman_update_rows(x, p_cov, y, h_jac, r_cov, slice(cols[0], cols[-1] + 1))
        assert not plain[3][-1]
        for a, b in zip(plain, direct, strict=True):
            assert a.shape == b.shape and a.dtype == b.dtype
            assert a.tobytes() == b.tobytes()


def test_the_buoy_banks_float_arrays_are_views_of_the_one_a_snapshot_copies() -> None:
    from bob_autonomy.estimation.buoy_ekf_bank import BuoyEkfBank

    bank = BuoyEkfBank(3, position_m=[[1.0, 2.0], [3.0, 4.0], [5.0, 6.0]], heading_rad=[0.1, 0.2, 0.3])
    for name in ("x", "P", "t", "accel", "t_accel", "thrust", "t_thrust", "nozzle", "t_nozzle"):
        assert np.shares_memory(getattr(bank, name), bank._floats), name
    assert bank.P.shape == (3, 10, 10) and bank.x[:, 0:2].tolist() == [[1.0, 2.0], [3.0, 4.0], [5.0, 6.0]]
    block = bank._snapshot(np.array([0, 2]))
    bank.x[:] = 7.0
    bank.P[2, 4, 4] = 9.0
    bank._restore(np.array([2]), block, np.array([1]))
    assert bank.x[2, 0:2].tolist() == [5.0, 6.0] and bank.P[2, 4, 4] != 9.0 and bank.x[0, 0] == 7.0


def test_a_copied_or_pickled_buoy_bank_keeps_its_arrays_views_of_its_own_floats() -> None:
    import copy
    import pickle

    from bob_autonomy.estimation.buoy_ekf_bank import BuoyEkfBank

    bank = BuoyEkfBank(2, position_m=[[1.0, 2.0], [3.0, 4.0]], heading_rad=0.5)
    for twin in (copy.deepcopy(bank), pickle.loads(pickle.dumps(bank))):
        assert np.shares_memory(twin.P, twin._floats) and not np.shares_memory(twin.P, bank._floats)
        assert twin.x.tobytes() == bank.x.tobytes() and twin.P.tobytes() == bank.P.tobytes()
    shallow = copy.copy(bank)
    assert np.shares_memory(shallow.x, bank._floats)
