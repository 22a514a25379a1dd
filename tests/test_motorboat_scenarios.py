"""The packaged motorboat experiments (issue: ordinary boats join the swarm) meet the buoy versions' criteria.

`aggregation-motorboats` and `aggregation-mixed` are the paper's experiment 4 with 45 motorboats and with 25
buoys + 20 motorboats; `leader-follower-motorboats` is experiment 5 with 45 motorboats, every boat (the leader
too) with the short-range collision avoidance of behaviors.collision_avoidance, checked at its packaged seed.
A motorboat cannot stop
in place, so the aggregation hull is taken over each vessel's mean position in a trailing 60 s window (the spot
it holds, sitl.experiments.station_metrics) and the wander about that spot is bounded here: about the turning radius
(4 m).
Run with the direct vehicle link like tests/test_physics_scenarios.py; the many-seed pass rates come from
`bob-sitl reproduce aggregation-motorboats aggregation-mixed leader-follower-motorboats --seeds 10`.
"""

from __future__ import annotations

import numpy as np
import pytest
from test_process_fleet import SPEED, free_ports

from sitl.experiments.reproduce import select_experiments
from sitl.experiments.runner import simulate
from sitl.experiments.scenario import load_scenario, validate_scenario
from sitl.experiments.swarm_metrics import nearest_neighbor_m
from sitl.fleets.process_fleet import ProcessOptions, run_processes_to_directory

MOTORBOAT_SCENARIOS = ("aggregation-motorboats", "aggregation-mixed", "leader-follower-motorboats")
TURNING_RADIUS_M = 4.0


def run(name: str, **overrides) -> dict:
    overrides.setdefault("link", "direct")
    return simulate(load_scenario(name).with_overrides(**overrides)).metrics


@pytest.mark.parametrize("name", MOTORBOAT_SCENARIOS)
def test_the_packaged_motorboat_scenarios_are_motorboats_judged_by_their_spot(name: str) -> None:
    scenario = load_scenario(name)
    boats = [g for g in scenario.groups if g.body == "motorboat"]
    assert sum(g.count for g in scenario.groups) == 45 and boats
    assert all(g.turning_radius_m == TURNING_RADIUS_M and g.top_speed_mps == 2.0 for g in boats)
    if scenario.metrics.kind == "aggregation":
        assert scenario.metrics.params["average_window_s"] == 60.0
    # reproduce runs them when named, not among the paper's own experiments
    assert [e.name for e in select_experiments([name])] == [name]
    assert name not in [e.name for e in select_experiments([])]


@pytest.mark.parametrize("name", ["aggregation-motorboats", "aggregation-mixed"])
def test_motorboats_aggregate_like_buoys_holding_spots_they_circle(name: str) -> None:
    # One seed (the packaged one) of a chaotic run; the pass rates over seeds come from reproduce (README).
    m = run(name)
    assert m["passed"], m["criteria"]
    # the buoy version's own bounds (tests/test_physics_scenarios.py), on the hull of 60 s mean positions
    assert 62_500 <= m["area_before_m2"] <= 250_000
    assert 625 <= m["area_aggregated_m2"] <= 2_500
    assert 240 <= m["aggregation_time_s"] <= 960
    assert m["area_final_m2"] >= 10 * m["area_aggregated_m2"]
    # boats circle or back about their spots: by about a turning radius, not more
    assert 0.0 < m["wander_rms_m_settled"] <= TURNING_RADIUS_M
    assert m["area_aggregated_instant_m2"] <= 2 * m["area_aggregated_m2"]
    assert m["estimation"]["motorboat"]["position_rms_m"] < 2.0


def test_motorboats_follow_a_leader_boat_and_keep_the_buoys_separation() -> None:
    # The packaged seed (4), direct link, followers keeping 3 m: closest approach 1.65 m at every step, all within 40 m
    # of the leader from 1,635 s (over MAVLink 1.26 m; with 2.5 m it was 1.04 m, and 0.84-0.86 m at seeds 8 and 103).
    # Before the weak boat kept 4 m from the others at the start, seeds 1-12 gave 1.08-1.65 m in the frames, and
    # without collision avoidance 0.66-1.34 m (the 1 m criterion missed at 3 seeds of 12).
    m = run("leader-follower-motorboats")
    assert m["passed"], m["criteria"]
    assert m["closest_approach_m"] >= 1.0 and m["leader_path_m"] >= 350.0
    assert m["weak_final_distance_to_leader_m"][0] <= 40.0  # the weak boat arrives too
    counts = m["collision_avoidance"]
    assert counts["leader"]["interventions"] > 0 and counts["followers"]["interventions"] > 0
    assert counts["leader"]["interventions"] < 0.1 * counts["leader"]["updates"]  # the leader mostly keeps its path


@pytest.mark.xdist_group("realtime")
def test_the_mixed_fleet_aggregates_in_separate_processes_too(tmp_path) -> None:
    """aggregation-mixed's buoys and motorboats, two of each, each its own bob-autonomy process (`--kind buoy` /
    `--kind motorboat` against the simulated ArduPilot frame of its body) at 3x real time: p0 100 m -> 5 m at 10 s
    over MAVLink, and the four come together.

    On a quiet machine the hull falls under a tenth of the square's at about 85 s and to 20 m^2 by 120 s; 160 s
    leaves room for a CI host whose other test worker starves the vessels (one such run was 60 s behind)."""
    base, (mesh, gcs) = free_ports(4, extra=2)
    packaged = load_scenario("aggregation-mixed")
    data = packaged.model_dump(mode="json", exclude_none=True)
    data.update(name="mixed-processes", duration_s=160.0, dt_s=0.1, log_period_s=1.0)
    hold = {"p0": 100.0, "H": 0, "speed_scale": 0.8, "max_speed": 1.0}
    for k, group in enumerate(data["groups"]):
        group.update(count=2, params=hold)
        group["start"] = {"lattice": {"center": [0.0, 100.0 * k], "spacing_m": 100.0, "kind": "square"}}
    data["events"] = [
        {
            "t_s": 10.0,
            "action": "set-behavior",
            "fraction": 1.0,
            "choice": {"behavior": "bob-rule", "params": {**hold, "p0": 5.0}},
        }
    ]
    data["metrics"] = {"kind": "aggregation", "params": {"average_window_s": 10.0}}
    scenario = validate_scenario(data, "test scenario")
    options = ProcessOptions(speed=SPEED, base_port=base, mesh_port=mesh, gcs_port=gcs)
    result = run_processes_to_directory(scenario, tmp_path / "run", options)
    m = result.metrics

    assert m["processes"]["exit_codes"] == [0] * 4 and m["processes"]["killed"] == 0
    assert result.fleet.events_log == [{"t_s": 10.0, "action": "set-behavior", "agents": [0, 1, 2, 3]}]
    assert m["area_before_m2"] == pytest.approx(10_000.0, rel=0.1)  # the 100 m square held until the switch
    assert m["area_final_m2"] < 0.1 * m["area_before_m2"]
    nn_end = nearest_neighbor_m(result.recorder.frames[-1].position)
    assert nn_end.max() < 30.0
    assert m["vehicles"]["refused"] == 0
    assert m["estimation"]["motorboat"]["position_rms_m"] < 5.0, worst_beliefs(result, m)


def worst_beliefs(result, metrics: dict) -> str:
    """What to look at when a process fleet's belief is far from the truth (it failed once in CI at 7.9 m rms, and
    has not again, under up to four busy loops): the estimation and realtime figures and the logged frames where a
    vessel's broadcast belief, carried forward to the frame, was over 5 m off."""
    far = []
    for frame in result.recorder.frames:
        if frame.estimate is None:
            continue
        error = np.hypot(*(frame.estimate[:, :2] - frame.position).T)
        pairs = zip(frame.agents, error, strict=True)
        far += [(round(frame.t, 1), int(agent), round(float(e), 1)) for agent, e in pairs if e > 5.0]
    return f"estimation {metrics['estimation']}; realtime {metrics['realtime']}; (t, agent, m) over 5 m: {far[:40]}"


@pytest.mark.xdist_group("realtime")
def test_motorboats_follow_a_leader_boat_in_separate_processes(tmp_path) -> None:
    """leader-follower-motorboats cut to a leader and three followers, each its own bob-autonomy process at 3x
    real time: the leader is driven 76 m, the followers hear where it is over the mesh only, go after it and keep
    clear of it and of each other.

    A holding follower gets under way when its wish reaches 1.5 x HOLD_SPEED_MPS = 0.3 m/s, or stays above
    HOLD_SPEED_MPS for HOLD_DWELL_S; the goal pull fades over goal_radius_m (60 m) to 0.6 m/s x d / 60 m, so a
    follower alone stops about 20 m from a stopped leader (where the pull falls under the hold speed).

    Two runs (2026-12-07, one beside two busy loops): the leader stops at about 155 s; the last follower comes
    within 50 m of it at 170-190 s and is 37.7-42.8 m off at 210-220 s; 220 s leaves that margin."""
    base, (mesh, gcs) = free_ports(4, extra=2)
    packaged = load_scenario("leader-follower-motorboats")
    data = packaged.model_dump(mode="json", exclude_none=True)
    data.update(name="leader-follower-processes", duration_s=220.0, dt_s=0.1, log_period_s=1.0)
    leader, followers = data["groups"][0], data["groups"][1]
    leader["params"].update(waypoints=[[40.0, 0.0], [60.0, 30.0]], speed=0.5)
    followers.update(count=3)
    followers["start"] = {"lattice": {"center": [-20.0, 0.0], "spacing_m": 10.0, "kind": "square"}}
    data["groups"] = [leader, followers]
    data["metrics"]["params"].update(min_path_m=70.0, weak_agents=[])
    scenario = validate_scenario(data, "test scenario")
    options = ProcessOptions(speed=SPEED, base_port=base, mesh_port=mesh, gcs_port=gcs)
    result = run_processes_to_directory(scenario, tmp_path / "run", options)
    m = result.metrics

    assert m["processes"]["exit_codes"] == [0] * 4 and m["processes"]["killed"] == 0
    assert m["leader_path_m"] >= 70.0
    assert m["closest_approach_m"] >= 1.0
    assert m["collision_avoidance"]["updates"] > 0 and len(m["collision_avoidance"]["by_vessel"]) == 4
    assert m["vehicles"]["refused"] == 0
    start, end = result.recorder.frames[0].position, result.recorder.frames[-1].position
    leader_end = end[0]
    before = np.hypot(*(start[1:] - leader_end).T)  # 70-85 m
    after = np.hypot(*(end[1:] - leader_end).T)
    assert (before - after > 25.0).all() and after.max() < 50.0, (before, after)
