"""Collective marching, as marabunta's MarchingRobot: spread, align and group.

The target direction mixes three vectors (all dimensionless):
  spread  = -sum_j (p_j - p_i) r0 / |p_j - p_i|^2, away from close neighbours;
  heading = the mean of the neighbours' unit heading vectors (consensus);
  group   = (c_i - p_i) / s_i, towards the neighbours' centroid c_i, scaled by
            their spread s_i = sqrt(mean_j |p_j - c_i|^2) (the root mean square
            of their distances from the centroid, as marabunta computes it), so
            "near" and "far" are relative to the group's size; zero with fewer
            than two neighbours (s_i would be 0).
target = w_spread spread + w_heading heading + w_group group. The agent moves
at `speed` along the target when |target|^2 > threshold and stops otherwise;
an agent that hears nobody keeps going along its own heading.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from behaviors.base import Behavior, FloatArray, View, Wish, heading_vectors, unit


@dataclass
class Marching(Behavior):
    """March as a group: keep apart, align, stay together.

    speed: marching speed, m/s.
    r0: length scale of the spreading term, m.
    w_spread, w_heading, w_group: weights of the three terms (dimensionless).
    threshold: least |target|^2 (dimensionless) worth moving for.
    """

    name: ClassVar[str] = "marching"
    rowwise: ClassVar[bool] = True
    speed: float = 0.2
    r0: float = 0.35
    w_spread: float = 2.0
    w_heading: float = 1.0
    w_group: float = 0.2
    threshold: float = 0.5

    def target(self, view: View) -> FloatArray:
        """(n, 2) the un-normalized marching direction (zero for agents hearing nobody)."""
        count = view.neighbor_count()
        per_neighbour = np.divide(1.0, count, out=np.zeros_like(count), where=count > 0)
        d = view.offsets()
        d2 = np.einsum("ij,ij->i", d, d)
        inverse = np.divide(1.0, d2, out=np.zeros_like(d2), where=d2 > 0.0)
        spread = -self.r0 * view.sum_pairs(d * inverse[:, None])
        heading = per_neighbour[:, None] * view.sum_pairs(heading_vectors(view.table.heading[view.pair_j]))
        to_centroid = per_neighbour[:, None] * view.sum_pairs(d)
        mean_d2 = per_neighbour * view.sum_pairs(d2)
        spread_sq = mean_d2 - np.einsum("ij,ij->i", to_centroid, to_centroid)
        # Neighbours all at one point have no spread (up to rounding): no group term.
        grouped = (count >= 2) & (spread_sq > 1e-12 * mean_d2)
        scale = np.sqrt(np.maximum(spread_sq, 0.0))
        inverse_scale = np.divide(1.0, scale, out=np.zeros_like(scale), where=grouped)
        group = to_centroid * inverse_scale[:, None]
        return self.w_spread * spread + self.w_heading * heading + self.w_group * group

    def step(self, view: View) -> Wish:
        target = self.target(view)
        moving = np.einsum("ij,ij->i", target, target) > self.threshold
        velocity = self.speed * unit(target) * moving[:, None]
        alone = view.neighbor_count() == 0
        velocity[alone] = self.speed * heading_vectors(view.heading[alone])
        return Wish(velocity, np.full(view.n, np.nan))
