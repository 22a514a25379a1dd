"""Who is within radio range of whom, round after round, without a k-d tree per round (a Verlet list).

`sitl.radio.medium.BroadcastMedium` needs, every broadcast round, every ordered pair of
transmitting agents within `range_m` of each other. Building a k-d tree and querying it
costs 3.6 ms at 10,000 agents and 40 ms at 100,000 (scipy cKDTree, ~10 neighbours
each), while agents move a few centimetres per round. `NeighbourPairs` queries the tree
once at `range_m + skin_m` and keeps those pairs as candidates; each round then tests
only the candidates' distances. It queries the tree again when the transmitting agents
change or one of them has moved more than `skin_m / 2` since, so no pair that has come
within `range_m` can be missing from the candidates.

A candidate is in range by exactly the test `cKDTree.query_pairs` makes between two
points: squared distance (dx * dx + dy * dy, float64) at most `range_m * range_m`.
The candidates are ordered pairs (listener, sender) sorted by listener, then sender,
which is the order the medium keeps what each listener heard in.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from behaviors.base import as_complex
from sitl.row_threads import ONE_THREAD, RowThreads

IntArray = NDArray[np.intp]
KeyArray = NDArray[np.int64]

# How far, as a fraction of the unsafe half skin, an agent may move before the tree is queried
# again: the rounding of a float64 distance is ~1e-16 of it, far inside this margin.
_MOVE_MARGIN = 1.0 - 1e-6


class NeighbourPairs:
    """Candidate (listener, sender) pairs of agents: all those within `range_m + skin_m` at the last query,
    plus pairs the caller asked to keep (`extra_keys` of `rebuild`), sorted by key listener * n + sender.

    n: agents (indices [0, n)). range_m, skin_m: radio range and the margin the candidates are queried
    with, m.
    """

    def __init__(self, n: int, range_m: float, skin_m: float) -> None:
        if range_m <= 0 or skin_m <= 0:
            raise ValueError("range_m and skin_m must be positive")
        self.n = n
        self.range_m = range_m
        self.skin_m = skin_m
        self._range2 = range_m * range_m  # the bound cKDTree.query_pairs compares squared distances with
        self._move2 = (0.5 * skin_m * _MOVE_MARGIN) ** 2  # squared displacement allowed between queries, m^2
        self.members: IntArray | None = None  # the transmitting agents at the last query (None: never queried)
        self._anchor = np.zeros((0, 2))  # their positions then, m
        self._first = np.zeros(0, dtype=np.intp)  # unordered candidate pairs (first, second), first < second
        self._second = np.zeros(0, dtype=np.intp)
        # (C,) the ordered candidates' listener and sender, sorted by key listener * n + sender
        self.listener = np.zeros(0, dtype=np.intp)
        self.sender = np.zeros(0, dtype=np.intp)
        # (C,) the unordered pair of each ordered candidate; an index past the unordered pairs for the kept
        # pairs that were not found within range_m + skin_m (never in range before the next query).
        self._half = np.zeros(0, dtype=np.intp)
        self.queries = 0  # k-d tree queries so far

    def stale(self, position: NDArray[np.float64], members: IntArray) -> bool:
        """Whether the candidates may miss a pair of `members` (transmitting agents, sorted) at `position`
        ((n, 2) m): other members than at the last query, or one has moved more than skin_m / 2 since (a
        non-finite position counts as moved)."""
        if self.members is None or not np.array_equal(members, self.members):
            return True
        moved = (position[: self.n] if members.size == self.n else position[members]) - self._anchor
        step2 = moved[:, 0] * moved[:, 0] + moved[:, 1] * moved[:, 1]
        return not bool(np.max(step2, initial=0.0) <= self._move2)  # NaN compares False: stale

    def rebuild(self, position: NDArray[np.float64], members: IntArray, extra_keys: KeyArray) -> IntArray:
        """Query the k-d tree over `members` (sorted agent indices) at `position` ((n, 2) m) for the pairs within
        range_m + skin_m; `extra_keys` (sorted listener * n + sender) are kept as candidates too, out of range
        until the next query. Returns where each of `extra_keys` now is among the candidates. Raises
        ValueError on non-finite positions (as cKDTree does)."""
        where = position[members]
        pairs = cKDTree(where).query_pairs(self.range_m + self.skin_m, output_type="ndarray")
        first, second = members[pairs[:, 0]], members[pairs[:, 1]]
        low, high = np.minimum(first, second), np.maximum(first, second)
        u = low.size
        keys = np.concatenate((low, high)).astype(np.int64) * self.n + np.concatenate((high, low))
        order = np.argsort(keys)
        keys = keys[order]
        half = np.where(order < u, order, order - u)
        at = np.searchsorted(keys, extra_keys)
        missing = extra_keys[keys[np.minimum(at, keys.size - 1)] != extra_keys] if keys.size else extra_keys
        if missing.size:  # held pairs now beyond range_m + skin_m
            keys = np.concatenate((keys, missing))
            half = np.concatenate((half, np.full(missing.size, u, dtype=np.intp)))
            order = np.argsort(keys)
            keys, half = keys[order], half[order]
            at = np.searchsorted(keys, extra_keys)
        self._half = half
        listener, sender = np.divmod(keys, self.n)
        self.listener, self.sender = listener.astype(np.intp), sender.astype(np.intp)
        self._first, self._second = low, high
        self.members = members.copy()
        self._anchor = where
        self.queries += 1
        return at

    @property
    def size(self) -> int:
        """Number of ordered candidate pairs."""
        return self.listener.size

    def keys(self, index: IntArray) -> KeyArray:
        """Keys listener * n + sender of the candidates `index` (sorted where `index` is)."""
        return self.listener[index].astype(np.int64) * self.n + self.sender[index]

    def in_range(self, position: NDArray[np.float64], threads: RowThreads = ONE_THREAD) -> NDArray[np.bool_]:
        """(C,) which candidates are within range_m of each other at `position` ((n, 2) m), by the test of
        cKDTree.query_pairs (squared distance <= range_m * range_m); in parts on `threads` when many."""
        # each (x, y) gathered as one complex number (two gathers, not four); the same float operations
        points = as_complex(position[: self.n])
        near = np.empty(self._first.size + 1, dtype=bool)
        near[-1] = False  # kept pairs beyond range_m + skin_m

        def test(lo: int, hi: int) -> None:
            d = points[self._first[lo:hi]] - points[self._second[lo:hi]]
            d2 = d.real * d.real
            d2 += d.imag * d.imag
            np.less_equal(d2, self._range2, out=near[lo:hi])

        ordered = np.empty(self._half.size, dtype=bool)

        def spread(lo: int, hi: int) -> None:  # each unordered pair's answer to both of its ordered candidates
            np.take(near, self._half[lo:hi], out=ordered[lo:hi], mode="clip")

        threads.map_rows(test, self._first.size)
        threads.map_rows(spread, self._half.size)
        return ordered
