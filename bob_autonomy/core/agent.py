"""One agent: body + network + behaviour, and its update step.

The same behaviour array function that steps a whole simulated swarm runs here
on a table of one agent (row 0) and the neighbours it hears (rows 1..k).
"""

from __future__ import annotations

import numpy as np

from behaviors.base import Behavior, SwarmTable, View, Wish
from bob_autonomy.core.clock import Clock
from bob_autonomy.core.interfaces import AgentState, Body, Network, Pose
from bob_autonomy.core.neighbors import NeighborTable


class Agent:
    """An autonomous agent; call `step()` once per control period."""

    def __init__(
        self,
        agent_id: int,
        body: Body,
        network: Network,
        behavior: Behavior,
        clock: Clock,
        neighbor_expiry_s: float = 1.0,
    ) -> None:
        self.agent_id = agent_id
        self.body = body
        self.network = network
        self.clock = clock
        self.neighbors = NeighborTable(neighbor_expiry_s)
        self.memory: dict[str, np.ndarray] = {}
        self.behavior = behavior

    @property
    def behavior(self) -> Behavior:
        return self._behavior

    @behavior.setter
    def behavior(self, behavior: Behavior) -> None:
        """Switch behaviour; memory fields it has not used before start empty."""
        self._behavior = behavior
        for name, spec in behavior.memory_fields.items():
            self.memory.setdefault(name, spec.empty(1)[0])

    def step(self) -> Wish:
        """Sense, listen, decide, act, broadcast. Returns the wish acted on."""
        now = self.clock.now()
        pose = self.body.pose()
        senses = self.body.senses()
        for state in self.network.receive():
            self.neighbors.update(state, now, (pose.x, pose.y))  # implausible claims refused, counted
        heard = [state for state, _age in self.neighbors.fresh(now)]
        table = self._table(pose, heard)
        k = len(heard)
        view = View(table, senses, np.zeros(1, dtype=np.intp), np.zeros(k, dtype=np.intp), np.arange(1, k + 1), now)
        wish = self.behavior.step(view)
        for name, values in wish.memory.items():
            self.memory[name] = np.asarray(values[0], dtype=float)
        self.body.command(wish.velocity[0], float(wish.heading[0]))
        self.network.broadcast(AgentState(self.agent_id, now, pose, {k: v.copy() for k, v in self.memory.items()}))
        return wish

    def _table(self, pose: Pose, heard: list[AgentState]) -> SwarmTable:
        poses = [pose, *(s.pose for s in heard)]
        memory = {}
        for name, spec in self.behavior.memory_fields.items():
            column = spec.empty(len(poses))
            column[0] = self.memory[name]
            for row, state in enumerate(heard, start=1):
                value = np.asarray(state.memory.get(name, ()), dtype=float)
                if value.size == column[row].size:  # a field of another size (or none) is unknown: the fill
                    column[row] = value.reshape(column[row].shape)
            memory[name] = column
        return SwarmTable(
            ids=np.array([self.agent_id, *(s.agent_id for s in heard)], dtype=np.intp),
            position=np.array([[p.x, p.y] for p in poses], dtype=float),
            heading=np.array([p.heading for p in poses], dtype=float),
            velocity=np.array([[p.vx, p.vy] for p in poses], dtype=float),
            memory=memory,
        )
