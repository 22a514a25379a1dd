"""An in-memory broadcast network for the lockstep simulator.

Every `period_s` each active agent broadcasts its state; every other active
agent within `range_m` hears it, or, with a radio channel model, hears it with
the channel's delivery probability (falling with distance and with the number
of transmitters around the listener) after its latency. Messages live in a ring buffer; each listener keeps, per sender,
the last message it heard, and forgets it `expiry_s` after hearing it.
Neighbour search uses a k-d tree, never all pairs.

Mesh security (`sitl.mesh_security.MediumSecurity`, optional): intruders
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

from behaviors.base import MemorySpec, SwarmTable, wrap_angle
from bob_autonomy.mesh import packet_bytes
from bob_autonomy.plausibility import JUMP, NON_FINITE, TOO_FAR, implausible
from bob_autonomy.plausibility import REASONS as PLAUSIBILITY_REASONS
from sitl.mesh_security import MediumSecurity, code_of
from sitl.radio import RadioChannel

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
        # On-air size of one state packet (bob_autonomy.mesh), signed with the fleet key or not.
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
        # bob_autonomy.plausibility's codes (0, NON_FINITE, TOO_FAR, JUMP) as the security's reason codes.
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
        rows = base + senders
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
        if self.security is not None:
            listener, sender = self._secure_round(t, base, senders, active, listener, sender)
        self._round_slot.insert(0, self._slot)
        self._round_heard_s.insert(0, t + latency_s)
        del self._round_slot[self.rounds_kept :], self._round_heard_s[self.rounds_kept :]
        self._slot = (self._slot + 1) % self.rounds_kept
        self._merge(t + latency_s, listener, sender)

    def _secure_round(
        self, t: float, base: int, senders: IntArray, active: NDArray[np.bool_], listener: IntArray, sender: IntArray
    ) -> tuple[IntArray, IntArray]:
        """Faulty headings, intruders' messages and deliveries, and the packets' tags of this round; the
        deliveries (listener, transmitter) with the intruders' appended."""
        sec, table = self.security, self.table
        faulty = senders[sec.faulty(senders, t)]
        table.heading[base + faulty] = wrap_angle(table.heading[faulty] + sec.heading_offset[faulty])
        on = np.flatnonzero(sec.intruders_on(t))
        transmitters = senders
        if on.size:
            rows = base + self.n + on
            self.sent_at_s[rows] = t
            table.ids[rows] = sec.intruder_claims[on]
            table.position[rows] = sec.intruder_claimed[on]
            table.heading[rows] = sec.intruder_heading[on]
            table.velocity[rows] = 0.0
            for name, values in table.memory.items():
                values[rows] = self._memory_fill[name]
            sec.intruder_sent += on.size
            hearer, intruder = self._intruder_deliveries(on, active, listener)
            sec.intruder_delivered += hearer.size
            listener, sender = np.concatenate((listener, hearer)), np.concatenate((sender, self.n + intruder))
            transmitters = np.concatenate((senders, self.n + on))
        if sec.key is not None:
            rows = base + transmitters
            self.auth_code[rows], self.stamp[rows] = sec.authenticate(t, table, rows, transmitters)
        return listener, sender

    def _intruder_deliveries(
        self, on: IntArray, active: NDArray[np.bool_], listener: IntArray
    ) -> tuple[IntArray, IntArray]:
        """(listener, intruder index) of the agents that hear the transmitting intruders `on` this round."""
        sec = self.security
        agents = np.flatnonzero(active)
        offset = self.table.position[agents][None, :, :] - sec.intruder_position[on][:, None, :]
        distance = np.hypot(offset[..., 0], offset[..., 1])  # (intruders on, active agents)
        # An agent ignores packets carrying its own id, as bob_autonomy.mesh.LinkMesh does (never counted).
        own_id = self.table.ids[agents][None, :] == sec.intruder_claims[on][:, None]
        k, j = np.nonzero((distance <= sec.intruder_reach_m[on][:, None]) & ~own_id)
        hearer, intruder, distance = agents[j], on[k], distance[k, j]
        if self.channel is not None and hearer.size:
            interferers = np.bincount(listener, minlength=self.n)[hearer]  # the agents it hears this round
            scaled = distance * self.channel.nominal_range_m / sec.intruder_reach_m[intruder]
            ok = self.channel.deliver(self.rng, scaled, interferers)
            hearer, intruder = hearer[ok], intruder[ok]
        return hearer, intruder

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
        """Newly heard messages (rank 0) replace older ones from the same sender; stale ones expire. With
        mesh security, new deliveries are vetted first and a listener keeps one message per agent id."""
        r, n_tx = self.rounds_kept, self.transmitters
        old = self._keys + 1  # one round older
        rank = old % r
        ring_alive = rank != 0  # rank wrapped past the ring: that slot was just overwritten
        heard = np.array(self._round_heard_s)[np.where(ring_alive, rank, 0)]
        old = old[ring_alive & (now - heard <= self.expiry_s + 1e-9)]
        if self.security is not None and self.security.checks and listener.size:
            keep = self._vet(now, listener, sender, old)
            listener, sender = listener[keep], sender[keep]
        new = (listener.astype(np.int64) * n_tx + sender) * r
        keys = np.sort(np.concatenate((new, old)))
        pair = keys // r
        first = np.ones(keys.size, dtype=bool)
        first[1:] = pair[1:] != pair[:-1]  # newest (lowest rank) first within each pair
        keys = keys[first]
        if self.n < n_tx:  # intruders: the newest message of each (listener, agent id), whoever sent it
            # (of one round, the last taken: agents' packets are taken before intruders')
            claimed_pair = self._claimed_pairs(keys)
            order = np.lexsort((-((keys // r) % n_tx), keys % r, claimed_pair))
            keep = np.ones(keys.size, dtype=bool)
            keep[1:] = claimed_pair[order][1:] != claimed_pair[order][:-1]
            keys = np.sort(keys[order][keep])
        self._keys = keys
        self._decode()

    def _decode(self) -> None:
        """Unpack the keys into listener, sender, message row and arrival time arrays."""
        r = self.rounds_kept
        pair, rank = np.divmod(self._keys, r)
        listener, sender = np.divmod(pair, self.transmitters)
        self.listener = listener.astype(np.intp)
        self.sender = sender.astype(np.intp)
        slots = np.array(self._round_slot or [0], dtype=np.intp)
        self.message = self.n + slots[rank] * self.transmitters + self.sender
        self.heard_at = np.array(self._round_heard_s or [0.0])[rank]

    def _rows_of(self, keys: NDArray[np.int64]) -> tuple[IntArray, IntArray, IntArray]:
        """(listener, message row, rank) of heard-message keys (ranks as of the round just inserted)."""
        pair, rank = np.divmod(keys, self.rounds_kept)
        listener, transmitter = np.divmod(pair, self.transmitters)
        slots = np.array(self._round_slot, dtype=np.intp)
        return listener.astype(np.intp), self.n + slots[rank] * self.transmitters + transmitter, rank

    def _claimed_pairs(self, keys: NDArray[np.int64]) -> NDArray[np.int64]:
        """listener * (id count) + claimed agent id of each key."""
        listener, row, _ = self._rows_of(keys)
        return listener.astype(np.int64) * self.security.n_ids + self.table.ids[row]

    def _held(self, pairs: NDArray[np.int64], old: NDArray[np.int64]) -> tuple[NDArray[np.bool_], IntArray, FloatArray]:
        """For each (listener, agent id) in `pairs`: whether an unexpired message of that id is held (`old`
        keys), its table row and when it was heard (s; NaN when none)."""
        o_listener, o_row, o_rank = self._rows_of(old)
        o_pairs = o_listener.astype(np.int64) * self.security.n_ids + self.table.ids[o_row]
        # Without intruders the keys' order is already (listener, id): no sort needed.
        in_order = o_pairs.size < 2 or bool(np.all(o_pairs[1:] > o_pairs[:-1]))
        order = np.arange(o_pairs.size) if in_order else np.argsort(o_pairs, kind="stable")
        if order.size == 0:
            return np.zeros(pairs.size, dtype=bool), np.zeros(pairs.size, dtype=np.intp), np.full(pairs.size, np.nan)
        # Looked up in increasing order: a binary search over ~10^5-10^6 keys with unsorted needles
        # misses the cache at every probe (8 ms at 10,000 agents), sorted needles share the probes.
        by_pair = np.argsort(pairs)
        at = np.empty(pairs.size, dtype=np.intp)
        at[by_pair] = order[np.minimum(np.searchsorted(o_pairs[order], pairs[by_pair]), order.size - 1)]
        found = o_pairs[at] == pairs
        heard_at = np.where(found, np.array(self._round_heard_s)[o_rank[at]], np.nan)
        return found, np.where(found, o_row[at], 0), heard_at

    def _vet(self, now: float, listener: IntArray, sender: IntArray, old: NDArray[np.int64]) -> NDArray[np.bool_]:
        """(M,) which new deliveries pass the key's and the plausibility checks; the others are counted.

        Each is judged against the message its listener holds from the same agent id (`old`, unexpired):
        replay (timestamp not newer), stale (timestamp outside the window of the arrival time), jump (moved
        too far since that message was heard); and too_far against the listener's own believed position.
        """
        sec, table = self.security, self.table
        rows = self.n + self._round_slot[0] * self.transmitters + sender
        claimed = table.ids[rows]
        pairs = listener.astype(np.int64) * sec.n_ids + claimed
        found, ref_row, ref_heard = self._held(pairs, old)
        code = np.zeros(rows.size, dtype=np.int8)
        if sec.key is not None:
            code = self.auth_code[rows].copy()
            replay = found & (self.stamp[rows] <= self.stamp[ref_row])
            stale = np.abs(self.stamp[rows] / 100_000 - now) > sec.window_s
            code[(code == 0) & replay] = code_of("replay")
            code[(code == 0) & stale] = code_of("stale")
        if sec.limits is not None:
            held = np.where(found[:, None], table.position[ref_row], np.nan)
            verdict = implausible(table.position[listener], table.position[rows], held, now - ref_heard, sec.limits)
            code = np.where(code == 0, self._plausibility_code[verdict], code)
        superseded = self._same_round_duplicates(code, pairs, rows, sender)
        sec.count(code, claimed)
        sec.intruder_refused += int(np.count_nonzero(code[sender >= self.n] > 0))
        keep = code == 0
        keep[superseded] = False
        return keep

    def _same_round_duplicates(self, code: NDArray[np.int8], pairs, rows: IntArray, sender: IntArray) -> IntArray:
        """Several accepted deliveries claiming one id for one listener in one round, taken in order (agents'
        before intruders', as a receiver reads them one by one): each later one is judged against the first
        (its code set when it jumped from it); the last that passes replaces the others. Returns the indices
        of the replaced ones."""
        if self.transmitters == self.n:  # no intruders: each agent sends its own id once a round
            return np.zeros(0, dtype=np.intp)
        ok = np.flatnonzero(code == 0)
        order = ok[np.lexsort((sender[ok], pairs[ok]))]
        later = np.zeros(order.size, dtype=bool)
        later[1:] = pairs[order][1:] == pairs[order][:-1]
        if not later.any():
            return np.zeros(0, dtype=np.intp)
        first_of = order[np.maximum.accumulate(np.where(~later, np.arange(order.size), 0))]
        dup, ref = order[later], first_of[later]
        limits = self.security.limits
        if limits is not None:
            nowhere = np.full((dup.size, 2), np.nan)  # no range check here: already done
            position = self.table.position
            verdict = implausible(nowhere, position[rows[dup]], position[rows[ref]], 0.0, limits)
            code[dup] = self._plausibility_code[verdict]
        taken = order[code[order] == 0]  # by (listener, id), then in the order read
        last = np.ones(taken.size, dtype=bool)
        last[:-1] = pairs[taken][1:] != pairs[taken][:-1]
        return taken[~last]

    def counters(self) -> dict:
        """For metrics.json: sent (agents' messages), delivered and dropped (agent-to-agent deliveries the
        channel let through / lost), packet_bytes (on-air size of one state packet), and with mesh security
        `mesh` (`sitl.mesh_security.MediumSecurity.counters`: refused deliveries by reason and claimed id)."""
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
        age = t - self.heard_at
        keep = (age >= -1e-9) & (age <= self.expiry_s + 1e-9) & listening[self.listener]
        return self.listener[keep], self.message[keep], age[keep]
