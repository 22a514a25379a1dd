"""The medium's fast path (no radio channel, no intruders: sitl.radio.neighbour_pairs' Verlet list and what each
listener holds kept per candidate pair) gives exactly what its general path (sorted keys) gives, round by
round, on random swarms; the Verlet list finds exactly cKDTree.query_pairs' pairs (the squared-length shortcut
of the plausibility jump test: tests/test_norms.py)."""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field

import numpy as np
import pytest
from scipy.spatial import cKDTree

from behaviors.base import MemorySpec
from sitl.radio.medium import BroadcastMedium
from sitl.radio.mesh_security import FaultSpec, MediumSecurity, MeshSecuritySpec, PlausibilitySpec
from sitl.radio.neighbour_pairs import NeighbourPairs

GOAL = {"goal": MemorySpec(shape=(2,))}
CHECKS = PlausibilitySpec(max_speed_mps=2.0, slack_m=3.0)  # Verlet skin: half the slack, 1.5 m


@dataclass
class Case:
    """A random swarm: n agents in a side_m box, each drifting (m per step) with jitter, some jumping up to
    8 m, some switched off and on; the medium's parameters and its security."""

    n: int = 300
    side_m: float = 150.0
    range_m: float = 15.0
    period_s: float = 0.1
    expiry_s: float = 2.5
    latency_s: float | None = 0.1  # None: random each round (rounds arrive out of order in time)
    drift_m: float = 0.03
    jitter_m: float = 0.01
    p_teleport: float = 0.05
    p_toggle: float = 0.02
    spec: MeshSecuritySpec | None = None
    key: bytes | None = None
    security_range_m: float | None = None  # plausibility's radio range (default the medium's)
    ids_change_at: int | None = None  # step at which the agents' ids stop being their indices
    nan_at: int | None = None  # step at which agent 0's position turns NaN
    steps: int = 120
    faults: list[int] = field(default_factory=list)


def make(case: Case, general: bool) -> BroadcastMedium:
    security = None
    if case.spec is not None:
        group = np.zeros(case.n, dtype=np.intp)
        security = MediumSecurity(case.spec, case.key, group, ["a"], case.security_range_m or case.range_m)
    m = BroadcastMedium(case.n, case.range_m, case.period_s, case.expiry_s, GOAL, security=security)
    if general:
        m._pairs = None  # the general path from the first round (what the fast path replaces)
    m.table.ids[: case.n] = np.arange(case.n)
    return m


def run_both(case: Case, seed: int) -> tuple[BroadcastMedium, BroadcastMedium]:
    """Step a fast-path and a general-path medium through the same random rounds, comparing every step."""
    rng = np.random.default_rng(seed)
    fast, general = make(case, False), make(case, True)
    n, dt = case.n, 0.1
    position = rng.uniform(0.0, case.side_m, (n, 2))
    velocity = rng.normal(0.0, case.drift_m, (n, 2))
    active = np.ones(n, dtype=bool)
    for k in range(case.steps):
        t = k * dt
        position += velocity + rng.normal(0.0, case.jitter_m, (n, 2))
        if rng.random() < case.p_teleport:
            jumpers = rng.integers(n, size=3)
            position[jumpers] += rng.uniform(-8.0, 8.0, (3, 2))  # some stay in range of their neighbours
        if rng.random() < case.p_toggle:
            toggled = rng.integers(n, size=max(1, n // 20))
            active[toggled] = ~active[toggled]
        if k == case.nan_at:
            position[0] = np.nan
        listening = active if rng.random() < 0.7 else rng.random(n) < 0.8
        latency = case.latency_s if case.latency_s is not None else float(rng.uniform(0.05, 0.8))
        heading, goal = rng.uniform(-3.0, 3.0, n), rng.normal(size=(n, 2))
        errors = []
        for m in (fast, general):
            if k == case.ids_change_at:
                m.table.ids[:n] = np.roll(np.arange(n), 1)
            m.table.position[:n], m.table.heading[:n], m.table.velocity[:n] = position, heading, 0.1
            m.table.memory["goal"][:n] = goal
            try:
                if m.due(t):
                    m.broadcast(t, active, latency_s=latency)
                errors.append(None)
            except ValueError as error:
                errors.append(str(error))
        assert errors[0] == errors[1]
        if errors[0] is not None:
            return fast, general
        for name in ("listener", "sender", "message", "heard_at"):
            a, b = getattr(fast, name), getattr(general, name)
            assert a.dtype == b.dtype and np.array_equal(a, b), (k, name)
        for a, b in zip(fast.heard(t + dt, listening), general.heard(t + dt, listening), strict=True):
            assert a.dtype == b.dtype and np.array_equal(a, b), k
        assert fast.counters() == general.counters(), k
    return fast, general


KEY = hashlib.sha256(b"fast path").digest()
CASES = {
    "no security": Case(),
    "plausibility, jumps": Case(spec=MeshSecuritySpec(plausibility=CHECKS)),
    "tiny slack (skin 2.5 cm)": Case(
        spec=MeshSecuritySpec(plausibility=PlausibilitySpec(max_speed_mps=0.1, slack_m=0.05)), period_s=0.2
    ),
    "too far": Case(spec=MeshSecuritySpec(plausibility=CHECKS), security_range_m=2.0, drift_m=0.3, p_teleport=0.3),
    "latency varies": Case(spec=MeshSecuritySpec(plausibility=CHECKS), latency_s=None, expiry_s=0.6),
    "broadcast every 1 s": Case(spec=MeshSecuritySpec(plausibility=CHECKS), period_s=1.0, expiry_s=5.0, drift_m=0.5),
    "key, faults": Case(
        n=40,
        side_m=60.0,
        period_s=0.3,
        spec=MeshSecuritySpec(
            key=True, plausibility=CHECKS, window_s=0.3, faults=[FaultSpec(agents=[1, 2], heading_offset_deg=90.0)]
        ),
        key=KEY,
        steps=60,
    ),
    "ids change": Case(spec=MeshSecuritySpec(plausibility=CHECKS), ids_change_at=50, steps=80),
    "non-finite position": Case(spec=MeshSecuritySpec(plausibility=CHECKS), nan_at=30),
}


@pytest.mark.parametrize("name", list(CASES))
def test_fast_path_gives_what_the_general_path_gives(name: str) -> None:
    case = CASES[name]
    for seed in (1, 2):
        fast, general = run_both(case, seed)
        assert general._pairs is None
        if case.ids_change_at is None and case.nan_at is None:
            assert fast._pairs is not None  # it stayed on the fast path
            assert fast.delivered > 0


def test_the_verlet_list_is_reused_between_queries_and_refusals_happen() -> None:
    fast, _ = run_both(Case(spec=MeshSecuritySpec(plausibility=CHECKS), steps=150), seed=3)
    assert fast._pairs.queries < 150 / 3  # drift 3 cm a step, skin 1.5 m: a query every ~20 rounds at most
    assert fast.counters()["mesh"]["rejected"]["jump"]  # teleports were refused as jumps


def test_neighbour_pairs_find_what_query_pairs_finds() -> None:
    rng = np.random.default_rng(4)
    n, range_m = 400, 10.0
    position = rng.uniform(0.0, 100.0, (n, 2))
    position[:20] = np.round(position[:20])  # some on a 1 m grid: pairs exactly at the range
    position[20:40] = position[:20] + np.array([range_m, 0.0])
    pairs = NeighbourPairs(n, range_m, 1.0)
    queries = 0
    for step in range(60):
        members = np.flatnonzero(rng.random(n) < 0.97) if step % 20 == 0 else np.arange(n)
        if pairs.stale(position, members):
            pairs.rebuild(position, members, np.zeros(0, dtype=np.int64))
            queries += 1
        near = pairs.in_range(position)
        found = cKDTree(position[members]).query_pairs(range_m, output_type="ndarray")
        a, b = members[found[:, 0]], members[found[:, 1]]
        expected = np.sort(np.concatenate((a * n + b, b * n + a)))
        assert np.array_equal(pairs.listener[near] * n + pairs.sender[near], expected), step
        position[20:] += rng.normal(0.0, 0.02, (n - 20, 2))
    assert queries < 60


def test_kept_pairs_beyond_the_skin_are_never_in_range() -> None:
    position = np.array([[0.0, 0.0], [5.0, 0.0], [100.0, 0.0]])
    pairs = NeighbourPairs(3, 10.0, 1.0)
    at = pairs.rebuild(position, np.arange(2), np.array([0 * 3 + 2, 2 * 3 + 1], dtype=np.int64))
    assert pairs.keys(at).tolist() == [2, 7]
    near = pairs.in_range(position)
    assert (pairs.listener[near].tolist(), pairs.sender[near].tolist()) == ([0, 1], [1, 0])
