"""FollowWaypoints and HoldPosition against hand-computed wishes."""

from __future__ import annotations

import numpy as np
import pytest
from behavior_helpers import make_table, make_view
from numpy.testing import assert_allclose

from behaviors.station_keeping import HoldPosition
from behaviors.waypoints import FollowWaypoints

PATH = [(10.0, 0.0), (10.0, 10.0)]


def waypoint_view(position, index):
    table = make_table([position], memory={"waypoint_index": np.array([float(index)])})
    return make_view(table, pairs=[])


def test_heads_for_the_current_waypoint_at_speed() -> None:
    # From (0, 0) to (10, 0) at 0.5 m/s: velocity (0.5, 0).
    wish = FollowWaypoints(waypoints=PATH, speed=0.5).step(waypoint_view([0.0, 0.0], 0))
    assert_allclose(wish.velocity, [[0.5, 0.0]])
    assert wish.memory["waypoint_index"][0] == 0


def test_advances_when_within_the_arrival_radius() -> None:
    # At (8, 0), 2 m from waypoint 0 (< 3 m): index 1, heading for (10, 10): direction (2, 10)/10.198.
    wish = FollowWaypoints(waypoints=PATH, speed=0.5).step(waypoint_view([8.0, 0.0], 0))
    assert wish.memory["waypoint_index"][0] == 1
    assert_allclose(wish.velocity[0], 0.5 * np.array([2.0, 10.0]) / np.hypot(2.0, 10.0))


def test_slows_into_the_last_waypoint_and_stays() -> None:
    # 1.5 m short of the last waypoint with a 3 m radius: half speed, index stays at the last.
    wish = FollowWaypoints(waypoints=PATH, speed=0.5).step(waypoint_view([10.0, 8.5], 1))
    assert wish.memory["waypoint_index"][0] == 1
    assert_allclose(wish.velocity, [[0.0, 0.25]])


def test_loop_starts_over() -> None:
    wish = FollowWaypoints(waypoints=PATH, speed=0.5, loop=True).step(waypoint_view([10.0, 9.0], 1))
    assert wish.memory["waypoint_index"][0] == 0


def test_empty_path_is_refused() -> None:
    with pytest.raises(ValueError, match="waypoints"):
        FollowWaypoints(waypoints=[])


def test_hold_position_remembers_and_returns() -> None:
    behavior = HoldPosition(gain_per_s=0.2, max_speed=0.5)
    table = make_table([[3.0, 4.0]], memory={"hold_position": np.full((1, 2), np.nan)})
    first = behavior.step(make_view(table, pairs=[]))
    assert_allclose(first.memory["hold_position"], [[3.0, 4.0]])
    assert_allclose(first.velocity, [[0.0, 0.0]])
    # Carried 2 m east: back west at 0.2 * 2 = 0.4 m/s; carried 5 m: capped at 0.5 m/s.
    table = make_table([[5.0, 4.0], [8.0, 4.0]], memory={"hold_position": np.array([[3.0, 4.0], [3.0, 4.0]])})
    wish = behavior.step(make_view(table, pairs=[]))
    assert_allclose(wish.velocity, [[-0.4, 0.0], [-0.5, 0.0]])
