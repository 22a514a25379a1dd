"""The radio medium's general path (sitl.radio.medium): a channel with losses, intruders and mesh security; what each
listener holds kept as sorted (listener, sender) keys, merged and vetted each round."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from behaviors.base import wrap_angle
from bob_autonomy.core.plausibility import implausible
from sitl.radio.mesh_security import code_of

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

# Verlet-list margin of the fast path, as a fraction of the radio range: candidates are queried at
# 1.2 x the range (~44 % more pairs to test each round) and again once an agent has moved 10 % of it
# (every ~36 rounds at 100,000 agents in fleet_step's open water; 1.1 x: 20 % more, every ~18 rounds,
# ~2 ms a step slower there). With plausibility checks it is kept under half their slack (see
# _implausible_fast).


class GeneralPathRounds:
    """The general path's rounds, mixed into BroadcastMedium (which holds the state they use)."""

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
        # An agent ignores packets carrying its own id, as bob_autonomy.network.mesh.LinkMesh does (never counted).
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
