"""The three parts of an agent, as small typed interfaces, and the state it broadcasts.

A body moves the robot and reads its senses; a network broadcasts this agent's
state and delivers what neighbours broadcast; a behaviour (package
`behaviors`) turns both into a wish. Any implementation of these protocols can
be swapped in: kinematic or MAVLink bodies, in-memory or radio networks.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from behaviors.base import Senses


@dataclass(frozen=True)
class Pose:
    """Where the body believes it is: x east, y north (m), heading (rad from east, CCW), velocity (m/s)."""

    x: float
    y: float
    heading: float
    vx: float = 0.0
    vy: float = 0.0


@dataclass(frozen=True)
class AgentState:
    """What an agent broadcasts: its id, when (s), its pose and its behaviour's memory fields."""

    agent_id: int
    t: float
    pose: Pose
    memory: dict[str, np.ndarray] = field(default_factory=dict)


class Body(Protocol):
    """The robot, as the autonomy sees it."""

    def pose(self) -> Pose:
        """Current pose estimate."""
        ...

    def senses(self) -> Senses:
        """Current senses, as a one-row Senses."""
        ...

    def command(self, velocity_mps: np.ndarray, heading_rad: float) -> None:
        """Move with this velocity (2,) m/s; face this heading (NaN: along the velocity)."""
        ...


class Network(Protocol):
    """A broadcast-only mesh: send my state, hear my neighbours'."""

    def broadcast(self, state: AgentState) -> None:
        """Send this agent's state to whoever is in range."""
        ...

    def receive(self) -> list[AgentState]:
        """States heard since the last call (may be empty)."""
        ...
