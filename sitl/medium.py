"""An in-memory broadcast network for the lockstep simulator.

Every `period_s` each active agent broadcasts its state; every other active
agent within `range_m` hears it (the radio model with loss and latency plugs in
here later). Messages live in a ring buffer; each listener keeps, per sender,
the last message it heard, and forgets it `expiry_s` after hearing it.
Neighbour search uses a k-d tree, never all pairs.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from behaviors.base import MemorySpec, SwarmTable

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]


class BroadcastMedium:
    """Who heard what: messages (a ring buffer of states) and heard (listener, message) pairs.

    `table` holds the agents' current states in rows [0, N) and the message
    ring buffer after them, so a behaviour reads its own state and what it
    heard from one SwarmTable without copying: message row m is table row N + m.
    """

    def __init__(
        self,
        n_agents: int,
        range_m: float,
        period_s: float,
        expiry_s: float,
        memory_fields: dict[str, MemorySpec],
    ) -> None:
        if range_m <= 0 or period_s <= 0 or expiry_s <= 0:
            raise ValueError("range_m, period_s and expiry_s must be positive")
        self.n = n_agents
        self.range_m = range_m
        self.period_s = period_s
        self.expiry_s = expiry_s
        rounds_kept = int(np.ceil(expiry_s / period_s)) + 1
        self.capacity = n_agents * rounds_kept
        rows = n_agents + self.capacity
        self.table = SwarmTable(
            ids=np.full(rows, -1, dtype=np.intp),
            position=np.zeros((rows, 2)),
            heading=np.zeros(rows),
            velocity=np.zeros((rows, 2)),
            memory={name: spec.empty(rows) for name, spec in memory_fields.items()},
        )
        self.sent_at_s = np.full(rows, -np.inf)
        self._slot = 0
        self.next_broadcast_s = 0.0
        self.listener = np.zeros(0, dtype=np.intp)
        self.sender = np.zeros(0, dtype=np.intp)
        self.message = np.zeros(0, dtype=np.intp)
        self.heard_at = np.zeros(0)
        self.sent = 0
        self.delivered = 0

    def due(self, t: float) -> bool:
        """Whether a broadcast round is due at time t (s)."""
        return t + 1e-9 >= self.next_broadcast_s

    def broadcast(self, t: float, active: NDArray[np.bool_], latency_s: float = 0.0) -> None:
        """Every active agent sends its current state (table rows [0, N)) at t (s); those in range hear it.

        A message arrives `latency_s` after it is sent; it is heard, and ages,
        from then on (the lockstep fleet passes one step: what is sent during
        step k is read at step k + 1).
        """
        self.next_broadcast_s += self.period_s * max(1.0, np.floor((t - self.next_broadcast_s) / self.period_s) + 1)
        senders = np.flatnonzero(active)
        rows = self.n + self._slot * self.n + senders
        self._slot = (self._slot + 1) % (self.capacity // self.n)
        table = self.table
        self.sent_at_s[rows] = t
        table.ids[rows] = table.ids[senders]
        table.position[rows] = table.position[senders]
        table.heading[rows] = table.heading[senders]
        table.velocity[rows] = table.velocity[senders]
        for values in table.memory.values():
            values[rows] = values[senders]
        self.sent += senders.size

        pairs = cKDTree(table.position[senders]).query_pairs(self.range_m, output_type="ndarray")
        a, b = senders[pairs[:, 0]], senders[pairs[:, 1]]
        new_listener = np.concatenate((a, b))
        new_sender = np.concatenate((b, a))
        new_message = np.concatenate((rows[pairs[:, 1]], rows[pairs[:, 0]]))
        self.delivered += new_listener.size
        self._merge(t + latency_s, new_listener, new_sender, new_message)

    def _merge(self, t: float, listener: IntArray, sender: IntArray, message: IntArray) -> None:
        """Newly heard messages replace older ones from the same sender; stale ones expire."""
        alive = t - self.heard_at <= self.expiry_s + 1e-9
        old_listener, old_sender = self.listener[alive], self.sender[alive]
        old_message, old_time = self.message[alive], self.heard_at[alive]
        if old_listener.size:
            superseded = np.isin(old_listener * self.n + old_sender, listener * self.n + sender)
            keep = ~superseded
            old_listener, old_sender = old_listener[keep], old_sender[keep]
            old_message, old_time = old_message[keep], old_time[keep]
        self.listener = np.concatenate((listener, old_listener))
        self.sender = np.concatenate((sender, old_sender))
        self.message = np.concatenate((message, old_message))
        self.heard_at = np.concatenate((np.full(listener.size, t), old_time))
        # Listener, then sender: the order an agent's neighbour table has, so sums agree to the bit.
        order = np.lexsort((self.sender, self.listener))
        self.listener, self.sender = self.listener[order], self.sender[order]
        self.message, self.heard_at = self.message[order], self.heard_at[order]

    def heard(self, t: float, listening: NDArray[np.bool_]) -> tuple[IntArray, IntArray, FloatArray]:
        """(listener, table row of the message, age s) of every unexpired message heard."""
        age = t - self.heard_at
        keep = (age >= -1e-9) & (age <= self.expiry_s + 1e-9) & listening[self.listener]
        return self.listener[keep], self.message[keep], age[keep]
