"""PerimeterDefense (eq. 3 negated, plus obstacle echoes) against values worked out by hand."""

from __future__ import annotations

import math

import numpy as np
import pytest
from behavior_helpers import assert_batch_equivalent, make_table, make_view
from numpy.testing import assert_allclose

from behaviors.base import Senses, View
from behaviors.perimeter_defense import PerimeterDefense, obstacle_repulsion, repulsion

NAN = math.nan


def lone_view(neighbours: list[list[float]], echoes: list[list[float]] | None = None) -> View:
    """Agent 0 at the origin hearing every other row; `echoes` are its (K, 2) obstacle offsets."""
    positions = [[0.0, 0.0], *neighbours]
    n = len(positions)
    table = make_table(positions)
    k = 0 if echoes is None else len(echoes)
    obstacles = np.full((n, k, 2), NAN)
    if echoes:
        obstacles[0] = np.asarray(echoes, dtype=float)
    senses = Senses(obstacles=obstacles, light=np.full((n, 2), NAN))
    return make_view(table, rows=[0], pairs=[(0, j) for j in range(1, n)], senses=senses)


# ----------------------------------------------------------------------------- neighbours


def test_one_neighbour_pushes_straight_away() -> None:
    view = lone_view([[2.0, 0.0]])
    # -(2, 0) / |(2, 0)|^2 = -(2, 0) / 4 = (-0.5, 0).
    assert_allclose(repulsion(view), [[-0.5, 0.0]], atol=1e-12)
    assert_allclose(PerimeterDefense().direction(view), [[-0.5, 0.0]], atol=1e-12)
    wish = PerimeterDefense(max_speed=0.2, full_speed_at=1.0).step(view)
    # |F| = 0.5 -> speed 0.2 * 0.5 = 0.1 m/s along (-1, 0); no heading preference.
    assert_allclose(wish.velocity, [[-0.1, 0.0]], atol=1e-12)
    assert np.all(np.isnan(wish.heading))


def test_two_neighbours_sum_with_weight_one_over_distance() -> None:
    view = lone_view([[1.0, 0.0], [0.0, 2.0]])
    # -(1, 0) / 1 - (0, 2) / 4 = (-1, -0.5).
    assert_allclose(PerimeterDefense().direction(view), [[-1.0, -0.5]], atol=1e-12)
    # |F| = sqrt(1.25) > full_speed_at = 1: full speed 0.2 along (-1, -0.5) / sqrt(1.25).
    wish = PerimeterDefense(max_speed=0.2, full_speed_at=1.0).step(view)
    norm = math.sqrt(1.25)
    assert_allclose(wish.velocity, [[-0.2 / norm, -0.1 / norm]], atol=1e-12)


def test_pair_table_moves_both_agents_apart() -> None:
    view = make_view(make_table([[0.0, 0.0], [0.0, 4.0]]))
    # Each: -(0, +-4) / 16 = (0, -+0.25); speed 0.2 * 0.25 = 0.05.
    wish = PerimeterDefense().step(view)
    assert_allclose(wish.velocity, [[0.0, -0.05], [0.0, 0.05]], atol=1e-12)


def test_symmetric_neighbours_cancel_and_the_agent_stops() -> None:
    wish = PerimeterDefense().step(lone_view([[1.0, 0.0], [-1.0, 0.0], [0.0, 3.0], [0.0, -3.0]]))
    assert np.array_equal(wish.velocity, [[0.0, 0.0]])


def test_dead_band_stops_a_nearly_balanced_agent() -> None:
    view = lone_view([[1.0, 0.0], [-1.01, 0.0]])
    # F = -1 + 1 / 1.01 = -0.00990...: below the 0.02 dead band -> exact stop.
    f = -1.0 + 1.0 / 1.01
    assert_allclose(PerimeterDefense().direction(view), [[f, 0.0]], atol=1e-12)
    assert np.array_equal(PerimeterDefense(dead_band=0.02).step(view).velocity, [[0.0, 0.0]])
    # With a smaller dead band it creeps: 0.2 * 0.0099 = 0.00198 m/s along -x.
    assert_allclose(PerimeterDefense(dead_band=0.005).step(view).velocity, [[0.2 * f, 0.0]], atol=1e-12)


def test_closer_neighbour_weighs_more() -> None:
    # Neighbours at (1, 0) and (-2, 0): (-1, 0) + (0.5, 0) = (-0.5, 0): away from the closer one.
    view = lone_view([[1.0, 0.0], [-2.0, 0.0]])
    assert_allclose(PerimeterDefense().direction(view), [[-0.5, 0.0]], atol=1e-12)
    assert PerimeterDefense().step(view).velocity[0, 0] < 0.0
    # And a neighbour at 1 m pushes twice as hard as one at 2 m.
    near = np.hypot(*repulsion(lone_view([[0.0, 1.0]]))[0])
    far = np.hypot(*repulsion(lone_view([[0.0, 2.0]]))[0])
    assert_allclose([near, far], [1.0, 0.5], atol=1e-12)


@pytest.mark.parametrize(
    ("max_speed", "full_speed_at", "expected_speed"),
    [
        (0.2, 1.0, 0.1),  # 0.2 * 0.5 / 1
        (0.2, 0.25, 0.2),  # 0.5 / 0.25 = 2 -> clipped to 1
        (0.4, 2.0, 0.1),  # 0.4 * 0.5 / 2
        (1.0, 0.5, 1.0),  # exactly at full speed
    ],
)
def test_speed_scales_with_the_force(max_speed: float, full_speed_at: float, expected_speed: float) -> None:
    view = lone_view([[0.0, -2.0]])  # F = -(0, -2) / 4 = (0, 0.5)
    wish = PerimeterDefense(max_speed=max_speed, full_speed_at=full_speed_at).step(view)
    assert_allclose(wish.velocity, [[0.0, expected_speed]], atol=1e-12)


def test_lone_agent_and_coincident_agents_do_not_move_or_nan() -> None:
    alone = PerimeterDefense().step(make_view(make_table([[3.0, 4.0]]), pairs=[]))
    assert np.array_equal(alone.velocity, [[0.0, 0.0]])
    same = PerimeterDefense().step(make_view(make_table([[1.0, 1.0], [1.0, 1.0]])))
    assert np.array_equal(same.velocity, np.zeros((2, 2)))


# ----------------------------------------------------------------------------- obstacle echoes


def test_echo_inside_range_pushes_with_one_over_d_minus_one_over_range() -> None:
    view = lone_view([], echoes=[[0.5, 0.0]])
    # 1 / 0.5 - 1 / 1.5 = 2 - 2/3 = 4/3, away from the echo: (-4/3, 0).
    pd = PerimeterDefense(obstacle_range_m=1.5)
    assert_allclose(pd.direction(view), [[-4.0 / 3.0, 0.0]], atol=1e-12)
    # 4/3 > full_speed_at = 1: full speed 0.2 along -x.
    assert_allclose(pd.step(view).velocity, [[-0.2, 0.0]], atol=1e-12)


def test_diagonal_echo() -> None:
    # Echo at (0.6, 0.8): d = 1, push 1 - 1/1.5 = 1/3 along -(0.6, 0.8) = (-0.2, -0.8/3).
    view = lone_view([], echoes=[[0.6, 0.8]])
    assert_allclose(PerimeterDefense().direction(view), [[-0.2, -0.8 / 3.0]], atol=1e-12)


@pytest.mark.parametrize("echo", [[1.5, 0.0], [0.0, -1.5], [2.0, 0.0], [NAN, NAN], [NAN, 0.5]])
def test_echo_at_or_beyond_range_or_missing_pushes_nothing(echo: list[float]) -> None:
    view = lone_view([], echoes=[echo])
    force = PerimeterDefense(obstacle_range_m=1.5).direction(view)
    assert np.array_equal(force, [[0.0, 0.0]])
    assert np.array_equal(PerimeterDefense().step(view).velocity, [[0.0, 0.0]])


def test_echoes_add_to_neighbours_and_each_other() -> None:
    # Neighbour at (2, 0): (-0.5, 0). Echo at (0, 0.5): (0, -4/3). Echo at (-1, 0): 1 - 2/3 = 1/3 -> (1/3, 0).
    # Echo beyond range and a NaN echo: nothing.
    view = lone_view([[2.0, 0.0]], echoes=[[0.0, 0.5], [-1.0, 0.0], [0.0, 3.0], [NAN, NAN]])
    assert_allclose(PerimeterDefense().direction(view), [[-0.5 + 1.0 / 3.0, -4.0 / 3.0]], atol=1e-12)
    # obstacle_weight 2 doubles the echo part only: (-0.5 + 2/3, -8/3).
    assert_allclose(PerimeterDefense(obstacle_weight=2.0).direction(view), [[-0.5 + 2.0 / 3.0, -8.0 / 3.0]], atol=1e-12)


def test_obstacle_weight_zero_ignores_echoes() -> None:
    view = lone_view([[2.0, 0.0]], echoes=[[0.0, 0.5], [0.3, 0.0]])
    assert_allclose(PerimeterDefense(obstacle_weight=0.0).direction(view), [[-0.5, 0.0]], atol=1e-12)
    view_no_neighbour = lone_view([], echoes=[[0.3, 0.0]])
    assert np.array_equal(PerimeterDefense(obstacle_weight=0.0).step(view_no_neighbour).velocity, [[0.0, 0.0]])


def test_obstacle_range_changes_the_fade() -> None:
    # Echo at 1 m: R = 2 -> 1 - 0.5 = 0.5; R = 1 -> nothing (at the range).
    assert_allclose(obstacle_repulsion(np.array([[[0.0, 1.0]]]), 2.0), [[0.0, -0.5]], atol=1e-12)
    assert np.array_equal(obstacle_repulsion(np.array([[[0.0, 1.0]]]), 1.0), [[0.0, 0.0]])
    assert obstacle_repulsion(np.zeros((3, 0, 2)), 1.5).shape == (3, 2)


def test_only_the_updated_rows_echoes_count() -> None:
    # Row 1 has an echo but only row 0 is updated: row 0 feels nothing from it.
    table = make_table([[0.0, 0.0], [10.0, 0.0]])
    obstacles = np.array([[[NAN, NAN]], [[0.2, 0.0]]])
    view = make_view(table, rows=[0], pairs=[], senses=Senses(obstacles=obstacles, light=np.full((2, 2), NAN)))
    assert np.array_equal(PerimeterDefense().direction(view), [[0.0, 0.0]])
    view1 = make_view(table, rows=[1], pairs=[], senses=Senses(obstacles=obstacles, light=np.full((2, 2), NAN)))
    # 1 / 0.2 - 1 / 1.5 = 5 - 2/3 = 13/3 away: (-13/3, 0).
    assert_allclose(PerimeterDefense().direction(view1), [[-13.0 / 3.0, 0.0]], atol=1e-12)


# ----------------------------------------------------------------------------- batch equivalence

SWARM = [[0.0, 0.0], [1.0, 0.5], [2.5, -1.0], [0.5, 2.0]]
SWARM_PAIRS = [(0, 1), (0, 2), (0, 3), (1, 0), (1, 2), (2, 1), (3, 0), (3, 1)]


@pytest.mark.parametrize(
    "behavior",
    [
        PerimeterDefense(),
        PerimeterDefense(max_speed=0.5, full_speed_at=3.0, dead_band=0.1),
        PerimeterDefense(obstacle_weight=0.0),
        PerimeterDefense(obstacle_weight=2.0, obstacle_range_m=1.0),
    ],
)
def test_batch_equals_one_vessel_at_a_time(behavior: PerimeterDefense) -> None:
    table = make_table(SWARM, headings=[0.1, 2.0, -1.0, 3.0], ids=[11, 12, 13, 14])
    obstacles = np.array(
        [
            [[0.4, 0.0], [NAN, NAN]],
            [[NAN, NAN], [NAN, NAN]],
            [[0.0, -0.9], [-0.7, 0.7]],
            [[1.6, 0.0], [0.0, 0.3]],
        ]
    )
    senses = Senses(obstacles=obstacles, light=np.full((4, 2), NAN))
    wish = assert_batch_equivalent(behavior, make_view(table, pairs=SWARM_PAIRS, senses=senses))
    assert np.all(np.isfinite(wish.velocity))
    assert np.any(wish.velocity != 0.0)
