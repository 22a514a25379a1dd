"""Heading consensus, eq. (2) of the paper, with leaders.

Each agent's target heading is the mean of the unit heading vectors of itself
and its neighbours, theta_i[k+1] = sum_{j in N_i + {i}} theta_j[k] / (N_i + 1).
A leader keeps a fixed heading and does not average; the others, averaging
with it, converge to it (leader-follower).

With `resilient_f` = F > 0 (beyond the paper) each agent first discards up to F
heard headings on each side of its own (the W-MSR rule, `behaviors.resilient`),
so that F neighbours broadcasting wrong headings cannot drag the swarm.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from behaviors.base import Behavior, MemorySpec, View, Wish, heading_vectors, wrap_angle
from behaviors.resilient import wmsr_keep


@dataclass
class HeadingConsensus(Behavior):
    """Align headings with the neighbours by averaging (eq. 2).

    cruise_speed: forward speed while aligning, m/s (0 turns in place).
    resilient_f: F of the W-MSR rule: up to F heard headings counter-clockwise of
        the agent's own (circular difference) and up to F clockwise of it, the
        most extreme, are discarded before averaging (0: eq. (2) as printed).
    """

    name: ClassVar[str] = "heading-consensus"
    rowwise: ClassVar[bool] = True
    cruise_speed: float = 0.0
    resilient_f: int = 0

    def __post_init__(self) -> None:
        if not isinstance(self.resilient_f, int | np.integer) or self.resilient_f < 0:
            raise ValueError(f"resilient_f must be a whole number >= 0, not {self.resilient_f!r}")

    def step(self, view: View) -> Wish:
        if self.resilient_f:
            difference = wrap_angle(view.table.heading[view.pair_j] - view.heading[view.pair_i])
            view = view.restrict(wmsr_keep(difference, view.pair_i, self.resilient_f))
        own = heading_vectors(view.heading)
        neighbours = heading_vectors(view.table.heading[view.pair_j])
        total = own + view.sum_pairs(neighbours)
        # A zero resultant (exactly opposed headings) has no mean: keep one's own.
        degenerate = np.hypot(total[:, 0], total[:, 1]) < 1e-12
        target = np.where(degenerate, view.heading, np.arctan2(total[:, 1], total[:, 0]))
        return Wish(self.cruise_speed * heading_vectors(target), wrap_angle(target))


@dataclass
class HoldHeading(Behavior):
    """A leader: stop averaging and hold a heading.

    The held heading is the agent's heading when it first runs this behaviour
    plus `turn_deg` (degrees, counter-clockwise), or `heading_deg` if given.
    cruise_speed: forward speed, m/s.
    """

    name: ClassVar[str] = "hold-heading"
    rowwise: ClassVar[bool] = True
    memory_fields: ClassVar[dict[str, MemorySpec]] = {"held_heading": MemorySpec()}
    turn_deg: float = 0.0
    heading_deg: float | None = None
    cruise_speed: float = 0.0

    def step(self, view: View) -> Wish:
        held = view.table.memory["held_heading"][view.rows].copy()
        unset = np.isnan(held)
        if self.heading_deg is not None:
            held[unset] = math.radians(self.heading_deg)
        else:
            held[unset] = view.heading[unset] + math.radians(self.turn_deg)
        held = wrap_angle(held)
        return Wish(self.cruise_speed * heading_vectors(held), held, {"held_heading": held})
