"""Motorboats in the lockstep fleet: the kinematic motorboat, the physics fidelity with the vessel's own autonomy
over MAVLink or direct, a mixed fleet, and wishes a motorboat cannot follow (said and counted)."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from sitl.experiments.runner import simulate
from sitl.experiments.scenario import validate_scenario
from sitl.fleets.fleet import LockstepFleet
from sitl.vehicles.bodies import MOTORBOAT, KinematicBodies
from sitl.world.world import World


def _scenario(**overrides) -> dict:
    data = {
        "name": "boats",
        "duration_s": 60.0,
        "dt_s": 0.5,
        "seed": 3,
        "log_period_s": 5.0,
        "fidelity": "physics",
        "environment": {"wind": {"speed_mps": 5.0, "toward_deg": 30.0}, "current": {"speed_mps": 0.05}},
        "network": {"range_m": 300.0, "broadcast_period_s": 1.0, "expiry_s": 5.0},
        "groups": [
            {
                "name": "boats",
                "count": 4,
                "body": "motorboat",
                "behavior": "bob-rule",
                "params": {"p0": 10.0, "H": 0, "speed_scale": 0.8, "max_speed": 1.0},
                "start": {"box": {"min": [0.0, 0.0], "max": [80.0, 80.0]}, "min_separation_m": 15.0},
                "top_speed_mps": 2.5,
                "turning_radius_m": 4.0,
            }
        ],
    }
    data.update(overrides)
    return data


def test_a_kinematic_motorboat_goes_only_where_it_points_and_turns_around_in_a_circle() -> None:
    bodies = KinematicBodies(np.array([MOTORBOAT]), np.zeros((1, 2)), np.zeros(1))
    bodies.turning_radius[:] = 5.0
    track = []
    for _ in range(400):  # wished: 1 m/s west, straight behind it
        bodies.apply(np.array([[-1.0, 0.0]]), np.array([np.nan]), 0.1, World())
        c, s = np.cos(bodies.heading[0]), np.sin(bodies.heading[0])
        vx, vy = bodies.velocity[0]
        assert abs(c * vy - s * vx) <= 0.03 * np.hypot(vx, vy) + 1e-12  # along the keel (the arc's mid heading)
        track.append(bodies.position[0].copy())
    track = np.array(track)
    assert bodies.velocity[0] == pytest.approx([-1.0, 0.0], abs=1e-3)
    assert track[:, 1].max() - track[:, 1].min() == pytest.approx(2 * 5.0, rel=0.1)  # a half circle of radius 5 m


@pytest.mark.parametrize("link", ["direct", "mavlink"])
def test_physical_motorboats_aggregate_with_their_own_estimates_over_either_link(link) -> None:
    scenario = validate_scenario(_scenario(vessel={"link": link}), "test")
    result = simulate(scenario)
    bodies = result.fleet.bodies
    first, last = result.recorder.frames[0].position, result.recorder.frames[-1].position
    spread = [np.sqrt(((p - p.mean(axis=0)) ** 2).sum(axis=1).mean()) for p in (first, last)]
    assert spread[1] < 0.6 * spread[0]  # they came together
    assert result.metrics["estimation"]["motorboat"]["position_rms_m"] < 2.0
    assert result.metrics["estimation"]["motorboat"]["heading_rms_deg"] < 5.0
    assert bodies.mpc_fallbacks == 0
    assert bodies.max_speed[bodies.motorboats].tolist() == [2.5] * 4
    if link == "mavlink":
        counters = result.metrics["vehicle_link"]
        assert counters["vehicle_commands"] > 0 and counters["vehicle_refused"] == 0
        assert counters["motorboat_sideways_wishes"] == 0


def test_a_mixed_fleet_of_buoys_and_motorboats_runs_and_logs_each_body() -> None:
    data = _scenario(duration_s=20.0)
    buoys = dict(data["groups"][0], name="buoys", body="buoy", count=3)
    del buoys["top_speed_mps"], buoys["turning_radius_m"]
    data["groups"].append(buoys)
    result = simulate(validate_scenario(data, "test"))
    assert result.recorder.body_names == ["motorboat"] * 4 + ["buoy"] * 3
    assert set(result.metrics["estimation"]) == {"buoy", "motorboat"}


def test_a_heading_held_in_place_is_said_and_counted_not_silently_dropped(caplog) -> None:
    data = _scenario(duration_s=5.0)
    data["groups"][0].update(behavior="heading-consensus", params={})  # cruise_speed 0: turn in place
    with caplog.at_level(logging.WARNING, logger="bob_autonomy.onboard.pipeline"):
        fleet = LockstepFleet(validate_scenario(data, "test"))
        for _ in range(4):
            fleet.step()
    assert fleet.bodies.motorboat_vessels.sideways_wishes == 4 * 4
    told = [r.getMessage() for r in caplog.records if "cannot turn in place or move sideways" in r.getMessage()]
    assert len(told) == 4  # once per boat


def test_motorboat_keys_belong_to_motorboats() -> None:
    data = _scenario()
    data["groups"][0]["body"] = "buoy"
    with pytest.raises(ValueError, match="only for body"):
        validate_scenario(data, "test")
