"""An in-memory broadcast network for the lockstep simulator.

Every `period_s` each active agent broadcasts its state; every other active
agent within `range_m` hears it, or, with a radio channel model, hears it with
the channel's delivery probability (falling with distance and with the number
of transmitters around the listener) after its latency. Messages live in a ring buffer; each listener keeps, per sender,
the last message it heard, and forgets it `expiry_s` after hearing it.
Neighbour search uses a k-d tree, never all pairs.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from behaviors.base import MemorySpec, SwarmTable
from sitl.radio import RadioChannel

# Bytes of one state message: id (2), time (4), x, y, heading, vx, vy (5 x 4) and 4 per memory value.
STATE_HEADER_BYTES = 26

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
        channel: RadioChannel | None = None,
        rng: np.random.Generator | None = None,
    ) -> None:
        if range_m <= 0 or period_s <= 0 or expiry_s <= 0:
            raise ValueError("range_m, period_s and expiry_s must be positive")
        if channel is not None and rng is None:
            raise ValueError("a radio channel needs a random generator")
        self.n = n_agents
        self.channel, self.rng = channel, rng
        self.payload_bytes = STATE_HEADER_BYTES + 4 * sum(int(np.prod(s.shape)) for s in memory_fields.values())
        if channel is not None:
            channel.check_payload(self.payload_bytes)
            range_m = min(range_m, channel.nominal_range_m)
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
        self.rounds_kept = rounds_kept
        self._slot = 0
        self._round_slot: list[int] = []  # ring slot of the latest rounds, newest first
        self._round_heard_s: list[float] = []  # when each of those rounds arrived, newest first
        self.next_broadcast_s = 0.0
        # Heard messages, one per (listener, sender), encoded as sorted int64 keys
        # ((listener * N + sender) * R + rank), rank = rounds since it was heard.
        self._keys = np.zeros(0, dtype=np.int64)
        self._decode()
        self.sent = 0
        self.delivered = 0
        self.dropped = 0

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
        listener, sender = np.concatenate((a, b)), np.concatenate((b, a))
        if self.channel is not None:
            listener, sender, latency_s = self._through_channel(listener, sender, latency_s)
        self.delivered += listener.size
        self._round_slot.insert(0, self._slot)
        self._round_heard_s.insert(0, t + latency_s)
        del self._round_slot[self.rounds_kept :], self._round_heard_s[self.rounds_kept :]
        self._slot = (self._slot + 1) % self.rounds_kept
        self._merge(t + latency_s, listener, sender)

    def _through_channel(self, listener: IntArray, sender: IntArray, step_s: float) -> tuple:
        """Keep the deliveries the radio channel lets through; the round arrives after its mean latency.

        A listener's interferers are the other transmitters within range of it
        (all active agents broadcast in a round). Latency below one lockstep
        step cannot be resolved: a round is heard `max(step, mean latency)` after it is sent.
        """
        in_range = np.bincount(listener, minlength=self.n)
        interferers = np.maximum(in_range[listener] - 1, 0)
        offset = self.table.position[sender] - self.table.position[listener]
        distance = np.hypot(offset[:, 0], offset[:, 1])
        ok = self.channel.deliver(self.rng, distance, interferers)
        self.dropped += int(np.count_nonzero(~ok))
        return listener[ok], sender[ok], max(step_s, self.channel.latency_mean_s)

    def _merge(self, now: float, listener: IntArray, sender: IntArray) -> None:
        """Newly heard messages (rank 0) replace older ones from the same sender; stale ones expire."""
        r = self.rounds_kept
        old = self._keys + 1  # one round older
        rank = old % r
        ring_alive = rank != 0  # rank wrapped past the ring: that slot was just overwritten
        heard = np.array(self._round_heard_s)[np.where(ring_alive, rank, 0)]
        old = old[ring_alive & (now - heard <= self.expiry_s + 1e-9)]
        new = (listener.astype(np.int64) * self.n + sender) * r
        keys = np.sort(np.concatenate((new, old)))
        pair = keys // r
        first = np.ones(keys.size, dtype=bool)
        first[1:] = pair[1:] != pair[:-1]  # newest (lowest rank) first within each pair
        self._keys = keys[first]
        self._decode()

    def _decode(self) -> None:
        """Unpack the keys into listener, sender, message row and arrival time arrays."""
        r = self.rounds_kept
        pair, rank = np.divmod(self._keys, r)
        listener, sender = np.divmod(pair, self.n)
        self.listener = listener.astype(np.intp)
        self.sender = sender.astype(np.intp)
        slots = np.array(self._round_slot or [0], dtype=np.intp)
        self.message = self.n + slots[rank] * self.n + self.sender
        self.heard_at = np.array(self._round_heard_s or [0.0])[rank]

    def heard(self, t: float, listening: NDArray[np.bool_]) -> tuple[IntArray, IntArray, FloatArray]:
        """(listener, table row of the message, age s) of every unexpired message heard, by listener then sender."""
        age = t - self.heard_at
        keep = (age >= -1e-9) & (age <= self.expiry_s + 1e-9) & listening[self.listener]
        return self.listener[keep], self.message[keep], age[keep]
