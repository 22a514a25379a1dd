"""Follow a scripted path of waypoints (a driven leader, a survey line).

Each agent goes to its current waypoint at `speed` and advances to the next
once within `arrival_radius_m`; after the last it holds there (or starts over
when `loop`). The waypoint index is kept in memory and broadcast.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from behaviors.base import Behavior, MemorySpec, View, Wish, unit


@dataclass
class FollowWaypoints(Behavior):
    """Drive through `waypoints` [(x, y), ...] in m at `speed` m/s.

    arrival_radius_m: distance at which a waypoint counts as reached.
    loop: start again from the first after the last.
    """

    name: ClassVar[str] = "waypoints"
    memory_fields: ClassVar[dict[str, MemorySpec]] = {"waypoint_index": MemorySpec(fill=0.0)}
    waypoints: list[tuple[float, float]] = field(default_factory=list)
    speed: float = 0.5
    arrival_radius_m: float = 3.0
    loop: bool = False

    def __post_init__(self) -> None:
        if not self.waypoints:
            raise ValueError("waypoints must hold at least one (x, y) point")

    def step(self, view: View) -> Wish:
        path = np.asarray(self.waypoints, dtype=float)
        last = path.shape[0] - 1
        index = np.nan_to_num(view.table.memory["waypoint_index"][view.rows]).astype(int).clip(0, last)
        reached = np.hypot(*(path[index] - view.position).T) <= self.arrival_radius_m
        if self.loop:
            index = np.where(reached, (index + 1) % (last + 1), index)
        else:
            index = np.where(reached, np.minimum(index + 1, last), index)
        to_go = path[index] - view.position
        distance = np.hypot(to_go[:, 0], to_go[:, 1])
        done = ~self.loop & (index == last) & (distance <= self.arrival_radius_m)
        # Slow down over the last arrival radius of the final waypoint instead of overshooting.
        speed = np.where(done, self.speed * distance / self.arrival_radius_m, self.speed)
        return Wish(unit(to_go) * speed[:, None], np.full(view.n, np.nan), {"waypoint_index": index.astype(float)})
