"""Marching against hand-computed spread, heading and group terms."""

from __future__ import annotations

import math

import numpy as np
from behavior_helpers import assert_batch_equivalent, make_table, make_view
from numpy.testing import assert_allclose

from behaviors.marching import Marching


def test_one_neighbour_spread_and_heading() -> None:
    # Neighbour at (1, 0), heading pi/2. spread = -(1, 0) * 0.35 / 1 = (-0.35, 0), weight 2;
    # heading mean = (0, 1), weight 1; group = 0 with one neighbour.
    # target = (-0.7, 1), |target|^2 = 1.49 > 0.5: move at 0.2 m/s along it.
    table = make_table([[0.0, 0.0], [1.0, 0.0]], headings=[0.0, math.pi / 2])
    view = make_view(table, rows=[0], pairs=[(0, 1)])
    assert_allclose(Marching().target(view), [[-0.7, 1.0]], atol=1e-12)
    expected = 0.2 * np.array([-0.7, 1.0]) / math.sqrt(1.49)
    wish = Marching().step(view)
    assert_allclose(wish.velocity, [expected], atol=1e-12)
    assert np.all(np.isnan(wish.heading))


def test_group_term_is_centroid_over_rms_spread() -> None:
    # Neighbours at (2, 0) and (0, 2): centroid (1, 1); each is sqrt(2) from it, so the
    # spread is sqrt(2) and group = (1, 1) / sqrt(2).
    table = make_table([[0.0, 0.0], [2.0, 0.0], [0.0, 2.0]])
    view = make_view(table, rows=[0], pairs=[(0, 1), (0, 2)])
    only_group = Marching(w_spread=0.0, w_heading=0.0, w_group=1.0)
    assert_allclose(only_group.target(view), [[0.70710678118654752, 0.70710678118654752]], atol=1e-12)
    # With the default weights: spread = -0.35 * ((2, 0)/4 + (0, 2)/4) = (-0.175, -0.175), x2;
    # heading mean (1, 0); group x0.2 = (0.14142136, 0.14142136).
    assert_allclose(Marching().target(view), [[0.79142135623730950, -0.20857864376269050]], atol=1e-12)


def test_group_term_uses_mean_offset_and_rms_distance_from_centroid() -> None:
    # Neighbours at (3, 0), (5, 0), (4, 3): centroid (4, 1). Offsets from it (-1, -1), (1, -1),
    # (0, 2): squared distances 2, 2, 4, mean 8/3, rms sqrt(8/3) = 1.6329931618554521.
    # group = (4, 1) / 1.6329931618554521 = (2.4494897427831781, 0.6123724356957945).
    table = make_table([[0.0, 0.0], [3.0, 0.0], [5.0, 0.0], [4.0, 3.0]])
    view = make_view(table, rows=[0], pairs=[(0, 1), (0, 2), (0, 3)])
    only_group = Marching(w_spread=0.0, w_heading=0.0, w_group=1.0)
    assert_allclose(only_group.target(view), [[2.4494897427831781, 0.6123724356957945]], atol=1e-12)


def test_two_neighbours_at_one_point_give_no_group_term() -> None:
    table = make_table([[0.0, 0.0], [2.0, 0.0], [2.0, 0.0]])
    view = make_view(table, rows=[0], pairs=[(0, 1), (0, 2)])
    only_group = Marching(w_spread=0.0, w_heading=0.0, w_group=1.0)
    assert np.array_equal(only_group.target(view), [[0.0, 0.0]])


def test_stops_below_threshold() -> None:
    # Neighbour at (0, -7), heading 0: spread = -0.35 * (0, -7) / 49 = (0, 0.05), x2 = (0, 0.1).
    # With w_heading = 0.6: target = (0.6, 0.1), |target|^2 = 0.37.
    table = make_table([[0.0, 0.0], [0.0, -7.0]])
    view = make_view(table, rows=[0], pairs=[(0, 1)])
    assert_allclose(Marching(w_heading=0.6).target(view), [[0.6, 0.1]], atol=1e-12)
    assert np.array_equal(Marching(w_heading=0.6).step(view).velocity, [[0.0, 0.0]])
    # 0.37 > 0.3: moves along (0.6, 0.1) at 0.2 m/s.
    moving = Marching(w_heading=0.6, threshold=0.3).step(view).velocity
    assert_allclose(moving, [0.2 * np.array([0.6, 0.1]) / math.sqrt(0.37)], atol=1e-12)


def test_balanced_neighbours_stop() -> None:
    # Neighbours at (0, 10) heading 0 and (0, -10) heading pi: spreads, headings and the
    # centroid offset all cancel.
    table = make_table([[0.0, 0.0], [0.0, 10.0], [0.0, -10.0]], headings=[0.0, 0.0, math.pi])
    view = make_view(table, rows=[0], pairs=[(0, 1), (0, 2)])
    assert np.array_equal(Marching().step(view).velocity, [[0.0, 0.0]])


def test_no_neighbours_keeps_own_heading() -> None:
    view = make_view(make_table([[0.0, 0.0]], headings=[math.pi / 2]), pairs=[])
    assert_allclose(Marching(speed=0.3).step(view).velocity, [[0.0, 0.3]], atol=1e-12)


def test_batch_equals_one_vessel_at_a_time() -> None:
    table = make_table([[0.0, 0.0], [0.5, 0.2], [0.1, -0.6], [1.0, 1.0]], headings=[0.0, 1.0, 2.0, -1.5])
    pairs = [(0, 1), (0, 2), (0, 3), (1, 0), (1, 3), (2, 0), (3, 1)]
    wish = assert_batch_equivalent(Marching(), make_view(table, pairs=pairs))
    assert np.all(np.hypot(wish.velocity[:, 0], wish.velocity[:, 1]) > 0.0)
