"""bob_autonomy/control/motorboat_mpc_batch.py: a fleet's motorboat MPCs solved in one mapped call give, bit for
bit, the commands each controller's own `solve` gives, over many steps (each command the next step's previous
one, each plan the next linearisation point), with boats holding, weak batteries, non-finite inputs, and when
the mapped call fails."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bob_autonomy.control.motorboat_control import MotorboatModel, MotorboatMpc
from bob_autonomy.control.motorboat_mpc_batch import MotorboatMpcBatch
from bob_autonomy.control.qp import _SolveError

N = 10
FIELDS = ("throttle", "steering", "ok", "fallback", "status", "heading_error_rad", "speed_ref_mps")


def fleet(n: int = N, **options) -> list[MotorboatMpc]:
    return [MotorboatMpc(time_budget_s=math.inf, **options) for _ in range(n)]


def random_step(rng: np.random.Generator, n: int = N) -> tuple[np.ndarray, ...]:
    desired = rng.uniform(-2.0, 2.0, (n, 2)) * rng.choice([0.0, 0.05, 1.0], (n, 1), p=[0.1, 0.1, 0.8])
    velocity = rng.uniform(-1.5, 1.5, (n, 2))
    water = rng.normal(0.0, 0.2, (n, 2))
    heading = rng.uniform(-4.0, 4.0, n)
    yaw_rate = rng.normal(0.0, 0.3, n)
    throttle = rng.choice([1.0, 0.6, 0.0, -0.2], n, p=[0.7, 0.15, 0.1, 0.05])
    for array in (desired, velocity, water):  # now and then a reading the estimator could not give
        array[rng.random(n) < 0.05, 0] = np.nan
    heading[rng.random(n) < 0.05] = np.inf
    return desired, velocity, water, heading, yaw_rate, throttle


def alone_commands(controllers, step, t_s):
    desired, velocity, water, heading, yaw_rate, throttle = step
    return [
        mpc.solve(desired[k], velocity[k], water[k], heading[k], yaw_rate[k], max_throttle=throttle[k], t_s=t_s)
        for k, mpc in enumerate(controllers)
    ]


def assert_same(batched, alone) -> None:
    for got, want in zip(batched, alone, strict=True):
        for field in FIELDS:
            assert getattr(got, field) == getattr(want, field), field


def assert_same_state(batch: MotorboatMpcBatch, alone: list[MotorboatMpc]) -> None:
    for mine, theirs in zip(batch.controllers, alone, strict=True):
        assert (mine.solves, mine.fallbacks, mine._previous) == (theirs.solves, theirs.fallbacks, theirs._previous)
        assert mine._output == theirs._output
        np.testing.assert_array_equal(mine._bar, theirs._bar)
        assert (mine.last_plan is None) == (theirs.last_plan is None)
        if mine.last_plan is not None:
            np.testing.assert_array_equal(mine.last_plan, theirs.last_plan)


SLEWED = MotorboatModel.for_top_speed(2.0, 4.0, throttle_slew_per_s=1.0)  # ArduPilot's MOT_SLEWRATE default


@pytest.mark.parametrize(("seed", "model"), [(s, MotorboatModel()) for s in range(5)] + [(5, SLEWED), (6, SLEWED)])
def test_the_batch_gives_each_boat_what_its_own_solve_gives(seed: int, model: MotorboatModel) -> None:
    rng = np.random.default_rng(seed)
    batch, alone = MotorboatMpcBatch(fleet(model=model)), fleet(model=model)
    for step in range(40):
        args = random_step(rng)
        t_s = 0.5 * step
        assert_same(batch.solve(*args, t_s), alone_commands(alone, args, t_s))
        assert_same_state(batch, alone)
    assert batch.unbatched == 0 and 30 <= batch.calls <= 40


def test_a_step_where_every_boat_holds_solves_nothing() -> None:
    batch, alone = MotorboatMpcBatch(fleet(3)), fleet(3)
    still = (np.zeros((3, 2)), np.zeros((3, 2)), np.zeros((3, 2)), np.zeros(3), np.zeros(3), np.ones(3))
    assert_same(batch.solve(*still, 0.0), alone_commands(alone, still, 0.0))
    assert batch.calls == 0 and all(c.solves == 0 for c in batch.controllers)


def test_a_failed_mapped_call_solves_that_step_boat_by_boat(monkeypatch) -> None:
    rng = np.random.default_rng(11)
    batch, alone = MotorboatMpcBatch(fleet()), fleet()
    steps = [random_step(rng) for _ in range(8)]

    def fail() -> None:
        raise _SolveError("motorboat_mpc_qp: simulated failure")

    for k, args in enumerate(steps):
        if k == 3:
            monkeypatch.setattr(batch, "_qp", fail)
        elif k == 5:
            monkeypatch.undo()
        assert_same(batch.solve(*args, 0.5 * k), alone_commands(alone, args, 0.5 * k))
        assert_same_state(batch, alone)
    assert batch.unbatched == 2 and batch.calls == 6


def test_a_non_finite_plan_falls_back_for_that_boat_only() -> None:
    batch, alone = MotorboatMpcBatch(fleet(3)), fleet(3)
    go = (np.array([[1.5, 0.0]] * 3), np.zeros((3, 2)), np.zeros((3, 2)), np.zeros(3), np.zeros(3), np.ones(3))
    real_qp = batch._qp

    def poisoned() -> None:
        real_qp()
        batch._x[1, 0] = np.nan

    batch._qp = poisoned
    commands = batch.solve(*go, 0.0)
    assert [c.fallback for c in commands] == [False, True, False]
    assert "non-finite" in commands[1].status and batch.controllers[1].last_plan is None
    expected = alone_commands(alone, go, 0.0)
    assert_same([commands[0], commands[2]], [expected[0], expected[2]])


def test_only_controllers_that_can_share_a_call_are_batched() -> None:
    assert MotorboatMpcBatch.fits(fleet(2))
    assert not MotorboatMpcBatch.fits(fleet(1))
    other = MotorboatModel.for_top_speed(3.0)
    assert not MotorboatMpcBatch.fits(
        [MotorboatMpc(time_budget_s=math.inf), MotorboatMpc(other, time_budget_s=math.inf)]
    )
    assert not MotorboatMpcBatch.fits(fleet(2, horizon=8) + fleet(1))
    assert not MotorboatMpcBatch.fits([MotorboatMpc(), MotorboatMpc()])  # a CPU-time budget is per solve
    assert not MotorboatMpcBatch.fits(fleet(2, solver="osqp"))
    with pytest.raises(ValueError, match="one model and tuning"):
        MotorboatMpcBatch(fleet(1))
