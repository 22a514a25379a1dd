"""The radio medium's fast path (sitl.radio.medium): with no radio channel and no intruders, the candidate pairs
of a Verlet list (sitl.radio.neighbour_pairs) and the message each listener holds kept per candidate pair, vetted for
plausibility only where a claim could fail. See the module docstring of sitl.radio.medium for when it is taken."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from bob_autonomy.core.plausibility import JUMP, TOO_FAR
from sitl.norms import exceeds
from sitl.radio.mesh_security import code_of
from sitl.row_threads import ONE_THREAD, RowThreads

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

# Verlet-list margin of the fast path, as a fraction of the radio range: candidates are queried at
# 1.2 x the range (~44 % more pairs to test each round) and again once an agent has moved 10 % of it
# (every ~36 rounds at 100,000 agents in fleet_step's open water; 1.1 x: 20 % more, every ~18 rounds,
# ~2 ms a step slower there). With plausibility checks it is kept under half their slack (see
# _implausible_fast).
_NEVER = np.int64(-(2**62))  # round number of a candidate pair that holds no message


class FastPathRounds:
    """The fast path's rounds, mixed into BroadcastMedium (which holds the state they use)."""

    threads: RowThreads = ONE_THREAD  # the lockstep fleet's, for the passes over the candidate pairs

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

        Deliveries are the candidates in range (sitl.radio.neighbour_pairs: the pairs cKDTree.query_pairs would
        find), already in (listener, sender) order; the held message a new one is vetted against is the
        one of the same candidate, and a kept delivery overwrites it. A message expires with its round
        (`self._round_alive`), exactly when the keys would drop it. Same deliveries, counters and heard
        messages as the general path, which sorts and searches ~2 keys per delivery every round
        (22 ms per round at 10,000 agents, 0.5 s at 100,000).
        """
        pairs, position = self._pairs, self.table.position
        if pairs.stale(position, senders):
            self._query_pairs(senders)
        near = self.threads.flatnonzero(pairs.in_range(position, self.threads))
        self.delivered += near.size
        if self.security is not None:
            none = np.zeros(0, dtype=np.intp)  # no intruders: no deliveries of theirs to add
            self._secure_round(t, base, senders, active, none, none)
        now = t + latency_s
        self._start_round(now)
        if self.security is not None and self.security.checks and near.size:
            refused = self._vet_fast(now, near)
            if refused is not None and refused.any():
                near = near[~refused]
        held_round, latest = self._held_round, self._round

        def keep(lo: int, hi: int) -> None:  # the new deliveries are sorted candidates: disjoint parts
            held_round[near[lo:hi]] = latest

        self.threads.map_rows(keep, near.size)
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

    def _decode_fast(self) -> None:
        """listener, sender, message row and arrival time of the messages held, by listener then sender (the
        gathers in parts on the medium's threads when many)."""
        held_round, pairs = self._held_round, self._pairs
        live = np.empty(held_round.size, dtype=bool)

        def test(lo: int, hi: int) -> None:
            live[lo:hi] = self._live(held_round[lo:hi])

        self.threads.map_rows(test, held_round.size)
        index = self._held_index = self.threads.flatnonzero(live)
        first_row = self.n + np.array(self._round_slot, dtype=np.intp) * self.transmitters  # of each round's slot
        round_heard_s = np.array(self._round_heard_s)
        listener, sender = np.empty_like(index), np.empty_like(index)
        message, heard_at = np.empty_like(index), np.empty(index.size)

        def gather(lo: int, hi: int) -> None:
            at = index[lo:hi]  # valid indices: "clip" is take's unbuffered mode (with out=), nothing is clipped
            np.take(pairs.listener, at, out=listener[lo:hi], mode="clip")
            np.take(pairs.sender, at, out=sender[lo:hi], mode="clip")
            rank = self._round - held_round[at]
            np.add(first_row[rank], sender[lo:hi], out=message[lo:hi])
            np.take(round_heard_s, rank, out=heard_at[lo:hi], mode="clip")

        self.threads.map_rows(gather, index.size)
        self.listener, self.sender, self.message, self.heard_at = listener, sender, message, heard_at

    def _vet_fast(self, now: float, near: IntArray) -> NDArray[np.bool_] | None:
        """`_vet` for the fast path: which new deliveries (candidates `near`) are refused (None: none); those
        are counted. Every agent's id is its index and there are no intruders (no same-round duplicates)."""
        sec, pairs = self.security, self._pairs
        round_of = np.empty(near.size, dtype=np.int64)

        def gather(lo: int, hi: int) -> None:
            np.take(self._held_round, near[lo:hi], out=round_of[lo:hi], mode="clip")  # (valid: unbuffered mode)

        self.threads.map_rows(gather, near.size)
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
        """`bob_autonomy.core.plausibility.implausible` of the fast path's deliveries (candidates `near`, whose held
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
        verdict[exceeds(claimed_x - x[row], claimed_y - y[row], bound[rank], bound)] = JUMP
        if not limits.max_distance_m > self.range_m * (1.0 + 1e-9):
            listener = pairs.listener[near]
            far_bound = np.array([limits.max_distance_m])
            far = exceeds(claimed_x - x[listener], claimed_y - y[listener], far_bound[np.zeros_like(near)], far_bound)
            verdict[far] = TOO_FAR
        return index, verdict
