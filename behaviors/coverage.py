"""Area coverage, as marabunta's AreaCoverageRobot: spread among neighbours and walls.

Every neighbour and every range-finder echo is a point p relative to the
agent; the agent moves along target = -sum_p p / |p|^3 (each point pushes with
1 / distance^2), so it leaves crowded places and walls alike and the swarm
covers the free area. It moves at `max_speed` along the target while
|target| exceeds `threshold` and stops when the pushes balance; an agent that
senses nothing at all keeps its heading at `max_speed` to find something.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np
from numpy.typing import NDArray

from behaviors.base import Behavior, FloatArray, View, Wish, heading_vectors, unit


def inverse_square_push(offsets: FloatArray) -> FloatArray:
    """(..., 2) -p / |p|^3 for each point p in (..., 2) offsets, 1/m^2; 0 for NaN or zero points."""
    d2 = np.einsum("...c,...c->...", offsets, offsets)
    seen = np.isfinite(d2) & (d2 > 0.0)
    weight = np.divide(-1.0, d2 * np.sqrt(d2), out=np.zeros_like(d2), where=seen)
    return np.where(seen[..., None], offsets, 0.0) * weight[..., None]


@dataclass
class AreaCoverage(Behavior):
    """Cover an area: move away from neighbours and obstacles, inverse-square.

    max_speed: speed while moving, m/s.
    threshold: least |target| (1/m^2) worth moving for; a single point at
        distance r gives |target| = 1 / r^2.
    """

    name: ClassVar[str] = "area-coverage"
    rowwise: ClassVar[bool] = True
    max_speed: float = 0.2
    threshold: float = 0.05

    def target(self, view: View) -> tuple[FloatArray, NDArray[np.bool_]]:
        """(n, 2) the push from all sensed points, 1/m^2, and (n,) whether anything was sensed."""
        obstacles = view.senses.obstacles[view.rows]
        push = view.sum_pairs(inverse_square_push(view.offsets()))
        push += inverse_square_push(obstacles).sum(axis=1)
        echoes = np.isfinite(obstacles).all(axis=2).sum(axis=1)
        return push, (view.neighbor_count() + echoes) > 0

    def step(self, view: View) -> Wish:
        push, sensed = self.target(view)
        moving = np.hypot(push[:, 0], push[:, 1]) > self.threshold
        velocity = self.max_speed * unit(push) * moving[:, None]
        velocity[~sensed] = self.max_speed * heading_vectors(view.heading[~sensed])
        return Wish(velocity, np.full(view.n, np.nan))
