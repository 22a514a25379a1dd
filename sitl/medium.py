"""An in-memory broadcast network for the lockstep simulator.

Every `period_s` each active agent broadcasts its state; every other active
agent within `range_m` hears it, or, with a radio channel model, hears it with
the channel's delivery probability (falling with distance and with the number
of transmitters around the listener) after its latency. Messages live in a ring buffer; each listener keeps, per sender,
the last message it heard, and forgets it `expiry_s` after hearing it.
Neighbour search uses a k-d tree, never all pairs.

Two paths give the same deliveries, counters and heard messages. Without a
radio channel or intruders (the fast path), the pairs in range are tested from a
Verlet list (`sitl.neighbour_pairs`: the k-d tree is queried only when an agent
has moved a tenth of the range) and what each listener holds is one entry per
candidate pair, overwritten in place; otherwise (the general path) the heard
messages are sorted int64 keys, merged and searched every round. At 10,000 agents
broadcasting every step a round costs ~2 ms on the fast path, ~22 ms on the general one.

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
from sitl.neighbour_pairs import NeighbourPairs
from sitl.radio import RadioChannel

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

# Verlet-list margin of the fast path, as a fraction of the radio range: candidates are queried at
# 1.2 x the range (~44 % more pairs to test each round) and again once an agent has moved 10 % of it
# (every ~36 rounds at 100,000 agents in fleet_step's open water; 1.1 x: 20 % more, every ~18 rounds,
# ~2 ms a step slower there). With plausibility checks it is kept under half their slack (see
# _implausible_fast).
SKIN_FRACTION = 0.2
_NEVER = np.int64(-(2**62))  # round number of a candidate pair that holds no message


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
        # Fast path (no radio channel, no intruders): what each listener holds is kept per candidate pair of
        # a Verlet list (sitl.neighbour_pairs) instead of as keys; see _fast_round.
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

    def _fast_path_holds(self, senders: IntArray) -> bool:
        """Whether the fast path still gives what the keys would: without vetting always; with it, while
        every agent's id is its index (a listener then holds one message per agent id and per transmitter
        alike)."""
        if self.security is None or not self.security.checks:
            return True
        return bool(np.array_equal(self.table.ids[senders], senders))

    def _leave_fast_path(self) -> None:
        """Hand what the listeners hold over to the keys of the general path, for good."""
        rank = self._round - self._held_round[self._held_index]
        pair = self.listener.astype(np.int64) * self.transmitters + self.sender
        self._keys = pair * self.rounds_kept + rank
        self._pairs = None

    def _fast_round(self, t: float, base: int, senders: IntArray, active: NDArray[np.bool_], latency_s: float) -> None:
        """One broadcast round without a radio channel or intruders, with what each listener holds kept per
        candidate pair (`self._held_round`: the round its message came in) instead of as sorted keys.

        Deliveries are the candidates in range (sitl.neighbour_pairs: the pairs cKDTree.query_pairs would
        find), already in (listener, sender) order; the held message a new one is vetted against is the
        one of the same candidate, and a kept delivery overwrites it. A message expires with its round
        (`self._round_alive`), exactly when the keys would drop it. Same deliveries, counters and heard
        messages as the general path, which sorts and searches ~2 keys per delivery every round
        (22 ms per round at 10,000 agents, 0.5 s at 100,000).
        """
        pairs, position = self._pairs, self.table.position
        if pairs.stale(position, senders):
            self._query_pairs(senders)
        near = np.flatnonzero(pairs.in_range(position))
        self.delivered += near.size
        if self.security is not None:
            none = np.zeros(0, dtype=np.intp)  # no intruders: no deliveries of theirs to add
            self._secure_round(t, base, senders, active, none, none)
        now = t + latency_s
        self._start_round(now)
        if self.security is not None and self.security.checks and near.size:
            refused = self._vet_fast(now, near)
            if refused is not None:
                near = near[~refused]
        self._held_round[near] = self._round
        self._decode_fast()

    def _query_pairs(self, senders: IntArray) -> None:
        """New candidate pairs around the transmitting agents `senders`; the messages held are carried over
        (their pairs stay candidates until they expire)."""
        pairs, held = self._pairs, self._held_index
        at = pairs.rebuild(self.table.position, senders, pairs.keys(held))
        rounds, self._held_round = self._held_round[held], np.full(pairs.size, _NEVER, dtype=np.int64)
        self._held_round[at] = rounds
        self._held_index = at
        self._queried_in = self._round + 1

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

    def _decode_fast(self) -> None:
        """listener, sender, message row and arrival time of the messages held, by listener then sender."""
        self._held_index = np.flatnonzero(self._live(self._held_round))
        self.listener = self._pairs.listener[self._held_index]
        self.sender = self._pairs.sender[self._held_index]
        rank = self._round - self._held_round[self._held_index]
        first_row = self.n + np.array(self._round_slot, dtype=np.intp) * self.transmitters  # of each round's slot
        self.message = first_row[rank] + self.sender
        self.heard_at = np.array(self._round_heard_s)[rank]

    def _vet_fast(self, now: float, near: IntArray) -> NDArray[np.bool_] | None:
        """`_vet` for the fast path: which new deliveries (candidates `near`) are refused (None: none); those
        are counted. Every agent's id is its index and there are no intruders (no same-round duplicates)."""
        sec, pairs = self.security, self._pairs
        round_of = self._held_round[near]
        code = None
        if sec.key is not None:
            sender = pairs.sender[near]
            rows = self.n + self._round_slot[0] * self.transmitters + sender
            found = self._live(round_of)
            slots = np.array(self._round_slot, dtype=np.intp)
            rank = np.minimum(self._round - round_of, slots.size - 1)  # exact where found
            ref_row = np.where(found, self.n + slots[rank] * self.transmitters + sender, 0)
            code = self.auth_code[rows].copy()
            replay = found & (self.stamp[rows] <= self.stamp[ref_row])
            stale = np.abs(self.stamp[rows] / 100_000 - now) > sec.window_s
            code[(code == 0) & replay] = code_of("replay")
            code[(code == 0) & stale] = code_of("stale")
        if sec.limits is not None:
            index, verdict = self._implausible_fast(now, near, round_of)
            if index.size:
                if code is None:
                    code = np.zeros(near.size, dtype=np.int8)
                code[index] = np.where(code[index] == 0, self._plausibility_code[verdict], code[index])
        if code is None:
            return None
        refused = code > 0
        sec.count(code[refused], pairs.sender[near[refused]])  # the claimed ids are the senders' indices
        return refused

    def _implausible_fast(
        self, now: float, near: IntArray, round_of: NDArray[np.int64]
    ) -> tuple[IntArray, NDArray[np.int8]]:
        """`bob_autonomy.plausibility.implausible` of the fast path's deliveries (candidates `near`, whose held
        messages came in the rounds `round_of`): (index, verdict) of those that can fail, the same verdicts
        from the same float64 operations; the others pass.

        non_finite never (the neighbour search refuses non-finite positions); too_far only when its limit
        is within the radio range (a delivery is within it); jump only when the held message came in before
        the candidates were queried: since then no transmitter has moved skin_m / 2 from where it was at
        the query, so its position now and in a later message are less than skin_m apart, and the skin is
        kept under half of slack_m, the least a jump must exceed (all are tested if it were not).
        """
        limits, pairs = self.security.limits, self._pairs
        x, y = self.table.position[:, 0], self.table.position[:, 1]
        if not limits.max_distance_m > self.range_m * (1.0 + 1e-9) or not limits.slack_m > pairs.skin_m:
            index = np.arange(near.size)
        else:
            index = np.flatnonzero(round_of < self._queried_in)
        if index.size == 0:
            return index, np.zeros(0, dtype=np.int8)
        near, round_of = near[index], round_of[index]
        sender = pairs.sender[near]
        claimed_x, claimed_y = x[sender], y[sender]  # = the message rows' position, copied this round
        heard = np.array(self._round_heard_s)
        elapsed = np.maximum(now - heard, 0.0)  # s since each round came in
        bound = np.full(self.rounds_kept + 1, np.nan)  # m, by rank; last: no message held (no check)
        bound[: heard.size] = np.where(
            self._rounds_held()[: heard.size], limits.slack_m + limits.max_speed_mps * elapsed, np.nan
        )
        slots = np.zeros(self.rounds_kept + 1, dtype=np.intp)
        slots[: heard.size] = self._round_slot
        rank = np.minimum(self._round - round_of, self.rounds_kept)
        row = self.n + slots[rank] * self.transmitters + sender  # the held message's row (where one is held)
        verdict = np.zeros(near.size, dtype=np.int8)
        verdict[_exceeds(claimed_x - x[row], claimed_y - y[row], bound[rank], bound)] = JUMP
        if not limits.max_distance_m > self.range_m * (1.0 + 1e-9):
            listener = pairs.listener[near]
            far_bound = np.array([limits.max_distance_m])
            far = _exceeds(claimed_x - x[listener], claimed_y - y[listener], far_bound[np.zeros_like(near)], far_bound)
            verdict[far] = TOO_FAR
        return index, verdict

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
        # Every message's arrival time is its round's: when every round is within the ages kept, so is
        # every message (the same float64 differences), and only who listens selects.
        rounds = t - np.array(self._round_heard_s)
        if bool(np.all((rounds >= -1e-9) & (rounds <= self.expiry_s + 1e-9))):
            if bool(np.all(listening)):
                return self.listener.copy(), self.message.copy(), age
            keep = listening[self.listener]
        else:
            keep = (age >= -1e-9) & (age <= self.expiry_s + 1e-9) & listening[self.listener]
        return self.listener[keep], self.message[keep], age[keep]


def _exceeds(dx: FloatArray, dy: FloatArray, bound: FloatArray, bounds: FloatArray) -> NDArray[np.bool_]:
    """np.hypot(dx, dy) > bound (m; NaN: False), element by element, with the same result as that
    expression but hypot (13 ns an element) evaluated only where the squared length is within 1e-12 of
    bound ** 2: hypot is within one unit in the last place of the exact length, dx * dx + dy * dy within
    three of its square, so farther from the bound both give the same answer. `bounds`: every value
    `bound` takes; outside [1e-100, 1e100] m (where squares could underflow or overflow) hypot is used
    throughout."""
    finite = bounds[np.isfinite(bounds)]
    if finite.size == 0:
        return np.zeros(dx.size, dtype=bool)  # NaN bounds: no check
    if not (finite.min() >= 1e-100 and finite.max() <= 1e100):
        return np.hypot(dx, dy) > bound
    length2 = dx * dx
    length2 += dy * dy
    bound2 = bound * bound
    out = length2 > bound2
    close = np.flatnonzero(np.abs(length2 - bound2) <= 1e-12 * bound2)
    if close.size:
        out[close] = np.hypot(dx[close], dy[close]) > bound[close]
    return out
