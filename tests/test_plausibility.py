"""Plausibility checks on what neighbours say (bob_autonomy.core.plausibility, NeighborTable, Agent)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from behaviors.heading_consensus import HeadingConsensus
from bob_autonomy import Agent, AgentState, ManualClock, NeighborTable, Pose
from bob_autonomy.core.plausibility import JUMP, NON_FINITE, PLAUSIBLE, TOO_FAR, PlausibilityLimits, implausible
from tests.test_agent import FakeBody, FakeNetwork

LIMITS = PlausibilityLimits(max_speed_mps=2.0, slack_m=20.0, range_m=300.0, range_factor=1.5)  # 470 m reach
NAN2 = (math.nan, math.nan)


def state(agent_id: int, t: float, x: float, y: float = 0.0) -> AgentState:
    return AgentState(agent_id, t, Pose(x, y, 0.0), {})


@pytest.mark.parametrize(
    ("own", "claimed", "held", "elapsed", "code"),
    [
        ((0, 0), (469.9, 0), NAN2, math.nan, PLAUSIBLE),  # just inside 1.5 * 300 + 20 m
        ((0, 0), (470.1, 0), NAN2, math.nan, TOO_FAR),
        ((0, 0), (0, -470.1), NAN2, math.nan, TOO_FAR),
        (NAN2, (5000, 0), NAN2, math.nan, PLAUSIBLE),  # own position unknown: no range check
        ((0, 0), (30, 0), (0, 0), 5.0, PLAUSIBLE),  # 30 m in 5 s: within 20 + 2 * 5
        ((0, 0), (30.1, 0), (0, 0), 5.0, JUMP),
        ((0, 0), (20.1, 0), (0, 0), 0.0, JUMP),  # no time has passed: only the slack
        ((0, 0), (20.1, 0), (0, 0), -3.0, JUMP),  # negative elapsed (clock step) counts as none
        ((0, 0), (400, 0), (0, 0), 200.0, PLAUSIBLE),  # a long silence allows a long way
        ((0, 0), (math.nan, 0), (0, 0), 1.0, NON_FINITE),
        ((0, 0), (0, math.inf), NAN2, math.nan, NON_FINITE),
        ((0, 0), (1000, 0), (0, 0), 1.0, TOO_FAR),  # both fail: the range check is reported
    ],
)
def test_each_check_by_hand(own, claimed, held, elapsed, code) -> None:
    assert implausible([own], [claimed], [held], [elapsed], LIMITS).tolist() == [code]


def test_the_array_form_checks_every_row_independently() -> None:
    own = np.array([[0.0, 0.0], [100.0, 100.0], [0.0, 0.0]])
    claimed = np.array([[10.0, 0.0], [700.0, 100.0], [60.0, 0.0]])
    held = np.array([NAN2, NAN2, [0.0, 0.0]])
    codes = implausible(own, claimed, held, [np.nan, np.nan, 10.0], LIMITS)
    assert codes.tolist() == [PLAUSIBLE, TOO_FAR, JUMP]
    assert codes.dtype == np.int8


@settings(max_examples=200, deadline=None, database=None)
@given(
    speed=st.floats(0.0, 2.0),
    heading=st.floats(-math.pi, math.pi),
    elapsed=st.floats(0.0, 100.0),
    noise=st.floats(0.0, 19.9),
)
def test_an_honest_member_moving_at_most_at_top_speed_is_never_refused(speed, heading, elapsed, noise) -> None:
    start = np.array([10.0, -5.0])
    moved = start + speed * elapsed * np.array([math.cos(heading), math.sin(heading)])
    claimed = moved + noise * np.array([math.sin(heading), -math.cos(heading)])  # error across the motion
    own = claimed + np.array([0.0, 449.0])  # within radio range and slack of the receiver
    assert implausible([own], [claimed], [start], [elapsed], LIMITS).tolist() == [PLAUSIBLE]


def test_limits_must_be_positive_and_finite() -> None:
    for bad in (0.0, -1.0, math.nan, math.inf):
        with pytest.raises(ValueError, match="max_speed_mps"):
            PlausibilityLimits(max_speed_mps=bad)


# -- the neighbour table ------------------------------------------------------------------------------------


def test_a_liar_jumping_away_is_refused_counted_and_the_honest_reference_kept() -> None:
    table = NeighborTable(expiry_s=5.0, limits=LIMITS)
    assert table.update(state(0, 1.0, 10.0), now=1.0, own_position=(0.0, 0.0)) is None
    # An intruder claiming agent 0 from 300 m away, one second later: refused, the real agent's state stays.
    assert table.update(state(0, 2.0, 310.0), now=2.0, own_position=(0.0, 0.0)) == "jump"
    assert table.update(state(0, 2.0, 11.0), now=2.0, own_position=(0.0, 0.0)) is None
    assert table.update(state(0, 3.0, 9000.0), now=3.0, own_position=(0.0, 0.0)) == "too_far"
    assert [(s.agent_id, s.pose.x) for s, _ in table.fresh(now=3.0)] == [(0, 11.0)]
    assert table.counters() == {"non_finite": {}, "too_far": {"0": 1}, "jump": {"0": 1}}


def test_a_member_whose_estimate_jumped_is_heard_again_once_its_old_entry_expires() -> None:
    table = NeighborTable(expiry_s=5.0, limits=LIMITS)
    table.update(state(3, 0.0, 0.0), now=0.0)
    assert table.update(state(3, 1.0, 100.0), now=1.0) == "jump"  # a filter reset moved it 100 m
    assert table.update(state(3, 5.0, 100.0), now=5.0) == "jump"  # 20 + 2 * 5 = 30 m allowed: still refused
    assert table.update(state(3, 5.5, 100.0), now=5.5) is None  # 5.5 s after the last accepted: expired
    assert table.fresh(now=5.5)[0][0].pose.x == 100.0


def test_no_limits_means_no_checks_as_before() -> None:
    table = NeighborTable(expiry_s=5.0, limits=None)
    table.update(state(3, 0.0, 0.0), now=0.0)
    assert table.update(state(3, 1.0, 1e6), now=1.0, own_position=(0.0, 0.0)) is None
    assert table.fresh(now=1.0)[0][0].pose.x == 1e6


def test_the_agent_checks_claims_against_its_own_pose() -> None:
    body, net, clock = FakeBody(Pose(1000.0, 0.0, 0.0)), FakeNetwork(), ManualClock()
    agent = Agent(7, body, net, HeadingConsensus(), clock, 5.0)
    net.inbox = [state(1, 0.0, 1010.0), state(2, 0.0, 0.0)]  # agent 2 claims a place 1000 m from us
    agent.step()
    assert [s.agent_id for s, _ in agent.neighbors.fresh(0.0)] == [1]
    assert agent.neighbors.counters()["too_far"] == {"2": 1}


def test_memory_fields_of_the_wrong_size_are_unknown_never_a_crash() -> None:
    from behaviors.heading_consensus import HoldHeading

    body, net, clock = FakeBody(Pose(0.0, 0.0, 0.0)), FakeNetwork(), ManualClock()
    agent = Agent(7, body, net, HoldHeading(turn_deg=10.0), clock, 5.0)
    memory = [{"held_heading": np.array([0.5])}, {"held_heading": np.array([])}, {"held_heading": np.ones(3)}]
    net.inbox = [AgentState(k, 0.0, Pose(1.0, 0.0, 0.0), m) for k, m in enumerate(memory, start=1)]
    agent.step()  # a scalar field as decoded (one value), one never sent (none), one of three values
    heard = agent._table(body.pose(), [s for s, _ in agent.neighbors.fresh(0.0)]).memory["held_heading"]
    assert heard[1] == 0.5 and np.isnan(heard[2:]).all()
