"""Station keeping: stay where you were when the behaviour started (a fixed swarm).

The first step remembers the agent's position; from then on it steers back
towards it with a proportional law, so wind and current cannot carry it off.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from behaviors.base import Behavior, MemorySpec, View, Wish, limit_speed


@dataclass
class HoldPosition(Behavior):
    """Hold the position held at the first step.

    gain_per_s: desired speed per metre of offset, 1/s. max_speed: m/s.
    """

    name: ClassVar[str] = "hold-position"
    memory_fields: ClassVar[dict[str, MemorySpec]] = {"hold_position": MemorySpec(shape=(2,))}
    gain_per_s: float = 0.2
    max_speed: float = 0.5

    def step(self, view: View) -> Wish:
        held = view.table.memory["hold_position"][view.rows].copy()
        unset = np.isnan(held).any(axis=1)
        held[unset] = view.position[unset]
        velocity = limit_speed(self.gain_per_s * (held - view.position), self.max_speed)
        return Wish(velocity, np.full(view.n, np.nan), {"hold_position": held})
