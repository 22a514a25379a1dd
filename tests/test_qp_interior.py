"""bob_autonomy/control/qp_interior.py: the unconstrained minimiser is taken only where it meets every bound, it is
then the solver's solution, and each row comes out the same bits whatever the batch."""

from __future__ import annotations

import math

import casadi as ca
import numpy as np
import pytest

from bob_autonomy.control.mpc import BuoyMpc
from bob_autonomy.control.qp_interior import InteriorMinimiser


def _random_qps(mpc: BuoyMpc, rng: np.random.Generator, n: int) -> tuple[np.ndarray, ...]:
    """n buoy-MPC QPs as the controller builds them: Hessian nonzeros, gradients and bounds (scaled units)."""
    scale, step, size = mpc.model.max_thrust_n, mpc.max_thrust_change_n / mpc.model.max_thrust_n, 2 * mpc.horizon
    data = mpc._data.function
    h, g, lbx, ubx, lba, uba = [], [], [], [], [], []
    for _ in range(n):
        water = rng.normal(0.0, 0.1, 2)
        desired = rng.uniform(-0.5, 0.5, 2) * rng.choice([0.1, 1.0])  # station keeping to a transit
        velocity = desired + rng.normal(0.0, rng.choice([0.02, 0.3]), 2)  # on its way, or far off
        limit = rng.choice([45.0, 30.0, 12.5])
        previous = mpc.into_polygon(rng.uniform(-10.0, 10.0, 2), limit) / scale
        hessian, gradient = data(np.concatenate((velocity, water, desired, previous)))
        h.append(np.array(hessian.nonzeros()))
        g.append(np.array(gradient).ravel())
        box = limit / scale
        low, high = np.full(size, -box), np.full(size, box)
        low[:2], high[:2] = np.maximum(-box, previous - step), np.minimum(box, previous + step)
        lbx.append(low)
        ubx.append(high)
        lba.append(np.concatenate((np.full(mpc._n_poly, box * mpc.polygon_lower_ratio), np.full(size - 2, -step))))
        uba.append(np.concatenate((np.full(mpc._n_poly, box * mpc.inradius_ratio), np.full(size - 2, step))))
    return tuple(np.array(a) for a in (h, g, lbx, ubx, lba, uba))


@pytest.fixture(scope="module")
def mpc() -> BuoyMpc:
    return BuoyMpc(solver="daqp", time_budget_s=math.inf)


def test_an_inside_minimiser_is_the_solvers_solution_and_an_outside_one_breaks_a_bound(mpc: BuoyMpc) -> None:
    rng = np.random.default_rng(3)
    h, g, lbx, ubx, lba, uba = _random_qps(mpc, rng, 300)
    x, inside = mpc._interior.solve(h, g, lbx, ubx, lba, uba)
    assert 30 < inside.sum() < 270  # both kinds among these QPs
    a = mpc._interior.constraint_matrix
    conic, sparsity = mpc._qp.function, mpc._data.function.sparsity_out("h")
    for k in range(len(g)):
        rows = a @ x[k]
        breaks = (x[k] < lbx[k]).any() or (x[k] > ubx[k]).any() or (rows < lba[k]).any() or (rows > uba[k]).any()
        assert breaks == (not inside[k])
        if inside[k]:
            hessian = ca.DM(sparsity, h[k])
            solved = conic(h=hessian, g=g[k], a=ca.DM(a), lbx=lbx[k], ubx=ubx[k], lba=lba[k], uba=uba[k])["x"]
            assert np.abs(np.array(solved).ravel() - x[k]).max() < 1e-12  # of full thrust


def test_each_row_is_the_same_bits_whatever_the_batch(mpc: BuoyMpc) -> None:
    rng = np.random.default_rng(4)
    qps = _random_qps(mpc, rng, 45)
    x, inside = mpc._interior.solve(*qps)
    for k in range(45):
        alone, alone_inside = mpc._interior.solve(*(a[k : k + 1] for a in qps))
        assert np.array_equal(alone[0], x[k]) and alone_inside[0] == inside[k]


def test_nan_and_a_singular_hessian_go_to_the_solver() -> None:
    sparsity = ca.Sparsity.dense(2, 2)
    minimiser = InteriorMinimiser(sparsity, ca.Sparsity.dense(1, 2), np.array([1.0, 1.0]))
    h = np.array([[2.0, 0.0, 0.0, 2.0], [2.0, 0.0, 0.0, 2.0]])
    g = np.array([[-1.0, -1.0], [np.nan, 0.0]])
    wide = np.full((2, 2), 10.0)
    x, inside = minimiser.solve(h, g, -wide, wide, np.full((2, 1), -10.0), np.full((2, 1), 10.0))
    np.testing.assert_array_equal(x[0], [0.5, 0.5])
    assert inside.tolist() == [True, False]
    singular = np.zeros((2, 4))
    _, inside = minimiser.solve(singular, g, -wide, wide, np.full((2, 1), -10.0), np.full((2, 1), 10.0))
    assert not inside.any()
