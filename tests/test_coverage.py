"""AreaCoverage against hand-computed inverse-square pushes."""

from __future__ import annotations

import math

import numpy as np
from behavior_helpers import assert_batch_equivalent, make_table, make_view
from numpy.testing import assert_allclose

from behaviors.base import Senses
from behaviors.coverage import AreaCoverage

NAN = math.nan


def senses(obstacles: list[list[list[float]]]) -> Senses:
    echoes = np.asarray(obstacles, dtype=float)
    return Senses(obstacles=echoes, light=np.full((echoes.shape[0], 2), NAN))


def test_neighbour_pushes_with_inverse_square() -> None:
    # Neighbour at (2, 0): push = -(2, 0) / 2^3 = (-0.25, 0); 0.25 > 0.05 -> 0.2 m/s along -x.
    view = make_view(make_table([[0.0, 0.0], [2.0, 0.0]]), rows=[0], pairs=[(0, 1)])
    push, sensed = AreaCoverage().target(view)
    assert_allclose(push, [[-0.25, 0.0]], atol=1e-12)
    assert sensed.tolist() == [True]
    assert_allclose(AreaCoverage().step(view).velocity, [[-0.2, 0.0]], atol=1e-12)


def test_obstacle_echo_pushes_and_nan_is_ignored() -> None:
    # Echo at (0, 0.5): push = -(0, 0.5) / 0.125 = (0, -4); the NaN echo adds nothing.
    table = make_table([[0.0, 0.0]], headings=[1.0])
    view = make_view(table, pairs=[], senses=senses([[[0.0, 0.5], [NAN, NAN]]]))
    push, _ = AreaCoverage().target(view)
    assert_allclose(push, [[0.0, -4.0]], atol=1e-12)
    assert_allclose(AreaCoverage().step(view).velocity, [[0.0, -0.2]], atol=1e-12)


def test_neighbours_and_obstacles_add() -> None:
    # Neighbour (1, 0): (-1, 0); echo (0, -0.5): (0, 0.5 / 0.125) = (0, 4). Sum (-1, 4).
    table = make_table([[0.0, 0.0], [1.0, 0.0]])
    view = make_view(
        table, rows=[0], pairs=[(0, 1)], senses=senses([[[0.0, -0.5], [NAN, NAN]], [[NAN, NAN], [NAN, NAN]]])
    )
    assert_allclose(AreaCoverage().target(view)[0], [[-1.0, 4.0]], atol=1e-12)
    expected = 0.2 * np.array([-1.0, 4.0]) / math.sqrt(17.0)
    assert_allclose(AreaCoverage().step(view).velocity, [expected], atol=1e-12)


def test_balanced_or_weak_push_stops() -> None:
    # Neighbours at (1, 0) and (-1, 0) cancel.
    view = make_view(make_table([[0.0, 0.0], [1.0, 0.0], [-1.0, 0.0]]), rows=[0], pairs=[(0, 1), (0, 2)])
    assert np.array_equal(AreaCoverage().step(view).velocity, [[0.0, 0.0]])
    # A lone neighbour at 10 m: |push| = 1 / 100 = 0.01 < 0.05: stop; > 0.005: move.
    far = make_view(make_table([[0.0, 0.0], [10.0, 0.0]]), rows=[0], pairs=[(0, 1)])
    assert np.array_equal(AreaCoverage().step(far).velocity, [[0.0, 0.0]])
    assert_allclose(AreaCoverage(threshold=0.005).step(far).velocity, [[-0.2, 0.0]], atol=1e-12)


def test_nothing_sensed_keeps_heading() -> None:
    table = make_table([[0.0, 0.0]], headings=[math.pi / 2])
    no_echo = make_view(table, pairs=[], senses=senses([[[NAN, NAN], [NAN, NAN]]]))
    assert_allclose(AreaCoverage(max_speed=0.1).step(no_echo).velocity, [[0.0, 0.1]], atol=1e-12)
    no_sensor = make_view(table, pairs=[])
    assert_allclose(AreaCoverage(max_speed=0.1).step(no_sensor).velocity, [[0.0, 0.1]], atol=1e-12)


def test_batch_equals_one_vessel_at_a_time() -> None:
    table = make_table([[0.0, 0.0], [0.5, 0.2], [0.1, -0.6], [3.0, 3.0]], headings=[0.0, 1.0, 2.0, -1.5])
    obstacles = senses(
        [
            [[0.3, 0.0], [NAN, NAN]],
            [[NAN, NAN], [NAN, NAN]],
            [[0.0, -0.4], [-0.2, 0.1]],
            [[NAN, NAN], [NAN, NAN]],
        ]
    )
    pairs = [(0, 1), (0, 2), (1, 0), (1, 2), (2, 0), (2, 1)]
    wish = assert_batch_equivalent(AreaCoverage(), make_view(table, pairs=pairs, senses=obstacles))
    # Agent 3 hears and senses nothing: it keeps its heading.
    assert_allclose(wish.velocity[3], [0.2 * math.cos(-1.5), 0.2 * math.sin(-1.5)])
