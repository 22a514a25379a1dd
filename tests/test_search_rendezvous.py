"""SearchRendezvous: detection, relay, phototaxis, gathering and patrol, worked out by hand.

Default parameters throughout unless said: detect_threshold 2 W/m^2, max_speed 0.2 m/s,
explore_speed 0.1 m/s, arrival_radius 0.4 m, spacing 0.3 m, phototaxis_gain 1.5,
hot_fraction 0.9, spread = PerimeterDefense() (max_speed 0.2, full_speed_at 1, dead_band 0.02,
obstacle range 1.5 m).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import pytest
from behavior_helpers import assert_batch_equivalent, make_table, make_view
from numpy.testing import assert_allclose

from behaviors.base import Senses, View, Wish
from behaviors.search_rendezvous import SearchRendezvous

NAN = math.nan
INF = math.inf


def view_of(
    positions: Sequence[Sequence[float]],
    light: Sequence[Sequence[float]] | None = None,
    *,
    headings: Sequence[float] | None = None,
    target: Sequence[Sequence[float]] | None = None,
    target_light: Sequence[float] | None = None,
    pairs: Sequence[tuple[int, int]] | None = None,
    rows: Sequence[int] | None = None,
    echoes: Sequence[Sequence[Sequence[float]]] | None = None,
) -> View:
    """A view with the behaviour's memory (default: nothing known) and senses (default: dark, no echoes)."""
    n = len(positions)
    memory = {
        "target": np.full((n, 2), NAN) if target is None else np.asarray(target, dtype=float),
        "target_light": np.full(n, -INF) if target_light is None else np.asarray(target_light, dtype=float),
    }
    table = make_table(positions, headings=headings, memory=memory)
    senses = Senses(
        obstacles=np.zeros((n, 0, 2)) if echoes is None else np.asarray(echoes, dtype=float),
        light=np.zeros((n, 2)) if light is None else np.asarray(light, dtype=float),
    )
    return make_view(table, pairs=pairs, rows=rows, senses=senses)


def step(view: View, **kwargs: object) -> Wish:
    return SearchRendezvous(**kwargs).step(view)  # type: ignore[arg-type]


# ----------------------------------------------------------------------------- detection


@pytest.mark.parametrize("light", [[0.5, 0.5], [1.9, 0.0], [NAN, NAN]])
def test_below_threshold_and_knowing_nothing_keeps_no_target(light: list[float]) -> None:
    # 0.5 + 0.5 = 1 < 2; 1.9 < 2; no light sensors reads 0.
    wish = step(view_of([[1.0, 2.0]], [light], headings=[0.0], pairs=[]))
    assert wish.memory["target_light"][0] == -INF
    assert np.all(np.isnan(wish.memory["target"][0]))
    # Lone and unpushed: patrols along its heading 0 at explore_speed 0.1.
    assert_allclose(wish.velocity, [[0.1, 0.0]], atol=1e-12)
    assert np.isnan(wish.heading[0])


@pytest.mark.parametrize(("light", "reading"), [([1.5, 1.0], 2.5), ([1.0, 1.0], 2.0)])
def test_reading_at_or_above_threshold_records_own_position(light: list[float], reading: float) -> None:
    wish = step(view_of([[3.0, 4.0]], [light], pairs=[]))
    assert_allclose(wish.memory["target"], [[3.0, 4.0]])
    assert_allclose(wish.memory["target_light"], [reading])


def test_a_brighter_reading_replaces_the_remembered_target() -> None:
    # Remembers 2.5 at (0, 0); now reads 3 at (1, 1): the new, brighter spot wins.
    wish = step(view_of([[1.0, 1.0]], [[1.5, 1.5]], target=[[0.0, 0.0]], target_light=[2.5], pairs=[]))
    assert_allclose(wish.memory["target"], [[1.0, 1.0]])
    assert_allclose(wish.memory["target_light"], [3.0])
    # A dimmer reading above threshold does not: reads 2.2 < remembered 3.
    wish = step(view_of([[1.0, 1.0]], [[1.1, 1.1]], target=[[0.0, 0.0]], target_light=[3.0], pairs=[]))
    assert_allclose(wish.memory["target"], [[0.0, 0.0]])
    assert_allclose(wish.memory["target_light"], [3.0])


# ----------------------------------------------------------------------------- relay


def test_brighter_broadcast_target_is_adopted_and_approached() -> None:
    # Agent 0 (dark, knows nothing) hears agent 1 at (5, 0), which broadcasts (10, 0) at 3 W/m^2.
    view = view_of(
        [[0.0, 0.0], [5.0, 0.0]],
        target=[[NAN, NAN], [10.0, 0.0]],
        target_light=[-INF, 3.0],
        rows=[0],
        pairs=[(0, 1)],
    )
    wish = step(view)
    assert_allclose(wish.memory["target"], [[10.0, 0.0]])
    assert_allclose(wish.memory["target_light"], [3.0])
    # 10 m > 2 * arrival_radius: full speed 0.2 towards (1, 0); the neighbour is beyond spacing.
    assert_allclose(wish.velocity, [[0.2, 0.0]], atol=1e-12)
    assert np.isnan(wish.heading[0])


def test_dimmer_broadcast_target_is_not_adopted() -> None:
    # Agent 0 remembers (-5, 0) at 4 W/m^2; agent 1 broadcasts (10, 0) at 3.
    view = view_of(
        [[0.0, 0.0], [5.0, 0.0]],
        target=[[-5.0, 0.0], [10.0, 0.0]],
        target_light=[4.0, 3.0],
        rows=[0],
        pairs=[(0, 1)],
    )
    wish = step(view)
    assert_allclose(wish.memory["target"], [[-5.0, 0.0]])
    assert_allclose(wish.memory["target_light"], [4.0])
    assert_allclose(wish.velocity, [[-0.2, 0.0]], atol=1e-12)


def test_equally_bright_broadcast_does_not_replace_the_own_target() -> None:
    # Agent 0 remembers (1, 1) at 3 W/m^2; agent 1 broadcasts (9, 9) also at 3: agent 0 keeps its own.
    view = view_of(
        [[0.0, 0.0], [5.0, 0.0]],
        target=[[1.0, 1.0], [9.0, 9.0]],
        target_light=[3.0, 3.0],
        rows=[0],
        pairs=[(0, 1)],
    )
    assert_allclose(step(view).memory["target"], [[1.0, 1.0]])


@pytest.mark.parametrize("order", [[1, 2, 3], [2, 1, 3], [3, 2, 1], [1, 3, 2]])
def test_brightest_of_several_neighbours_wins(order: list[int]) -> None:
    # Neighbours broadcast 3 W/m^2 at (0, 10), 7 at (10, 0), 5 at (0, -10): 7 wins whatever the order heard.
    view = view_of(
        [[0.0, 0.0], [1.0, 0.0], [2.0, 0.0], [3.0, 0.0]],
        target=[[NAN, NAN], [0.0, 10.0], [10.0, 0.0], [0.0, -10.0]],
        target_light=[-INF, 3.0, 7.0, 5.0],
        rows=[0],
        pairs=[(0, j) for j in order],
    )
    wish = step(view)
    assert_allclose(wish.memory["target"], [[10.0, 0.0]])
    assert_allclose(wish.memory["target_light"], [7.0])


def test_brightest_is_chosen_per_listener_in_a_batch() -> None:
    # Agent 0 hears 2 (light 3); agent 1 hears 2 and 3 (lights 3, 6); agents 2 and 3 hear nobody.
    view = view_of(
        [[0.0, 0.0], [0.0, 5.0], [5.0, 5.0], [5.0, 0.0]],
        target=[[NAN, NAN], [NAN, NAN], [20.0, 20.0], [-20.0, -20.0]],
        target_light=[-INF, -INF, 3.0, 6.0],
        pairs=[(0, 2), (1, 2), (1, 3)],
    )
    wish = step(view)
    assert_allclose(wish.memory["target"], [[20.0, 20.0], [-20.0, -20.0], [20.0, 20.0], [-20.0, -20.0]])
    assert_allclose(wish.memory["target_light"], [3.0, 6.0, 3.0, 6.0])


def test_relay_through_a_chain_moves_one_hop_per_iteration() -> None:
    # Line 0 - 1 - 2 - 3, 5 m apart, each hearing only its neighbours; only agent 0 is lit
    # (1.5 + 1.5 = 3 >= 2), the others read 0.2. Agents do not move; the memory is fed back.
    view = view_of(
        [[0.0, 0.0], [5.0, 0.0], [10.0, 0.0], [15.0, 0.0]],
        [[1.5, 1.5], [0.1, 0.1], [0.1, 0.1], [0.1, 0.1]],
        pairs=[(0, 1), (1, 0), (1, 2), (2, 1), (2, 3), (3, 2)],
    )
    behavior = SearchRendezvous()

    def iterate() -> np.ndarray:
        wish = behavior.step(view)
        for key, value in wish.memory.items():
            view.table.memory[key] = value.copy()
        return np.isfinite(wish.memory["target_light"])

    # Iteration 0: agent 0 sees the light and records it; nobody else has heard yet
    # (its neighbours read its previous, empty broadcast).
    assert iterate().tolist() == [True, False, False, False]
    # Then one hop per iteration: agent 3 knows after the 3rd relay iteration and not before.
    assert iterate().tolist() == [True, True, False, False]
    assert iterate().tolist() == [True, True, True, False]
    assert iterate().tolist() == [True, True, True, True]
    assert_allclose(view.table.memory["target"], [[0.0, 0.0]] * 4)
    assert_allclose(view.table.memory["target_light"], [3.0] * 4)


# ----------------------------------------------------------------------------- phototaxis


@pytest.mark.parametrize(("light", "turn"), [([1.5, 1.0], 0.3), ([1.0, 1.5], -0.3), ([1.25, 1.25], 0.0)])
def test_hot_agent_steers_towards_the_brighter_sensor(light: list[float], turn: float) -> None:
    # Reading 2.5 >= 2 and >= 0.9 * 2.5 (it is the best known): contrast (1.5 - 1) / 2.5 = 0.2,
    # steer = heading + 1.5 * 0.2 = heading + 0.3 (left brighter -> turns left, counter-clockwise).
    heading = 0.5
    wish = step(view_of([[0.0, 0.0]], [light], headings=[heading], pairs=[]))
    expected = heading + turn
    assert_allclose(wish.heading, [expected], atol=1e-12)
    assert_allclose(wish.velocity, [[0.2 * math.cos(expected), 0.2 * math.sin(expected)]], atol=1e-12)


def test_phototaxis_gain_scales_the_turn() -> None:
    # Left 3, right 1: contrast 2 / 4 = 0.5; gain 0.4 -> turn 0.2.
    wish = step(view_of([[0.0, 0.0]], [[3.0, 1.0]], headings=[0.0], pairs=[]), phototaxis_gain=0.4)
    assert_allclose(wish.heading, [0.2], atol=1e-12)


def test_hot_agent_close_to_a_brighter_broadcast_still_homes_in() -> None:
    # Reads 9.5 >= 0.9 * 10 (the neighbour's broadcast): hot, steers by its sensors (5 vs 4.5:
    # contrast 0.5 / 9.5, turn 1.5 * 0.5 / 9.5), while adopting the brighter target.
    view = view_of(
        [[0.0, 0.0], [5.0, 0.0]],
        [[5.0, 4.5], [0.0, 0.0]],
        headings=[1.0, 0.0],
        target=[[NAN, NAN], [7.0, 7.0]],
        target_light=[-INF, 10.0],
        rows=[0],
        pairs=[(0, 1)],
    )
    wish = step(view)
    assert_allclose(wish.memory["target"], [[7.0, 7.0]])
    assert_allclose(wish.memory["target_light"], [10.0])
    assert_allclose(wish.heading, [1.0 + 1.5 * 0.5 / 9.5], atol=1e-12)


def test_seeing_light_but_far_dimmer_than_the_best_goes_to_the_target() -> None:
    # Reads 2.5 >= 2 but < 0.9 * 10: not hot; goes to the relayed target (0, -10) at full speed.
    view = view_of(
        [[0.0, 0.0], [5.0, 0.0]],
        [[1.5, 1.0], [0.0, 0.0]],
        target=[[NAN, NAN], [0.0, -10.0]],
        target_light=[-INF, 10.0],
        rows=[0],
        pairs=[(0, 1)],
    )
    wish = step(view)
    assert_allclose(wish.memory["target"], [[0.0, -10.0]])
    assert_allclose(wish.velocity, [[0.0, -0.2]], atol=1e-12)
    assert np.isnan(wish.heading[0])


def test_reading_below_own_threshold_is_not_hot_even_near_the_best() -> None:
    # A picky agent (threshold 5) hears a broadcast of 3 W/m^2 at (0, 10) and reads 2.9 >= 0.9 * 3,
    # but 2.9 < 5: it does not count as seeing the light, so it goes to the target instead of steering.
    view = view_of(
        [[0.0, 0.0], [5.0, 0.0]],
        [[1.9, 1.0], [0.0, 0.0]],
        target=[[NAN, NAN], [0.0, 10.0]],
        target_light=[-INF, 3.0],
        rows=[0],
        pairs=[(0, 1)],
    )
    wish = step(view, detect_threshold=5.0)
    assert_allclose(wish.velocity, [[0.0, 0.2]], atol=1e-12)
    assert np.isnan(wish.heading[0])
    assert_allclose(wish.memory["target_light"], [3.0])


# ----------------------------------------------------------------------------- gathering


@pytest.mark.parametrize(
    ("target", "velocity"),
    [
        ([10.0, 0.0], [0.2, 0.0]),  # far: full speed
        ([0.0, 0.8], [0.0, 0.2]),  # exactly 2 r: (0.8 - 0.4) / 0.4 = 1 -> full speed
        ([0.0, -0.6], [0.0, -0.1]),  # (0.6 - 0.4) / 0.4 = 0.5 -> 0.1 m/s
        ([0.3, 0.0], [0.0, 0.0]),  # inside arrival_radius: stop
        ([0.4, 0.0], [0.0, 0.0]),  # on the arrival radius: stop
    ],
)
def test_going_to_the_target_slows_and_stops_within_arrival_radius(target: list[float], velocity: list[float]) -> None:
    wish = step(view_of([[0.0, 0.0]], target=[target], target_light=[3.0], pairs=[]))
    assert_allclose(wish.velocity, [velocity], atol=1e-12)
    assert_allclose(wish.memory["target"], [target])


def test_gathering_agents_closer_than_spacing_push_apart() -> None:
    # Both know target (0.1, 0), 0.1 m away: no approach term. They are 0.2 m apart < spacing 0.3:
    # push = max_speed * spacing^2 / d = 0.2 * 0.09 / 0.2 = 0.09 m/s, away from each other.
    view = view_of([[0.0, 0.0], [0.2, 0.0]], target=[[0.1, 0.0]] * 2, target_light=[3.0, 3.0])
    wish = step(view)
    assert_allclose(wish.velocity, [[-0.09, 0.0], [0.09, 0.0]], atol=1e-12)


def test_gathering_agents_beyond_spacing_do_not_push() -> None:
    # 0.35 m apart > 0.3: no push; both within arrival radius of (0.175, 0): standing still.
    view = view_of([[0.0, 0.0], [0.35, 0.0]], target=[[0.175, 0.0]] * 2, target_light=[3.0, 3.0])
    assert np.array_equal(step(view).velocity, np.zeros((2, 2)))


def test_gathering_push_is_capped_at_max_speed() -> None:
    # 0.05 m apart: push 0.2 * 0.09 / 0.05 = 0.36 > 0.2: capped to 0.2.
    view = view_of([[0.0, 0.0], [0.0, 0.05]], target=[[0.0, 0.025]] * 2, target_light=[3.0, 3.0])
    assert_allclose(step(view).velocity, [[0.0, -0.2], [0.0, 0.2]], atol=1e-12)


# ----------------------------------------------------------------------------- search and patrol


@pytest.mark.parametrize("heading", [0.0, math.pi / 2, -2.0])
def test_settled_searcher_patrols_along_its_heading(heading: float) -> None:
    wish = step(view_of([[0.0, 0.0]], headings=[heading], pairs=[]))
    assert_allclose(wish.velocity, [[0.1 * math.cos(heading), 0.1 * math.sin(heading)]], atol=1e-12)
    assert np.isnan(wish.heading[0])


@pytest.mark.parametrize(
    ("echo", "velocity"),
    [
        # Wall echo at (-1, 0): push 1 - 1/1.5 = 1/3 along (1, 0); spread speed 0.2 / 3 = 1/15 < 0.1,
        # so it patrols: + 0.1 * (0, 1) (the push rotated +90 deg).
        ([-1.0, 0.0], [1.0 / 15.0, 0.1]),
        # Wall to the south: push (0, 1/3) -> drift (-0.1, 0).
        ([0.0, -1.0], [-0.1, 1.0 / 15.0]),
    ],
)
def test_wall_pushed_searcher_drifts_counter_clockwise_across_the_push(
    echo: list[float], velocity: list[float]
) -> None:
    # The heading (pi) is ignored once there is a push.
    wish = step(view_of([[0.0, 0.0]], headings=[math.pi], pairs=[], echoes=[[echo]]))
    assert_allclose(wish.velocity, [velocity], atol=1e-12)
    push = -np.asarray(echo)  # unit push direction
    # The component across the push is exactly explore_speed, counter-clockwise.
    across = np.array([-push[1], push[0]])
    assert_allclose(wish.velocity[0] @ across, 0.1, atol=1e-12)


def test_neighbour_pushed_searcher_drifts_across() -> None:
    # Neighbour at (4, 0): F = -(4, 0) / 16 = (-0.25, 0); spread speed 0.05 < 0.1: + 0.1 * (0, -1).
    view = view_of([[0.0, 0.0], [4.0, 0.0]], rows=[0], pairs=[(0, 1)])
    assert_allclose(step(view).velocity, [[-0.05, -0.1]], atol=1e-12)


def test_strongly_pushed_searcher_only_spreads() -> None:
    # Neighbour at (1, 0): F = (-1, 0): full spread speed 0.2 >= explore_speed, no drift.
    view = view_of([[0.0, 0.0], [1.0, 0.0]], headings=[1.0, 0.0], rows=[0], pairs=[(0, 1)])
    assert_allclose(step(view).velocity, [[-0.2, 0.0]], atol=1e-12)


def test_patrol_speed_is_capped_at_max_speed() -> None:
    # explore_speed 0.3 > max_speed 0.2 with a lone agent: capped to 0.2 along the heading.
    wish = step(view_of([[0.0, 0.0]], headings=[0.0], pairs=[]), explore_speed=0.3)
    assert_allclose(wish.velocity, [[0.2, 0.0]], atol=1e-12)


# ----------------------------------------------------------------------------- batch equivalence

SWARM = [[0.0, 0.0], [1.0, 0.5], [1.2, 0.4], [0.5, 2.0]]
SWARM_PAIRS = [(0, 1), (0, 2), (0, 3), (1, 0), (1, 2), (2, 1), (3, 0), (3, 1)]


@pytest.mark.parametrize(
    "behavior",
    [SearchRendezvous(), SearchRendezvous(detect_threshold=1.0, hot_fraction=0.5, spacing=0.5, arrival_radius=1.0)],
)
def test_batch_equals_one_vessel_at_a_time(behavior: SearchRendezvous) -> None:
    # 0 reads 4.8 (hot: adopts 2's broadcast 5, 4.8 >= 4.5); 1 and 2 go to (4, -2), 1 and 2
    # being 0.22 m apart (< spacing); 3 hears only unknowing agents and patrols near a wall.
    view = view_of(
        SWARM,
        [[2.5, 2.3], [0.2, 0.1], [0.1, 0.1], [NAN, NAN]],
        headings=[0.1, 2.0, -1.0, 3.0],
        target=[[NAN, NAN], [NAN, NAN], [4.0, -2.0], [NAN, NAN]],
        target_light=[-INF, -INF, 5.0, -INF],
        pairs=SWARM_PAIRS,
        echoes=[[[NAN, NAN]], [[0.3, 0.0]], [[NAN, NAN]], [[0.0, 1.2]]],
    )
    wish = assert_batch_equivalent(behavior, view)
    assert np.all(np.isfinite(wish.velocity))
    assert np.all(np.isfinite(wish.memory["target_light"][:3]))
