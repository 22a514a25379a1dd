"""bob_autonomy: neighbour table, clock, the agent loop (with fakes), and agent-by-agent vs lockstep equivalence."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np
import pytest
from numpy.testing import assert_allclose

from behaviors.base import Behavior, MemorySpec, Senses, View, Wish
from bob_autonomy import Agent, AgentState, ManualClock, NeighborTable, Pose, WallClock
from sitl.experiments.scenario import Scenario, load_scenario, validate_scenario
from sitl.fleets.adapters import AgentFleet
from sitl.fleets.fleet import LockstepFleet


def state(agent_id: int, t: float, x: float = 0.0, y: float = 0.0, **memory: float) -> AgentState:
    return AgentState(agent_id, t, Pose(x, y, 0.0), {k: np.asarray(v, dtype=float) for k, v in memory.items()})


# ---------------------------------------------------------------- NeighborTable


def test_neighbor_table_keeps_newest_by_state_time() -> None:
    table = NeighborTable(expiry_s=1.0)
    table.update(state(4, t=2.0, x=2.0), now=2.1)
    # An older state (t = 1.5) arriving later is ignored, its arrival does not refresh the entry either.
    table.update(state(4, t=1.5, x=1.5), now=2.5)
    [(held, age)] = table.fresh(now=2.6)
    assert held.pose.x == 2.0
    assert age == pytest.approx(0.5)  # 2.6 - 2.1
    # A state with the same or a later time replaces it.
    table.update(state(4, t=2.0, x=2.2), now=2.7)
    assert table.fresh(now=2.7)[0][0].pose.x == 2.2
    table.update(state(4, t=3.0, x=3.0), now=2.8)
    assert table.fresh(now=2.8)[0][0].pose.x == 3.0


def test_neighbor_table_fresh_returns_ages_sorted_by_id() -> None:
    table = NeighborTable(expiry_s=1.0)
    table.update(state(9, t=0.0), now=0.2)
    table.update(state(3, t=0.0), now=0.5)
    fresh = table.fresh(now=0.9)
    assert [s.agent_id for s, _ in fresh] == [3, 9]
    assert_allclose([age for _, age in fresh], [0.4, 0.7])


def test_neighbor_table_expiry_removes() -> None:
    table = NeighborTable(expiry_s=1.0)
    table.update(state(1, t=0.0), now=0.0)
    table.update(state(2, t=0.5), now=0.5)
    # At 1.0 s agent 1 is exactly 1.0 s old: still fresh; at 1.25 s it is 1.25 s old: dropped.
    assert [s.agent_id for s, _ in table.fresh(now=1.0)] == [1, 2]
    assert [s.agent_id for s, _ in table.fresh(now=1.25)] == [2]
    assert len(table) == 1
    assert table.fresh(now=1.6) == []
    assert len(table) == 0


def test_neighbor_table_rejects_non_positive_expiry() -> None:
    with pytest.raises(ValueError):
        NeighborTable(0.0)


# ---------------------------------------------------------------- clocks


def test_manual_clock() -> None:
    clock = ManualClock(start_s=2.0)
    assert clock.now() == 2.0
    clock.advance(0.5)
    assert clock.now() == 2.5
    clock.set(2.5)  # the same time is allowed
    clock.set(4.0)
    assert clock.now() == 4.0
    with pytest.raises(ValueError):
        clock.set(3.9)
    with pytest.raises(ValueError):
        clock.advance(-0.1)
    assert clock.now() == 4.0


def test_wall_clock_is_monotonic() -> None:
    clock = WallClock()
    a = clock.now()
    assert clock.now() >= a


# ---------------------------------------------------------------- Agent.step with fakes


class FakeBody:
    def __init__(self, pose: Pose) -> None:
        self.current = pose
        self.current_senses = Senses(obstacles=np.full((1, 6, 2), np.nan), light=np.array([[0.25, 0.5]]))
        self.commands: list[tuple[np.ndarray, float]] = []

    def pose(self) -> Pose:
        return self.current

    def senses(self) -> Senses:
        return self.current_senses

    def command(self, velocity_mps: np.ndarray, heading_rad: float) -> None:
        self.commands.append((np.array(velocity_mps, dtype=float), heading_rad))


class FakeNetwork:
    def __init__(self) -> None:
        self.inbox: list[AgentState] = []
        self.sent: list[AgentState] = []

    def receive(self) -> list[AgentState]:
        out, self.inbox = self.inbox, []
        return out

    def broadcast(self, state: AgentState) -> None:
        self.sent.append(state)


@dataclass
class Recording(Behavior):
    """Remembers the views it was given; wishes a fixed velocity; counts its steps in memory."""

    name: ClassVar[str] = "recording"
    memory_fields: ClassVar[dict[str, MemorySpec]] = {"steps": MemorySpec(), "target": MemorySpec(shape=(2,))}
    heading: float = 0.7
    views: list[View] = field(default_factory=list)

    def step(self, view: View) -> Wish:
        self.views.append(view)
        steps = np.nan_to_num(view.table.memory["steps"][view.rows], nan=-1.0) + 1.0
        return Wish(
            np.tile([0.1, -0.2], (view.n, 1)),
            np.full(view.n, self.heading),
            {"steps": steps, "target": view.table.memory["target"][view.rows]},
        )


def make_agent(expiry_s: float = 1.0) -> tuple[Agent, FakeBody, FakeNetwork, Recording, ManualClock]:
    body, net, behavior, clock = FakeBody(Pose(1.0, 2.0, 0.3, 0.05, 0.0)), FakeNetwork(), Recording(), ManualClock()
    return Agent(7, body, net, behavior, clock, expiry_s), body, net, behavior, clock


def test_agent_step_alone() -> None:
    agent, body, net, behavior, clock = make_agent()
    clock.set(5.0)
    wish = agent.step()
    [view] = behavior.views
    assert view.t == 5.0
    assert view.rows.tolist() == [0]
    assert view.pair_i.size == 0 and view.pair_j.size == 0
    assert view.table.ids.tolist() == [7]
    assert_allclose(view.table.position, [[1.0, 2.0]])
    assert_allclose(view.table.heading, [0.3])
    assert_allclose(view.table.velocity, [[0.05, 0.0]])
    assert view.senses is body.current_senses
    # The body gets the wish of row 0.
    [(velocity, heading)] = body.commands
    assert_allclose(velocity, [0.1, -0.2])
    assert heading == 0.7
    assert_allclose(wish.velocity, [[0.1, -0.2]])
    # Broadcast: its id, the time, the pose it decided from, and its memory after the step.
    [sent] = net.sent
    assert (sent.agent_id, sent.t, sent.pose) == (7, 5.0, Pose(1.0, 2.0, 0.3, 0.05, 0.0))
    assert sent.memory["steps"] == 0.0
    assert np.all(np.isnan(sent.memory["target"])) and sent.memory["target"].shape == (2,)


def test_agent_step_with_neighbours() -> None:
    agent, _body, net, behavior, clock = make_agent()
    clock.set(1.0)
    # Heard in the order 5, 2; agent 5 does not carry the "target" field.
    net.inbox = [state(5, 0.9, x=4.0, y=2.0, steps=3.0), state(2, 0.95, x=1.0, y=5.0, steps=1.0, target=[8.0, 9.0])]
    agent.step()
    view = behavior.views[-1]
    # Row 0 is the agent itself, rows 1..k its fresh neighbours by id.
    assert view.table.ids.tolist() == [7, 2, 5]
    assert_allclose(view.table.position, [[1.0, 2.0], [1.0, 5.0], [4.0, 2.0]])
    assert view.pair_i.tolist() == [0, 0]
    assert view.pair_j.tolist() == [1, 2]
    assert_allclose(view.offsets(), [[0.0, 3.0], [3.0, 0.0]])
    # Own memory before the first step is the fill (NaN); neighbours' as broadcast; missing fields filled.
    assert_allclose(view.table.memory["steps"], [np.nan, 1.0, 3.0])
    assert_allclose(view.table.memory["target"], [[np.nan, np.nan], [8.0, 9.0], [np.nan, np.nan]])


def test_agent_memory_persists_and_broadcast_is_a_copy() -> None:
    agent, _body, net, _behavior, clock = make_agent()
    for k in range(3):
        clock.set(0.1 * k)
        agent.step()
    # steps: NaN -> 0 -> 1 -> 2, each step reading its own previous value.
    assert [float(s.memory["steps"]) for s in net.sent] == [0.0, 1.0, 2.0]
    agent.memory["steps"][...] = 99.0
    assert float(net.sent[-1].memory["steps"]) == 2.0


def test_neighbour_that_stops_broadcasting_disappears_after_expiry() -> None:
    agent, _body, net, behavior, clock = make_agent(expiry_s=1.0)
    net.inbox = [state(3, 0.0, x=2.0)]
    agent.step()  # heard at 0.0
    seen = {}
    for t in (0.5, 1.0, 1.1, 2.0):
        clock.set(t)
        agent.step()
        seen[t] = behavior.views[-1].table.ids.tolist()
    # Age 0.5 and 1.0 (= expiry): still used; 1.1 > 1.0: gone for good.
    assert seen == {0.5: [7, 3], 1.0: [7, 3], 1.1: [7], 2.0: [7]}


def test_repeated_message_does_not_reset_age_but_a_newer_one_does() -> None:
    agent, _body, net, behavior, clock = make_agent(expiry_s=1.0)
    net.inbox = [state(3, 0.0)]
    agent.step()
    clock.set(0.8)
    net.inbox = [state(3, 0.0)]  # the same message again (same time stamp): kept, re-stamped as heard now
    agent.step()
    clock.set(1.5)
    agent.step()
    assert behavior.views[-1].table.ids.tolist() == [7, 3]  # 1.5 - 0.8 = 0.7 <= 1.0
    clock.set(1.9)
    agent.step()
    assert behavior.views[-1].table.ids.tolist() == [7]  # 1.9 - 0.8 = 1.1 > 1.0


def test_switching_behaviour_adds_its_memory_fields() -> None:
    agent, _body, net, _behavior, clock = make_agent()
    agent.step()

    @dataclass
    class Other(Behavior):
        name: ClassVar[str] = "other"
        memory_fields: ClassVar[dict[str, MemorySpec]] = {"level": MemorySpec(fill=-1.0)}

        def step(self, view: View) -> Wish:
            return Wish.still(view.n)

    agent.behavior = Other()
    assert agent.memory["level"] == -1.0
    assert agent.memory["steps"] == 0.0  # kept from the first behaviour
    clock.set(0.1)
    agent.step()
    assert set(net.sent[-1].memory) == {"steps", "target", "level"}
    assert math.isnan(agent.body.commands[-1][1])  # type: ignore[attr-defined]


# ---------------------------------------------------------------- AgentFleet vs LockstepFleet


def scenario(name: str, **changes: object) -> Scenario:
    data = load_scenario(name).model_dump(exclude_none=True)
    data.update(changes)
    return validate_scenario(data, f"test variant of {name}")


def early_leader() -> Scenario:
    # The packaged heading consensus with its leader event moved from 22 s to 3 s, so 100 steps include it.
    data = load_scenario("heading-consensus").model_dump(exclude_none=True)
    assert data["events"][0]["action"] == "set-behavior"
    data["events"][0]["t_s"] = 3.0
    return validate_scenario(data, "early leader")


def run_both(sc: Scenario, steps: int) -> tuple[LockstepFleet, LockstepFleet]:
    lockstep, stepped = LockstepFleet(sc), LockstepFleet(sc)
    agents = AgentFleet(stepped)
    assert_allclose(lockstep.bodies.position, stepped.bodies.position, atol=0)
    for _ in range(steps):
        lockstep.step()
        agents.step()
    assert lockstep.t == stepped.t
    return lockstep, stepped


def assert_same_fleet(a: LockstepFleet, b: LockstepFleet, tol: float = 1e-9) -> None:
    assert_allclose(a.bodies.position, b.bodies.position, rtol=0, atol=tol)
    assert_allclose(np.mod(a.bodies.heading - b.bodies.heading + np.pi, 2 * np.pi) - np.pi, 0.0, atol=tol)
    assert_allclose(a.bodies.velocity, b.bodies.velocity, rtol=0, atol=tol)
    assert a.active.tolist() == b.active.tolist()
    assert a.behavior_names() == b.behavior_names()


def test_agents_match_lockstep_heading_consensus() -> None:
    lockstep, stepped = run_both(load_scenario("heading-consensus"), 100)
    assert_same_fleet(lockstep, stepped)
    assert (
        np.abs(lockstep.bodies.heading - LockstepFleet(load_scenario("heading-consensus")).bodies.heading).max() > 0.1
    )


def test_agents_match_lockstep_heading_consensus_with_leader() -> None:
    lockstep, stepped = run_both(early_leader(), 100)
    assert_same_fleet(lockstep, stepped)
    # The leader event happened (agent 0 holds a heading) and the headings actually moved.
    assert lockstep.behavior_names()[0] == "hold-heading"
    assert lockstep.events_log == stepped.events_log
    assert_allclose(lockstep.own_memory["held_heading"][0], stepped.own_memory["held_heading"][0], atol=1e-12)
    initial = LockstepFleet(early_leader()).bodies.heading
    assert np.abs(lockstep.bodies.heading - initial).max() > 0.1


@pytest.mark.parametrize("name", ["heading-consensus", "perimeter-defense", "search-exploration"])
def test_agent_decisions_match_lockstep_from_the_same_state(name: str) -> None:
    """Each step, the wishes of the one-by-one agents equal the vectorized decision from the same state."""
    fleet = LockstepFleet(scenario(name))
    agents = AgentFleet(fleet)
    moved = 0.0
    for _ in range(100):
        fleet.apply_events()
        fleet.sync_table()
        expected = fleet.decide(fleet.senses())
        agents.step()  # same state: applies no event twice, re-syncs, decides agent by agent, moves
        assert_allclose(agents.wishes["velocity"], expected.velocity, rtol=0, atol=1e-12)
        assert_allclose(agents.wishes["heading"], expected.heading, rtol=0, atol=1e-12)
        moved = max(moved, float(np.abs(expected.velocity).max()), float(np.abs(np.nan_to_num(expected.heading)).max()))
    assert moved > 0.01  # the behaviours did something


def test_agents_match_lockstep_perimeter_defense() -> None:
    lockstep, stepped = run_both(scenario("perimeter-defense"), 100)
    assert_same_fleet(lockstep, stepped)


def test_agents_match_lockstep_after_a_removal() -> None:
    # Agent 3 is removed at 1.0 s; its last message (0.9 s) must be forgotten by everyone at the same step.
    sc = scenario("heading-consensus", events=[{"t_s": 1.0, "action": "remove", "agents": [3]}])
    lockstep, stepped = run_both(sc, 30)
    assert not lockstep.active[3]
    assert_same_fleet(lockstep, stepped)
