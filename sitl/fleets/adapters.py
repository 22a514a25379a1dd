"""The simulator's bodies and network behind the single-agent interfaces of `bob_autonomy`.

With these, real `bob_autonomy.Agent` objects run against the lockstep fleet,
one `Agent.step()` each per simulated step: the path a vessel takes, used to
check that the vectorized fleet step computes exactly what each agent would.
"""

from __future__ import annotations

import numpy as np

from behaviors.base import Senses, Wish
from bob_autonomy.core.agent import Agent
from bob_autonomy.core.clock import ManualClock
from bob_autonomy.core.interfaces import AgentState, Pose
from sitl.fleets.fleet import LockstepFleet


class FleetBody:
    """Agent `index` of the fleet as a Body: truth pose (kinematic mode has no estimator)."""

    def __init__(self, fleet: LockstepFleet, index: int, wishes: dict[str, np.ndarray]) -> None:
        self.fleet, self.index, self._wishes = fleet, index, wishes
        self.current_senses: Senses | None = None

    def pose(self) -> Pose:
        b, i = self.fleet.bodies, self.index
        return Pose(*b.position[i], b.heading[i], *b.velocity[i])

    def senses(self) -> Senses:
        s, i = self.current_senses, self.index
        return Senses(obstacles=s.obstacles[i : i + 1], light=s.light[i : i + 1])

    def command(self, velocity_mps: np.ndarray, heading_rad: float) -> None:
        self._wishes["velocity"][self.index] = velocity_mps
        self._wishes["heading"][self.index] = heading_rad


class FleetNetwork:
    """Agent `index`'s radio on the fleet's broadcast medium."""

    def __init__(self, fleet: LockstepFleet, index: int) -> None:
        self.fleet, self.index = fleet, index
        self._last_round = -np.inf

    def broadcast(self, state: AgentState) -> None:
        table, i = self.fleet.medium.table, self.index
        table.position[i] = (state.pose.x, state.pose.y)
        table.heading[i] = state.pose.heading
        table.velocity[i] = (state.pose.vx, state.pose.vy)
        for name, value in state.memory.items():
            table.memory[name][i] = value

    def receive(self) -> list[AgentState]:
        medium, table = self.fleet.medium, self.fleet.medium.table
        listener, message = medium.heard_pairs(self.fleet.t, self.fleet.active)
        mine = message[listener == self.index]
        new = mine[medium.sent_at_s[mine] > self._last_round]
        out = []
        for row in new:
            pose = Pose(*table.position[row], table.heading[row], *table.velocity[row])
            memory = {name: values[row].copy() for name, values in table.memory.items()}
            out.append(AgentState(int(table.ids[row]), float(medium.sent_at_s[row]), pose, memory))
        if new.size:
            self._last_round = float(medium.sent_at_s[new].max())
        return out


class AgentFleet:
    """A lockstep fleet whose agents are stepped one by one through `bob_autonomy.Agent`."""

    def __init__(self, fleet: LockstepFleet) -> None:
        self.fleet = fleet
        self.clock = ManualClock()
        self.wishes = {"velocity": np.zeros((fleet.n, 2)), "heading": np.full(fleet.n, np.nan)}
        expiry = fleet.scenario.network.expiry_s
        self.bodies = [FleetBody(fleet, i, self.wishes) for i in range(fleet.n)]
        self.agents = [
            Agent(i, body, FleetNetwork(fleet, i), fleet.behaviors[fleet.assignment[i]], self.clock, expiry)
            for i, body in enumerate(self.bodies)
        ]

    def step(self) -> None:
        fleet = self.fleet
        fleet.apply_events()
        fleet.sync_table()
        self.clock.set(fleet.t)
        senses = fleet.senses()
        self.wishes["velocity"][:] = 0.0
        self.wishes["heading"][:] = np.nan
        for i in np.flatnonzero(fleet.active):
            self.bodies[i].current_senses = senses
            agent = self.agents[i]
            behavior = fleet.behaviors[fleet.assignment[i]]
            if agent.behavior is not behavior:
                agent.behavior = behavior
            agent.step()
        fleet.finish_step(Wish(self.wishes["velocity"].copy(), self.wishes["heading"].copy()))
