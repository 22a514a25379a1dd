"""Why the paper's eBots took seconds to agree on a heading, and why that cannot also give a fast follow.

Issue 14 item 4 asks for a physics model in which heading consensus agrees within a factor of 2 of the paper's
"about 11 s" and still follows a leader turned 90 degrees away within 5 degrees by t = 40 s (18 s after the leader
appears at t = 22 s). These tests pin the two facts that decide it, on the project's own code.

1. Rounds (behaviour only). On a complete graph of 10, one synchronous round of eq. (2) agrees exactly (every
   agent averages the same 10 vectors), while followers of a leader 90 degrees off need 30 rounds to come within
   5 degrees of it (each round keeps about 9/10 of their offset). Whatever sets the length of a round
   (broadcast period, update period, Bluetooth round trips), following takes about 30 rounds and agreeing one or
   two: no round length gives agreement after 5.5 s and following within 18 s.

2. The paper's own software, emulated (simulator). The eBots ran marabunta (the paper's footnote
   github.com/david-mateo/marabunta; examples/dr3demo/heading.py and leader.py run "the Taurus (eBot + Raspberry
   + XBee) platform used in SUTD's MEC lab"): `XBeeExpirationNetwork(1.4, slot, slot + 0.1, 1, ID)` sends one
   state per second in the robot's own 0.1 s slot; `send_state` queues a state only when the outbox is empty,
   so the state sent is the one queued just after the previous send (about 0.9 s old); a receiver drops it 1.4 s
   after it was made (so each neighbour is heard only about half of each second); `HeadingConsensusRobot` aims
   at the circular mean of the neighbours heard (not itself); `ebotBody.move_background` turns the robot at
   omega = (3 / pi) * error rad/s every 0.1 s ("too big and the robot oscillates": each cycle is a Bluetooth
   round trip, `2P` then `8w`). The emulation below does exactly that on top of the simulator's medium (which
   broadcasts every 0.1 s, so the slot schedule is carried in the broadcast memory fields) and through the
   kinematic eBot's turning law (omega = 4 * (wish - heading), sitl.vehicles.bodies): the wish is heading + (3/pi)/4 *
   error. It agrees in 3-5 s and is still about 45 degrees off the leader at t = 40 s (about 60-80 s to
   follow within 5 degrees at physics fidelity).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import pytest
from behavior_helpers import make_table, make_view

from behaviors import registry
from behaviors.base import Behavior, MemorySpec, View, Wish, heading_vectors, wrap_angle
from behaviors.heading_consensus import HeadingConsensus
from sitl.experiments.runner import simulate
from sitl.experiments.scenario import validate_scenario

DEG = math.pi / 180.0
TOLERANCE_DEG = 5.0


def spread_deg(headings: np.ndarray) -> float:
    """Largest deviation (deg) of any heading from the circular mean (as sitl.experiments.metrics measures it)."""
    mean = math.atan2(np.sin(headings).mean(), np.cos(headings).mean())
    return float(np.degrees(np.abs(wrap_angle(headings - mean))).max())


# ----------------------------------------------------------------------------- 1. rounds


def rounds_to_agree(headings: np.ndarray) -> int:
    """Synchronous rounds of eq. (2) on a complete graph until every heading is within 5 deg of the mean."""
    n = headings.size
    table = make_table(np.column_stack((np.arange(n), np.zeros(n))).tolist(), headings=headings.tolist())
    rounds = 0
    while spread_deg(table.heading) > TOLERANCE_DEG:
        table.heading = HeadingConsensus().step(make_view(table)).heading.copy()
        rounds += 1
    return rounds


def rounds_to_follow(n: int, leader_offset_deg: float) -> int:
    """Synchronous rounds until n - 1 agreed followers are within 5 deg of a leader `leader_offset_deg` away."""
    headings = np.zeros(n)
    headings[0] = leader_offset_deg * DEG
    table = make_table(np.column_stack((np.arange(n), np.zeros(n))).tolist(), headings=headings.tolist())
    followers = list(range(1, n))
    pairs = [(k, j) for k, i in enumerate(followers) for j in range(n) if j != i]  # complete graph
    rounds = 0
    while np.degrees(np.abs(wrap_angle(table.heading[1:] - table.heading[0]))).max() > TOLERANCE_DEG:
        table.heading[1:] = HeadingConsensus().step(make_view(table, pairs=pairs, rows=followers)).heading
        rounds += 1
    return rounds


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_one_synchronous_round_of_eq2_agrees_on_a_complete_graph(seed: int) -> None:
    headings = np.random.default_rng(seed).uniform(-math.pi, math.pi, 10)
    assert spread_deg(headings) > 90.0
    assert rounds_to_agree(headings) == 1


def test_following_a_leader_90_degrees_off_takes_30_rounds() -> None:
    # Each round a follower aims at the circular mean of 9 followers and the leader: its offset shrinks by
    # atan2(sin d, 9 + cos d) (6.3 deg the first round, then nearly d / 10): 30 rounds to within 5 deg.
    assert rounds_to_follow(10, 90.0) == 30


def test_no_round_length_agrees_after_5_5_s_and_follows_within_18_s() -> None:
    follow_rounds = rounds_to_follow(10, 90.0)
    longest_round_s = 18.0 / follow_rounds  # t = 22 s to t = 40 s
    agree_rounds = max(rounds_to_agree(np.random.default_rng(s).uniform(-math.pi, math.pi, 10)) for s in range(20))
    assert agree_rounds * longest_round_s < 11.0 / 2.0


# ----------------------------------------------------------------------------- 2. the paper's software

SLOT_PERIOD_S = 1.0  # XBeeExpirationNetwork(..., period=1): one message per robot per second
SLOT_S = 0.1  # its window: [slot, slot + 0.1) of each second, slot = 0.1 * robot number
EXPIRY_S = 1.4  # dropped 1.4 s after the sender made it (sender's clock)
MARABUNTA_GAIN_PER_S = 3.0 / math.pi  # ebotBody.move_background: omega = gain * heading error
SIM_TURN_GAIN_PER_S = 4.0  # sitl.vehicles.bodies: the kinematic eBot turns at omega = 4 * (wish - heading)
FIELDS = {name: MemorySpec() for name in ("queued_heading", "queued_t", "sent_heading", "sent_t")}


def xbee_schedule(view: View) -> dict[str, np.ndarray]:
    """marabunta's XBeeNetwork for the updated rows: in its slot a robot sends what it queued (and empties the
    queue); out of it, an empty queue takes the current heading (send_state only fills an empty outbox)."""
    memory = {name: view.table.memory[name][view.rows].copy() for name in FIELDS}
    slot = (view.table.ids[view.rows] % 10) * SLOT_S
    in_slot = np.mod(view.t - slot + 1e-9, SLOT_PERIOD_S) < SLOT_S - 1e-9
    send = in_slot & np.isfinite(memory["queued_t"])
    memory["sent_heading"][send], memory["sent_t"][send] = memory["queued_heading"][send], memory["queued_t"][send]
    memory["queued_heading"][send], memory["queued_t"][send] = np.nan, np.nan
    fill = ~in_slot & ~np.isfinite(memory["queued_t"])
    memory["queued_heading"][fill], memory["queued_t"][fill] = view.heading[fill], view.t
    return memory


def marabunta_wish(view: View, target: np.ndarray) -> np.ndarray:
    """Wished heading that makes the simulator's eBot turn at marabunta's omega = (3/pi) * error."""
    return wrap_angle(view.heading + MARABUNTA_GAIN_PER_S / SIM_TURN_GAIN_PER_S * wrap_angle(target - view.heading))


@dataclass
class MarabuntaConsensus(Behavior):
    """HeadingConsensusRobot.update: aim at the circular mean of the neighbours heard (their sent headings)."""

    name: ClassVar[str] = "test-marabunta-consensus"
    memory_fields: ClassVar[dict[str, MemorySpec]] = FIELDS

    def step(self, view: View) -> Wish:
        sent_t = view.table.memory["sent_t"][view.pair_j]
        heard = view.restrict(np.isfinite(sent_t) & (view.t < sent_t + EXPIRY_S))
        total = heard.sum_pairs(heading_vectors(view.table.memory["sent_heading"][heard.pair_j]))
        some = np.hypot(total[:, 0], total[:, 1]) > 1e-12
        target = np.where(some, np.arctan2(total[:, 1], total[:, 0]), view.heading)
        return Wish(np.zeros((view.n, 2)), marabunta_wish(view, target), xbee_schedule(view))


@dataclass
class MarabuntaLeader(Behavior):
    """The leader: holds its heading + 90 deg, broadcasting on the same schedule."""

    name: ClassVar[str] = "test-marabunta-leader"
    memory_fields: ClassVar[dict[str, MemorySpec]] = {**FIELDS, "held_heading": MemorySpec()}

    def step(self, view: View) -> Wish:
        held = view.table.memory["held_heading"][view.rows].copy()
        held = wrap_angle(np.where(np.isnan(held), view.heading + 90.0 * DEG, held))
        return Wish(np.zeros((view.n, 2)), marabunta_wish(view, held), {**xbee_schedule(view), "held_heading": held})


START = {"box": {"min": [0.0, 0.0], "max": [3.0, 3.0]}, "heading_deg": "random", "min_separation_m": 0.4}


def marabunta_scenario(seed: int):
    """The packaged heading-consensus (10 eBots, leader at 22 s) with marabunta's network and turning."""
    return validate_scenario(
        {
            "name": "heading-consensus-marabunta",
            "duration_s": 45.0,
            "dt_s": 0.1,
            "seed": seed,
            "log_period_s": 0.1,
            "network": {"range_m": 50.0, "broadcast_period_s": 0.1, "expiry_s": 1.0},
            "groups": [
                {
                    "name": "ebots",
                    "count": 10,
                    "body": "ebot",
                    "behavior": MarabuntaConsensus.name,
                    "start": START,
                }
            ],
            "events": [
                {"t_s": 22.0, "action": "set-behavior", "agents": [0], "choice": {"behavior": MarabuntaLeader.name}}
            ],
            "metrics": {"kind": "heading-consensus", "params": {"consensus_by_s": 11.0, "follow_by_s": 40.0}},
        },
        "marabunta emulation",
    )


@pytest.mark.parametrize("seed", [1, 2])
def test_the_papers_software_agrees_within_seconds_but_follows_far_too_slowly(seed: int, monkeypatch) -> None:
    monkeypatch.setitem(registry.BEHAVIORS, MarabuntaConsensus.name, MarabuntaConsensus)
    monkeypatch.setitem(registry.BEHAVIORS, MarabuntaLeader.name, MarabuntaLeader)
    metrics = simulate(marabunta_scenario(seed)).metrics
    # Agreement: far slower than one round (the 0.1 s medium, eq. (2): about 1 s), yet within the paper's
    # 0-11 s zoom and short of 11 s / 2.
    assert 2.0 < metrics["consensus_time_s"] < 5.5
    assert metrics["leader_offset_from_swarm_deg"] > 60.0
    # Following: still about 45 deg off the leader at t = 40 s.
    assert metrics["deviation_from_leader_at_deadline_deg"] > 30.0
