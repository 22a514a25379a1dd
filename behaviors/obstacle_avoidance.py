"""Obstacle avoidance as a wrapper around any behaviour (marabunta's correct_target).

The inner behaviour decides where to go; this one only vetoes collisions. For
each agent it takes the nearest range-finder echo. Within `safe_distance`, if
the wish moves towards that echo, the towards component is removed (the
velocity slides along the obstacle, the removed part turned to the obstacle's
left so that an agent blocked head-on goes around it) and a push away is added that grows from
zero at `safe_distance` to the inner wish's speed at `stop_distance`. Inside
`stop_distance` only moving straight away is allowed: the agent backs off at
the inner wish's speed. The speed never exceeds the inner wish's, so a
behaviour that wants to stand still stands still. Agents without range
finders (K = 0), or with no echo near, keep the inner wish.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from behaviors.base import Behavior, View, Wish, limit_speed


@dataclass
class AvoidObstacles(Behavior):
    """Wrap `inner` so that its agents never drive into what their range finders see.

    inner: the behaviour that chooses the motion.
    safe_distance: echoes closer than this (m) correct the wish.
    stop_distance: echoes closer than this (m) allow only backing away.
    """

    inner: Behavior
    safe_distance: float = 0.35
    stop_distance: float = 0.12

    def __post_init__(self) -> None:
        if not 0.0 <= self.stop_distance < self.safe_distance:
            raise ValueError("need 0 <= stop_distance < safe_distance")
        self.name = f"avoid+{self.inner.name}"
        self.memory_fields = self.inner.memory_fields

    def step(self, view: View) -> Wish:
        wish = self.inner.step(view)
        obstacles = view.senses.obstacles[view.rows]
        if obstacles.shape[1] == 0:
            return wish
        d2 = np.einsum("nkc,nkc->nk", obstacles, obstacles)
        d2 = np.where(np.isfinite(d2) & (d2 > 0.0), d2, np.inf)
        nearest = np.argmin(d2, axis=1)
        distance = np.sqrt(np.take_along_axis(d2, nearest[:, None], axis=1)[:, 0])
        near = distance < self.safe_distance
        echo = np.take_along_axis(obstacles, nearest[:, None, None], axis=1)[:, 0, :]
        direction = np.where(near[:, None], echo / np.where(near, distance, 1.0)[:, None], 0.0)

        velocity = wish.velocity
        speed = np.hypot(velocity[:, 0], velocity[:, 1])
        towards = np.einsum("ij,ij->i", velocity, direction)
        inside = near & (distance < self.stop_distance)
        closeness = np.clip((self.safe_distance - distance) / (self.safe_distance - self.stop_distance), 0, 1)
        # The removed towards component turns into a slide to the left of the obstacle, always the
        # same side (as a bug algorithm does), so that an agent blocked head-on goes around it
        # instead of stopping, and does not dither between sides as its sonar readings shift.
        left = np.column_stack((-direction[:, 1], direction[:, 0]))
        blocked = np.maximum(towards, 0.0)
        slide = velocity - (blocked + speed * closeness)[:, None] * direction + blocked[:, None] * left
        corrected = limit_speed(np.where(inside[:, None], -speed[:, None] * direction, slide), speed)
        affected = near & ((towards > 0.0) | inside)
        new = np.where(affected[:, None], corrected, velocity)
        changed = np.hypot(*(new - velocity).T) > 1e-9 * speed + 1e-12
        return Wish(new, np.where(changed, np.nan, wish.heading), wish.memory)
