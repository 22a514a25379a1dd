"""Readings decoded vehicle by vehicle and fused as batches over vehicles: same estimates, per-vessel order kept."""

from __future__ import annotations

import numpy as np

import sitl.vehicles.vehicle_transport as transport
from firmware_bridge.batch_decoder import Row
from firmware_bridge.readings import CompassReading, GpsFix, ImuReading
from sitl.experiments.scenario import load_scenario
from sitl.fleets.fleet import LockstepFleet
from sitl.vehicles.reading_batches import merge_by_round


def _gps(agent: int, t: float, velocity: bool = True) -> GpsFix:
    v = np.array([[0.1 * agent, 0.0]]) if velocity else None
    return GpsFix(np.array([agent]), np.array([t]), np.array([50.0 + agent]), np.array([8.0]), v)


def _compass(agent: int, t: float) -> CompassReading:
    return CompassReading(np.array([agent]), np.array([t]), np.array([0.1 * agent]))


def test_rounds_merge_same_kinds_keep_each_vehicles_order_and_pass_other_objects_through() -> None:
    imu = ImuReading(np.array([2]), np.array([0.9]), np.zeros((1, 2)), np.zeros(1))
    per_vehicle = [
        [_gps(0, 1.0), _compass(0, 1.0)],
        [_compass(1, 1.1), _gps(1, 1.1), "status"],  # another order, and something that is not a reading
        [imu, _gps(2, 1.2, velocity=False)],  # a fix without velocity is not merged with fixes that have one
    ]
    merged = merge_by_round(per_vehicle)
    kinds = [(type(r).__name__, r.agents.tolist() if hasattr(r, "agents") else r) for r in merged]
    assert kinds == [
        ("GpsFix", [0]),
        ("CompassReading", [1]),
        ("ImuReading", [2]),
        ("CompassReading", [0]),
        ("GpsFix", [1]),
        ("GpsFix", [2]),
        ("str", "status"),
    ]
    # every agent's own readings in its own order
    for agent, expected in ((0, ["GpsFix", "CompassReading"]), (1, ["CompassReading", "GpsFix"])):
        mine = [type(r).__name__ for r in merged if hasattr(r, "agents") and agent in r.agents.tolist()]
        assert mine == expected


def test_same_kind_rows_become_one_reading_with_all_rows_and_fields() -> None:
    merged = merge_by_round([[_gps(k, 1.0 + k)] for k in range(4)])
    assert len(merged) == 1
    fix = merged[0]
    assert fix.agents.tolist() == [0, 1, 2, 3] and fix.t_s.tolist() == [1.0, 2.0, 3.0, 4.0]
    assert fix.velocity_mps.shape == (4, 2) and fix.lat_deg.tolist() == [50.0, 51.0, 52.0, 53.0]
    assert merge_by_round([]) == [] and merge_by_round([[], []]) == []


def _one_by_one(per_vehicle, columns=None) -> list:
    """Every reading on its own, vehicle after vehicle (rows decoded column-wise taken one at a time)."""
    return [columns.take(r.key, [r.index]) if isinstance(r, Row) else r for rs in per_vehicle for r in rs]


def test_a_buoy_fleet_over_mavlink_estimates_the_same_merged_or_not(monkeypatch) -> None:
    """Each vessel's filter does the same arithmetic on its own rows; batching only changes how numpy groups it,
    so the estimates agree to rounding (the last bits of a float), not necessarily bit for bit."""
    scenario = load_scenario("aggregation").with_overrides(duration_s=30.0)
    merged, one_by_one = LockstepFleet(scenario), LockstepFleet(scenario)
    largest = 0.0
    for _ in range(60):
        merged.step()
        monkeypatch.setattr(transport, "merge_by_round", _one_by_one)
        one_by_one.step()
        monkeypatch.undo()
        a, b = merged.bodies.buoy_vessels.estimator, one_by_one.bodies.buoy_vessels.estimator
        assert np.allclose(a.x, b.x, rtol=1e-12, atol=1e-9) and np.allclose(a.P, b.P, rtol=1e-12, atol=1e-12)
        largest = max(largest, float(np.abs(a.x - b.x).max()))
    assert largest < 1e-9
    assert np.allclose(merged.bodies.position, one_by_one.bodies.position, rtol=0.0, atol=1e-9)
