"""The latest state heard from each neighbour, with its age; stale entries expire."""

from __future__ import annotations

from dataclasses import dataclass

from bob_autonomy.interfaces import AgentState


@dataclass
class Heard:
    """A neighbour's state and when (s, local clock) it was heard."""

    state: AgentState
    heard_at: float


class NeighborTable:
    """Neighbour id -> latest state; entries older than `expiry_s` are dropped."""

    def __init__(self, expiry_s: float) -> None:
        if expiry_s <= 0:
            raise ValueError(f"expiry_s must be positive, got {expiry_s}")
        self.expiry_s = expiry_s
        self._heard: dict[int, Heard] = {}

    def update(self, state: AgentState, now: float) -> None:
        """Keep `state` unless a newer one (by its own time stamp) is already held."""
        held = self._heard.get(state.agent_id)
        if held is None or state.t >= held.state.t:
            self._heard[state.agent_id] = Heard(state, now)

    def fresh(self, now: float) -> list[tuple[AgentState, float]]:
        """(state, age s) of every neighbour heard within `expiry_s`, by id; expired ones are removed."""
        for agent_id in [k for k, h in self._heard.items() if now - h.heard_at > self.expiry_s]:
            del self._heard[agent_id]
        return [(h.state, now - h.heard_at) for _, h in sorted(self._heard.items())]

    def __len__(self) -> int:
        return len(self._heard)
