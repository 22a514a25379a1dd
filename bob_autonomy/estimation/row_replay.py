"""Time handling of a bank of EKFs held as rows (the buoy's and the eBot's): each call's readings handled in
order, or by stored-state replay when late, with the per-agent logs that replay needs; the outcome codes and
their counters; the shaping of batch arguments."""

from __future__ import annotations

import bisect
from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from bob_autonomy.estimation.kalman_rows import any_row, every_row
from bob_autonomy.estimation.simple_estimator import FloatArray, IntArray

# What came of a reading: the names the single filters' methods return; the codes are what a bank logs.
OUTCOMES = (
    "predicted", "fused", "init", "gated", "reset", "model_gated", "model_reset", "failed", "rejected", "late",
    "ignored",
)  # fmt: skip
(_PREDICTED, _FUSED, _INIT, _GATED, _RESET, _MODEL_GATED, _MODEL_RESET, _FAILED, _REJECTED, _LATE,
 _IGNORED) = range(len(OUTCOMES))  # fmt: skip


class _ReplayParams(Protocol):
    replay_window_s: float


def _vectors(values: ArrayLike | None, k: int) -> FloatArray | None:
    """(k, 2) float rows (a copy) of a batch argument, broadcast; None stays None."""
    if values is None:
        return None
    arr = np.array(values, dtype=float)
    return arr if arr.shape == (k, 2) else np.array(np.broadcast_to(arr, (k, 2)))


def _scalars(values: ArrayLike, k: int) -> FloatArray:
    """(k,) float values (a copy) of a batch argument, broadcast."""
    arr = np.array(values, dtype=float).reshape(-1)
    return arr if arr.size == k else np.array(np.broadcast_to(arr, (k,)))


def _distinct(idx: IntArray) -> bool:
    """Whether no agent is named twice in a call's rows idx (k,): at once when they are increasing (a fleet's
    calls name its agents in order), else by np.unique."""
    return np.count_nonzero(idx[1:] <= idx[:-1]) == 0 or np.unique(idx).size == idx.size


def _take(data: tuple, rows: ArrayLike) -> tuple:
    """The given rows of each array of a call's data (None stays None)."""
    return tuple(None if values is None else values[rows] for values in data)


class _RowReplay:
    """Time, log and replay of a bank of filters held as rows (a base of the bank, which holds the arrays declared
    here, names in _fields the per-agent arrays a replay snapshot holds, and handles the readings in _handle)."""

    _fields: tuple[str, ...]
    params: _ReplayParams
    t: FloatArray
    _rejected: NDArray[np.int64]
    _late: NDArray[np.int64]
    _pruned: list[list[int]]
    _logs: list[list[list]]
    _times: list[list[float]]

    def _init_replay(self, n: int, fields: tuple[str, ...]) -> None:
        """Empty logs and counters for n agents; fields: the names of the per-agent arrays a snapshot holds."""
        self._fields = fields
        self._rejected = np.zeros(n, dtype=np.int64)
        self._late = np.zeros(n, dtype=np.int64)
        # Outcomes of entries gone from the logs, per agent and outcome (Python ints: one is counted per entry
        # pruned, about one per agent and reading, where a numpy element's increment costs several times more).
        self._pruned = [[0] * len(OUTCOMES) for _ in range(n)]
        # Replay logs, one per agent: entries [t, call, row in call, snapshot block, row in block, outcome].
        self._logs: list[list[list]] = [[] for _ in range(n)]
        self._times: list[list[float]] = [[] for _ in range(n)]

    @staticmethod
    def _batch(agents: ArrayLike, t_s: ArrayLike) -> tuple[IntArray, FloatArray]:
        idx = np.asarray(agents, dtype=np.intp).reshape(-1)
        return idx, _scalars(t_s, idx.size)

    def _submit(self, kind: int, idx: IntArray, t: FloatArray, data: tuple) -> IntArray:
        """Handle a call's readings (rows idx at times t): in order, or by replay; returns the outcome codes."""
        k = idx.size
        if k > 1 and not _distinct(idx):  # an agent twice in one call: one row at a time, in order
            return np.concatenate(
                [self._submit(kind, idx[i : i + 1], t[i : i + 1], _take(data, [i])) for i in range(k)]
            )
        good = np.isfinite(t)
        for values in data:
            if values is not None:
                good &= np.isfinite(values.reshape(k, -1)).all(axis=1)
        clock = self.t[idx]
        in_order = good & ~(t < clock)  # NaN clock (no reading yet): in order
        if every_row(in_order):  # the usual case: every reading finite and in time order
            return self._run(kind, idx, t, data)
        codes = np.full(k, _REJECTED)
        if not every_row(good):
            np.add.at(self._rejected, idx[~good], 1)
        late = good & (t < clock)
        if any_row(in_order):
            rows = np.flatnonzero(in_order)
            codes[rows] = self._run(kind, idx[rows], t[rows], _take(data, rows))
        if any_row(late):
            rows = late.nonzero()[0]
            codes[rows] = self._replay(kind, idx[rows], t[rows], _take(data, rows))
        return codes

    def _run(self, kind: int, idx: IntArray, t: FloatArray, data: tuple) -> IntArray:
        """In-order readings: handle, log with a snapshot, prune the logs."""
        codes = self._handle(kind, idx, t, data)
        call = (kind, data)
        block = self._snapshot(idx)
        # Keep the window's entries and the one before (the state to restart from): cut at filter time - window.
        cuts = (self.t[idx] - self.params.replay_window_s).tolist()
        pruned, logs, all_times = self._pruned, self._logs, self._times
        for r, (a, ta, code, cut) in enumerate(zip(idx.tolist(), t.tolist(), codes.tolist(), cuts, strict=True)):
            log, times = logs[a], all_times[a]
            log.append([ta, call, r, block, r, code])
            times.append(ta)
            if len(times) > 1 and times[1] <= cut:
                j = bisect.bisect_right(times, cut) - 1
                counts = pruned[a]
                for entry in log[:j]:
                    counts[entry[5]] += 1
                del log[:j], times[:j]
        return codes

    def _replay(self, kind: int, idx: IntArray, t: FloatArray, data: tuple) -> IntArray:
        """Late readings: back to the state just before each, fuse it there, re-run the later entries."""
        codes = np.full(idx.size, _LATE)
        live: list[tuple[int, int, int]] = []  # (row in this call, agent, insertion index in its log)
        older: list[int] = []  # rows older than their agent's whole log
        restore: dict[int, tuple[tuple, list[int], list[int]]] = {}
        for r, (a, ta) in enumerate(zip(idx.tolist(), t.tolist(), strict=True)):
            times = self._times[a]
            if not times or ta < times[0]:
                older.append(r)
                continue
            j = bisect.bisect_right(times, ta)  # >= 1
            previous = self._logs[a][j - 1]
            group = restore.setdefault(id(previous[3]), (previous[3], [], []))
            group[1].append(a)
            group[2].append(previous[4])
            live.append((r, a, j))
        if older:
            rows_older = np.array(older)
            codes[rows_older] = self._older_than_log(kind, idx[rows_older], t[rows_older], _take(data, rows_older))
        if not live:
            return codes
        for block, agents, rows in restore.values():
            self._restore(np.array(agents), block, np.array(rows))
        rows_in_call = np.array([r for r, _, _ in live])
        agents = idx[rows_in_call]
        sub = _take(data, rows_in_call)
        new_codes = self._handle(kind, agents, t[rows_in_call], sub)
        codes[rows_in_call] = new_codes
        call = (kind, sub)
        block = self._snapshot(agents)
        pending: list[tuple[int, list]] = []
        for n, ((r, a, j), code) in enumerate(zip(live, new_codes.tolist(), strict=True)):
            self._logs[a].insert(j, [float(t[r]), call, n, block, n, code])
            self._times[a].insert(j, float(t[r]))
            pending.append((a, self._logs[a][j + 1 :]))
        depth = 0
        while True:  # re-run the later entries, round by round; the agents of one logged call together
            groups: dict[int, list[tuple[int, list]]] = {}
            for a, entries in pending:
                if depth < len(entries):
                    groups.setdefault(id(entries[depth][1]), []).append((a, entries[depth]))
            if not groups:
                break
            for members in groups.values():
                kind_e, data_e = members[0][1][1]
                agents_e = np.array([a for a, _ in members])
                t_e = np.array([e[0] for _, e in members])
                redo = self._handle(kind_e, agents_e, t_e, _take(data_e, [e[2] for _, e in members]))
                block_e = self._snapshot(agents_e)
                for n, ((_, entry), code) in enumerate(zip(members, redo.tolist(), strict=True)):
                    entry[3], entry[4], entry[5] = block_e, n, code
            depth += 1
        return codes

    def _older_than_log(self, kind: int, idx: IntArray, t: FloatArray, data: tuple) -> IntArray:
        """Readings older than everything their agents' logs hold, so no state to replay them from: counted
        late (a bank may take some otherwise, see BuoyEkfBank)."""
        np.add.at(self._late, idx, 1)
        return np.full(idx.size, _LATE)

    def _snapshot(self, idx: IntArray) -> tuple:
        return tuple(getattr(self, name)[idx] for name in self._fields)  # fancy indexing copies

    def _restore(self, idx: IntArray, block: tuple, rows: IntArray) -> None:
        for name, values in zip(self._fields, block, strict=True):
            getattr(self, name)[idx] = values[rows]

    def _handle(self, kind: int, idx: IntArray, t: FloatArray, data: tuple) -> IntArray:
        raise NotImplementedError

    # ------------------------------------------------------------ counters

    def outcome_counts(self, outcome: str) -> NDArray[np.int64]:
        """(N,) how many readings of each agent had this outcome (one of OUTCOMES), replays accounted for."""
        code = OUTCOMES.index(outcome)
        if code == _REJECTED:
            return self._rejected.copy()
        if code == _LATE:
            return self._late.copy()
        live = np.array([sum(e[5] == code for e in log) for log in self._logs], dtype=np.int64)
        return np.array([counts[code] for counts in self._pruned], dtype=np.int64) + live

    @property
    def rejected(self) -> int:
        """Non-finite readings (never fused)."""
        return int(self._rejected.sum())

    @property
    def late(self) -> int:
        """Readings older than the replay window."""
        return int(self._late.sum())

    @property
    def gated(self) -> int:
        """Sensor readings rejected by the innovation gate."""
        return int(self.outcome_counts("gated").sum())

    @property
    def resets(self) -> int:
        """Re-initialisations after gate_reset_count consecutive gated readings of one sensor."""
        return int(self.outcome_counts("reset").sum())

    @property
    def failures(self) -> int:
        """Steps undone because they would have left a non-finite or non-positive-definite state."""
        return int(self.outcome_counts("failed").sum())
