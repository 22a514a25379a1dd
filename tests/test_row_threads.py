"""A lockstep fleet's passes in parts on threads (sitl.row_threads): the same bits as in one thread."""

from __future__ import annotations

import itertools
import threading

import numpy as np
import pytest

from behaviors.base import Senses, SwarmTable, View, Wish
from behaviors.registry import BEHAVIORS
from sitl.experiments.scenario import load_scenario
from sitl.fleets.fleet import LockstepFleet
from sitl.row_threads import ONE_THREAD, RowThreads


def test_ranges_cover_the_rows_in_order_as_the_work_allows() -> None:
    threads = RowThreads(3, min_work=10)
    assert threads.ranges(100) == [(0, 33), (33, 66), (66, 100)]
    assert threads.ranges(100, work=25) == [(0, 50), (50, 100)]  # two parts of at least 10 elements of work
    assert threads.ranges(100, work=19) == [(0, 100)]
    assert threads.ranges(2, work=1000) == [(0, 1), (1, 2)]  # never more parts than rows
    assert threads.ranges(0) == [(0, 0)]
    assert ONE_THREAD.ranges(10**7) == [(0, 10**7)]


@pytest.mark.parametrize("threads, min_work", [(0, 1), (1.5, 1), (True, 1), (2, 0)])
def test_bad_settings_are_refused(threads, min_work) -> None:
    with pytest.raises(ValueError, match=r"threads|min_work"):
        RowThreads(threads, min_work=min_work)


def test_parts_run_in_several_threads_and_come_back_in_order() -> None:
    threads = RowThreads(2, min_work=1)
    seen = threads.map_rows(lambda lo, hi: (lo, hi, threading.get_ident()), 10)
    assert [(lo, hi) for lo, hi, _ in seen] == [(0, 5), (5, 10)]
    assert seen[0][2] == threading.get_ident() != seen[1][2]


def test_an_error_in_any_part_reaches_the_caller() -> None:
    def work(lo: int, hi: int) -> int:
        if lo:
            raise ArithmeticError(f"part {lo}..{hi}")
        return hi

    with pytest.raises(ArithmeticError, match=r"part 5\.\.10"):
        RowThreads(2, min_work=1).map_rows(work, 10)


def _fleet_run(name: str, threads: RowThreads, steps: int, **overrides) -> LockstepFleet:
    fleet = LockstepFleet(load_scenario(name).with_overrides(**overrides), threads)
    for _ in range(steps):
        fleet.step()
    return fleet


@pytest.mark.parametrize(
    "name, overrides",
    [
        ("perimeter-defense", {}),  # eBots: walls and sonars
        ("heading-consensus", {}),  # memory fields and a behaviour switched by an event
        ("aggregation", {"fidelity": "kinematic", "agents": 30}),  # eq. (5): the shell of each lattice
    ],
)
def test_a_fleet_stepped_in_parts_is_the_same_to_the_bit(name: str, overrides: dict) -> None:
    """Every pass split, however small (min_work=1): positions, headings, memory and what the radio holds."""
    steps = 250 if name == "heading-consensus" else 150
    whole = _fleet_run(name, ONE_THREAD, steps, **overrides)
    parts = _fleet_run(name, RowThreads(2, min_work=1), steps, **overrides)
    for a, b in [
        (whole.bodies.position, parts.bodies.position),
        (whole.bodies.heading, parts.bodies.heading),
        (whole.medium.listener, parts.medium.listener),
        (whole.medium.message, parts.medium.message),
        (whole.medium.heard_at, parts.medium.heard_at),
        *((whole.table.memory[k], parts.table.memory[k]) for k in whole.table.memory),
    ]:
        assert a.tobytes() == b.tobytes()
    assert whole.medium.counters() == parts.medium.counters()
    assert whole.events_log == parts.events_log


def _random_view(rng: np.random.Generator, n: int, pairs: int, sorted_pairs: bool = True) -> View:
    """n agents (rows 0..n-1 of a table of 2n) hearing random neighbours, with random sonar echoes."""
    rows = 2 * n
    table = SwarmTable(
        ids=np.arange(rows),
        position=rng.uniform(0.0, 20.0, (rows, 2)),
        heading=rng.uniform(-np.pi, np.pi, rows),
        velocity=rng.normal(0.0, 0.3, (rows, 2)),
        memory={"goal": rng.uniform(0.0, 20.0, (rows, 2)), "held_heading": np.full(rows, np.nan)},
    )
    pair_i = rng.integers(0, n, pairs)
    pair_i = np.sort(pair_i) if sorted_pairs else pair_i
    pair_j = rng.integers(0, rows, pairs)
    pair_j[pair_j == pair_i] = rows - 1  # nobody hears itself
    obstacles = rng.uniform(-1.0, 1.0, (rows, 6, 2))
    obstacles[rng.random((rows, 6)) < 0.5] = np.nan
    senses = Senses(obstacles=obstacles, light=np.full((rows, 2), np.nan))
    return View(table, senses, np.arange(n), pair_i.astype(np.intp), pair_j.astype(np.intp), 3.0)


@pytest.mark.parametrize("seed", range(5))
def test_a_rowwise_behaviour_gives_the_same_bits_in_parts(seed: int) -> None:
    """Each behaviour that says it may be stepped in parts (`rowwise`), in its variants: the wishes of the
    parts joined are the wish of the whole, bit for bit."""

    rng = np.random.default_rng(seed)
    view = _random_view(rng, 60, 500)
    variants = {
        "bob-rule": [{}, {"H": 1, "leader_id": 3}, {"nearest": 3}, {"gabriel": True}, {"shell_range": 1.3}],
        "heading-consensus": [{}, {"resilient_f": 1}],
    }
    checked = 0
    for name, cls in BEHAVIORS.items():
        if not cls.rowwise:
            continue
        for params in variants.get(name, [{}]):
            behavior = cls(**params)
            whole = behavior.step(view)
            cuts = sorted(rng.choice(np.arange(1, view.n), size=3, replace=False))
            edges = [0, *cuts, view.n]
            joined = Wish.joined([behavior.step(view.part(lo, hi)) for lo, hi in itertools.pairwise(edges)])
            assert joined.velocity.tobytes() == whole.velocity.tobytes(), (name, params)
            assert joined.heading.tobytes() == whole.heading.tobytes(), (name, params)
            assert joined.memory.keys() == whole.memory.keys()
            for key in whole.memory:
                assert joined.memory[key].tobytes() == whole.memory[key].tobytes(), (name, params, key)
            checked += 1
    assert checked >= 8


def test_a_part_of_pairs_out_of_listener_order_is_refused() -> None:
    view = _random_view(np.random.default_rng(1), 40, 300, sorted_pairs=False)
    assert view.part(0, 20) is None or view.part(20, 40) is None
    ordered = _random_view(np.random.default_rng(1), 40, 300)
    first, second = ordered.part(0, 20), ordered.part(20, 40)
    assert first.pair_i.size + second.pair_i.size == 300
    assert first.n == second.n == 20 and second.pair_i.min() >= 0 and first.pair_i.max() < 20


def test_a_forked_child_makes_its_own_threads() -> None:
    """A pool's threads do not survive fork(): the child must not queue work for threads it does not have."""
    import os
    import signal

    threads = RowThreads(2, min_work=1)
    threads.map_rows(lambda lo, hi: hi, 10)  # the parent's pool exists now
    pid = os.fork()
    if pid == 0:  # the child: exit 0 only if the split work comes back (killed by SIGALRM if it hangs)
        signal.alarm(10)
        try:
            os._exit(0 if threads.map_rows(lambda lo, hi: hi, 10) == [5, 10] else 1)
        finally:
            os._exit(2)
    _, status = os.waitpid(pid, 0)
    assert os.waitstatus_to_exitcode(status) == 0
