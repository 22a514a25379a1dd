"""An in-memory broadcast network for the lockstep simulator.

Every `period_s` each active agent broadcasts its state; every other active
agent within `range_m` hears it, or, with a radio channel model, hears it with
the channel's delivery probability (falling with distance and with the number
of transmitters around the listener) after its latency. Messages live in a ring buffer; each listener keeps, per sender,
the last message it heard, and forgets it `expiry_s` after hearing it.
Neighbour search uses a k-d tree, never all pairs.

Two paths give the same deliveries, counters and heard messages. Without a
radio channel or intruders (the fast path), the pairs in range are tested from a
Verlet list (`sitl.radio.neighbour_pairs`: the k-d tree is queried only when an agent
has moved a tenth of the range) and what each listener holds is one entry per
candidate pair, overwritten in place; otherwise (the general path) the heard
messages are sorted int64 keys, merged and searched every round. At 10,000 agents
broadcasting every step a round costs ~2 ms on the fast path, ~22 ms on the general one.

Mesh security (`sitl.radio.mesh_security.MediumSecurity`, optional): intruders
transmit in every round as extra transmitters (message rows after the
agents'); faulty agents' messages carry their heading turned; and every new
delivery is vetted as a vessel would vet it (key: tag, replay, freshness;
plausibility: against the listener's own believed position and the last message
it accepted from the same agent id) before it is heard. A listener then holds
one message per agent *id* (the newest accepted, whichever transmitter sent
it); refused deliveries are counted by reason and claimed id. Within one round
the agents' packets are taken before the intruders': a second packet claiming
the same id in the same round is checked against the first one accepted.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from behaviors.base import MemorySpec, SwarmTable
from bob_autonomy.core.plausibility import JUMP, NON_FINITE, TOO_FAR
from bob_autonomy.core.plausibility import REASONS as PLAUSIBILITY_REASONS
from bob_autonomy.network.mesh import packet_bytes
from sitl.radio.channel import RadioChannel
from sitl.radio.medium_fast import FastPathRounds
from sitl.radio.medium_general import GeneralPathRounds
from sitl.radio.mesh_security import MediumSecurity, code_of
from sitl.radio.neighbour_pairs import NeighbourPairs

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

# Verlet-list margin of the fast path, as a fraction of the radio range: candidates are queried at
# 1.2 x the range (~44 % more pairs to test each round) and again once an agent has moved 10 % of it
# (every ~36 rounds at 100,000 agents in fleet_step's open water; 1.1 x: 20 % more, every ~18 rounds,
# ~2 ms a step slower there). With plausibility checks it is kept under half their slack (see
# _implausible_fast).
SKIN_FRACTION = 0.2


class BroadcastMedium(FastPathRounds, GeneralPathRounds):
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
        security: MediumSecurity | None = None,
    ) -> None:
        if range_m <= 0 or period_s <= 0 or expiry_s <= 0:
            raise ValueError("range_m, period_s and expiry_s must be positive")
        if channel is not None and rng is None:
            raise ValueError("a radio channel needs a random generator")
        self.n = n_agents
        self.channel, self.rng = channel, rng
        self.security = security
        self.transmitters = n_agents + (security.m if security is not None else 0)  # agents, then intruders
        signed = security is not None and security.key is not None
        # On-air size of one state packet (bob_autonomy.network.mesh), signed with the fleet key or not.
        self.payload_bytes = packet_bytes([int(np.prod(s.shape)) for s in memory_fields.values()], signed)
        if channel is not None:
            channel.check_payload(self.payload_bytes)
            range_m = min(range_m, channel.nominal_range_m)
        self.range_m = range_m
        self.period_s = period_s
        self.expiry_s = expiry_s
        rounds_kept = int(np.ceil(expiry_s / period_s)) + 1
        self.capacity = self.transmitters * rounds_kept
        rows = n_agents + self.capacity
        self.table = SwarmTable(
            ids=np.full(rows, -1, dtype=np.intp),
            position=np.zeros((rows, 2)),
            heading=np.zeros(rows),
            velocity=np.zeros((rows, 2)),
            memory={name: spec.empty(rows) for name, spec in memory_fields.items()},
        )
        self._memory_fill = {name: spec.empty(1)[0] for name, spec in memory_fields.items()}
        # bob_autonomy.core.plausibility's codes (0, NON_FINITE, TOO_FAR, JUMP) as the security's reason codes.
        self._plausibility_code = np.array(
            [0, *(code_of(PLAUSIBILITY_REASONS[c]) for c in (NON_FINITE, TOO_FAR, JUMP))], dtype=np.int8
        )
        self.sent_at_s = np.full(rows, -np.inf)
        self.auth_code = np.zeros(rows, dtype=np.int8)  # keyed runs: 0, or the code of unsigned / bad_mac
        self.stamp = np.full(rows, -1, dtype=np.int64)  # keyed runs: the packet's timestamp, 10 us units
        self.rounds_kept = rounds_kept
        self._slot = 0
        self._round_slot: list[int] = []  # ring slot of the latest rounds, newest first
        self._round_heard_s: list[float] = []  # when each of those rounds arrived, newest first
        self.next_broadcast_s = 0.0
        # Heard messages, one per (listener, transmitter), encoded as sorted int64 keys
        # ((listener * T + transmitter) * R + rank), rank = rounds since it was heard, T transmitters.
        self._keys = np.zeros(0, dtype=np.int64)
        self._decode()
        # Fast path (no radio channel, no intruders): what each listener holds is kept per candidate pair of
        # a Verlet list (sitl.radio.neighbour_pairs) instead of as keys; see _fast_round.
        skin_m = SKIN_FRACTION * range_m
        if security is not None and security.limits is not None:
            skin_m = min(skin_m, 0.5 * security.limits.slack_m)
        self._pairs = (
            NeighbourPairs(n_agents, range_m, skin_m) if channel is None and self.transmitters == n_agents else None
        )
        self._held_round = np.zeros(0, dtype=np.int64)  # (C,) round each candidate's held message came in
        self._queried_in = 0  # the round in which the candidate pairs were last queried
        self._held_index = np.zeros(0, dtype=np.intp)  # candidates holding a live message (as decoded)
        self._round = -1  # number of the latest round (0 the first)
        self._round_alive: list[bool] = []  # newest first: whether that round's messages are still held
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
        base = self.n + self._slot * self.transmitters
        # Everyone transmitting (the rule): rows [0, N) copied as one block (3 ms of fancy indexing at 100,000).
        everyone = senders.size == self.n
        source = slice(0, self.n) if everyone else senders
        rows = slice(base, base + self.n) if everyone else base + senders
        table = self.table
        self.sent_at_s[rows] = t
        table.ids[rows] = table.ids[source]
        table.position[rows] = table.position[source]
        table.heading[rows] = table.heading[source]
        table.velocity[rows] = table.velocity[source]
        for values in table.memory.values():
            values[rows] = values[source]
        self.sent += senders.size
        if self._pairs is not None and not self._fast_path_holds(senders):
            self._leave_fast_path()
        if self._pairs is not None:
            self._fast_round(t, base, senders, active, latency_s)
            return

        pairs = cKDTree(table.position[senders]).query_pairs(self.range_m, output_type="ndarray")
        a, b = senders[pairs[:, 0]], senders[pairs[:, 1]]
        listener, sender = np.concatenate((a, b)), np.concatenate((b, a))
        if self.channel is not None:
            listener, sender, latency_s = self._through_channel(listener, sender, latency_s)
        self.delivered += listener.size
        if self.security is not None:
            listener, sender = self._secure_round(t, base, senders, active, listener, sender)
        self._round_slot.insert(0, self._slot)
        self._round_heard_s.insert(0, t + latency_s)
        del self._round_slot[self.rounds_kept :], self._round_heard_s[self.rounds_kept :]
        self._slot = (self._slot + 1) % self.rounds_kept
        self._merge(t + latency_s, listener, sender)

    def _start_round(self, now: float) -> None:
        """The new round (arriving at `now`, s) takes the next ring slot; rounds whose messages the keys
        would drop now (slot about to be reused, or heard more than expiry_s before `now`) die."""
        self._round_slot.insert(0, self._slot)
        self._round_heard_s.insert(0, now)
        del self._round_slot[self.rounds_kept :], self._round_heard_s[self.rounds_kept :]
        self._slot = (self._slot + 1) % self.rounds_kept
        self._round += 1
        heard = np.array(self._round_heard_s)
        fresh = now - heard <= self.expiry_s + 1e-9
        self._round_alive = [True, *(a and bool(f) for a, f in zip(self._round_alive, fresh[1:], strict=False))]

    def _rounds_held(self) -> NDArray[np.bool_]:
        """(R,) whether the messages of the round `rank` rounds old (0 the latest) are still held."""
        alive = np.zeros(self.rounds_kept, dtype=bool)
        alive[: len(self._round_alive)] = self._round_alive
        return alive

    def _live(self, round_of: NDArray[np.int64]) -> NDArray[np.bool_]:
        """Which of the held messages that came in the rounds `round_of` are still held."""
        alive = self._rounds_held()
        dead = np.flatnonzero(~alive)
        if dead.size == 0 or not alive[dead[0] :].any():  # the live rounds are the newest ones (the rule)
            return round_of > self._round - (dead[0] if dead.size else alive.size)
        rank = self._round - round_of
        return (rank < alive.size) & alive[np.minimum(rank, alive.size - 1)]

    def counters(self) -> dict:
        """For metrics.json: sent (agents' messages), delivered and dropped (agent-to-agent deliveries the
        channel let through / lost), packet_bytes (on-air size of one state packet), and with mesh security
        `mesh` (`sitl.radio.mesh_security.MediumSecurity.counters`: refused deliveries by reason and claimed id)."""
        out: dict = {
            "sent": self.sent,
            "delivered": self.delivered,
            "dropped": self.dropped,
            "packet_bytes": self.payload_bytes,
        }
        if self.security is not None:
            out["mesh"] = self.security.counters()
        return out

    def heard(self, t: float, listening: NDArray[np.bool_]) -> tuple[IntArray, IntArray, FloatArray]:
        """(listener, table row of the message, age s) of every unexpired message heard, by listener then sender."""
        keep = self._heard_keep(t, listening)
        age = t - self.heard_at
        if keep is None:
            return self.listener.copy(), self.message.copy(), age
        return self.listener[keep], self.message[keep], age[keep]

    def heard_pairs(self, t: float, listening: NDArray[np.bool_]) -> tuple[IntArray, IntArray]:
        """`heard` without the ages, read-only: the medium's own arrays when every message heard is kept (the
        lockstep fleet's every step; two copies of 10^6 pairs saved at 100,000 agents)."""
        keep = self._heard_keep(t, listening)
        if keep is not None:
            return self.listener[keep], self.message[keep]
        listener, message = self.listener.view(), self.message.view()
        listener.flags.writeable = message.flags.writeable = False
        return listener, message

    def _heard_keep(self, t: float, listening: NDArray[np.bool_]) -> NDArray[np.bool_] | None:
        """Which messages held are heard at t (s) by the `listening` agents (None: all of them)."""
        # Every message's arrival time is its round's: when every round is within the ages kept, so is
        # every message (the same float64 differences), and only who listens selects.
        rounds = t - np.array(self._round_heard_s)
        if bool(np.all((rounds >= -1e-9) & (rounds <= self.expiry_s + 1e-9))):
            return None if bool(np.all(listening)) else listening[self.listener]
        age = t - self.heard_at
        return (age >= -1e-9) & (age <= self.expiry_s + 1e-9) & listening[self.listener]
