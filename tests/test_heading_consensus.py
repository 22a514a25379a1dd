"""HeadingConsensus (eq. 2) and HoldHeading against values worked out by hand."""

from __future__ import annotations

import math

import numpy as np
import pytest
from behavior_helpers import all_pairs, assert_batch_equivalent, make_table, make_view
from numpy.testing import assert_allclose

from behaviors.base import SwarmTable, View, Wish, wrap_angle
from behaviors.heading_consensus import HeadingConsensus, HoldHeading

DEG = math.pi / 180.0


def angle_error(a: np.ndarray | float, b: np.ndarray | float) -> np.ndarray:
    """|a - b| across the wrap, rad."""
    return np.abs(wrap_angle(np.asarray(a) - np.asarray(b)))


def line_pairs(n: int) -> list[tuple[int, int]]:
    """Each agent of a line hears only its left and right neighbours."""
    return [(i, j) for i in range(n) for j in (i - 1, i + 1) if 0 <= j < n]


def spread(headings: np.ndarray) -> float:
    """Largest angle between any two headings, rad (for headings within a half circle)."""
    return float(max(angle_error(a, b) for a in headings for b in headings))


def hold_table(positions: list[list[float]], headings: list[float]) -> SwarmTable:
    n = len(positions)
    return make_table(positions, headings=headings, memory={"held_heading": np.full(n, math.nan)})


# ----------------------------------------------------------------------------- HeadingConsensus


def test_two_agents_at_0_and_90_degrees_both_target_45() -> None:
    view = make_view(make_table([[0.0, 0.0], [1.0, 0.0]], headings=[0.0, math.pi / 2]))
    wish = HeadingConsensus().step(view)
    # (1, 0) + (0, 1) = (1, 1): atan2(1, 1) = 45 deg for both; cruise_speed 0 -> no velocity.
    assert_allclose(wish.heading, [math.pi / 4, math.pi / 4], atol=1e-12)
    assert_allclose(wish.velocity, np.zeros((2, 2)), atol=1e-12)


def test_three_agents_0_90_180_all_to_all_target_90() -> None:
    table = make_table([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]], headings=[0.0, math.pi / 2, math.pi])
    wish = HeadingConsensus().step(make_view(table))
    # (1, 0) + (0, 1) + (-1, 0) = (0, 1): 90 deg for everyone (each hears the other two).
    assert_allclose(wish.heading, [math.pi / 2] * 3, atol=1e-12)


def test_one_sided_listening_only_moves_the_listener() -> None:
    # Agent 0 (heading 0) hears agent 1 (heading 90) and agent 2 (heading 90);
    # nobody hears agent 0. Agent 0: (1, 0) + 2 (0, 1) = (1, 2) -> atan2(2, 1).
    table = make_table([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]], headings=[0.0, math.pi / 2, math.pi / 2])
    wish = HeadingConsensus().step(make_view(table, pairs=[(0, 1), (0, 2)]))
    assert_allclose(wish.heading, [math.atan2(2.0, 1.0), math.pi / 2, math.pi / 2], atol=1e-12)


def test_agent_without_neighbours_keeps_its_heading() -> None:
    view = make_view(make_table([[0.0, 0.0]], headings=[1.234]), pairs=[])
    assert_allclose(HeadingConsensus().step(view).heading, [1.234], atol=1e-12)


def test_mean_is_taken_across_the_wrap() -> None:
    # 170 deg = (-cos 10, sin 10), -170 deg = (-cos 10, -sin 10): sum (-2 cos 10, 0) -> 180 deg,
    # not the arithmetic mean 0 deg.
    table = make_table([[0.0, 0.0], [1.0, 0.0]], headings=[170.0 * DEG, -170.0 * DEG])
    wish = HeadingConsensus().step(make_view(table))
    assert np.all(angle_error(wish.heading, math.pi) < 1e-9)
    assert np.all(np.abs(wish.heading) <= math.pi)


def test_exactly_opposed_headings_keep_their_own() -> None:
    # (1, 0) + (-1, 0) = (0, 0): no mean direction, each keeps its own heading (documented).
    table = make_table([[0.0, 0.0], [1.0, 0.0]], headings=[0.0, math.pi])
    wish = HeadingConsensus(cruise_speed=0.5).step(make_view(table))
    assert_allclose(wish.heading, [0.0, math.pi], atol=1e-12)
    assert_allclose(wish.velocity, [[0.5, 0.0], [-0.5, 0.0]], atol=1e-12)
    assert np.all(np.isfinite(wish.velocity))


def test_cruise_speed_gives_velocity_along_the_target() -> None:
    view = make_view(make_table([[0.0, 0.0], [1.0, 0.0]], headings=[0.0, math.pi / 2]))
    wish = HeadingConsensus(cruise_speed=0.3).step(view)
    # Target 45 deg: 0.3 (cos 45, sin 45) = 0.3 / sqrt(2) (1, 1).
    c = 0.3 / math.sqrt(2.0)
    assert_allclose(wish.velocity, [[c, c], [c, c]], atol=1e-12)


def test_target_is_wrapped_into_minus_pi_pi() -> None:
    # A lone agent at heading 3 pi / 2 (unwrapped) targets -pi / 2.
    view = make_view(make_table([[0.0, 0.0]], headings=[1.5 * math.pi]), pairs=[])
    wish = HeadingConsensus(cruise_speed=1.0).step(view)
    assert_allclose(wish.heading, [-math.pi / 2], atol=1e-12)
    assert_allclose(wish.velocity, [[0.0, -1.0]], atol=1e-12)


def test_degenerate_case_returns_the_own_heading_wrapped() -> None:
    # Headings 2 pi + 0.5 and pi + 0.5 (unwrapped) are exactly opposed: each keeps its own,
    # reported in (-pi, pi]: 0.5 and pi + 0.5 - 2 pi = 0.5 - pi.
    table = make_table([[0.0, 0.0], [1.0, 0.0]], headings=[2.0 * math.pi + 0.5, math.pi + 0.5])
    wish = HeadingConsensus().step(make_view(table))
    assert_allclose(wish.heading, [0.5, 0.5 - math.pi], atol=1e-9)


def iterate_consensus(table: SwarmTable, pairs: list[tuple[int, int]], iterations: int) -> np.ndarray:
    """Apply the consensus update to the headings directly (no bodies)."""
    behavior = HeadingConsensus()
    for _ in range(iterations):
        table.heading = behavior.step(make_view(table, pairs=pairs)).heading.copy()
    return table.heading


def test_iterating_on_a_line_graph_converges_to_a_common_heading() -> None:
    headings = [-1.0, 0.2, 1.3, -0.4, 0.9]
    table = make_table([[float(i), 0.0] for i in range(5)], headings=headings)
    pairs = line_pairs(5)
    # A single step does not align them yet (information needs hops to travel).
    one_step = HeadingConsensus().step(make_view(table, pairs=pairs)).heading
    assert spread(one_step) > 0.1
    final = iterate_consensus(table, pairs, 200)
    assert spread(final) < 1e-6
    # The common heading lies within the initial range (a mean, not a drift elsewhere).
    assert -1.0 < final[0] < 1.3


def test_line_graph_across_the_wrap_converges_near_pi() -> None:
    headings = [170.0 * DEG, -175.0 * DEG, 160.0 * DEG, -165.0 * DEG]
    table = make_table([[float(i), 0.0] for i in range(4)], headings=headings)
    final = iterate_consensus(table, line_pairs(4), 200)
    assert spread(final) < 1e-6
    # All initial headings are within 20 deg of 180: so is the consensus (not near 0).
    assert np.all(angle_error(final, math.pi) < 20.0 * DEG)


# ----------------------------------------------------------------------------- HoldHeading


def test_hold_heading_first_step_holds_heading_plus_turn() -> None:
    table = hold_table([[0.0, 0.0], [5.0, 0.0]], headings=[0.5, -0.2])
    view = make_view(table, pairs=[(0, 1)], rows=[0])
    wish = HoldHeading(turn_deg=30.0, cruise_speed=0.2).step(view)
    held = 0.5 + math.radians(30.0)
    assert_allclose(wish.heading, [held], atol=1e-12)
    assert_allclose(wish.memory["held_heading"], [held], atol=1e-12)
    assert_allclose(wish.velocity, [[0.2 * math.cos(held), 0.2 * math.sin(held)]], atol=1e-12)


def test_hold_heading_keeps_the_remembered_heading_when_its_own_changes() -> None:
    behavior = HoldHeading(turn_deg=90.0)
    table = hold_table([[0.0, 0.0]], headings=[0.0])
    first = behavior.step(make_view(table, pairs=[]))
    assert_allclose(first.heading, [math.pi / 2], atol=1e-12)
    # The body has turned elsewhere (say to -1 rad) but the memory holds 90 deg: no further turn.
    table.heading = np.array([-1.0])
    table.memory["held_heading"] = first.memory["held_heading"].copy()
    second = behavior.step(make_view(table, pairs=[]))
    assert_allclose(second.heading, [math.pi / 2], atol=1e-12)
    assert_allclose(second.memory["held_heading"], [math.pi / 2], atol=1e-12)


def test_hold_heading_turn_wraps() -> None:
    # 170 deg + 30 deg = 200 deg -> -160 deg.
    table = hold_table([[0.0, 0.0]], headings=[170.0 * DEG])
    wish = HoldHeading(turn_deg=30.0).step(make_view(table, pairs=[]))
    assert_allclose(wish.heading, [-160.0 * DEG], atol=1e-12)


def test_hold_heading_deg_overrides_own_heading_and_turn() -> None:
    table = hold_table([[0.0, 0.0], [1.0, 0.0]], headings=[2.0, -1.0])
    wish = HoldHeading(heading_deg=-45.0, turn_deg=30.0, cruise_speed=1.0).step(make_view(table))
    assert_allclose(wish.heading, [-math.pi / 4] * 2, atol=1e-12)
    c = math.sqrt(0.5)
    assert_allclose(wish.velocity, [[c, -c], [c, -c]], atol=1e-12)


def test_hold_heading_ignores_neighbours() -> None:
    table = hold_table([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]], headings=[0.0, 2.0, 3.0])
    wish = HoldHeading().step(make_view(table, rows=[0], pairs=[(0, 1), (0, 2)]))
    assert_allclose(wish.heading, [0.0], atol=1e-12)


def test_leader_follower_converges_to_the_leaders_heading() -> None:
    # Row 0 leads holding 60 deg; rows 1-4 follow, everybody hearing everybody.
    leader_heading = 60.0 * DEG
    table = hold_table([[float(i), 0.0] for i in range(5)], headings=[0.0, -0.5, 0.3, 1.8, -1.2])
    leader = HoldHeading(heading_deg=60.0)
    follower = HeadingConsensus()
    every_pair = all_pairs(5)
    # Followers: rows 1..4, pair_i indexes into rows (0..3) and pair_j is any other table row.
    follower_pairs = [(i - 1, j) for i, j in every_pair if i != 0]
    for _ in range(200):
        lead: Wish = leader.step(make_view(table, rows=[0], pairs=[]))
        follow: Wish = follower.step(make_view(table, rows=[1, 2, 3, 4], pairs=follower_pairs))
        table.memory["held_heading"][[0]] = lead.memory["held_heading"]
        table.heading = np.concatenate((lead.heading, follow.heading))
    assert_allclose(table.heading[0], leader_heading, atol=1e-12)
    assert np.all(angle_error(table.heading[1:], leader_heading) < 1e-6)


# ----------------------------------------------------------------------------- batch equivalence

SWARM = [[0.0, 0.0], [5.0, 1.0], [12.0, -3.0], [4.0, 9.0]]
SWARM_PAIRS = [(0, 1), (0, 2), (0, 3), (1, 0), (1, 2), (2, 1), (3, 0), (3, 1)]


@pytest.mark.parametrize(
    "behavior",
    [HeadingConsensus(), HeadingConsensus(cruise_speed=0.4), HoldHeading(turn_deg=45.0, cruise_speed=0.1)],
)
def test_batch_equals_one_vessel_at_a_time(behavior: HeadingConsensus | HoldHeading) -> None:
    table = make_table(
        SWARM,
        headings=[0.1, 2.0, -1.0, 3.0],
        ids=[11, 12, 13, 14],
        memory={"held_heading": np.array([math.nan, 0.7, math.nan, -2.5])},
    )
    view: View = make_view(table, pairs=SWARM_PAIRS)
    wish = assert_batch_equivalent(behavior, view)
    assert np.all(np.isfinite(wish.heading))
    # Not a trivially constant answer: the agents' targets differ.
    assert np.ptp(wish.heading) > 0.1
