"""Search and rendezvous: spread out until someone sees the light, then all go there.

Phase one is perimeter defence (eq. 3); once settled, agents patrol, drifting
across the spreading force so that the swarm circulates along the perimeter. An agent whose light sensors read above
`detect_threshold` records a target: its own position and the reading there.
Targets travel in the broadcast state; every agent adopts the brightest target
it hears (relay), so the word spreads hop by hop. An agent that currently reads
close to the best known light climbs the light gradient with its two sensors
(phototaxis), refining the target towards the source; the rest go to the
target and stop within `arrival_radius` of it, keeping `spacing` between them.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from behaviors.base import (
    Behavior,
    FloatArray,
    MemorySpec,
    View,
    Wish,
    heading_vectors,
    limit_speed,
    unit,
    wrap_angle,
)
from behaviors.perimeter_defense import PerimeterDefense, repulsion


def brightest_heard(view: View, own_target: FloatArray, own_light: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Best (target, light) among each agent's own memory and its neighbours' broadcasts."""
    heard_light = view.table.memory["target_light"][view.pair_j]
    best_light = own_light.copy()
    np.maximum.at(best_light, view.pair_i, heard_light)
    better = (heard_light > own_light[view.pair_i]) & (heard_light == best_light[view.pair_i])
    best_target = own_target.copy()
    best_target[view.pair_i[better]] = view.table.memory["target"][view.pair_j[better]]
    return best_target, best_light


@dataclass
class SearchRendezvous(Behavior):
    """Find a light source together and meet there.

    detect_threshold: summed light reading (W/m^2) that counts as seeing the target.
    max_speed: m/s. explore_speed: least speed while searching, m/s, along the
    current heading when the spreading force has settled.
    arrival_radius: distance (m) from the target inside which an agent stops.
    spacing: distance (m) kept between agents gathering at the target.
    phototaxis_gain: rad of steering per unit of normalized left-right
    difference. hot_fraction: an agent whose reading is at least this fraction
    of the best known light homes in on the source itself.
    """

    name: ClassVar[str] = "search-rendezvous"
    memory_fields: ClassVar[dict[str, MemorySpec]] = {
        "target": MemorySpec(shape=(2,)),
        "target_light": MemorySpec(fill=-np.inf),
    }
    detect_threshold: float = 2.0
    max_speed: float = 0.2
    explore_speed: float = 0.1
    arrival_radius: float = 0.4
    spacing: float = 0.3
    phototaxis_gain: float = 1.5
    hot_fraction: float = 0.9
    spread: PerimeterDefense = field(default_factory=PerimeterDefense)

    def step(self, view: View) -> Wish:
        light = view.senses.light[view.rows]
        reading = np.nan_to_num(light.sum(axis=1), nan=0.0)
        own_target = view.table.memory["target"][view.rows].copy()
        own_light = view.table.memory["target_light"][view.rows].copy()
        seen = (reading >= self.detect_threshold) & (reading > own_light)
        own_target[seen] = view.position[seen]
        own_light[seen] = reading[seen]
        target, best = brightest_heard(view, own_target, own_light)

        velocity = self._search(view)
        heading = np.full(view.n, np.nan)
        known = np.isfinite(best)
        hot = known & (reading >= self.detect_threshold) & (reading >= self.hot_fraction * best)
        going = known & ~hot
        if np.any(going):
            velocity[going] = self._gather(view, target)[going]
        if np.any(hot):
            steer = self._phototaxis(view, light)
            velocity[hot] = self.max_speed * heading_vectors(steer)[hot]
            heading[hot] = steer[hot]
        return Wish(velocity, heading, {"target": target, "target_light": best})

    def _search(self, view: View) -> FloatArray:
        """Perimeter defence, and once settled, patrol: drift at `explore_speed` across the spreading force.

        A settled agent moves perpendicular (counter-clockwise) to the net
        push of its neighbours and the walls, so the spread swarm circulates
        along the perimeter and a lone agent follows the walls; with no push
        at all it keeps going along its heading.
        """
        force = self.spread.direction(view)
        velocity = self.spread.step(view).velocity
        speed = np.hypot(velocity[:, 0], velocity[:, 1])
        slow = speed < self.explore_speed
        pushed = np.hypot(force[:, 0], force[:, 1]) > self.spread.dead_band
        across = unit(force) @ np.array([[0.0, 1.0], [-1.0, 0.0]])  # rotate +90 degrees
        drift = np.where(pushed[:, None], across, heading_vectors(view.heading)) * self.explore_speed
        velocity[slow] = limit_speed(velocity[slow] + drift[slow], self.max_speed)
        return velocity

    def _gather(self, view: View, target: FloatArray) -> FloatArray:
        """Go to the target, slowing inside the arrival radius, keeping spacing."""
        to_target = target - view.position
        distance = np.hypot(to_target[:, 0], to_target[:, 1])
        speed = self.max_speed * np.clip((distance - self.arrival_radius) / self.arrival_radius, 0.0, 1.0)
        velocity = unit(to_target) * speed[:, None]
        d = view.offsets()
        close = np.einsum("ij,ij->i", d, d) < self.spacing**2
        push = repulsion(view.restrict(close)) * self.spacing**2
        return limit_speed(velocity + self.max_speed * push, self.max_speed)

    def _phototaxis(self, view: View, light: FloatArray) -> FloatArray:
        """Heading (rad) turned towards the brighter of the left and right sensors."""
        left, right = np.nan_to_num(light[:, 0]), np.nan_to_num(light[:, 1])
        contrast = (left - right) / np.maximum(left + right, 1e-12)
        return wrap_angle(view.heading + self.phototaxis_gain * contrast)
