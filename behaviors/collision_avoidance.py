"""Short-range collision avoidance between agents, as a wrapper around any behaviour (a sampled velocity obstacle).

The inner behaviour decides where to go; this layer only changes the wish when
following it would bring the agent within `safe_distance_m` of a neighbour in
the next `horizon_s` seconds, as a skipper's collision avoidance does whatever
the mission. It uses only what the agent hears: each neighbour's position and
velocity as broadcast, within `range_m`.

Prediction: the neighbour keeps its velocity v_j; the agent, now at velocity
v_0, answers a new wish c with a first-order lag of time constant `lag_s`
(tau): its displacement after t is v_0 t + (c - v_0) g(t), with
g(t) = t - tau (1 - exp(-t / tau)). The offset to the neighbour after t is

    r(t) = d + (v_j - v_0) t - (c - v_0) g(t),

d the offset now, sampled at t_k = k horizon_s / samples, k = 1..samples.

Threat of c: the mean over the samples, summed over the neighbours, of
max(0, 1 - |r(t_k)| / safe_distance_m)^2 (zero while every neighbour stays
beyond the safe distance; 1 for a collision from the first sample on).

Candidates: the wish w; w turned 30, 60, 90 deg either way; w at half speed;
stopping; `escape_speed_mps` in 8 directions, two of them ahead and astern along
the hull. Cost of c:

    (|c - w|^2 + slowdown_weight * max(0, |w| - |c|)^2) / max(|w|, escape)^2 + threat_weight * threat(c)
      + axis_weight * sin^2(angle between c and the hull) + port_penalty (turns to port)

slowdown_weight makes losing speed dearer than turning, as the COLREGs' rule 8
prefers an early alteration of course with sea room: with it (2, the default)
two agents head on turn to starboard and pass; without it the cheapest answer
of each is to slow down, and they end stopped face to face 2.5 m apart (a
90 deg turn, |c - w|^2 = 2 |w|^2, then costs more than stopping).
axis_weight (0 for a body that moves any way) is for a hull that cannot move
sideways (a motorboat): a wish across its hull costs a turn with way on, so
astern and ahead are preferred. port_penalty makes a symmetric encounter break
to starboard, as the COLREGs ask (two boats head on both turn right and pass
port to port). Where the wish itself is not threatened it is kept unchanged
(the layer is then invisible); otherwise the cheapest candidate becomes the wish
(it may be the wish itself) and, if it changed, the heading preference is
dropped (NaN).

Why here, in the behaviour layer, and not in the controller: avoiding a
neighbour needs the neighbours, and only a behaviour sees them (the View: their
positions and velocities as heard over the mesh); the controller sees one boat's
wish and state. As a wrapper it runs the same on a vessel (a table of one agent
and those it hears) and in a simulated swarm, for any behaviour, a driven
leader's `waypoints` too. How a changed wish is met is the controller's: a
motorboat brakes astern for a stop, backs for an escape astern, turns for a turn
(bob_autonomy.control.motorboat_control).

Not modelled: the age of what is heard (up to a broadcast period; the safe
distance has to cover it, with the GPS error between two receivers). Moving a
heard state on by its age does not help two vessels that avoid each other:
each would move the other on along a course it has already left. So the layer
needs broadcasts at most half its horizon apart (`hearing_problem`; README).

Counted: `interventions` (agent-updates whose wish was changed) and `updates`
(agent-updates); each change is logged at DEBUG on "behaviors.collision_avoidance".
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from behaviors.base import Behavior, FloatArray, View, Wish

logger = logging.getLogger("behaviors.collision_avoidance")
TURNS_DEG = (-30.0, 30.0, -60.0, 60.0, -90.0, 90.0)  # negative: clockwise, to starboard
ESCAPE_DIRECTIONS = 8


@dataclass
class AvoidCollisions(Behavior):
    """Wrap `inner` so that its agents keep `safe_distance_m` from the neighbours they hear.

    safe_distance_m: the separation to keep, centre to centre, m.
    range_m: neighbours heard farther than this are ignored, m.
    horizon_s: how far ahead encounters are predicted, s; samples: prediction times over it.
    lag_s: time constant of the agent's answer to a new wish, s (the prediction's own motion).
    escape_speed_mps: speed of the escape candidates, m/s (and the least speed that normalises the deviation).
    threat_weight: weight of the threat against the deviation from the wish.
    slowdown_weight: extra weight of the speed lost, against turning (COLREG rule 8; module docstring).
    axis_weight: cost of moving across the hull (sin^2 of the angle off it); 0 for a body that moves any way.
    port_penalty: cost of a candidate turned to port (COLREG: give way to starboard).
    """

    inner: Behavior
    safe_distance_m: float = 2.5
    range_m: float = 10.0
    horizon_s: float = 5.0
    samples: int = 10
    lag_s: float = 1.5
    escape_speed_mps: float = 0.5
    threat_weight: float = 100.0
    slowdown_weight: float = 2.0
    axis_weight: float = 0.0
    port_penalty: float = 0.05

    def __post_init__(self) -> None:
        if not 0.0 < self.safe_distance_m <= self.range_m:
            raise ValueError("need 0 < safe_distance_m <= range_m")
        if self.horizon_s <= 0.0 or self.samples < 1 or self.lag_s < 0.0 or self.escape_speed_mps <= 0.0:
            raise ValueError("need horizon_s > 0, samples >= 1, lag_s >= 0 and escape_speed_mps > 0")
        if min(self.threat_weight, self.slowdown_weight, self.axis_weight, self.port_penalty) < 0.0:
            raise ValueError("weights must be >= 0")
        self.name = f"avoid-collisions+{self.inner.name}"
        self.memory_fields = self.inner.memory_fields
        self.interventions = 0
        self.updates = 0

    def hearing_problem(self, broadcast_period_s: float) -> str | None:
        """Why neighbours heard every `broadcast_period_s` (s) are too old for this layer, or None.

        Two buoys avoiding each other at 0.5 m/s (3 m over 5 s) kept 1.6-3.1 m apart with broadcasts every
        1 or 2 s, and came to 0.3 m in one of 8 encounters every 5 s: past half the horizon each has changed
        course long before the other hears of it.
        """
        if broadcast_period_s <= 0.5 * self.horizon_s:
            return None
        return (
            f"collision avoidance predicts {self.horizon_s:g} s ahead but hears its neighbours only every "
            f"{broadcast_period_s:g} s, so two vessels avoiding each other act on courses already changed; "
            f"broadcast at least every {0.5 * self.horizon_s:g} s"
        )

    def candidates(self, wish: FloatArray, heading: FloatArray) -> FloatArray:
        """(n, C, 2) candidate velocities, m/s: the wish first (module docstring)."""
        n = wish.shape[0]
        out = [wish]
        for degrees in TURNS_DEG:
            a = np.radians(degrees)
            out.append(np.column_stack((wish[:, 0] * np.cos(a) - wish[:, 1] * np.sin(a),
                                        wish[:, 0] * np.sin(a) + wish[:, 1] * np.cos(a))))  # fmt: skip
        out.append(0.5 * wish)
        out.append(np.zeros((n, 2)))
        for k in range(ESCAPE_DIRECTIONS):
            angle = heading + k * 2.0 * np.pi / ESCAPE_DIRECTIONS
            out.append(self.escape_speed_mps * np.column_stack((np.cos(angle), np.sin(angle))))
        return np.stack(out, axis=1)

    def threat(self, view: View, candidates: FloatArray) -> FloatArray:
        """(n, C) threat of each candidate (module docstring), summed over the neighbours within range_m; only
        the wish's (column 0) where the wish is not threatened (the others are then never looked at: 0)."""
        n, c = candidates.shape[:2]
        out = np.zeros((n, c))
        d = view.offsets()
        near = np.einsum("ij,ij->i", d, d) <= self.range_m**2
        if not near.any():
            return out
        i, d = view.pair_i[near], d[near]
        own = np.nan_to_num(view.table.velocity[view.rows][i])
        other = np.nan_to_num(view.table.velocity[view.pair_j[near]])
        t = self.horizon_s * np.arange(1, self.samples + 1) / self.samples
        g = t - self.lag_s * (1.0 - np.exp(-t / self.lag_s)) if self.lag_s > 0 else t
        drift = d[:, None, :] + (other - own)[:, None, :] * t[None, :, None]  # (M, K, 2)
        out[:, 0] = np.bincount(
            i, weights=self._penalty(drift, candidates[i, :1] - own[:, None, :], g)[:, 0], minlength=n
        )
        # The other candidates, for the pairs of the agents whose wish is threatened (a few): same sums, fewer pairs.
        keep = out[i, 0] > 0.0
        if keep.any():
            i, own = i[keep], own[keep]
            penalty = self._penalty(drift[keep], candidates[i] - own[:, None, :], g)  # (M', C)
            for k in range(c):
                out[:, k] = np.bincount(i, weights=penalty[:, k], minlength=n)
        return out

    def _penalty(self, drift: FloatArray, change: FloatArray, g: FloatArray) -> FloatArray:
        """(M, C) mean over the samples of max(0, 1 - |r| / safe_distance_m)^2, r = drift (M, K, 2) - change
        (M, C, 2) g (K,)."""
        r = drift[:, None, :, :] - change[:, :, None, :] * g[None, None, :, None]  # (M, C, K, 2)
        distance = np.hypot(r[..., 0], r[..., 1])
        return (np.maximum(0.0, 1.0 - distance / self.safe_distance_m) ** 2).mean(axis=2)

    def step(self, view: View) -> Wish:
        wish = self.inner.step(view)
        self.updates += view.n
        if view.n == 0:
            return wish
        velocity = np.nan_to_num(wish.velocity)
        heading = view.heading
        options = self.candidates(velocity, np.nan_to_num(heading))
        threat = self.threat(view, options)
        threatened = threat[:, 0] > 0.0
        if not threatened.any():
            return wish
        speed = np.hypot(velocity[:, 0], velocity[:, 1])
        scale = np.maximum(speed, self.escape_speed_mps) ** 2
        lost = np.maximum(0.0, speed[:, None] - np.hypot(options[..., 0], options[..., 1]))
        deviation = ((options - velocity[:, None, :]) ** 2).sum(axis=2) + self.slowdown_weight * lost**2
        cost = deviation / scale[:, None] + self.threat_weight * threat
        if self.axis_weight > 0.0:
            along = np.cos(heading)[:, None] * options[..., 0] + np.sin(heading)[:, None] * options[..., 1]
            norm2 = (options**2).sum(axis=2)
            across = np.divide(norm2 - along**2, norm2, out=np.zeros_like(norm2), where=norm2 > 1e-12)
            cost += self.axis_weight * across
        cost[:, 1 : 1 + len(TURNS_DEG)] += [self.port_penalty if a > 0 else 0.0 for a in TURNS_DEG]
        best = np.argmin(cost, axis=1)
        changed = threatened & (best != 0)
        if not changed.any():
            return wish
        self.interventions += int(changed.sum())
        if logger.isEnabledFor(logging.DEBUG):
            for row in np.flatnonzero(changed):
                logger.debug("agent %d at t=%.1f s: wish %s changed to %s (threat %.3f -> %.3f)",
                             view.table.ids[view.rows[row]], view.t, velocity[row], options[row, best[row]],
                             threat[row, 0], threat[row, best[row]])  # fmt: skip
        chosen = options[np.arange(view.n), best]
        new = np.where(changed[:, None], chosen, wish.velocity)
        return Wish(new, np.where(changed, np.nan, wish.heading), wish.memory)


def collision_layer(behavior: Behavior) -> AvoidCollisions | None:
    """The AvoidCollisions in `behavior`'s chain of wrappers (`inner`), or None when it has none."""
    while not isinstance(behavior, AvoidCollisions):
        behavior = getattr(behavior, "inner", None)
        if behavior is None:
            return None
    return behavior
