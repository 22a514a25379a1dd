"""BobRule (eq. 5) against values worked out by hand for 1-4 agents."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from behavior_helpers import assert_batch_equivalent, make_table, make_view
from numpy.testing import assert_allclose

from behaviors.base import SwarmTable
from behaviors.bob_rule import BobRule

# speed_scale 1 and a cap far away: the wish velocity is v_i of eq. (5) itself.
P0 = 10.0


def rule(**kwargs: object) -> BobRule:
    params: dict[str, object] = {"p0": P0, "speed_scale": 1.0, "max_speed": 100.0}
    params.update(kwargs)
    return BobRule(**params)  # type: ignore[arg-type]


def test_two_agents_at_twice_p0_attract_with_factor_three_quarters() -> None:
    view = make_view(make_table([[0.0, 0.0], [20.0, 0.0]]))
    wish = rule(H=0).step(view)
    # f = 1 - 10^2 / 20^2 = 0.75, N = 1, gamma = +-(1, 0).
    assert_allclose(wish.velocity, [[0.75, 0.0], [-0.75, 0.0]], atol=1e-12)
    assert np.all(np.isnan(wish.heading))


@pytest.mark.parametrize("other", [[10.0, 0.0], [6.0, 8.0]])
def test_pair_term_is_exactly_zero_at_p0(other: list[float]) -> None:
    view = make_view(make_table([[0.0, 0.0], other]))
    assert np.array_equal(rule(H=0).step(view).velocity, np.zeros((2, 2)))


def test_aggregation_repels_inside_p0_and_averages_over_neighbours() -> None:
    # Agent 0 hears (20, 0): f = 1 - 100/400 = 0.75 along (1, 0),
    # and (0, 5): f = 1 - 100/25 = -3 along (0, 1); N = 2 -> (0.75, -3) / 2.
    # Headings are set but H = 0 ignores them.
    table = make_table([[0.0, 0.0], [20.0, 0.0], [0.0, 5.0]], headings=[0.3, 1.0, -2.0])
    wish = rule(H=0).step(make_view(table, pairs=[(0, 1), (0, 2)], rows=[0]))
    assert_allclose(wish.velocity, [[0.375, -1.5]], atol=1e-12)


def test_h1_outside_p0_is_pure_goal_plus_own_heading() -> None:
    # Goal (0, 30): beta = (0, 1). Neighbour at 20 m > p0: f = min(0, 0.75) = 0 and it is
    # not in R_0, so only theta_0 = (1, 0) counts, divided by N = 1.
    table = make_table([[0.0, 0.0], [20.0, 0.0]], headings=[0.0, math.pi / 2])
    wish = rule(H=1, goal=(0.0, 30.0)).step(make_view(table, rows=[0], pairs=[(0, 1)]))
    assert_allclose(wish.velocity, [[1.0, 1.0]], atol=1e-12)


def test_h1_repels_inside_p0_and_consensus_runs_over_r_i_plus_self() -> None:
    # Agent 0 at the origin, heading 0, goal (0, -40): beta = (0, -1). It hears 3 agents:
    #   (5, 0), heading pi/2: d = 5, f = min(0, 1 - 100/25) = -3, in R_0;
    #   (0, 20), heading pi: d = 20, f = 0, not in R_0;
    #   (-30, 0), heading pi/2: d = 30, f = 0, not in R_0.
    # pair term = (-3, 0) / 3 = (-1, 0); consensus = ((1, 0) + (0, 1)) / 3.
    # v = (0, -1) + (-1, 0) + (1/3, 1/3) = (-2/3, -2/3).
    table = make_table(
        [[0.0, 0.0], [5.0, 0.0], [0.0, 20.0], [-30.0, 0.0]],
        headings=[0.0, math.pi / 2, math.pi, math.pi / 2],
    )
    view = make_view(table, rows=[0], pairs=[(0, 1), (0, 2), (0, 3)])
    wish = rule(H=1, goal=(0.0, -40.0)).step(view)
    assert_allclose(wish.velocity, [[-2.0 / 3.0, -2.0 / 3.0]], atol=1e-12)


def test_speed_scale_and_cap() -> None:
    view = make_view(make_table([[0.0, 0.0], [20.0, 0.0]]))
    # v = (0.75, 0) scaled by 0.5 m/s -> 0.375 m/s, under the 0.6 m/s cap.
    assert_allclose(BobRule(p0=P0, speed_scale=0.5, max_speed=0.6).step(view).velocity[0], [0.375, 0.0])
    # Capped at 0.3 m/s.
    assert_allclose(BobRule(p0=P0, speed_scale=0.5, max_speed=0.3).step(view).velocity[0], [0.3, 0.0])


def test_lone_agent_has_only_the_goal_term() -> None:
    view = make_view(make_table([[0.0, 0.0]], headings=[1.0]), pairs=[])
    # Goal (3, 4) from the origin: beta = (0.6, 0.8); no pair or consensus term, no NaN.
    assert_allclose(rule(H=1, goal=(3.0, 4.0)).step(view).velocity, [[0.6, 0.8]], atol=1e-12)
    assert np.array_equal(rule(H=0).step(view).velocity, [[0.0, 0.0]])


def test_coincident_agents_give_no_nan() -> None:
    view = make_view(make_table([[1.0, 1.0], [1.0, 1.0]]))
    assert np.array_equal(rule(H=0).step(view).velocity, np.zeros((2, 2)))


def leader_table(memory_goal: list[list[float]]) -> SwarmTable:
    # ids 7 (leader, origin, heading pi), 8 at (30, 40) heading 0, 9 at (30, -40) heading pi/2.
    return make_table(
        [[0.0, 0.0], [30.0, 40.0], [30.0, -40.0]],
        headings=[math.pi, 0.0, math.pi / 2],
        ids=[7, 8, 9],
        memory={"goal": np.asarray(memory_goal, dtype=float)},
    )


def test_leader_follower_takes_the_leaders_position_by_id() -> None:
    nan = math.nan
    table = leader_table([[100.0, 0.0], [nan, nan], [nan, nan]])
    wish = rule(H=1, leader_id=7).step(make_view(table))
    # Follower 8: beta = (0 - 30, 0 - 40) / 50 = (-0.6, -0.8); both others are beyond p0
    # (50 m and 80 m): f = 0 and R empty; consensus = theta_8 / N = (1, 0) / 2.
    assert_allclose(wish.velocity[1], [-0.1, -0.8], atol=1e-12)
    # Follower 9: beta = (-30, 40) / 50 = (-0.6, 0.8); consensus (0, 1) / 2.
    assert_allclose(wish.velocity[2], [-0.6, 1.3], atol=1e-12)
    # The leader ignores its stale remembered goal (100, 0) and is not its own goal:
    # only its consensus term (-1, 0) / 2 remains.
    assert_allclose(wish.velocity[0], [-0.5, 0.0], atol=1e-12)
    assert_allclose(wish.memory["goal"][1:], [[0.0, 0.0], [0.0, 0.0]])


def test_leader_follower_remembers_the_leader_when_it_drops_out() -> None:
    nan = math.nan
    # Step 1: 8 hears the leader 7; 9 hears only 8 (the leader is in the table, not heard).
    table = leader_table([[nan, nan], [nan, nan], [nan, nan]])
    first = rule(H=1, leader_id=7).step(make_view(table, pairs=[(0, 0), (0, 2), (1, 1)], rows=[1, 2]))
    assert_allclose(first.memory["goal"][0], [0.0, 0.0])
    assert np.all(np.isnan(first.memory["goal"][1]))
    # 9 has no goal: only the consensus over itself, (0, 1) / 1 (8 is 80 m away: f = 0).
    assert_allclose(first.velocity[1], [0.0, 1.0], atol=1e-12)

    # Step 2: the leader is gone; 8 keeps going to (0, 0), remembered.
    table2 = make_table(
        [[30.0, 40.0], [30.0, -40.0]],
        headings=[0.0, math.pi / 2],
        ids=[8, 9],
        memory={"goal": first.memory["goal"]},
    )
    second = rule(H=1, leader_id=7).step(make_view(table2))
    # 8: beta = (-0.6, -0.8), consensus (1, 0) / 1 -> (0.4, -0.8).
    assert_allclose(second.velocity[0], [0.4, -0.8], atol=1e-12)
    assert_allclose(second.memory["goal"][0], [0.0, 0.0])
    assert_allclose(second.velocity[1], [0.0, 1.0], atol=1e-12)


def test_leader_never_heard_means_no_goal_term_even_without_memory_field() -> None:
    table = make_table([[0.0, 0.0], [20.0, 0.0]], headings=[0.0, 0.0], ids=[1, 2])
    wish = rule(H=1, leader_id=5).step(make_view(table))
    # Only consensus theta_i / 1 = (1, 0); the pair is beyond p0.
    assert_allclose(wish.velocity, [[1.0, 0.0], [1.0, 0.0]], atol=1e-12)


SWARM = [[0.0, 0.0], [5.0, 1.0], [12.0, -3.0], [4.0, 9.0]]
SWARM_PAIRS = [(0, 1), (0, 2), (0, 3), (1, 0), (1, 2), (2, 1), (3, 0), (3, 1)]


@pytest.mark.parametrize(
    "behavior",
    [
        rule(H=0),
        rule(H=1, goal=(30.0, 30.0)),
        rule(H=1, leader_id=12),
        BobRule(p0=6.0, H=1, goal=(-5.0, 2.0)),
    ],
)
def test_batch_equals_one_vessel_at_a_time(behavior: BobRule) -> None:
    nan = math.nan
    table = make_table(
        SWARM,
        headings=[0.1, 2.0, -1.0, 3.0],
        ids=[11, 12, 13, 14],
        memory={"goal": np.array([[nan, nan], [nan, nan], [1.0, 2.0], [3.0, -4.0]])},
    )
    wish = assert_batch_equivalent(behavior, make_view(table, pairs=SWARM_PAIRS))
    assert np.all(np.isfinite(wish.velocity))
    assert np.any(wish.velocity != 0.0)


def test_invalid_parameters() -> None:
    with pytest.raises(ValueError):
        BobRule(H=2)
    with pytest.raises(ValueError):
        BobRule(H=1, goal=(0.0, 0.0), leader_id=3)


def test_nearest_limits_the_neighbourhood_to_the_k_closest() -> None:
    # Agent 0 at the origin hears agents at 2, 3 and 50 m east (p0 = 10, H = 0). With nearest = 2 only the
    # ones at 2 and 3 m count: v = ((1 - 100/4) + (1 - 100/9)) / 2 * (1, 0) = (-24 - 10.1111) / 2 = -17.0556
    # along x; capped at max_speed 1 m/s -> (-1, 0). With all three, the far one adds (1 - 100/2500) = 0.96
    # and N = 3: (-24 - 10.1111 + 0.96) / 3 = -11.0504 -> still capped; so compare uncapped values.
    from behaviors.base import Senses, SwarmTable, View
    from behaviors.bob_rule import BobRule

    table = SwarmTable(
        ids=np.arange(4),
        position=np.array([[0.0, 0.0], [2.0, 0.0], [3.0, 0.0], [50.0, 0.0]]),
        heading=np.zeros(4),
        velocity=np.zeros((4, 2)),
        memory={"goal": np.full((4, 2), np.nan)},
    )
    view = View(table, Senses.none(4), np.array([0]), np.zeros(3, dtype=np.intp), np.array([1, 2, 3]))
    near = BobRule(p0=10.0, H=0, speed_scale=1.0, max_speed=100.0, nearest=2).step(view)
    everyone = BobRule(p0=10.0, H=0, speed_scale=1.0, max_speed=100.0).step(view)
    np.testing.assert_allclose(near.velocity, [[(-24.0 - 100.0 / 9.0 + 1.0) / 2.0, 0.0]])
    np.testing.assert_allclose(everyone.velocity, [[(-24.0 - 100.0 / 9.0 + 1.0 + 0.96) / 3.0, 0.0]])


def test_gabriel_neighbourhood_drops_a_neighbour_shadowed_by_a_closer_one() -> None:
    # Agent 0 at the origin hears 1 at (2, 0), 2 at (4, 0.5) and 3 at (0, 3).
    # Pair 0-2: agent 1 sees the segment 0-2 under an obtuse angle ((0-2,0-0).(4-2,0.5-0) = -4 < 0) -> dropped.
    # Pair 0-1: nobody inside the circle on 0-1. Pair 0-3: agent 1: (-2,0).(-2,3) = 4 > 0; agent 2:
    # (-4,-0.5).(-4,2.5) = 14.75 > 0 -> kept. So N = 2 (agents 1 and 3); with p0 = 1, H = 0:
    # v = [(1 - 1/4)(1, 0) + (1 - 1/9)(0, 1)] / 2 = (0.375, 0.444444).
    from behaviors.base import Senses, SwarmTable, View
    from behaviors.bob_rule import BobRule, gabriel_pairs

    table = SwarmTable(
        ids=np.arange(4),
        position=np.array([[0.0, 0.0], [2.0, 0.0], [4.0, 0.5], [0.0, 3.0]]),
        heading=np.zeros(4),
        velocity=np.zeros((4, 2)),
        memory={"goal": np.full((4, 2), np.nan)},
    )
    view = View(table, Senses.none(4), np.array([0]), np.zeros(3, dtype=np.intp), np.array([1, 2, 3]))
    assert gabriel_pairs(view).tolist() == [True, False, True]
    wish = BobRule(p0=1.0, H=0, speed_scale=1.0, max_speed=100.0, gabriel=True).step(view)
    np.testing.assert_allclose(wish.velocity, [[0.375, 8.0 / 18.0]])


# --- skirt: go around a group that blocks the way (not in the paper; see behaviors/bob_rule.py) ---


@pytest.mark.parametrize(
    ("neighbour", "expected_skirt"),
    [
        # Dead ahead at 5 m: f = -3, repulsion (0, -3), n = (0, -1); the pull (0, 1) is fully opposed, b = 1,
        # and pushes along -n = (0, 1) turned +90 deg: (-1, 0), to the left of the neighbour.
        ([0.0, 5.0], [-1.0, 0.0]),
        # At (3, 4), 5 m: repulsion -3 (0.6, 0.8), n = (-0.6, -0.8); b = 0.8; -n turned +90 deg = (-0.8, 0.6).
        ([3.0, 4.0], [-0.64, 0.48]),
        # Behind at (0, -5): the repulsion helps the pull (b < 0): no sideways term.
        ([0.0, -5.0], [0.0, 0.0]),
        # Beyond p0 (H = 1 repels only inside p0): no repulsion, no sideways term.
        ([0.0, 15.0], [0.0, 0.0]),
    ],
)
def test_skirt_turns_the_opposed_part_of_the_pull_to_the_left_of_the_neighbours(
    neighbour: list[float], expected_skirt: list[float]
) -> None:
    # Goal (0, 40): beta = (0, 1). Headings 0 and pi: the consensus terms cancel when both count.
    table = make_table([[0.0, 0.0], neighbour], headings=[0.0, math.pi])
    view = make_view(table, rows=[0], pairs=[(0, 1)])
    plain = rule(H=1, goal=(0.0, 40.0)).step(view).velocity
    skirting = rule(H=1, goal=(0.0, 40.0), skirt=True).step(view).velocity
    assert_allclose(skirting - plain, [expected_skirt], atol=1e-12)


def test_skirt_changes_nothing_for_a_lone_agent() -> None:
    view = make_view(make_table([[0.0, 0.0]], headings=[1.0]), pairs=[])
    assert_allclose(rule(H=1, goal=(3.0, 4.0), skirt=True).step(view).velocity, [[0.6, 0.8]], atol=1e-12)


def test_skirt_needs_h1() -> None:
    with pytest.raises(ValueError, match="skirt"):
        BobRule(H=0, skirt=True)


def test_skirt_is_batch_equivalent() -> None:
    table = make_table(SWARM, headings=[0.1, 2.0, -1.0, 3.0], ids=[11, 12, 13, 14])
    wish = assert_batch_equivalent(BobRule(p0=6.0, H=1, goal=(-5.0, 12.0), skirt=True), make_view(table))
    assert np.all(np.isfinite(wish.velocity))


def run_past_wall(skirt: bool, steps: int = 1200, dt: float = 0.5) -> np.ndarray:
    """(steps + 1, 2) path of one agent (p0 = 10 m, nearest 2) from (3, -30) m to a goal at (0, 30) m.

    Between them a fixed wall of 11 agents 6 m apart on y = 0 (x from -30 to 30 m), with a
    2 m deep notch at its middle: too tight to pass for p0 = 10 m, and head-on, so plain
    eq. (5) has a local minimum in front of it. Courses are aligned (align_course, as in the
    avoidance scenarios) and every table velocity is zero, so the consensus term is zero.
    """
    wall = np.column_stack((np.arange(-30.0, 31.0, 6.0), np.zeros(11)))
    wall[5, 1] = 2.0
    behavior = BobRule(
        p0=10.0,
        H=1,
        goal=(0.0, 30.0),
        speed_scale=1.0,
        max_speed=1.0,
        nearest=2,
        align_course=True,
        skirt=skirt,
    )
    position = np.array([3.0, -30.0])
    path = [position.copy()]
    for _ in range(steps):
        table = make_table(np.vstack((position, wall)))
        velocity = behavior.step(make_view(table, rows=[0], pairs=[(0, j) for j in range(1, 12)])).velocity[0]
        position = position + dt * velocity
        path.append(position.copy())
    return np.array(path)


def test_without_skirt_a_head_on_wall_is_a_local_minimum() -> None:
    path = run_past_wall(skirt=False)
    assert np.hypot(*(path[-1] - [0.0, 30.0])) > 30.0  # stuck in front of the wall
    assert np.hypot(*(path[-1] - path[-100])) < 0.5  # and not moving


def test_with_skirt_the_agent_goes_around_the_wall_to_its_goal() -> None:
    path = run_past_wall(skirt=True)
    assert np.hypot(*(path[-1] - [0.0, 30.0])) < 1.0
    # Around, not through: it crosses the line of the wall only beyond its west end (x < -30 m),
    # to the left of the wall as seen from the agent, and never comes closer than 3 m to a wall agent.
    crossing = np.flatnonzero(np.diff(np.sign(path[:, 1])) != 0)
    assert crossing.size and np.all(path[crossing, 0] < -30.0)
    wall = np.column_stack((np.arange(-30.0, 31.0, 6.0), np.zeros(11)))
    assert np.hypot(*(path[:, None, :] - wall[None]).transpose(2, 0, 1)).min() > 3.0


# --- shell_range: N_i is the agent's own shell once it is inside a lattice (see behaviors/bob_rule.py) ---


def _hexagon_and_far_agent(far: list[float]) -> tuple[SwarmTable, object]:
    """Agent 0 at the origin, six agents at 10 m (= P0) at 0, 60, ..., 300 deg, and one more at `far`."""
    from behaviors.base import Senses, View

    ring = [[10.0 * math.cos(k * math.pi / 3), 10.0 * math.sin(k * math.pi / 3)] for k in range(6)]
    table = make_table([[0.0, 0.0], *ring, far])
    view = View(table, Senses.none(8), np.array([0]), np.zeros(7, dtype=np.intp), np.arange(1, 8))
    return table, view


def test_inside_a_lattice_only_the_shell_counts() -> None:
    # Six heard within 2 P0 = 20 m (>= lattice_min 6): N_0 is those within 1.5 P0 = 15 m, the ring at P0,
    # where f = 0: v = 0. The agent at (30, 0) is left out; with every agent heard it pulls:
    # f = 1 - 100/900 = 8/9 along (1, 0), N = 7 -> (8/63, 0).
    from behaviors.bob_rule import shell_pairs

    _, view = _hexagon_and_far_agent([30.0, 0.0])
    assert shell_pairs(view, 15.0, 20.0, 6, None).tolist() == [True] * 6 + [False]
    shell = rule(H=0, shell_range=1.5, lattice_range=2.0, lattice_min=6).step(view)
    everyone = rule(H=0).step(view)
    assert_allclose(shell.velocity, [[0.0, 0.0]], atol=1e-12)
    assert_allclose(everyone.velocity, [[8.0 / 63.0, 0.0]], atol=1e-12)


def test_outside_a_lattice_every_agent_heard_counts_or_the_nearest() -> None:
    # lattice_min 7: only six within 20 m, so agent 0 is not inside a lattice and counts all seven heard
    # (as without shell_range), or with nearest = 6 the ring only.
    from behaviors.bob_rule import shell_pairs

    _, view = _hexagon_and_far_agent([30.0, 0.0])
    assert shell_pairs(view, 15.0, 20.0, 7, None).all()
    assert shell_pairs(view, 15.0, 20.0, 7, 6).tolist() == [True] * 6 + [False]
    wide = rule(H=0, shell_range=1.5, lattice_range=2.0, lattice_min=7).step(view)
    assert_allclose(wide.velocity, [[8.0 / 63.0, 0.0]], atol=1e-12)
    # A seventh agent at (0, 18) is also within 20 m: now inside a lattice, and the one at 18 m is outside
    # the shell (15 m): v = 0 again.
    table = make_table([[0.0, 0.0], *view.table.position[1:7].tolist(), [0.0, 18.0]])
    closer = replace(view, table=table)
    assert shell_pairs(closer, 15.0, 20.0, 7, None).tolist() == [True] * 6 + [False]


def test_shell_range_is_batch_equivalent_and_checked() -> None:
    assert_batch_equivalent(rule(H=0, shell_range=1.5, lattice_min=2), make_view(make_table(SWARM), pairs=SWARM_PAIRS))
    for bad in (
        {"shell_range": -1.0},
        {"lattice_range": 0.0},
        {"lattice_min": 0},
        {"shell_range": 1.5, "gabriel": True},
    ):
        with pytest.raises(ValueError):
            BobRule(**bad)  # type: ignore[arg-type]
