"""Resilient consensus (issue 15, item 3): the W-MSR rule, as an array function over neighbour pairs.

Beyond the paper. In eq. (2) and in the consensus sum of eq. (5) one neighbour that broadcasts a wrong
value (a stuck compass, a liar) drags every agent that hears it, and the whole connected swarm with them:
a stubborn neighbour is a leader. The Weighted-Mean-Subsequence-Reduced rule (LeBlanc, Zhang, Koutsoukos
and Sundaram, "Resilient asymptotic consensus in robust networks", IEEE JSAC 31(4), 2013) bounds that
influence: at each step each agent discards up to F of the values it heard that are strictly greater than
its own and up to F strictly smaller (the most extreme ones), then averages what is left with its own. If
at most F neighbours of any agent are faulty and the network is robust enough ((2F + 1)-robust; a
complete graph of at least 3F + 1 agents is), the normal agents agree on a value within the range of their
own initial values, whatever the faulty ones say.

Headings live on a circle: "greater" and "smaller" are the signed circular difference from the agent's own
heading, wrapped into (-pi, pi]. A leader is, to this rule, indistinguishable from a faulty agent: the
swarm follows a leader only if it is not among the F most extreme values on its side (e.g. a faulty
neighbour further out on the same side is discarded instead).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from behaviors.base import FloatArray, IntArray

__all__ = ["wmsr_keep"]


def wmsr_keep(difference: FloatArray, pair_i: IntArray, f: int) -> NDArray[np.bool_]:
    """(M,) mask of the neighbour pairs W-MSR keeps.

    difference: (M,) each heard value minus its listener's own value (for angles: the circular difference,
    rad, in (-pi, pi]); non-finite differences count as equal to the own value (never discarded).
    pair_i: (M,) the listener of each pair. f: how many values to discard on each side (0: keep all).
    For each listener, of the pairs with a difference > 0 the f largest are dropped (all of them if there
    are fewer), and of those < 0 the f smallest; equal values are never dropped. Ties at the cut are
    broken by pair order.
    """
    if f < 0:
        raise ValueError(f"F (values discarded on each side) must be at least 0, got {f}")
    m = difference.shape[0]
    keep = np.ones(m, dtype=bool)
    if f == 0 or m == 0:
        return keep
    d = np.where(np.isfinite(difference), difference, 0.0)
    order = np.lexsort((np.arange(m), d, pair_i))  # by listener, then value, then pair order
    listener, value = pair_i[order], d[order]
    position = np.arange(m)
    from_bottom = position - np.searchsorted(listener, listener, side="left")
    from_top = np.searchsorted(listener, listener, side="right") - 1 - position
    drop = ((value < 0.0) & (from_bottom < f)) | ((value > 0.0) & (from_top < f))
    keep[order] = ~drop
    return keep
