"""The lockstep medium's mesh security (sitl.radio.medium + sitl.radio.mesh_security): intruders, key, plausibility,
faults."""

from __future__ import annotations

import hashlib
import math

import numpy as np
import pytest

from behaviors.base import MemorySpec
from sitl.radio.medium import BroadcastMedium
from sitl.radio.mesh_security import IntruderSpec, MediumSecurity, MeshSecuritySpec, PlausibilitySpec

KEY = hashlib.sha256(b"lockstep fleet").digest()
GOAL = {"goal": MemorySpec(shape=(2,))}


def medium(
    positions: list[list[float]],
    spec: MeshSecuritySpec,
    key: bytes | None = None,
    range_m: float = 300.0,
    groups: list[int] | None = None,
) -> BroadcastMedium:
    n = len(positions)
    group_of = np.array(groups if groups is not None else [0] * n, dtype=np.intp)
    security = MediumSecurity(spec, key, group_of, ["a", "b"][: int(group_of.max()) + 1], range_m)
    m = BroadcastMedium(n, range_m, 1.0, 5.0, GOAL, security=security)
    m.table.ids[:n] = np.arange(n)
    m.table.position[:n] = positions
    return m


def heard_from(m: BroadcastMedium, listener: int, t: float) -> dict[int, tuple[float, float]]:
    """Agent id -> claimed position of what `listener` holds at t, checking one message per id."""
    active = np.ones(m.n, dtype=bool)
    who, rows, _ = m.heard(t, active)
    out: dict[int, tuple[float, float]] = {}
    for i, row in zip(who.tolist(), rows.tolist(), strict=True):
        if i == listener:
            agent = int(m.table.ids[row])
            assert agent not in out, f"listener {listener} holds two messages from agent {agent}"
            out[agent] = tuple(m.table.position[row].tolist())
    return out


def refused(m: BroadcastMedium) -> dict[str, dict[str, int]]:
    """The reasons under which something was refused (metrics.json lists every reason)."""
    return {reason: by_id for reason, by_id in m.counters()["mesh"]["rejected"].items() if by_id}


def run_rounds(m: BroadcastMedium, rounds: int, move=None) -> None:
    active = np.ones(m.n, dtype=bool)
    for k in range(rounds):
        if move is not None:
            move(m, k)
        m.broadcast(float(k), active, latency_s=0.5)


INTRUDER = IntruderSpec(claims_agent=0, position=(0.0, 250.0))  # 250 m from both members
OPEN = MeshSecuritySpec(plausibility=PlausibilitySpec(enabled=False), intruders=[INTRUDER])


def test_without_defences_an_intruder_takes_agent_0s_place() -> None:
    m = medium([[0.0, 0.0], [10.0, 0.0]], OPEN)
    run_rounds(m, 3)
    # Agent 1 holds one message from "agent 0": the intruder's (read after the real one in each round);
    # agent 0 never holds a message claiming its own id.
    assert heard_from(m, 1, 2.5) == {0: (0.0, 250.0)}
    assert heard_from(m, 0, 2.5) == {1: (10.0, 0.0)}
    assert m.counters()["mesh"]["rejected_total"] == 0
    assert m.counters()["mesh"]["intruder_sent"] == 3


def test_with_the_key_every_intruder_packet_is_refused_as_unsigned_and_counted() -> None:
    spec = MeshSecuritySpec(key=True, plausibility=PlausibilitySpec(enabled=False), intruders=[INTRUDER])
    m = medium([[0.0, 0.0], [10.0, 0.0]], spec, key=KEY)
    run_rounds(m, 3)
    assert heard_from(m, 1, 2.5) == {0: (0.0, 0.0)}
    assert heard_from(m, 0, 2.5) == {1: (10.0, 0.0)}
    mesh = m.counters()["mesh"]
    # Agent 1 hears the intruder in each of 3 rounds (agent 0 ignores packets claiming its own id).
    assert refused(m) == {"unsigned": {"0": 3}}
    assert mesh["intruder_delivered"] == 3
    # The packets were really encoded and signed: 38 bytes + goal (1 + 8) + the 14-byte trailer.
    assert mesh["packet_bytes"] == m.payload_bytes == 61


def test_plausibility_alone_refuses_an_intruder_that_claims_a_jump_from_the_real_agent() -> None:
    spec = MeshSecuritySpec(intruders=[INTRUDER])
    m = medium([[0.0, 0.0], [10.0, 0.0]], spec)
    run_rounds(m, 4)
    assert heard_from(m, 1, 3.5) == {0: (0.0, 0.0)}
    # Round 0: the real agent 0 is taken first, the intruder's packet of the same round is judged against it.
    assert refused(m) == {"jump": {"0": 4}}


def test_a_claimed_position_beyond_radio_range_is_refused_as_too_far() -> None:
    liar = IntruderSpec(claims_agent=7, position=(5.0, 0.0), claimed_position=(5000.0, 0.0))
    m = medium([[0.0, 0.0], [10.0, 0.0]], MeshSecuritySpec(intruders=[liar]))
    run_rounds(m, 2)
    assert 7 not in heard_from(m, 0, 1.5)
    assert refused(m) == {"too_far": {"7": 4}}


def test_an_intruder_beyond_its_reach_is_not_heard_and_one_with_more_reach_is() -> None:
    far = IntruderSpec(claims_agent=5, position=(0.0, 400.0))
    m = medium([[0.0, 0.0]], MeshSecuritySpec(plausibility=PlausibilitySpec(enabled=False), intruders=[far]))
    run_rounds(m, 2)
    assert m.counters()["mesh"]["intruder_delivered"] == 0
    strong = IntruderSpec(claims_agent=5, position=(0.0, 400.0), reach_m=600.0)
    m = medium([[0.0, 0.0]], MeshSecuritySpec(plausibility=PlausibilitySpec(enabled=False), intruders=[strong]))
    run_rounds(m, 2)
    assert heard_from(m, 0, 1.5) == {5: (0.0, 400.0)}


def test_a_member_that_jumps_is_refused_until_its_old_message_expires() -> None:
    m = medium([[0.0, 0.0], [10.0, 0.0]], MeshSecuritySpec())

    def teleport(medium_: BroadcastMedium, k: int) -> None:
        if k == 2:
            medium_.table.position[1] = [110.0, 0.0]  # a filter reset moves agent 1's belief 100 m

    run_rounds(m, 9, teleport)
    rejected = refused(m)
    # Rounds 2..6 are refused (heard at 2.5 .. 6.5 s, the old message heard at 1.5 s: 20 + 2 x 5 = 30 m at
    # most); by round 7 (heard 7.5 s) the old message has expired (5 s) and the new position is accepted.
    assert rejected == {"jump": {"1": 5}}
    assert heard_from(m, 0, 8.5) == {1: (110.0, 0.0)}


def test_faulty_members_broadcast_their_heading_turned_but_keep_their_own() -> None:
    spec = MeshSecuritySpec(faults=[{"group": "b", "heading_offset_deg": 120.0}])
    m = medium([[0.0, 0.0], [10.0, 0.0]], spec, groups=[0, 1])
    m.table.heading[:2] = [0.0, math.radians(100.0)]
    run_rounds(m, 1)
    active = np.ones(2, dtype=bool)
    who, rows, _ = m.heard(0.5, active)
    by_listener = dict(zip(who.tolist(), rows.tolist(), strict=True))
    assert math.degrees(m.table.heading[by_listener[0]]) == pytest.approx(-140.0)  # 100 + 120, wrapped
    assert m.table.heading[by_listener[1]] == 0.0  # the honest one as it is
    assert math.degrees(m.table.heading[1]) == pytest.approx(100.0)  # its own row untouched


def test_faults_and_intruders_are_checked_against_the_groups_and_agents() -> None:
    with pytest.raises(ValueError, match="not a group"):
        MediumSecurity(
            MeshSecuritySpec(faults=[{"group": "nobody", "heading_offset_deg": 1.0}]),
            None,
            np.zeros(2, dtype=np.intp),
            ["a"],
            300.0,
        )
    with pytest.raises(ValueError, match="agent 5 does not exist"):
        MediumSecurity(
            MeshSecuritySpec(faults=[{"agents": [5], "heading_offset_deg": 1.0}]),
            None,
            np.zeros(2, dtype=np.intp),
            ["a"],
            300.0,
        )


def test_a_key_with_too_many_memory_values_is_refused_before_the_run() -> None:
    spec = MeshSecuritySpec(key=True)
    security = MediumSecurity(spec, KEY, np.zeros(2, dtype=np.intp), ["a"], 300.0)
    m = BroadcastMedium(2, 300.0, 1.0, 5.0, {"big": MemorySpec(shape=(13,))}, security=security)
    assert m.payload_bytes == 105  # over the XBee's 100: the channel model would refuse it
    with pytest.raises(ValueError, match="105 bytes"):
        m.broadcast(0.0, np.ones(2, dtype=bool))


def test_a_process_fleet_gets_the_lockstep_runs_key_and_reads_what_its_vessels_refused(tmp_path) -> None:
    import json
    import os

    from sitl.experiments.scenario import load_scenario
    from sitl.radio.mesh_security import medium_security, mesh_log_counters, write_fleet_key

    scenario = load_scenario("leader-follower-intruder")
    path = write_fleet_key(scenario, tmp_path)
    assert path is not None and os.stat(path).st_mode & 0o777 == 0o600
    group_of = np.repeat(np.arange(3), [g.count for g in scenario.groups])
    assert path.read_bytes() == medium_security(scenario, group_of).key and len(path.read_bytes()) == 32
    assert write_fleet_key(load_scenario("leader-follower"), tmp_path / "none") is None  # no key: no file

    line = {"sent": 5, "rejected": {"unsigned": {"0": 23}, "stale": {}}, "implausible": {"jump": {"4": 2}}}
    (tmp_path / "vessel-02.log").write_text("start\nvessel 2 stopped: {}\nvessel 2 mesh: " + json.dumps(line) + "\n")
    (tmp_path / "vessel-03.log").write_text("vessel 3 stopped: {}\n")  # killed before it could say
    report = mesh_log_counters({2: tmp_path / "vessel-02.log", 3: tmp_path / "vessel-03.log"})
    assert report == {"rejected_total": 25, "by_vessel": {"2": line}, "unreported": [3]}
