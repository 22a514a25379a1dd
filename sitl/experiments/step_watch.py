"""What a run's "ever" and "never" criteria need from every step, not only from the logged frames.

A run logs a frame every `log_period_s` (5 s in the buoy and motorboat scenarios, 10 steps of 0.5 s), which is
enough for figures and plots but not for "no two vessels ever came closer than 1 m" or "no robot ever left the
room": two boats closing at 2 m/s can come within 1 m and part again between two frames. The runners (lockstep
and process fleets) hand every step's ground truth to a `StepWatch`, and the metrics read its extremes.

Closest approach: between two steps each agent is taken to move along the straight line from its position at
the first to its position at the second, and each pair's least distance on those segments (the closest point of
approach) counts, not only the distances at the steps. Beyond ALL_PAIRS_UP_TO agents the candidate pairs come from a
k-d tree: a pair closer than the step's least end distance m at any moment of the step is within m + 2 D at its
end, D the longest move of any agent in the step, so only pairs within that radius are examined.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from sitl.world.world import FloatArray


@dataclass(frozen=True)
class Approach:
    """The least distance (m) two agents came to, which two (ids) and when (s, the end of the step it fell in)."""

    distance_m: float
    agents: tuple[int, int]
    t_s: float


class ClosestApproach:
    """The least distance between any two active agents over a run, steps and the straight lines between them
    included (module docstring)."""

    def __init__(self) -> None:
        self.closest: Approach | None = None
        self._previous = np.full((0, 2), np.nan)  # by agent id: position (m) at the last step, NaN if not active

    def observe(self, t_s: float, agents: NDArray[np.intp], positions: FloatArray) -> None:
        """Take the positions (k, 2) m of the active agents (ids) at t_s."""
        if agents.size and agents.max() >= len(self._previous):
            grown = np.full((int(agents.max()) + 1, 2), np.nan)
            grown[: len(self._previous)] = self._previous
            self._previous = grown
        start = self._previous[agents]
        start = np.where(np.isnan(start), positions, start)  # an agent just active did not travel there
        self._previous[:] = np.nan
        self._previous[agents] = positions
        if len(agents) < 2:
            return
        found = least_approach(start, positions)
        if found is not None and (self.closest is None or found[0] < self.closest.distance_m):
            distance, i, j = found
            self.closest = Approach(distance, (int(agents[i]), int(agents[j])), t_s)

    @property
    def distance_m(self) -> float | None:
        return None if self.closest is None else self.closest.distance_m


ALL_PAIRS_UP_TO = 150  # agents: up to this many every pair is examined (cheaper than building a k-d tree)


@functools.cache
def _all_pairs(k: int) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    return np.triu_indices(k, 1)


def least_approach(start: FloatArray, end: FloatArray) -> tuple[float, int, int] | None:
    """(distance m, i, j) of the pair of rows that comes closest while each moves in a straight line from
    start (k, 2) to end (k, 2) m; None for fewer than two rows."""
    k = len(end)
    if k < 2:
        return None
    if k <= ALL_PAIRS_UP_TO:
        i, j = _all_pairs(k)
    else:
        tree = cKDTree(end)
        nearest, _ = tree.query(end, k=2)
        longest_move = float(np.hypot(*(end - start).T).max())
        pairs = tree.query_pairs(float(nearest[:, 1].min()) + 2.0 * longest_move + 1e-9, output_type="ndarray")
        i, j = pairs[:, 0], pairs[:, 1]
    r0 = start[j] - start[i]  # the pair's offset at the start of the step ...
    dr = (end[j] - end[i]) - r0  # ... and its change over the step
    span = np.einsum("ij,ij->i", dr, dr)
    s = np.clip(-np.einsum("ij,ij->i", r0, dr) / np.where(span > 0.0, span, 1.0), 0.0, 1.0)
    gap = np.hypot(*(r0 + s[:, None] * dr).T)
    best = int(np.argmin(gap))
    return float(gap[best]), int(i[best]), int(j[best])


class AlwaysInside:
    """Whether every active agent was inside the region (`inside(points) -> bool per point`) at every step, and
    the first step one was not."""

    def __init__(self, inside: Callable[[FloatArray], NDArray[np.bool_]]) -> None:
        self.inside = inside
        self.first_outside: tuple[float, int] | None = None  # (t s, agent id)

    def observe(self, t_s: float, agents: NDArray[np.intp], positions: FloatArray) -> None:
        if self.first_outside is not None or len(agents) == 0:
            return
        outside = ~np.asarray(self.inside(positions), dtype=bool)
        if outside.any():
            self.first_outside = (t_s, int(agents[int(np.argmax(outside))]))

    @property
    def always(self) -> bool:
        return self.first_outside is None


class StepWatch:
    """The watches a run's metric kind needs, fed the ground truth of every step (`observe`)."""

    def __init__(self, closest: ClosestApproach | None = None, inside: AlwaysInside | None = None) -> None:
        self.closest = closest
        self.inside = inside

    @property
    def watching(self) -> bool:
        return self.closest is not None or self.inside is not None

    def observe(self, t_s: float, agents: NDArray[np.intp], positions: FloatArray) -> None:
        """Take the active agents' ids (k,) and true positions (k, 2) m at t_s."""
        for watch in (self.closest, self.inside):
            if watch is not None:
                watch.observe(t_s, agents, positions)
