"""Plausibility checks on what neighbours say (issue 15, item 2), as one array function.

A key proves who sent a packet, not that what it says is true: a member with a failing GPS, or any sender
on an open mesh, can claim a position its vehicle cannot be at. A neighbour's state is refused when

* ``non_finite``: its position is NaN or infinite (the packet decoder already refuses these; the array path
  of the lockstep simulator checks again);
* ``too_far``: it claims a position farther from the receiver's own position than the radio can carry,
  with margin: more than ``range_factor * range_m + slack_m``. A packet heard at all was sent from within
  radio range, so such a claim is false (or the receiver's own position is);
* ``jump``: it moved farther since the last state accepted from the same agent than any member can:
  more than ``slack_m + max_speed_mps * elapsed`` with `elapsed` the receiver's own time (s) since it
  accepted that state (never the sender's time stamps, which a liar chooses).

`slack_m` absorbs position noise, estimator resets and latency. A refused state is not the new reference:
a member whose estimate really jumped (a filter reset) is refused until its old entry expires from the
neighbour table, after which its next state is accepted afresh. The same function serves the neighbour
table of one vessel (`bob_autonomy.core.neighbors.NeighborTable`, one row) and the lockstep simulator's medium
(`sitl.radio.medium`, every delivery of a broadcast round at once).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["JUMP", "NON_FINITE", "PLAUSIBLE", "REASONS", "TOO_FAR", "PlausibilityLimits", "implausible"]

PLAUSIBLE, NON_FINITE, TOO_FAR, JUMP = 0, 1, 2, 3
REASONS = {NON_FINITE: "non_finite", TOO_FAR: "too_far", JUMP: "jump"}  # code -> counter name


@dataclass(frozen=True)
class PlausibilityLimits:
    """What a neighbour's state may claim.

    max_speed_mps: the fastest any member of the swarm can move, with margin, m/s (default 2: twice the BoB
        buoy's top speed, ten times the eBot's).
    slack_m: position error allowed on top of any motion, m (GPS noise and outages, estimator resets).
    range_m: the radio's range, m (the XBee's rated line-of-sight range by default).
    range_factor: how many radio ranges away a claimed position must be to be refused.
    """

    max_speed_mps: float = 2.0
    slack_m: float = 20.0
    range_m: float = 300.0
    range_factor: float = 1.5

    def __post_init__(self) -> None:
        for name in ("max_speed_mps", "slack_m", "range_m", "range_factor"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise ValueError(f"plausibility limit {name} must be a positive finite number, got {value!r}")

    @property
    def max_distance_m(self) -> float:
        """Farthest a claimed position may be from the receiver's own, m."""
        return self.range_factor * self.range_m + self.slack_m


def implausible(
    own_xy: ArrayLike,
    claimed_xy: ArrayLike,
    held_xy: ArrayLike,
    elapsed_s: ArrayLike,
    limits: PlausibilityLimits,
) -> NDArray[np.int8]:
    """(M,) why each of M received states is refused (PLAUSIBLE = 0 when it is not; see the module docstring).

    own_xy: (M, 2) the receiver's own position, m (NaN: unknown, no range check). claimed_xy: (M, 2) the
    position the state claims, m. held_xy: (M, 2) the position of the last state accepted from the same
    agent, m (NaN: none held, no jump check). elapsed_s: (M,) receiver time since that state was accepted, s.
    The first failing check in the order non_finite, too_far, jump gives the code.
    """
    own = np.asarray(own_xy, dtype=float).reshape(-1, 2)
    claimed = np.asarray(claimed_xy, dtype=float).reshape(-1, 2)
    held = np.asarray(held_xy, dtype=float).reshape(-1, 2)
    elapsed = np.maximum(np.asarray(elapsed_s, dtype=float).reshape(-1), 0.0)
    code = np.zeros(claimed.shape[0], dtype=np.int8)
    with np.errstate(invalid="ignore"):
        far = np.hypot(*(claimed - own).T) > limits.max_distance_m  # NaN compares False: no check
        jump = np.hypot(*(claimed - held).T) > limits.slack_m + limits.max_speed_mps * elapsed
    code[jump] = JUMP
    code[far] = TOO_FAR
    code[~np.isfinite(claimed).all(axis=1)] = NON_FINITE
    return code
