"""Swell in the simulator (sitl.world.waves): hulls rolled and pitched, their IMU and ATTITUDE tilted, and the
vessels' estimators, levelling their IMUs, as good as on flat water, over MAVLink."""

from __future__ import annotations

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink
from scipy.spatial.transform import Rotation

from bob_autonomy.estimation import tilt
from firmware_bridge.autopilot_requests import set_message_interval
from firmware_bridge.commands import Encoder
from firmware_bridge.decoder import STANDARD_GRAVITY_MPS2, TelemetryDecoder
from firmware_bridge.readings import CompassReading, ImuReading, SensorReadings
from sitl.experiments.scenario import Scenario, ScenarioError, load_scenario
from sitl.fleets.fleet import LockstepFleet
from sitl.vehicles.mavlink_vehicle import BUOY, SimulatedVehicle, encode_readings, prepend_streams
from sitl.vehicles.sensors import tilted_imu
from sitl.world.waves import WaveSpec, hull_tilt


def _to_ned(heading, pitch, roll) -> Rotation:
    return Rotation.from_euler("ZYX", np.column_stack((np.pi / 2 - heading, pitch, roll)))


def test_a_hull_pitches_heading_into_the_waves_and_rolls_across_them() -> None:
    spec = WaveSpec(tilt_deg=6.0, period_s=4.0, length_m=20.0, toward_deg=0.0)  # travelling east
    at_crest_slope = np.zeros((2, 2))  # x = 0 at t = 0: the slope is at its largest
    roll, pitch, _ = hull_tilt(spec, 0.0, at_crest_slope, np.array([0.0, np.pi / 2]), np.zeros(2))
    np.testing.assert_allclose(np.degrees(pitch), [6.0, 0.0], atol=1e-12)  # heading east: along the waves
    # heading north, the surface rising to the east (the hull's right): right side up, a negative roll
    np.testing.assert_allclose(np.degrees(roll), [0.0, -6.0], atol=1e-12)


@pytest.mark.parametrize("seed", range(3))
def test_the_body_rates_are_those_of_the_attitude_the_hull_goes_through(seed: int) -> None:
    """Body rates from two scipy rotations of the hull's attitude 2 us apart, turning at random rates."""
    rng = np.random.default_rng(seed)
    spec = WaveSpec(
        tilt_deg=float(rng.uniform(3, 15)), period_s=float(rng.uniform(3, 9)), toward_deg=float(rng.uniform(0, 360))
    )
    n, h, t = 50, 1e-6, float(rng.uniform(0, 100))
    position, heading, turn = rng.uniform(-100, 100, (n, 2)), rng.uniform(-np.pi, np.pi, n), rng.normal(0, 0.5, n)
    roll, pitch, body = hull_tilt(spec, t, position, heading, turn)
    before = _to_ned(heading - turn * h, *hull_tilt(spec, t - h, position, heading - turn * h, turn)[1::-1])
    after = _to_ned(heading + turn * h, *hull_tilt(spec, t + h, position, heading + turn * h, turn)[1::-1])
    np.testing.assert_allclose((before.inv() * after).as_rotvec() / (2 * h), body, atol=1e-6)
    assert np.max(np.abs(roll)) > 0 and np.max(np.abs(pitch)) > 0


@pytest.mark.parametrize("seed", range(3))
def test_the_tilted_imu_reads_scipys_specific_force(seed: int) -> None:
    rng = np.random.default_rng(seed)
    k = 100
    level, roll, pitch = rng.normal(0, 1, (k, 2)), rng.uniform(-0.5, 0.5, k), rng.uniform(-0.5, 0.5, k)
    force, _ = tilted_imu(level, roll, pitch, np.zeros((k, 3)))
    a_frd = np.column_stack((level[:, 0], -level[:, 1], np.zeros(k)))
    want = _to_ned(np.full(k, np.pi / 2), pitch, roll).inv().apply(a_frd - [0.0, 0.0, STANDARD_GRAVITY_MPS2])
    np.testing.assert_allclose(force, want * [1.0, -1.0, -1.0], atol=1e-12)


def test_bad_wave_parameters_are_refused_with_the_scenarios_usual_error() -> None:
    data = load_scenario("aggregation").model_dump()
    for waves, words in (({"tilt_deg": 45.0}, "tilt_deg must be within 0-30"), ({"period_s": 0}, "period_s must be"),
                         ({"height_m": 1.0}, "height_m")):  # fmt: skip
        data["environment"]["waves"] = waves
        with pytest.raises((ScenarioError, ValueError), match=words):
            Scenario.model_validate(data)


def _estimate_errors(seed: int, tilt_deg: float) -> tuple[float, float]:
    """RMS position (m) and velocity (m/s) errors of 8 buoys' estimates against truth from 15 to 40 s, aggregation
    at physics fidelity over MAVLink with the waves' tilt."""
    data = load_scenario("aggregation").with_overrides(fidelity="physics", link="mavlink", agents=8, seed=seed)
    data = data.model_dump()
    data["environment"]["waves"] = {"tilt_deg": tilt_deg, "period_s": 5.0}
    fleet = LockstepFleet(Scenario.model_validate(data))
    bodies = fleet.bodies
    position, velocity = [], []
    while fleet.t < 40.0:
        fleet.step()
        if fleet.t > 15.0:
            e = bodies.buoy_vessels.estimate(fleet.t)
            position.append(np.hypot(*(e.position - bodies.physics.buoy.position_m).T))
            velocity.append(np.hypot(*(e.velocity - bodies.physics.buoy.velocity_mps).T))
    return float(np.sqrt(np.mean(np.square(position)))), float(np.sqrt(np.mean(np.square(velocity))))


@pytest.mark.parametrize("seed", range(3))
def test_buoys_in_8_degree_waves_estimate_as_well_as_on_flat_water_once_levelled(seed: int, monkeypatch) -> None:
    """8 deg of swell every 5 s, the whole stack (the simulated autopilots send the tilted SCALED_IMU and ATTITUDE,
    the vessels decode and level them). Levelled, the errors stay near flat water's (10 buoys, flat: 0.55 m,
    0.066 m/s); seeds 0-2, levelled 0.50-0.66 m, 0.066-0.076 m/s, with levelling switched off 0.53-1.48 m,
    0.13-0.44 m/s."""
    levelled = _estimate_errors(seed, 8.0)
    monkeypatch.setattr(tilt.TiltTracker, "level", lambda self, reading: reading)
    raw = _estimate_errors(seed, 8.0)
    print(f"seed {seed}: levelled {levelled[0]:.2f} m {levelled[1]:.3f} m/s; not {raw[0]:.2f} m {raw[1]:.3f} m/s")
    assert levelled[0] < 1.0 and levelled[1] < 0.12
    assert raw[1] > 1.5 * levelled[1]


@pytest.mark.parametrize("streams", ["sensor-rate", "ardupilot"])
def test_a_tilted_hulls_readings_go_out_in_attitude_and_the_whole_imu(streams: str) -> None:
    """A simulated autopilot handed tilted readings sends them in ATTITUDE (roll, pitch, rates) and SCALED_IMU (z
    and the x, y rates), at sensor rate or at its stream rates, and the vessel's decoder reads them back (to the
    messages' resolution: float32 angles, mG and mrad/s)."""
    vehicle = SimulatedVehicle(1, BUOY, 50.0, armed=True, streams=streams)
    if streams == "ardupilot":
        for message in (mavlink.MAVLINK_MSG_ID_ATTITUDE, mavlink.MAVLINK_MSG_ID_SCALED_IMU):
            vehicle.receive(set_message_interval(Encoder(), 1, message, 10.0), 0.0)
    one, t = np.array([0]), np.array([1.0])
    compass = CompassReading(
        one, t, np.array([0.7]), np.array([0.1]), np.array([-0.05]), np.array([[0.02, -0.03, 0.4]])
    )
    imu = ImuReading(one, t, np.array([[1.2, -0.8]]), np.array([-0.4]), np.array([9.7]), np.array([[0.02, 0.03]]))
    frames = [bytearray()]
    encode_readings(SensorReadings(compass=compass, imu=imu), 1.0, [vehicle], frames)
    prepend_streams(1.0, [vehicle], frames)
    readings = TelemetryDecoder(lambda: 1.0, source_system=1, source_component=1).feed(bytes(frames[0]))
    attitude = next(r for r in readings if isinstance(r, CompassReading))
    level = next(r for r in readings if isinstance(r, ImuReading))
    np.testing.assert_allclose([attitude.roll_rad[0], attitude.pitch_rad[0]], [0.1, -0.05], atol=1e-7)
    np.testing.assert_allclose(attitude.body_rates_frd_radps, [[0.02, -0.03, 0.4]], atol=1e-7)
    np.testing.assert_allclose(level.accel_z_mps2, [9.7], atol=0.01)
    np.testing.assert_allclose(level.gyro_xy_radps, [[0.02, 0.03]], atol=0.001)
    np.testing.assert_allclose(level.gyro_z_radps, [-0.4], atol=0.001)
