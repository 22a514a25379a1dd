"""BroadcastMedium (sitl/radio/medium.py): who hears whom, for how long, and the counters."""

from __future__ import annotations

import math

import numpy as np
import pytest
from numpy.testing import assert_allclose

from behaviors.base import MemorySpec
from sitl.radio.medium import BroadcastMedium

ALL3 = np.ones(3, dtype=bool)


def medium(
    positions: list[list[float]],
    range_m: float = 10.0,
    period_s: float = 0.5,
    expiry_s: float = 2.0,
    memory: dict[str, MemorySpec] | None = None,
) -> BroadcastMedium:
    m = BroadcastMedium(len(positions), range_m, period_s, expiry_s, memory or {})
    n = len(positions)
    m.table.ids[:n] = np.arange(n)
    m.table.position[:n] = positions
    return m


def heard_pairs(m: BroadcastMedium, t: float, active: np.ndarray) -> dict[tuple[int, int], tuple[int, float]]:
    """(listener, sender id) -> (message row, age s), checking there is one entry per pair."""
    listener, message, age = m.heard(t, active)
    out = {}
    for i, row, a in zip(listener.tolist(), message.tolist(), age.tolist(), strict=True):
        key = (i, int(m.table.ids[row]))
        assert key not in out, f"two entries for listener {i}, sender {key[1]}"
        out[key] = (row, a)
    return out


def line3() -> BroadcastMedium:
    # 0 at x = 0 and 1 at x = 5 are 5 m apart (in range 10); 2 at x = 20 is 15 and 20 m away (out of range).
    return medium([[0.0, 0.0], [5.0, 0.0], [20.0, 0.0]])


def test_rejects_non_positive_parameters() -> None:
    for args in ((0.0, 0.1, 1.0), (10.0, 0.0, 1.0), (10.0, 0.1, -1.0)):
        with pytest.raises(ValueError):
            BroadcastMedium(2, *args, {})


def test_in_range_hear_each_other_out_of_range_do_not() -> None:
    m = line3()
    m.broadcast(0.0, ALL3)
    heard = heard_pairs(m, 0.0, ALL3)
    assert set(heard) == {(0, 1), (1, 0)}
    # Messages of round 0 (slot 0) sit at table rows N + 0 * N + sender = 3 + sender.
    assert heard[(0, 1)] == (4, 0.0)
    assert heard[(1, 0)] == (3, 0.0)
    assert_allclose(m.table.position[4], [5.0, 0.0])


def test_range_uses_current_positions() -> None:
    m = line3()
    m.broadcast(0.0, ALL3)
    # Agent 2 comes to x = 12: 7 m from agent 1 (in range), 12 m from agent 0 (out of range).
    m.table.position[2] = [12.0, 0.0]
    m.broadcast(0.5, ALL3)
    assert set(heard_pairs(m, 0.5, ALL3)) == {(0, 1), (1, 0), (1, 2), (2, 1)}


def test_message_heard_until_expiry_then_gone() -> None:
    m = line3()
    m.broadcast(0.0, ALL3)
    # Expiry 2.0 s after hearing: still there at 1.9 s (age 1.9), gone at 2.1 s.
    heard = heard_pairs(m, 1.9, ALL3)
    assert set(heard) == {(0, 1), (1, 0)}
    assert heard[(0, 1)][1] == pytest.approx(1.9)
    assert heard_pairs(m, 2.1, ALL3) == {}


def test_newer_message_replaces_older_one() -> None:
    m = line3()
    m.broadcast(0.0, ALL3)
    m.table.position[1] = [6.0, 0.0]
    m.broadcast(0.5, ALL3)
    heard = heard_pairs(m, 0.5, ALL3)  # one entry per (listener, sender) is checked inside
    assert set(heard) == {(0, 1), (1, 0)}
    # Round 1 (slot 1) rows: 3 + 1 * 3 + sender; the newer message carries the new position.
    assert heard[(0, 1)] == (7, 0.0)
    assert_allclose(m.table.position[7], [6.0, 0.0])
    # The old message in slot 0 is kept in the ring buffer, unchanged, but no longer heard.
    assert_allclose(m.table.position[4], [5.0, 0.0])
    assert len(m.listener) == 2


def test_ring_buffer_reuses_slots() -> None:
    m = line3()
    # ceil(2.0 / 0.5) + 1 = 5 rounds kept: capacity 5 * 3 = 15 rows after the 3 agent rows.
    assert m.capacity == 15
    assert len(m.table) == 18
    for k in range(7):
        m.broadcast(0.5 * k, ALL3)
        # The message of sender 1 heard by 0 after round k is in slot k mod 5.
        assert heard_pairs(m, 0.5 * k, ALL3)[(0, 1)][0] == 3 + (k % 5) * 3 + 1


def test_removed_agent_stops_broadcasting_but_is_heard_until_expiry() -> None:
    m = line3()
    m.broadcast(0.0, ALL3)
    active = np.array([True, False, True])
    m.table.position[1] = [1.0, 0.0]  # it moves (or is carried) after removal: nobody learns about it
    for k in range(1, 6):
        t = 0.5 * k
        m.broadcast(t, active)
        heard = heard_pairs(m, t, active)
        if t < 2.0:
            # Agent 0 still holds 1's last message (sent at 0, at x = 5); agent 1 hears nothing (inactive).
            assert set(heard) == {(0, 1)}
            row, age = heard[(0, 1)]
            assert age == pytest.approx(t)
            assert_allclose(m.table.position[row], [5.0, 0.0])
        if t > 2.0:
            assert heard == {}
    # Between rounds, at 1.9 s, the message is 1.9 s old: still heard.
    m2 = line3()
    m2.broadcast(0.0, ALL3)
    m2.broadcast(0.5, active)
    m2.broadcast(1.0, active)
    m2.broadcast(1.5, active)
    assert set(heard_pairs(m2, 1.9, active)) == {(0, 1)}
    # Expired by 2.1 s, even without another round.
    assert heard_pairs(m2, 2.1, active) == {}


def test_inactive_listener_hears_nothing() -> None:
    m = line3()
    m.broadcast(0.0, ALL3)
    assert set(heard_pairs(m, 0.1, np.array([True, False, True]))) == {(0, 1)}


def test_broadcast_period_is_respected() -> None:
    m = line3()
    assert m.due(0.0)
    m.broadcast(0.0, ALL3)
    assert not m.due(0.4)
    assert m.due(0.5)
    assert m.due(0.5 - 1e-10)  # accumulated float error of the step clock is tolerated
    m.broadcast(0.5, ALL3)
    assert not m.due(0.99)
    assert m.due(1.0)


def test_late_broadcast_skips_missed_rounds() -> None:
    m = line3()
    m.broadcast(0.0, ALL3)
    # Next round was due at 0.5; a broadcast at 1.3 covers rounds 0.5 and 1.0: next due 1.5, not 1.0 or 1.8.
    m.broadcast(1.3, ALL3)
    assert not m.due(1.49)
    assert m.due(1.5)


def test_sent_and_delivered_counters() -> None:
    # A 3 m square (corners 0..3) in 3.5 m range: 4 sides in range, diagonals (4.24 m) not; agent 4 far away.
    m = medium([[0.0, 0.0], [3.0, 0.0], [3.0, 3.0], [0.0, 3.0], [100.0, 100.0]], range_m=3.5, period_s=0.2)
    everyone = np.ones(5, dtype=bool)
    for k in range(3):
        m.broadcast(0.2 * k, everyone)
    # Per round: 5 sent, 4 undirected pairs = 8 deliveries.
    assert (m.sent, m.delivered) == (15, 24)
    assert len(heard_pairs(m, 0.4, everyone)) == 8
    without0 = np.array([False, True, True, True, True])
    m.broadcast(0.6, without0)
    # 4 sent; sides 1-2 and 2-3 remain: 4 deliveries.
    assert (m.sent, m.delivered) == (19, 28)
    heard = heard_pairs(m, 0.6, without0)
    # 1 and 3 still hold 0's message of 0.4 s (age 0.2 s); 0 itself hears nothing now.
    assert set(heard) == {(1, 0), (1, 2), (2, 1), (2, 3), (3, 2), (3, 0)}
    assert heard[(1, 0)][1] == pytest.approx(0.2)
    assert heard[(1, 2)][1] == 0.0


def test_memory_fields_are_broadcast() -> None:
    m = medium([[0.0, 0.0], [1.0, 0.0]], memory={"target": MemorySpec(shape=(2,)), "level": MemorySpec(fill=-1.0)})
    assert np.all(np.isnan(m.table.memory["target"]))
    assert np.all(m.table.memory["level"] == -1.0)
    m.table.memory["target"][1] = [3.0, 4.0]
    m.table.memory["level"][1] = 2.0
    both = np.ones(2, dtype=bool)
    m.broadcast(0.0, both)
    row, _ = heard_pairs(m, 0.0, both)[(0, 1)]
    assert_allclose(m.table.memory["target"][row], [3.0, 4.0])
    assert m.table.memory["level"][row] == 2.0
    # A later change of the sender's own row does not alter the message already sent.
    m.table.memory["level"][1] = math.pi
    assert m.table.memory["level"][row] == 2.0


def test_each_listener_hears_its_senders_in_id_order() -> None:
    # Four agents all within range of each other, then agent 0 falls silent: its old message stays heard.
    m = medium([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])
    everyone = np.ones(4, dtype=bool)
    m.broadcast(0.0, everyone)
    m.broadcast(0.5, np.array([False, True, True, True]))
    listener, message, _age = m.heard(0.5, everyone)
    for i in range(4):
        senders = m.table.ids[message[listener == i]].tolist()
        assert senders == sorted(senders), f"listener {i} hears {senders}"
