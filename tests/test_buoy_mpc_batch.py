"""bob_autonomy/control/buoy_mpc_batch.py: a fleet's buoy MPCs solved together (mapped QP data, the unconstrained
minimisers at once, the solver for the vessels with an active bound) give, bit for bit, the commands each
controller's own `solve` gives, over many steps (each command the next step's previous thrust), with weak
batteries, vessels without thrust, non-finite inputs, and when a vessel's solver fails."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bob_autonomy.control.buoy_mpc_batch import BuoyMpcBatch
from bob_autonomy.control.mpc import BuoyMpc

N = 12
FIELDS = ("thrust_body_n", "thrust_world_n", "ok", "fallback", "status")


def fleet(n: int = N) -> list[BuoyMpc]:
    return [BuoyMpc(time_budget_s=math.inf) for _ in range(n)]


def random_step(rng: np.random.Generator, n: int = N) -> tuple[np.ndarray, ...]:
    desired = rng.uniform(-0.9, 0.9, (n, 2))
    velocity = rng.uniform(-0.9, 0.9, (n, 2))
    water = rng.normal(0.0, 0.15, (n, 2))
    heading = rng.uniform(-4.0, 4.0, n)
    limit = rng.choice([45.0, 30.0, 12.5, 0.0, -3.0], n, p=[0.5, 0.2, 0.15, 0.1, 0.05])
    for array in (desired, velocity, water):  # now and then a reading the estimator could not give
        array[rng.random(n) < 0.05, 0] = np.nan
    heading[rng.random(n) < 0.05] = np.inf
    return desired, velocity, water, heading, limit


def assert_same(batched, alone) -> None:
    for got, want in zip(batched, alone, strict=True):
        for field in FIELDS:
            np.testing.assert_array_equal(getattr(got, field), getattr(want, field), err_msg=field)


@pytest.mark.parametrize("seed", range(5))
def test_the_batch_gives_each_vessel_what_its_own_solve_gives(seed: int) -> None:
    rng = np.random.default_rng(seed)
    batch, alone = BuoyMpcBatch(fleet()), fleet()
    for _ in range(30):
        desired, velocity, water, heading, limit = random_step(rng)
        results = batch.solve(desired, velocity, water, heading, limit)
        expected = [mpc.solve(desired[k], velocity[k], water[k], heading[k], limit[k]) for k, mpc in enumerate(alone)]
        assert_same(results, expected)
    assert batch.calls == 30
    assert batch.interior > 0 and batch.solver_calls > 0  # both ways were taken (a limit of 12.5 N binds)
    for mine, theirs in zip(batch.controllers, alone, strict=True):
        assert (mine.solves, mine.fallbacks, mine.interior_solves) == (
            theirs.solves,
            theirs.fallbacks,
            theirs.interior_solves,
        )
        np.testing.assert_array_equal(mine.last_plan_world_n, theirs.last_plan_world_n)


def _never_interior(batch: BuoyMpcBatch, mpcs: list[BuoyMpc], k: int) -> None:
    """Vessel k's QPs infeasible (its rate rows' lower bounds above their upper ones), in the batch's bounds and
    in the controllers' own: never interior, and the solver fails."""
    n_poly = mpcs[0]._n_poly
    batch._lba[k, n_poly:] = 1e3
    for mpc in (batch.controllers[k], mpcs[k]):
        mpc._qp.inputs["lba"][n_poly:] = 1e3


def test_a_failed_solve_gives_that_vessel_the_fallback_of_its_own_solve() -> None:
    rng = np.random.default_rng(11)
    batch, alone = BuoyMpcBatch(fleet()), fleet()
    _never_interior(batch, alone, 3)
    for _ in range(6):
        desired, velocity, water, heading, limit = random_step(rng)
        limit[3] = 45.0
        results = batch.solve(desired, velocity, water, heading, limit)
        expected = [mpc.solve(desired[i], velocity[i], water[i], heading[i], limit[i]) for i, mpc in enumerate(alone)]
        assert_same(results, expected)
        assert results[3].fallback and results[3].status.startswith("fallback: _SolveError: daqp")
    assert batch.calls == 6 and batch.controllers[3].fallbacks == 6


def test_only_controllers_that_can_share_a_call_are_batched() -> None:
    assert BuoyMpcBatch.fits(fleet(2))
    assert not BuoyMpcBatch.fits(fleet(1))
    assert not BuoyMpcBatch.fits([BuoyMpc(time_budget_s=math.inf), BuoyMpc(time_budget_s=math.inf, horizon=8)])
    assert not BuoyMpcBatch.fits([BuoyMpc(time_budget_s=0.02), BuoyMpc(time_budget_s=0.02)])
    assert not BuoyMpcBatch.fits([BuoyMpc(solver="osqp", time_budget_s=math.inf) for _ in range(2)])
    with pytest.raises(ValueError, match="one tuning"):
        BuoyMpcBatch(fleet(1))


@pytest.mark.parametrize("seed", range(3))
def test_the_batch_arrays_are_the_commands_of_each_vessels_own_solve(seed: int) -> None:
    rng = np.random.default_rng(100 + seed)
    batch, alone = BuoyMpcBatch(fleet()), fleet()
    for _ in range(30):
        desired, velocity, water, heading, limit = random_step(rng)
        body, world = batch.thrust(desired, velocity, water, heading, limit)
        expected = [mpc.solve(desired[k], velocity[k], water[k], heading[k], limit[k]) for k, mpc in enumerate(alone)]
        np.testing.assert_array_equal(body, np.array([r.thrust_body_n for r in expected]))
        np.testing.assert_array_equal(world, np.array([r.thrust_world_n for r in expected]))
    for mine, theirs in zip(batch.controllers, alone, strict=True):
        assert (mine.solves, mine.fallbacks, mine._last_thrust) == (
            theirs.solves,
            theirs.fallbacks,
            theirs._last_thrust,
        )


def test_the_row_wise_polygon_and_rate_limit_are_the_controllers_own() -> None:
    """Points all around the polygon, many within round-off of its inscribed circle (the fast path's edge)."""
    rng = np.random.default_rng(7)
    batch = BuoyMpcBatch(fleet())
    mpc = batch.controllers[0]
    for _ in range(200):
        limit = rng.choice([45.0, 30.0, 12.5, 1e-3, 0.0, 1e-170, 1e-90, 1e90, 1e170], N)
        angle = rng.uniform(-math.pi, math.pi, N)
        radius = limit * mpc.inradius_ratio * (1.0 + rng.choice([0.0, 1e-16, -1e-16, 1e-9, -1e-9, 0.3, -0.3], N))
        thrust = np.column_stack((radius * np.cos(angle), radius * np.sin(angle)))
        previous = batch._into_polygon(rng.uniform(-50.0, 50.0, (N, 2)), limit)
        expected = [mpc._into_polygon(x, y, lim) for (x, y), lim in zip(thrust.tolist(), limit.tolist(), strict=True)]
        np.testing.assert_array_equal(batch._into_polygon(thrust, limit), np.array(expected))
        limited = [
            mpc._within_limits((x, y), (px, py), lim)
            for (x, y), (px, py), lim in zip(thrust.tolist(), previous.tolist(), limit.tolist(), strict=True)
        ]
        np.testing.assert_array_equal(batch._within_limits(thrust, previous, limit), np.array(limited))


def test_a_non_finite_plan_gives_that_vessel_the_fallback_of_its_own_solve(monkeypatch) -> None:
    rng = np.random.default_rng(5)
    batch, alone = BuoyMpcBatch(fleet()), fleet()
    _never_interior(batch, alone, 4)
    for mpc in (batch.controllers[4], alone[4]):
        monkeypatch.setattr(mpc, "_solve_qp", _nan_plan.__get__(mpc))
    for _ in range(3):
        desired, velocity, water, heading, limit = random_step(rng)
        limit[4] = 45.0
        results = batch.solve(desired, velocity, water, heading, limit)
        expected = [mpc.solve(desired[k], velocity[k], water[k], heading[k], limit[k]) for k, mpc in enumerate(alone)]
        assert_same(results, expected)
        assert results[4].fallback and "non-finite" in results[4].status
    assert batch.controllers[4].fallbacks == 3


def _nan_plan(self, *_args) -> np.ndarray:
    return np.full((self.horizon, 2), np.nan)
