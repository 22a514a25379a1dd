"""AvoidCollisions (behaviors.collision_avoidance): invisible when nothing threatens, keeps two agents on a
collision course apart (kinematic agents, then two simulated motorboats with their MPC), passes to starboard."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import pytest
from behavior_helpers import assert_batch_equivalent, make_table, make_view

from behaviors.base import Behavior, MemorySpec, View, Wish
from behaviors.collision_avoidance import AvoidCollisions
from bob_autonomy.core.behavior_config import BehaviorChoice
from sitl.experiments.runner import hearing_problems, simulate
from sitl.experiments.scenario import load_scenario, packaged_scenarios, validate_scenario
from sitl.fleets.fleet import LockstepFleet


@dataclass
class Constant(Behavior):
    """Wish fixed velocities (n, 2) m/s with heading 0.25 rad, and a memory value."""

    name: ClassVar[str] = "constant"
    memory_fields: ClassVar[dict[str, MemorySpec]] = {"mark": MemorySpec()}
    velocity: list[list[float]]

    def step(self, view: View) -> Wish:
        agent = view.table.ids[view.rows] - 1  # make_table numbers the agents 1..N
        velocity = np.array(self.velocity, dtype=float)[agent]
        return Wish(velocity, np.full(view.n, 0.25), {"mark": agent + 0.5})


def test_a_wish_nothing_threatens_is_kept_exactly() -> None:
    inner = Constant([[0.5, 0.0], [0.0, 0.5], [-0.5, 0.0]])
    avoid = AvoidCollisions(inner)
    view = make_view(make_table([[0.0, 0.0], [0.0, 20.0], [30.0, 0.0]]))  # diverging or far apart
    wish = assert_batch_equivalent(avoid, view)
    assert np.array_equal(wish.velocity, inner.step(view).velocity)
    assert np.array_equal(wish.heading, [0.25] * 3) and np.array_equal(wish.memory["mark"], [0.5, 1.5, 2.5])
    assert avoid.interventions == 0 and avoid.updates > 0


def test_a_threatened_wish_changes_the_same_in_a_batch_as_on_each_vessel() -> None:
    avoid = AvoidCollisions(Constant([[0.5, 0.0], [-0.5, 0.0], [0.0, 0.3]]))
    table = make_table([[0.0, 0.0], [3.0, 0.1], [1.0, -2.0]], headings=[0.0, np.pi, np.pi / 2])
    table.velocity[:] = [[0.5, 0.0], [-0.5, 0.0], [0.0, 0.3]]
    wish = assert_batch_equivalent(avoid, make_view(table))
    assert not np.allclose(wish.velocity[:2], [[0.5, 0.0], [-0.5, 0.0]])
    assert np.isnan(wish.heading[:2]).all()  # the heading preference goes with the changed wish
    assert avoid.interventions > 0


def _head_on(avoid: bool, seconds: float = 30.0, dt: float = 0.1) -> tuple[float, np.ndarray]:
    """Two agents 20 m apart wishing 0.5 m/s straight at each other, each answering its wish with a 1.5 s lag
    and hearing the other's true position and velocity. (closest approach m, offset of 1 from 0 then)."""
    inner = Constant([[0.5, 0.0], [-0.5, 0.0]])
    behavior = AvoidCollisions(inner) if avoid else inner
    table = make_table([[0.0, 0.0], [20.0, 0.0]], headings=[0.0, np.pi])
    table.velocity[:] = [[0.5, 0.0], [-0.5, 0.0]]
    closest, offset = np.inf, np.zeros(2)
    for _ in range(round(seconds / dt)):
        wish = behavior.step(make_view(table))
        table.velocity += (wish.velocity - table.velocity) * (dt / 1.5)
        table.position += table.velocity * dt
        table.heading = np.arctan2(table.velocity[:, 1], table.velocity[:, 0])
        distance = float(np.hypot(*(table.position[1] - table.position[0])))
        if distance < closest:
            closest, offset = distance, table.position[1] - table.position[0]
    return closest, offset


def test_two_agents_head_on_keep_the_safe_distance_and_pass_port_to_port() -> None:
    blind, _ = _head_on(avoid=False)
    assert blind < 0.1  # straight through each other
    closest, offset = _head_on(avoid=True)
    assert closest >= 0.8 * AvoidCollisions.safe_distance_m  # 2.5 m: a soft cost, some intrusion (2.18 m)
    # Both gave way to starboard (COLREG): agent 1, coming from the east, passed north of agent 0 (its port side).
    assert offset[1] > 0.0


def _two_boats(avoid: bool) -> dict:
    """leader-follower-motorboats cut to two motorboats driven along the same line from opposite ends, 60 m
    apart, at 0.5 m/s; physics, the MPC, GPS noise, 1 s broadcasts, the direct vehicle link."""
    data = load_scenario("leader-follower-motorboats").model_dump(mode="json", exclude_none=True)
    leader = data["groups"][0]
    groups = []
    for name, start, goal, heading in (("east", 0.0, 60.0, 0.0), ("west", 60.0, 0.0, 180.0)):
        group = {**leader, "name": name, "avoid_collisions": avoid}
        if not avoid:
            group.pop("collision_params", None)
        group["params"] = {"waypoints": [[goal, 0.0]], "speed": 0.5, "arrival_radius_m": 3.0}
        group["start"] = {"box": {"min": [start, 0.0], "max": [start + 0.01, 0.01]}, "heading_deg": heading}
        groups.append(group)
    data.update(name="two-boats", duration_s=240.0, groups=groups, seed=1, log_period_s=0.5)
    data["metrics"]["params"].update(min_path_m=40.0, weak_agents=[], arrival_radius_m=100.0)
    return simulate(validate_scenario(data, "test scenario").with_overrides(link="direct")).metrics


def test_two_motorboats_on_a_collision_course_keep_clear_only_with_collision_avoidance() -> None:
    blind = _two_boats(avoid=False)
    assert blind["closest_approach_m"] < 1.0 and "collision_avoidance" not in blind
    m = _two_boats(avoid=True)
    assert m["closest_approach_m"] >= 1.25, m["closest_approach_m"]  # 1.59 m (0.76 m without)
    assert m["leader_path_m"] >= 40.0  # both still get where they were driven
    counts = m["collision_avoidance"]
    assert counts["east"]["interventions"] > 0 and counts["west"]["interventions"] > 0


def test_the_choice_builds_the_wrapper_and_refuses_bad_parameters() -> None:
    choice = BehaviorChoice(behavior="waypoints", params={"waypoints": [[1.0, 2.0]]}, avoid_collisions=True,
                            collision_params={"safe_distance_m": 2.0}, avoid_obstacles=True)  # fmt: skip
    built = choice.build()
    assert built.name == "avoid+avoid-collisions+waypoints" and built.inner.safe_distance_m == 2.0
    with pytest.raises(ValueError, match="bogus"):
        BehaviorChoice(behavior="waypoints", params={"waypoints": [[1.0, 2.0]]}, avoid_collisions=True,
                       collision_params={"bogus": 1.0})  # fmt: skip
    with pytest.raises(ValueError, match="without avoid_collisions"):
        BehaviorChoice(behavior="waypoints", params={"waypoints": [[1.0, 2.0]]}, collision_params={"range_m": 5.0})
    with pytest.raises(ValueError, match="safe_distance_m"):
        AvoidCollisions(Constant([[0.0, 0.0]]), safe_distance_m=20.0, range_m=10.0)


def test_broadcasts_more_than_half_the_horizon_apart_are_named_as_too_slow() -> None:
    layer = AvoidCollisions(Constant([[0.0, 0.0]]), horizon_s=5.0)
    assert layer.hearing_problem(0.1) is None and layer.hearing_problem(2.5) is None
    problem = layer.hearing_problem(10.0)
    assert "5 s ahead" in problem and "every 10 s" in problem and "at least every 2.5 s" in problem


def test_a_scenario_avoiding_collisions_on_slow_broadcasts_is_warned_about_and_the_packaged_ones_are_not(
    caplog,
) -> None:
    data = load_scenario("leader-follower").model_dump(mode="json", exclude_none=True)
    data["network"].update(broadcast_period_s=10.0, expiry_s=30.0)
    data.update(duration_s=1.0, fidelity="kinematic")
    data["groups"][1]["count"] = 2
    data["metrics"]["params"]["weak_agents"] = [3.0]
    with caplog.at_level("WARNING", logger="sitl.experiments.runner"):
        simulate(validate_scenario(data, "test scenario"))
    said = [r.getMessage() for r in caplog.records if "collision avoidance predicts" in r.getMessage()]
    # followers and the weak buoy predict 5 s ahead (at least every 2.5 s), the leader 3 s (1.5 s)
    assert len(said) == 3 and any("leader: " in m and "every 1.5 s" in m for m in said), said
    for name in packaged_scenarios():
        fleet = LockstepFleet(load_scenario(name).with_overrides(fidelity="kinematic"))
        try:
            assert hearing_problems(fleet) == [], name
        finally:
            fleet.close()
