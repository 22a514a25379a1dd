"""The latest state heard from each neighbour, with its age; stale entries expire; implausible states refused."""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass

import numpy as np

from bob_autonomy.core.interfaces import AgentState
from bob_autonomy.core.plausibility import PLAUSIBLE, REASONS, PlausibilityLimits, implausible

DEFAULT_LIMITS = PlausibilityLimits()


@dataclass
class Heard:
    """A neighbour's state and when (s, local clock) it was heard."""

    state: AgentState
    heard_at: float


class NeighborTable:
    """Neighbour id -> latest state; entries older than `expiry_s` are dropped.

    limits: the plausibility checks on what neighbours claim (`bob_autonomy.core.plausibility`; None: none).
    A refused state is counted in `rejected[reason][agent id]` and changes nothing: the last accepted
    state stays the reference until it expires.
    """

    def __init__(self, expiry_s: float, limits: PlausibilityLimits | None = DEFAULT_LIMITS) -> None:
        if expiry_s <= 0:
            raise ValueError(f"expiry_s must be positive, got {expiry_s}")
        self.expiry_s = expiry_s
        self.limits = limits
        self._heard: dict[int, Heard] = {}
        self.rejected: dict[str, Counter[int]] = {reason: Counter() for reason in REASONS.values()}

    def update(self, state: AgentState, now: float, own_position: tuple[float, float] | None = None) -> str | None:
        """Keep `state` unless a newer one (by its own time stamp) is already held or it is implausible
        (claimed from `own_position`, m, when given). Returns the reason it was refused, or None."""
        held = self._heard.get(state.agent_id)
        if held is not None and now - held.heard_at > self.expiry_s:
            held = None  # expired: no reference any more
        if self.limits is not None:
            reference = (held.state.pose.x, held.state.pose.y) if held is not None else (math.nan, math.nan)
            code = int(
                implausible(
                    own_position if own_position is not None else (math.nan, math.nan),
                    (state.pose.x, state.pose.y),
                    reference,
                    np.nan if held is None else now - held.heard_at,
                    self.limits,
                )[0]
            )
            if code != PLAUSIBLE:
                self.rejected[REASONS[code]][state.agent_id] += 1
                return REASONS[code]
        if held is None or state.t >= held.state.t:
            self._heard[state.agent_id] = Heard(state, now)
        return None

    def fresh(self, now: float) -> list[tuple[AgentState, float]]:
        """(state, age s) of every neighbour heard within `expiry_s`, by id; expired ones are removed."""
        for agent_id in [k for k, h in self._heard.items() if now - h.heard_at > self.expiry_s]:
            del self._heard[agent_id]
        return [(h.state, now - h.heard_at) for _, h in sorted(self._heard.items())]

    def counters(self) -> dict[str, dict[str, int]]:
        """`rejected` as plain dicts (reason -> {agent id as text -> count}), for logs and metrics."""
        return {reason: {str(k): v for k, v in sorted(c.items())} for reason, c in self.rejected.items()}

    def __len__(self) -> int:
        return len(self._heard)
