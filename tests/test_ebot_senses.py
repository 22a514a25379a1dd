"""eBot range finders and light sensors over MAVLink: the simulated vehicle's telemetry, the decoder, and the
vessel's Senses built from it, checked against the simulator's own sonar geometry."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bob_autonomy.core.geodesy import LocalFrame
from bob_autonomy.onboard.senses import EbotSenses
from bob_autonomy.onboard.vessel import EbotConfig
from firmware_bridge.decoder import TelemetryDecoder
from firmware_bridge.readings import LightReading, RangeReading
from firmware_bridge.telemetry import TelemetryEncoder
from sitl.vehicles.bodies import EBOT, EBOT_SONAR_ANGLES_RAD
from sitl.vehicles.mavlink_vehicle import SimulatedVehicle, encode_senses
from sitl.vehicles.sensors import LightSpec, RangeSpec
from sitl.vehicles.vehicle_physics import VehiclePhysics
from sitl.world.environment import CurrentSpec, Environment, WindSpec
from sitl.world.world import World, polygon_segments


def test_the_vessel_knows_the_simulated_sonar_layout() -> None:
    np.testing.assert_allclose(np.radians(EbotConfig().sonar_angles_deg), EBOT_SONAR_ANGLES_RAD)


def test_range_and_light_telemetry_round_trip() -> None:
    enc, clock = TelemetryEncoder(4), [10.0]
    data = enc.distance_sensor(1.0, 2, 0.734, 1.5) + enc.distance_sensor(1.0, 5, math.nan, 1.5) + enc.light(1.0, 3, 1)
    readings = TelemetryDecoder(lambda: clock[0]).feed(data)
    ranges = [r for r in readings if isinstance(r, RangeReading)]
    lights = [r for r in readings if isinstance(r, LightReading)]
    assert (int(ranges[0].sensor[0]), ranges[0].distance_m[0]) == (2, pytest.approx(0.73))  # 1 cm steps
    assert int(ranges[1].sensor[0]) == 5 and math.isnan(ranges[1].distance_m[0])  # no echo
    assert [(int(r.side[0]), float(r.intensity[0])) for r in lights] == [(0, 3.0), (1, 1.0)]

    senses = EbotSenses(EBOT_SONAR_ANGLES_RAD, max_age_s=1.0)
    senses.feed(readings)
    s = senses.senses(heading_rad=math.pi / 2, now_s=10.5)  # facing north
    bearing = math.pi / 2 + EBOT_SONAR_ANGLES_RAD[2]
    np.testing.assert_allclose(s.obstacles[0, 2], 0.73 * np.array([math.cos(bearing), math.sin(bearing)]))
    assert np.isnan(s.obstacles[0, [0, 1, 3, 4, 5]]).all()
    np.testing.assert_allclose(s.light[0], [3.0, 1.0])
    stale = senses.senses(heading_rad=0.0, now_s=12.0)
    assert np.isnan(stale.obstacles).all() and np.isnan(stale.light).all()


def test_the_vessel_sees_the_walls_the_simulator_sees() -> None:
    room = np.array([[0.0, 0.0], [3.0, 0.0], [3.0, 2.0], [0.0, 2.0]])
    world = World(walls=polygon_segments(room), rooms=[room])
    physics = VehiclePhysics(
        np.array([EBOT]),
        np.array([[1.0, 1.0]]),
        np.array([0.0]),
        Environment(WindSpec(), CurrentSpec(), np.random.default_rng(1)),
        LocalFrame(1.3406, 103.9266),
        np.random.default_rng(2),
        np.ones(1),
        {"ranges": RangeSpec(noise_m=0.0), "light": LightSpec(noise_rel=0.0)},
    )
    ranges, light = physics.ebot_senses(world)
    vehicle = SimulatedVehicle(1, "ebot", 0.2)
    frames = [bytearray()]
    encode_senses(0.0, [vehicle], frames, [0], ranges, light, 1.5)
    senses = EbotSenses(EBOT_SONAR_ANGLES_RAD)
    senses.feed(TelemetryDecoder(lambda: 0.0).feed(bytes(frames[0])))
    seen = senses.senses(heading_rad=0.0, now_s=0.0).obstacles[0]
    # Facing east 1 m from the west wall and 1 m from the floor: the rear sonar echoes at 1 m, the front at 2 m
    # is beyond the 1.5 m range.
    np.testing.assert_allclose(seen[3], [-1.0, 0.0], atol=0.011)
    assert np.isnan(seen[0]).all()
    np.testing.assert_allclose(np.hypot(*seen.T), ranges[0], atol=0.011, equal_nan=True)


def test_the_ebot_estimator_ignores_range_and_light_readings() -> None:
    from bob_autonomy.onboard.pipeline import EbotPipeline

    enc = TelemetryEncoder(1)
    readings = TelemetryDecoder(lambda: 1.0).feed(
        enc.distance_sensor(1.0, 0, 0.5, 1.5) + enc.light(1.0, 1, 2) + enc.wheel_distance(1.0, (0.1, 0.1))
    )
    pipeline = EbotPipeline(np.zeros((1, 2)), np.zeros(1), 0.1, 0.2, 0.001, estimator="ekf", controller="simple")
    pipeline.feed(readings)  # wheel travel is fused; a range reading is not mistaken for it
    assert pipeline.ignored == 3


def test_lockstep_ebots_sense_through_mavlink() -> None:
    from sitl.experiments.runner import simulate
    from sitl.experiments.scenario import load_scenario

    scenario = load_scenario("perimeter-defense").with_overrides(duration_s=5.0, fidelity="physics", link="mavlink")
    fleet = simulate(scenario).fleet
    transport = fleet.bodies.ebot_link
    for link in transport.links:
        assert link.decoder.counters.by_type["DISTANCE_SENSOR"] >= 6 * 50  # 6 sonars each step
        assert link.decoder.counters.by_type["NAMED_VALUE_FLOAT"] >= 2 * 50
    # In the room's corner where they start, every robot hears at least one echo (walls or a neighbour).
    assert all(np.isfinite(s.ranges_m).any() for s in transport.sensing)
