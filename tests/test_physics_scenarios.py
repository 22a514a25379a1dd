"""The buoy and eBot experiments at physics fidelity meet their criteria (DESIGN.md experiments 2 to 7).

Run with the direct vehicle link (readings and commands handed over in memory) to keep the suite fast;
tests/test_full_stack.py checks that the MAVLink link (the default) behaves the same and meets the
aggregation criteria end to end.
"""

from __future__ import annotations

import pytest

from sitl.experiments.runner import simulate
from sitl.experiments.scenario import load_scenario


def run(name: str, **overrides) -> dict:
    overrides.setdefault("link", "direct")
    return simulate(load_scenario(name).with_overrides(**overrides)).metrics


def test_aggregation_shrinks_then_spreads() -> None:
    m = run("aggregation")
    assert 62_500 <= m["area_before_m2"] <= 250_000
    assert 625 <= m["area_aggregated_m2"] <= 2_500
    assert 240 <= m["aggregation_time_s"] <= 960
    assert m["area_final_m2"] >= 10 * m["area_aggregated_m2"]
    assert m["network"]["dropped"] > 0  # the lossy radio is in the loop
    assert m["passed"]


def test_leader_follower_keeps_the_group_and_spacing() -> None:
    m = run("leader-follower")
    assert m["leader_path_m"] >= 350
    # At every step and between steps; eq. (5) alone came to 0.70-0.88 m at 3 of seeds 1-10: the buoys run the
    # collision avoidance layer (followers keep 3 m), which acts in the crowd and hardly ever for the leader (a
    # stand-on vessel). The packaged seed (4), direct link: 1.56 m.
    assert m["closest_approach_m"] >= 1.0
    avoidance = m["collision_avoidance"]
    assert avoidance["followers"]["interventions"] > 0
    assert avoidance["leader"]["interventions"] < 0.01 * avoidance["leader"]["updates"]
    assert m["all_within_radius_of_leader_s"] is not None
    # The weak buoy lags but arrives with the group.
    assert m["weak_final_distance_to_leader_m"][0] <= 40.0
    assert m["passed"]


@pytest.mark.parametrize("case", ["yield", "through", "around"])
def test_avoidance_outcomes(case: str) -> None:
    m = run(f"avoidance-{case}")
    assert m["arrival_time_s"] is not None
    assert m["outcome"] == case
    assert m["passed"]
    if case == "around":
        # The fixed swarm stays put, and the mover (skirt) keeps outside it all the way, instead of
        # stopping in a pocket of its edge or in a gap wider than its p0.
        assert m["swarm_max_displacement_m"] <= 20.0
        assert m["path_fraction_inside_swarm"] == 0.0


def test_five_rooms_all_visited() -> None:
    m = run("five-rooms")
    assert m["all_rooms_visited_s"] is not None
    assert all(t is not None for t in m["first_visit_s"].values())
    assert m["passed"]


def test_radio_table_within_three_points() -> None:
    m = run("radio-table")
    assert len(m["table"]) == 8
    assert all(abs(row["difference_pp"]) <= 3.0 for row in m["table"])
    assert m["passed"]


@pytest.mark.parametrize("name", ["heading-consensus", "perimeter-defense", "search-exploration"])
def test_ebot_scenarios_hold_at_physics_fidelity(name: str) -> None:
    m = run(name, fidelity="physics")
    assert m["passed"], m["criteria"]
    # Each eBot acts on its own dead reckoning (encoders + compass); its error against truth is reported.
    errors = m["estimation"]["ebot"]
    assert 0.0 < errors["position_rms_m"] <= errors["position_max_m"] < 5.0
    assert errors["heading_rms_deg"] < 10.0
