"""AvoidObstacles: hand-computed corrections of given wishes near an echo."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import pytest
from behavior_helpers import assert_batch_equivalent, make_table, make_view
from numpy.testing import assert_allclose

from behaviors.base import Behavior, MemorySpec, Senses, View, Wish
from behaviors.bob_rule import BobRule
from behaviors.obstacle_avoidance import AvoidObstacles

NAN = math.nan


@dataclass
class Constant(Behavior):
    """Wish the given velocities (n, 2) m/s and headings (n,) rad, and a memory value."""

    name: ClassVar[str] = "constant"
    memory_fields: ClassVar[dict[str, MemorySpec]] = {"mark": MemorySpec()}
    velocity: list[list[float]]
    heading: list[float]

    def step(self, view: View) -> Wish:
        return Wish(np.array(self.velocity, dtype=float), np.array(self.heading), {"mark": np.arange(view.n) + 0.5})


def run(velocity: list[list[float]], echoes: list[list[list[float]]], heading: list[float] | None = None) -> Wish:
    n = len(velocity)
    obstacles = np.asarray(echoes, dtype=float).reshape(n, -1, 2)
    view = make_view(
        make_table([[10.0 * i, 0.0] for i in range(n)]),
        pairs=[],
        senses=Senses(obstacles=obstacles, light=np.full((n, 2), NAN)),
    )
    inner = Constant(velocity, heading if heading is not None else [0.5] * n)
    return AvoidObstacles(inner).step(view)


def test_driving_straight_at_a_wall_removes_the_approach() -> None:
    # Wall echo 0.2 m ahead along +x, wish (0.2, 0). The towards component 0.2 goes, turned to the
    # obstacle's left (0, 0.2), and a push 0.2 * (0.35 - 0.2) / (0.35 - 0.12) = 0.13043478 m/s away is
    # added: (-0.13043478, 0.2), speed 0.23877 capped to the wish's 0.2 (x 0.837610):
    # (-0.10925356, 0.16752212).
    wish = run([[0.2, 0.0]], [[[0.2, 0.0], [NAN, NAN]]])
    assert wish.velocity[0, 0] <= 0.0
    assert_allclose(wish.velocity, [[-0.10925356, 0.16752212]], atol=1e-7)
    assert math.isnan(wish.heading[0])


def test_oblique_wish_slides_along_the_wall() -> None:
    # Wish (0.1, 0.1) (speed 0.14142136), echo (0.2, 0): towards = 0.1 removed and turned left (0, 0.1),
    # push 0.14142136 * 0.15 / 0.23 = 0.09223132 -> (-0.09223132, 0.2), speed 0.22024 capped to
    # 0.14142136 (x 0.642124): (-0.05922334, 0.12842350).
    wish = run([[0.1, 0.1]], [[[0.2, 0.0]]])
    assert_allclose(wish.velocity, [[-0.05922334, 0.12842350]], atol=1e-7)


def test_wish_parallel_to_the_wall_or_away_is_unchanged() -> None:
    wish = run([[0.0, 0.2], [-0.2, 0.05]], [[[0.2, 0.0]], [[0.2, 0.0]]], heading=[1.0, 2.0])
    assert_allclose(wish.velocity, [[0.0, 0.2], [-0.2, 0.05]])
    assert_allclose(wish.heading, [1.0, 2.0])


def test_far_or_missing_echoes_change_nothing() -> None:
    wish = run([[0.2, 0.0], [0.2, 0.0]], [[[0.5, 0.0]], [[NAN, NAN]]], heading=[1.0, 2.0])
    assert_allclose(wish.velocity, [[0.2, 0.0], [0.2, 0.0]])
    assert_allclose(wish.heading, [1.0, 2.0])


@pytest.mark.parametrize("velocity", [[0.2, 0.0], [0.0, 0.2], [0.1, -0.1], [-0.1, 0.15]])
def test_inside_stop_distance_only_backing_away(velocity: list[float]) -> None:
    # Echo 0.1 m ahead (< 0.12 m): whatever the wish, move straight away at the wish's speed.
    wish = run([velocity], [[[0.1, 0.0]]])
    speed = math.hypot(*velocity)
    assert wish.velocity[0, 0] < 0.0
    assert_allclose(wish.velocity, [[-speed, 0.0]], atol=1e-12)


def test_standing_still_stays_still() -> None:
    wish = run([[0.0, 0.0]], [[[0.05, 0.0]]], heading=[1.0])
    assert np.array_equal(wish.velocity, [[0.0, 0.0]])
    assert_allclose(wish.heading, [1.0])


def test_the_nearest_echo_is_the_one_avoided() -> None:
    # Echoes (0.3, 0) and (0, 0.2): the nearest is along +y. Wish (0, 0.2) straight at it -> the head-on
    # case rotated by 90 degrees (left of +y is -x): (-0.16752212, -0.10925356); the +x echo is ignored.
    wish = run([[0.0, 0.2]], [[[0.3, 0.0], [0.0, 0.2], [NAN, NAN]]])
    assert_allclose(wish.velocity, [[-0.16752212, -0.10925356]], atol=1e-7)


def test_never_faster_than_the_inner_wish() -> None:
    # Echo 0.13 m ahead: push 0.2 * 0.22 / 0.23 = 0.1913 plus whatever remains: capped at 0.2.
    wish = run([[0.2, 0.1]], [[[0.13, 0.0]]])
    assert math.hypot(*wish.velocity[0]) <= math.hypot(0.2, 0.1) + 1e-12
    assert wish.velocity[0, 0] < 0.0


def test_no_range_finders_pass_through_and_memory_is_kept() -> None:
    inner = Constant([[0.2, 0.0]], [0.7])
    view = make_view(make_table([[0.0, 0.0]]), pairs=[])
    wish = AvoidObstacles(inner).step(view)
    assert_allclose(wish.velocity, [[0.2, 0.0]])
    assert_allclose(wish.heading, [0.7])
    assert_allclose(wish.memory["mark"], [0.5])
    near = run([[0.2, 0.0]], [[[0.2, 0.0]]])
    assert_allclose(near.memory["mark"], [0.5])


def test_name_and_memory_fields_follow_the_inner_behaviour() -> None:
    wrapped = AvoidObstacles(BobRule(H=1, leader_id=3))
    assert wrapped.name == "avoid+bob-rule"
    assert wrapped.memory_fields == BobRule.memory_fields
    assert AvoidObstacles(Constant([[0.0, 0.0]], [0.0])).memory_fields == {"mark": MemorySpec()}
    with pytest.raises(ValueError):
        AvoidObstacles(BobRule(), safe_distance=0.1, stop_distance=0.2)


def test_batch_equals_one_vessel_at_a_time() -> None:
    table = make_table(
        [[0.0, 0.0], [0.5, 0.2], [0.1, -0.6], [1.0, 1.0]],
        headings=[0.0, 1.0, 2.0, -1.5],
        memory={"goal": np.full((4, 2), NAN)},
    )
    obstacles = np.array(
        [
            [[0.2, 0.0], [NAN, NAN]],
            [[NAN, NAN], [0.0, -0.1]],
            [[0.3, 0.3], [0.0, 0.5]],
            [[NAN, NAN], [NAN, NAN]],
        ]
    )
    view = make_view(table, senses=Senses(obstacles=obstacles, light=np.full((4, 2), NAN)))
    behavior = AvoidObstacles(BobRule(p0=0.5, H=1, goal=(5.0, 0.0), speed_scale=0.1, max_speed=0.2))
    assert_batch_equivalent(behavior, view)
