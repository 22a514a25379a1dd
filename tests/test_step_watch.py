"""The "ever" and "never" criteria are checked at every step and between steps, not only at logged frames
(sitl.experiments.step_watch): closest approach of two agents, and robots inside the room."""

from __future__ import annotations

import numpy as np
import pytest

from sitl.experiments import step_watch
from sitl.experiments.metrics import METRICS, perimeter_defense_metrics
from sitl.experiments.recorder import Frame, Recorder
from sitl.experiments.runner import simulate
from sitl.experiments.scenario import load_scenario
from sitl.experiments.step_watch import AlwaysInside, ClosestApproach, StepWatch, least_approach
from sitl.experiments.swarm_metrics import nearest_neighbor_m
from sitl.fleets.fleet import LockstepFleet


def brute_force_least_approach(start: np.ndarray, end: np.ndarray) -> float:
    """Least distance of any pair moving in straight lines from start to end, sampled finely."""
    s = np.linspace(0.0, 1.0, 2001)[:, None, None]
    paths = start[None] + s * (end - start)[None]  # (samples, k, 2)
    i, j = np.triu_indices(len(end), 1)
    return float(np.hypot(*(paths[:, j] - paths[:, i]).transpose(2, 0, 1)).min())


def test_two_boats_that_pass_within_half_a_metre_between_steps_are_caught() -> None:
    start = np.array([[-1.0, 0.0], [1.0, 0.5]])
    end = np.array([[1.0, 0.0], [-1.0, 0.5]])  # at both steps 2.06 m apart; mid-step 0.5 m
    distance, i, j = least_approach(start, end)
    assert distance == pytest.approx(0.5)
    assert (i, j) == (0, 1)
    assert nearest_neighbor_m(end).min() == pytest.approx(np.hypot(2.0, 0.5))


@pytest.mark.parametrize("seed", range(20))
@pytest.mark.parametrize("pairs_from", ["all pairs", "k-d tree"])
def test_the_least_approach_misses_no_pair(seed: int, pairs_from: str, monkeypatch) -> None:
    """Random crowds with random moves up to 3 m: the least approach is the brute-force one over all pairs, with
    every pair examined and with the k-d tree's candidates."""
    if pairs_from == "k-d tree":
        monkeypatch.setattr(step_watch, "ALL_PAIRS_UP_TO", 1)
    rng = np.random.default_rng(seed)
    k = int(rng.integers(2, 40))
    start = rng.uniform(0.0, 20.0, (k, 2))
    end = start + rng.uniform(-3.0, 3.0, (k, 2)) * rng.uniform(0.0, 1.0, (k, 1))
    distance, i, j = least_approach(start, end)
    assert distance == pytest.approx(brute_force_least_approach(start, end), abs=2e-3)
    assert distance <= nearest_neighbor_m(end).min() + 1e-12
    assert distance <= nearest_neighbor_m(start).min() + 1e-12
    assert i < j


def test_closest_approach_follows_agents_by_id_as_they_come_and_go() -> None:
    watch = ClosestApproach()
    watch.observe(0.0, np.array([0, 1, 2]), np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0]]))
    assert watch.distance_m == pytest.approx(10.0)
    # Agent 1 is removed; agent 2 moves from (0, 10) to (0, 4): the pair (0, 2) is 4 m apart at the end.
    watch.observe(0.5, np.array([0, 2]), np.array([[0.0, 0.0], [0.0, 4.0]]))
    assert watch.closest.distance_m == pytest.approx(4.0)
    assert watch.closest.agents == (0, 2) and watch.closest.t_s == 0.5
    # Agent 3 appears 1 m from agent 0: it did not travel there from anywhere (no segment from the origin).
    watch.observe(1.0, np.array([0, 2, 3]), np.array([[0.0, 0.0], [0.0, 4.0], [1.0, 0.0]]))
    assert watch.closest.distance_m == pytest.approx(1.0)
    assert watch.closest.agents == (0, 3)


def test_a_robot_outside_the_room_between_two_logged_frames_fails_always_inside() -> None:
    """A perimeter-defence recording: the frames (once a second) all inside; one step in between outside."""
    fleet = LockstepFleet(load_scenario("perimeter-defense").with_overrides(agents=2))
    inside = [[1.0, 1.0], [12.0, 5.0]]
    rec = Recorder(1.0, ["ebot"] * 2, watch=StepWatch(inside=AlwaysInside(fleet.world.inside_rooms)))
    active = np.ones(2, dtype=bool)
    for step in range(21):  # 2 s at 0.1 s
        t = round(0.1 * step, 9)
        positions = np.array(inside)
        if step == 13:
            positions[1] = [14.0, 5.0]  # 0.5 m beyond the right wall
        if rec.due(t):
            rec.record(Frame(t, np.arange(2), positions.copy(), np.zeros(2), np.zeros((2, 2)), ["pd"] * 2))
        rec.observe_step(t, active, positions)
    assert all(fleet.world.inside_rooms(f.position).all() for f in rec.frames)
    assert rec.watch.inside.first_outside == (1.3, 1)
    params = {"cover_radius_m": 2.5, "min_coverage": 0.7, "min_recovered": 0.3}
    assert perimeter_defense_metrics(fleet, rec, params)["always_inside_room"] is False


def test_a_leader_follower_run_reports_the_closest_approach_of_every_step() -> None:
    """45 buoys (kinematic, 60 s, frames every 5 s): the closest approach is that of the watched steps, at most
    the least distance in any logged frame, and names the pair and the time."""
    scenario = load_scenario("leader-follower").with_overrides(fidelity="kinematic", duration_s=60.0)
    result = simulate(scenario)
    m = result.metrics
    logged = min(nearest_neighbor_m(f.position).min() for f in result.recorder.frames)
    assert m["closest_approach_m"] <= logged
    assert m["closest_approach_m"] == result.recorder.watch.closest.distance_m
    a, b = m["closest_approach_agents"]
    assert 0 <= a < b < 45 and 0.0 <= m["closest_approach_t_s"] <= 60.0
    assert m["criteria"]["no_two_closer_than_1_m"] == (m["closest_approach_m"] >= 1.0)
    # Without a watch (a recording made by hand), the metric falls back to the logged frames.
    plain = Recorder(result.recorder.period_s, result.recorder.body_names, result.recorder.frames)
    assert METRICS["leader-follower"](result.fleet, plain, {})["closest_approach_m"] == logged
