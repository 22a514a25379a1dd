"""bob_autonomy/control/mpc.py: the buoy's linear MPC (QP) and the eBot's MPC.

The closed loops run a first-order simulator written here (not the SITL's):
m dv/dt = T - (c1 + c2 |v - w|)(v - w) with the nominal coefficients (35 kg,
5 N/(m/s), 40 N/(m/s)^2), integrated with 50 explicit Euler sub-steps per 0.5 s
control step (0.01 s, far below the fastest time constant, 0.4 s). Tests that
are not about the time budget give a generous one, so a loaded machine cannot
turn a solve into a fallback.
"""

from __future__ import annotations

import logging
import math

import casadi as ca
import numpy as np
import pytest

from bob_autonomy.control.ebot_mpc import DiffDriveMpc, _clipped
from bob_autonomy.control.mpc import BuoyMpc, polygon_normals, polygon_rows
from bob_autonomy.control.velocity_control import BuoyModel

MODEL = BuoyModel()
DT_S = 0.5
RELAXED_BUDGET_S = 1.0
TOL_N = 1e-9


def drag(relative: np.ndarray) -> np.ndarray:
    return (MODEL.linear_drag_n_per_mps + MODEL.quadratic_drag_n_per_mps2 * np.hypot(*relative)) * relative


def simulate(velocity: np.ndarray, thrust: np.ndarray, water: np.ndarray, dt: float = DT_S) -> np.ndarray:
    h = dt / 50
    for _ in range(50):
        velocity = velocity + h * (thrust - drag(velocity - water)) / MODEL.mass_kg
    return velocity


def in_polygon(mpc: BuoyMpc, thrust: np.ndarray, limit: float) -> bool:
    return float(np.max(polygon_normals(mpc.polygon_sides) @ thrust)) <= limit * math.cos(math.pi / 16) + TOL_N


def closed_loop(mpc: BuoyMpc, desired, water, steps: int, limit: float = 45.0, heading: float = 0.3):
    velocity = np.zeros(2)
    velocities, results = [], []
    for _ in range(steps):
        result = mpc.solve(np.asarray(desired, float), velocity, np.asarray(water, float), heading, limit)
        velocity = simulate(velocity, result.thrust_world_n, np.asarray(water, float))
        velocities.append(velocity)
        results.append(result)
    return np.array(velocities), results


# ---------------------------------------------------------------- buoy: closed loop


@pytest.mark.parametrize("water", [(0.0, 0.1), (-0.1, 0.0), (0.1, 0.0)], ids=["cross", "head", "following"])
def test_reaches_and_holds_the_desired_velocity_against_a_current(water) -> None:
    mpc = BuoyMpc(time_budget_s=RELAXED_BUDGET_S)
    desired = np.array([0.5, 0.0])
    velocities, results = closed_loop(mpc, desired, water, steps=60)  # 30 s
    error = np.hypot(*(velocities - desired).T)
    assert all(r.ok and not r.fallback and r.status == "optimal" for r in results)
    assert error[19] < 0.02, "within 10 s"
    assert error[20:].max() < 0.02, "held: the drift is fed forward"
    assert error[-1] < 1e-3
    # At rest in the water the thrust balances the drag of the drift-relative velocity.
    np.testing.assert_allclose(results[-1].thrust_world_n, drag(desired - np.asarray(water)), atol=0.05)


def test_without_the_drift_the_same_loop_misses() -> None:
    # The MPC told there is no current, while there is one: the feed-forward is what holds the velocity.
    mpc = BuoyMpc(time_budget_s=RELAXED_BUDGET_S)
    desired, water = np.array([0.5, 0.0]), np.array([0.0, 0.1])
    velocity = np.zeros(2)
    for _ in range(60):
        result = mpc.solve(desired, velocity, np.zeros(2), 0.0, 45.0)
        velocity = simulate(velocity, result.thrust_world_n, water)
    assert np.hypot(*(velocity - desired)) > 0.02


def test_thrust_change_per_step_is_bounded() -> None:
    mpc = BuoyMpc(time_budget_s=RELAXED_BUDGET_S)
    rng = np.random.default_rng(11)
    velocity, previous = np.zeros(2), np.zeros(2)
    largest = 0.0
    for k in range(200):
        if k % 10 == 0:  # abrupt new wishes: full reversals included
            desired = rng.uniform(-1.0, 1.0, 2)
        result = mpc.solve(desired, velocity, np.zeros(2), 0.0, 45.0)
        largest = max(largest, float(np.max(np.abs(result.thrust_world_n - previous))))
        velocity = simulate(velocity, result.thrust_world_n, np.zeros(2))
        previous = result.thrust_world_n
    assert largest <= mpc.max_thrust_change_n + TOL_N
    assert largest > 0.99 * mpc.max_thrust_change_n, "the bound is reached, so the test can fail"


def test_change_bound_applies_from_the_given_previous_thrust() -> None:
    mpc = BuoyMpc(time_budget_s=RELAXED_BUDGET_S)
    previous = np.array([-20.0, 10.0])
    result = mpc.solve(np.array([1.0, 0.0]), np.zeros(2), np.zeros(2), 0.0, 45.0, previous)
    assert np.max(np.abs(result.thrust_world_n - previous)) <= 15.0 + TOL_N
    np.testing.assert_allclose(result.thrust_world_n[0], -5.0, atol=1e-6)  # pushed east as far as allowed


def test_thrust_never_leaves_the_polygon() -> None:
    mpc = BuoyMpc(time_budget_s=RELAXED_BUDGET_S)
    rng = np.random.default_rng(5)
    normals = polygon_normals(16)
    reached = 0.0
    for _ in range(1000):
        limit = float(rng.choice([0.0, rng.uniform(1.0, 60.0)], p=[0.02, 0.98]))
        previous = None if rng.random() < 0.2 else rng.uniform(-80.0, 80.0, 2)  # also far outside
        heading = rng.uniform(-math.pi, math.pi)
        result = mpc.solve(
            rng.uniform(-2.0, 2.0, 2), rng.uniform(-1.5, 1.5, 2), rng.normal(0.0, 0.3, 2), heading, limit, previous
        )
        world = result.thrust_world_n
        assert float(np.max(normals @ world)) <= limit * math.cos(math.pi / 16) + TOL_N
        assert np.hypot(*result.thrust_body_n) <= limit + TOL_N
        np.testing.assert_allclose(np.hypot(*result.thrust_body_n), np.hypot(*world), atol=1e-9)
        reached = max(reached, float(np.max(normals @ world)) / max(limit, 1e-9))
    assert reached > 0.99 * math.cos(math.pi / 16), "commands do reach the bound"


def test_body_frame_output_at_heading_90_degrees_by_hand() -> None:
    mpc = BuoyMpc(time_budget_s=RELAXED_BUDGET_S)
    # Heading north: the body x axis points north, the body y axis (left) points west.
    north = mpc.solve(np.array([0.0, 0.5]), np.array([0.0, 0.5]), np.zeros(2), math.pi / 2, 45.0, np.array([0, 12.5]))
    np.testing.assert_allclose(north.thrust_world_n, [0.0, 12.5], atol=1e-6)  # holds 0.5 m/s: 5*0.5 + 40*0.25
    np.testing.assert_allclose(north.thrust_body_n, [12.5, 0.0], atol=1e-6)  # straight ahead
    mpc.reset()
    east = mpc.solve(np.array([0.5, 0.0]), np.array([0.5, 0.0]), np.zeros(2), math.pi / 2, 45.0, np.array([12.5, 0]))
    np.testing.assert_allclose(east.thrust_world_n, [12.5, 0.0], atol=1e-6)
    np.testing.assert_allclose(east.thrust_body_n, [0.0, -12.5], atol=1e-6)  # to the right of a north heading
    # In general: body = (wy, -wx) at 90 degrees.
    wx, wy = north.thrust_world_n
    np.testing.assert_allclose(north.thrust_body_n, [wy, -wx], atol=1e-12)


@pytest.mark.parametrize("limit", [18.0, 0.0])
def test_weak_battery_limit_is_respected(limit: float) -> None:
    mpc = BuoyMpc(time_budget_s=RELAXED_BUDGET_S)
    velocities, results = closed_loop(mpc, (1.0, 0.0), (0.0, 0.0), steps=40, limit=limit)  # 1 m/s needs 45 N
    norms = np.array([np.hypot(*r.thrust_world_n) for r in results])
    assert all(in_polygon(mpc, r.thrust_world_n, limit) for r in results)
    assert norms.max() <= limit + TOL_N
    if limit > 0.0:
        assert all(r.ok for r in results)
        assert norms[-1] > 0.99 * limit * math.cos(math.pi / 16), "it uses what the battery gives"
        assert velocities[-1, 0] < 0.7  # 18 N holds about 0.6 m/s, not 1
    else:
        assert all(r.status == "no thrust available" and not r.fallback for r in results)
        assert not velocities.any()


def test_plan_matches_ipopt_on_the_same_problem() -> None:
    mpc = BuoyMpc(time_budget_s=RELAXED_BUDGET_S)
    nlp = ca.nlpsol("check", "ipopt", mpc.problem, {"print_time": False, "ipopt": {"print_level": 0, "sb": "yes"}})
    rng = np.random.default_rng(2)
    for _ in range(10):
        desired, velocity, water = rng.uniform(-1, 1, 2), rng.uniform(-1, 1, 2), rng.normal(0, 0.2, 2)
        limit, previous = rng.uniform(10.0, 45.0), mpc.into_polygon(rng.uniform(-30, 30, 2), 45.0)
        previous = mpc.into_polygon(previous, limit)
        mpc.reset()
        assert mpc.solve(desired, velocity, water, 0.0, limit, previous).ok
        p = np.concatenate((velocity, water, desired, previous / MODEL.max_thrust_n))
        x = np.array(nlp(p=p, **mpc.qp_bounds(limit, previous))["x"]).ravel() * MODEL.max_thrust_n
        np.testing.assert_allclose(mpc.last_plan_world_n, x.reshape(-1, 2), atol=1e-3)


@pytest.mark.parametrize("sides", range(3, 18))
def test_polygon_rows_bound_the_same_polygon_as_its_sides(sides: int) -> None:
    # Two-sided rows for an even number of sides (opposite sides are parallel), one row per side otherwise: the
    # largest support over the rows is the largest over all sides, for any point.
    rows, two_sided = polygon_rows(sides)
    assert two_sided == (sides % 2 == 0) and len(rows) == (sides // 2 if two_sided else sides)
    points = np.random.default_rng(sides).normal(0.0, 30.0, (500, 2))
    support = np.abs(points @ rows.T) if two_sided else points @ rows.T
    np.testing.assert_allclose(support.max(axis=1), (points @ polygon_normals(sides).T).max(axis=1), rtol=1e-14)


def test_plans_are_those_of_the_qp_with_one_row_per_side() -> None:
    # The QP as it was built before the rows were paired (16 one-sided rows per step, each with a lower bound that
    # is never active), solved by the same solver on the same Hessian and gradient: the same plans to round-off.
    mpc = BuoyMpc(time_budget_s=RELAXED_BUDGET_S)
    n, sides, scale = 2 * mpc.horizon, mpc.polygon_sides, MODEL.max_thrust_n
    constraints = np.zeros((sides * mpc.horizon + n - 2, n))
    for k in range(mpc.horizon):
        constraints[sides * k : sides * (k + 1), 2 * k : 2 * k + 2] = polygon_normals(sides)
    for j in range(n - 2):
        constraints[sides * mpc.horizon + j, j + 2], constraints[sides * mpc.horizon + j, j] = 1.0, -1.0
    one_sided = ca.conic(
        "one_sided", mpc.solver, {"h": ca.Sparsity.dense(n, n), "a": ca.Sparsity.dense(*constraints.shape)}
    )
    data = mpc._data.function
    rng = np.random.default_rng(11)
    largest = 0.0
    for _ in range(200):
        desired, velocity, water = rng.uniform(-1, 1, 2), rng.uniform(-1, 1, 2), rng.normal(0, 0.2, 2)
        limit = rng.uniform(5.0, 45.0)
        previous = mpc.into_polygon(rng.uniform(-40, 40, 2), limit)
        plan = mpc._solve_qp(tuple(desired), tuple(velocity), tuple(water), limit, tuple(previous))
        h, g = data(np.concatenate((velocity, water, desired, previous / scale)))
        box, step, prev = limit / scale, mpc.max_thrust_change_n / scale, previous / scale
        lbx, ubx = np.full(n, -box), np.full(n, box)
        lbx[:2], ubx[:2] = np.maximum(-box, prev - step), np.minimum(box, prev + step)
        lba = np.concatenate((np.full(sides * mpc.horizon, -2.0 * box), np.full(n - 2, -step)))
        uba = np.concatenate((np.full(sides * mpc.horizon, box * mpc.inradius_ratio), np.full(n - 2, step)))
        x = one_sided(h=h, g=g, a=constraints, lbx=lbx, ubx=ubx, lba=lba, uba=uba)["x"]
        largest = max(largest, float(np.abs(plan - scale * np.array(x).reshape(-1, 2)).max()))
    assert largest < 1e-9  # N


# ---------------------------------------------------------------- buoy: failures


def _raise(*_args, **_kwargs):
    raise RuntimeError("solver exploded")


def _nan_plan(self, *_args, **_kwargs):
    return np.full((self.horizon, 2), np.nan)


@pytest.mark.parametrize("failure", ["raises", "nan", "budget"])
def test_forced_failure_gives_the_fallback_within_limits(failure: str, monkeypatch, caplog) -> None:
    mpc = BuoyMpc(time_budget_s=0.0 if failure == "budget" else RELAXED_BUDGET_S)
    if failure == "raises":
        monkeypatch.setattr(mpc, "_solve_qp", _raise)
    elif failure == "nan":
        monkeypatch.setattr(mpc, "_solve_qp", _nan_plan.__get__(mpc))
    desired, velocity, water, limit = np.array([0.8, 0.0]), np.array([0.1, 0.0]), np.array([0.0, 0.1]), 30.0
    previous = np.array([5.0, 0.0])
    with caplog.at_level(logging.WARNING, logger="bob_autonomy.control.mpc"):
        result = mpc.solve(desired, velocity, water, math.pi / 2, limit, previous)
    assert not result.ok and result.fallback and mpc.fallbacks == 1
    assert "fallback" in result.status and any(r.name == "bob_autonomy.control.mpc" for r in caplog.records)
    if failure == "budget":
        assert "time budget" in result.status
    # Saturated proportional command: feed-forward 5*0.806 + 40*0.806^2 ~ 30 N east plus 42 N of
    # correction is above 30 N, then at most 15 N from the previous 5 N per component.
    assert in_polygon(mpc, result.thrust_world_n, limit)
    assert np.max(np.abs(result.thrust_world_n - previous)) <= 15.0 + TOL_N
    np.testing.assert_allclose(result.thrust_world_n[0], 20.0, atol=1e-6)
    wx, wy = result.thrust_world_n
    np.testing.assert_allclose(result.thrust_body_n, [wy, -wx], atol=1e-12)
    # The next call falls back again and is counted again.
    mpc.solve(desired, velocity, water, 0.0, limit)
    assert mpc.fallbacks == 2


def test_a_real_solver_failure_is_a_counted_fallback_naming_the_solver() -> None:
    # The conic solvers raise when they do not solve (error_on_fail; no stats() per call): make the QPs infeasible
    # (constraint lower bounds above their upper bounds) and the solver's own failure must become the fallback.
    buoy = BuoyMpc(time_budget_s=RELAXED_BUDGET_S)
    buoy._qp.inputs["lba"][buoy._n_poly :] = 1e3
    result = buoy.solve(np.array([0.5, 0.0]), np.zeros(2), np.zeros(2), 0.0, 30.0)
    assert not result.ok and result.fallback and buoy.fallbacks == 1
    assert result.status.startswith(f"fallback: _SolveError: {buoy.solver}: ")
    assert in_polygon(buoy, result.thrust_world_n, 30.0)
    ebot = DiffDriveMpc(time_budget_s=RELAXED_BUDGET_S)
    infeasible = (np.full(ebot.horizon, 1.0), np.full(ebot.horizon, -2.0))  # every row's upper bound below its lower
    ebot._row_bounds = lambda lowest_forward: infeasible
    result = ebot.solve(np.array([0.0, 0.2]), 0.0)
    assert not result.ok and ebot.fallbacks == 1 and ebot.solver in result.status
    assert result.wheels_mps[1] > result.wheels_mps[0]  # the heuristic turns left


def test_fallback_without_limits_to_reach_is_the_proportional_command(monkeypatch) -> None:
    mpc = BuoyMpc(time_budget_s=RELAXED_BUDGET_S)
    monkeypatch.setattr(mpc, "_solve_qp", _raise)
    desired, velocity, water = np.array([0.3, 0.0]), np.array([0.28, 0.0]), np.array([0.0, 0.0])
    result = mpc.solve(desired, velocity, water, 0.0, 45.0, np.array([5.1, 0.0]))
    expected = (5.0 + 40.0 * 0.3) * 0.3 + 35.0 * 1.5 * 0.02  # drag feed-forward + mass * gain * error
    np.testing.assert_allclose(result.thrust_world_n, [expected, 0.0], atol=1e-9)


def test_determinism() -> None:
    def run() -> np.ndarray:
        mpc = BuoyMpc(time_budget_s=RELAXED_BUDGET_S)
        rng = np.random.default_rng(9)
        out = []
        for _ in range(50):
            r = mpc.solve(rng.uniform(-1, 1, 2), rng.uniform(-1, 1, 2), rng.normal(0, 0.1, 2), rng.uniform(-3, 3), 40)
            out.append(np.concatenate((r.thrust_body_n, r.thrust_world_n)))
        return np.array(out)

    np.testing.assert_array_equal(run(), run())


def _buoy_inputs(seed: int, steps: int = 40) -> list[tuple]:
    rng = np.random.default_rng(seed)
    return [
        (rng.uniform(-1, 1, 2), rng.uniform(-1, 1, 2), rng.normal(0, 0.1, 2), rng.uniform(-3, 3), rng.uniform(20, 45))
        for _ in range(steps)
    ]


def assert_shared_but_independent(make, first: list[tuple], second: list[tuple], command) -> None:
    """Two controllers from `make()` share their casadi Functions, yet solving `first` and `second` in turn
    gives exactly the commands (`command(result)`) that each sequence gives a controller of its own."""
    alone = []
    for inputs in (first, second):
        mpc = make()
        alone.append([command(mpc.solve(*args)) for args in inputs])
    a, b = make(), make()
    assert a._qp.function is b._qp.function and a._data.function is b._data.function
    together: tuple[list, list] = ([], [])
    for args_a, args_b in zip(first, second, strict=True):
        together[0].append(command(a.solve(*args_a)))
        together[1].append(command(b.solve(*args_b)))
    for mine, by_itself in zip(together, alone, strict=True):
        np.testing.assert_array_equal(np.array(mine), np.array(by_itself))


@pytest.mark.parametrize("solver", [s for s in ("daqp", "osqp") if ca.has_conic(s)])
def test_controllers_of_one_tuning_share_the_solver_but_not_its_state(solver: str) -> None:
    """A fleet builds the QP once (the casadi Functions are shared); each controller keeps its own buffers, so
    two controllers solving in turn give exactly what each gives alone (OSQP's warm start lives there too)."""

    def make() -> BuoyMpc:
        return BuoyMpc(solver=solver, time_budget_s=RELAXED_BUDGET_S)

    assert_shared_but_independent(make, _buoy_inputs(1), _buoy_inputs(2), lambda r: r.thrust_world_n)
    other = BuoyMpc(solver=solver, horizon=8, time_budget_s=RELAXED_BUDGET_S)
    assert other._qp.function is not make()._qp.function


# ---------------------------------------------------------------- eBot


@pytest.mark.parametrize("form", ["linear", "nonlinear"])
def test_ebot_wheel_speeds_within_limits(form: str) -> None:
    mpc = DiffDriveMpc(form=form, time_budget_s=RELAXED_BUDGET_S)
    rng = np.random.default_rng(3)
    for _ in range(300 if form == "linear" else 60):
        previous = None if rng.random() < 0.3 else rng.uniform(-0.3, 0.3, 2)
        result = mpc.solve(rng.uniform(-1.0, 1.0, 2), rng.uniform(-math.pi, math.pi), previous)
        assert result.wheels_mps.shape == (2,)
        assert np.all(np.abs(result.wheels_mps) <= 0.2 + 1e-12)
        assert result.ok


@pytest.mark.parametrize("form", ["linear", "nonlinear"])
@pytest.mark.parametrize("side", [1.0, -1.0], ids=["left", "right"])
def test_ebot_turns_towards_a_direction_90_degrees_off(form: str, side: float) -> None:
    mpc = DiffDriveMpc(form=form, time_budget_s=RELAXED_BUDGET_S)
    heading = 0.0
    desired = 0.2 * np.array([0.0, side])  # 90 degrees to the side of the heading
    first = mpc.solve(desired, heading, np.array([0.2, 0.2]))  # driving straight ahead
    assert side * (first.wheels_mps[1] - first.wheels_mps[0]) > 0.05  # yaw rate towards the desired side
    wheels = first.wheels_mps
    for _ in range(20):  # 2 s of exact unicycle
        heading += (wheels[1] - wheels[0]) / 0.1 * 0.1
        wheels = mpc.solve(desired, heading).wheels_mps
    assert abs(heading - side * math.pi / 2) < 0.1
    assert np.all(wheels > 0.15), "then it drives forwards"


def test_ebot_default_form_turns_from_rest() -> None:
    # The nonlinear form's initial guess from rest is a stationary point for an exact 90-degree wish;
    # the default (linear) form turns at once.
    mpc = DiffDriveMpc(time_budget_s=RELAXED_BUDGET_S)
    assert mpc.form == "linear"
    wheels = mpc.solve(np.array([0.0, 0.2]), 0.0).wheels_mps
    assert wheels[1] - wheels[0] > 0.2


def test_ebot_default_form_backs_up_to_a_wish_almost_behind() -> None:
    # Driving east, the wish turns to 160 degrees: the velocity vector is tracked backwards,
    # the tail swinging round to point at it, rather than by a U-turn.
    mpc = DiffDriveMpc(time_budget_s=RELAXED_BUDGET_S)
    desired = 0.2 * np.array([math.cos(math.radians(160)), math.sin(math.radians(160))])
    heading, wheels, errors = 0.0, np.array([0.2, 0.2]), []
    for k in range(30):
        wheels = mpc.solve(desired, heading, wheels if k == 0 else None).wheels_mps
        forward, turn = 0.5 * (wheels[0] + wheels[1]), (wheels[1] - wheels[0]) / 0.1 * 0.1
        velocity = forward * np.array([math.cos(heading + turn / 2), math.sin(heading + turn / 2)])
        heading += turn
        errors.append(np.hypot(*(velocity - desired)))
    assert np.all(wheels < -0.19)
    assert abs(heading - math.radians(-20)) < 0.02
    assert np.mean(errors) < 0.02  # a U-turn averages 0.056 m/s


@pytest.mark.parametrize("form", ["linear", "nonlinear"])
def test_ebot_forward_only_turns_on_the_spot_instead_of_backing_up(form: str) -> None:
    # The same wish 160 degrees round, for a robot that must face where it goes (a wished heading): no planned
    # step ever runs backwards; it pivots (wheels opposite, forward speed 0) and then drives off facing the wish.
    mpc = DiffDriveMpc(form=form, time_budget_s=RELAXED_BUDGET_S)
    desired = 0.2 * np.array([math.cos(math.radians(160)), math.sin(math.radians(160))])
    heading, wheels = 0.0, np.array([0.2, 0.2])
    for k in range(30):
        wheels = mpc.solve(desired, heading, wheels if k == 0 else None, forward_only=True).wheels_mps
        assert 0.5 * (wheels[0] + wheels[1]) >= -1e-6
        assert np.all(0.5 * (mpc._plan[0::2] + mpc._plan[1::2]) >= -1e-6)  # the whole plan, not only its first step
        heading += (wheels[1] - wheels[0]) / 0.1 * 0.1
    assert abs(heading - math.radians(160)) < math.radians(1.0)
    assert np.all(wheels > 0.19), "then it drives forwards"


def test_ebot_forward_only_holds_for_random_wishes() -> None:
    mpc = DiffDriveMpc(time_budget_s=RELAXED_BUDGET_S)
    rng = np.random.default_rng(5)
    for _ in range(300):
        previous = None if rng.random() < 0.3 else rng.uniform(-0.2, 0.2, 2)
        result = mpc.solve(rng.uniform(-0.3, 0.3, 2), rng.uniform(-math.pi, math.pi), previous, forward_only=True)
        assert result.ok
        assert result.wheels_mps.sum() >= -1e-6
        assert np.all(np.abs(result.wheels_mps) <= 0.2 + 1e-12)


def test_ebot_forced_failure_gives_the_heuristic_fallback(monkeypatch, caplog) -> None:
    mpc = DiffDriveMpc(time_budget_s=RELAXED_BUDGET_S)
    monkeypatch.setattr(mpc, "_solve_plan", _raise)
    with caplog.at_level(logging.WARNING, logger="bob_autonomy.control.mpc"):
        result = mpc.solve(np.array([0.0, 0.5]), 0.0)
    assert not result.ok and result.fallback and mpc.fallbacks == 1
    assert any(r.name == "bob_autonomy.control.mpc" for r in caplog.records)
    assert np.all(np.abs(result.wheels_mps) <= 0.2 + 1e-12)
    assert result.wheels_mps[1] > result.wheels_mps[0]  # the heuristic turns left too


def test_ebot_determinism() -> None:
    def run() -> np.ndarray:
        mpc = DiffDriveMpc(time_budget_s=RELAXED_BUDGET_S)
        rng = np.random.default_rng(4)
        return np.array([mpc.solve(rng.uniform(-0.3, 0.3, 2), rng.uniform(-3, 3)).wheels_mps for _ in range(50)])

    np.testing.assert_array_equal(run(), run())


def test_ebot_controllers_of_one_tuning_share_the_solver_but_not_its_state() -> None:
    def inputs(seed: int) -> list[tuple]:
        rng = np.random.default_rng(seed)
        return [(rng.uniform(-0.3, 0.3, 2), rng.uniform(-3, 3)) for _ in range(40)]

    def make() -> DiffDriveMpc:
        return DiffDriveMpc(time_budget_s=RELAXED_BUDGET_S)

    assert_shared_but_independent(make, inputs(5), inputs(6), lambda r: r.wheels_mps)


def test_ebot_wheel_clipping_is_numpys_clip_of_nan_to_num() -> None:
    rng = np.random.default_rng(3)
    specials = [math.nan, math.inf, -math.inf, 0.0, -0.0, 0.2, -0.2, 1e308]
    values = [[a, b] for a in specials for b in specials] + rng.normal(0.0, 0.3, (200, 2)).tolist()
    for w in values:
        np.testing.assert_array_equal(_clipped(np.array(w), 0.2), np.clip(np.nan_to_num(np.array(w)), -0.2, 0.2))
