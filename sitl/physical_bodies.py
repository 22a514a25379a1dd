"""Bodies at physics fidelity: dynamics, wind and current, sensors, and the vessel's own estimator and controller.

The behaviour sees only what the vessel believes: the pose its estimator makes
of the simulated sensors' readings. Its wish goes through the vessel's velocity
controller (autonomy code, `bob_autonomy`) into thrust or wheel commands, which
the simulated dynamics apply. Truth stays here, for the metrics and the
recording. Same interface as the kinematic bodies, so the lockstep fleet runs
either.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from bob_autonomy.geodesy import LocalFrame
from bob_autonomy.simple_estimator import AlphaBetaBuoyEstimator, OdometryEstimator, PoseEstimate
from bob_autonomy.velocity_control import BuoyVelocityController, DiffDriveController
from firmware_bridge.readings import SensorReadings
from sitl.bodies import KinematicBodies
from sitl.dynamics import BuoyDynamics, BuoyParams, DiffDriveDynamics, DiffDriveParams
from sitl.environment import Environment
from sitl.sensors import (
    CompassSpec,
    EncoderSpec,
    GpsSpec,
    ImuSpec,
    LightSpec,
    RangeSpec,
    SensorSuite,
    noisy_light,
    noisy_ranges,
)
from sitl.world import FloatArray, World

PRE_ROLL_S = 2.0  # sensors and estimators run this long before t = 0, as a vessel powered up before the mission


class PhysicalBodies(KinematicBodies):
    """Truth from the dynamics; `believed()` from each vessel's estimator; commands from its controller."""

    def __init__(
        self,
        kinds: NDArray[np.int_],
        position: FloatArray,
        heading: FloatArray,
        environment: Environment,
        frame: LocalFrame,
        rng: np.random.Generator,
        thrust_fraction: FloatArray,
        sensor_specs: dict[str, object],
    ) -> None:
        super().__init__(kinds, position, heading)
        self.environment = environment
        self.rng = rng
        b, e = self.buoys, self.ebots
        self.buoy_params, self.ebot_params = BuoyParams(), DiffDriveParams()
        self.buoy = BuoyDynamics(self.buoy_params, self.position[b], self.heading[b], rng) if b.size else None
        self.ebot = DiffDriveDynamics(self.ebot_params, self.position[e], self.heading[e], rng) if e.size else None
        self.max_thrust_n = self.buoy_params.max_thrust_n * np.asarray(thrust_fraction, dtype=float)[b]
        self.range_spec: RangeSpec = sensor_specs.get("ranges", RangeSpec())
        self.light_spec: LightSpec = sensor_specs.get("light", LightSpec())
        encoders: EncoderSpec = sensor_specs.get("encoders", EncoderSpec())
        self.buoy_sensors = SensorSuite(
            b.size,
            frame,
            rng,
            sensor_specs.get("gps", GpsSpec()),
            sensor_specs.get("compass", CompassSpec()),
            sensor_specs.get("imu", ImuSpec()),
            None,
        )
        self.ebot_sensors = SensorSuite(
            e.size,
            frame,
            rng,
            None,
            sensor_specs.get("compass", CompassSpec()),
            sensor_specs.get("imu", ImuSpec()),
            encoders,
        )
        self.frame = frame
        self.buoy_estimator = AlphaBetaBuoyEstimator(b.size)
        # eBots start from a known pose (the paper's robots are told theirs) and dead-reckon from there.
        self.ebot_estimator = OdometryEstimator(
            self.position[e], self.heading[e], self.ebot_params.wheel_base_m, encoders.metres_per_tick
        )
        self.buoy_controller = BuoyVelocityController()
        self.ebot_controller = DiffDriveController(self.ebot_params.wheel_base_m, self.ebot_params.max_wheel_speed_mps)
        self.t = -PRE_ROLL_S
        self.wind = np.zeros_like(self.position)
        self.current = np.zeros_like(self.position)
        self.estimator_rejected = 0
        while self.t < -1e-9:
            self._advance(np.zeros((len(self), 2)), np.full(len(self), np.nan), 0.1, World())

    def believed(self) -> tuple[FloatArray, FloatArray, FloatArray]:
        """(position, heading, velocity) each vessel believes it has (estimates, not truth)."""
        estimate = self._estimate()
        return estimate.position, estimate.heading, estimate.velocity

    def _estimate(self) -> PoseEstimate:
        n = len(self)
        out = PoseEstimate(np.full((n, 2), np.nan), np.zeros((n, 2)), np.full(n, np.nan))
        for rows, estimator in ((self.buoys, self.buoy_estimator), (self.ebots, self.ebot_estimator)):
            if rows.size:
                e = estimator.estimate(self.t)
                out.position[rows], out.velocity[rows], out.heading[rows] = e.position, e.velocity, e.heading
        return out

    def apply(self, wish_velocity: FloatArray, wish_heading: FloatArray, dt: float, world: World) -> None:
        """One control step: controllers on the estimates, dynamics, environment, sensors, estimators."""
        self._advance(wish_velocity, wish_heading, dt, world)

    def _advance(self, wish_velocity: FloatArray, wish_heading: FloatArray, dt: float, world: World) -> None:
        estimate = self._estimate()
        b, e = self.buoys, self.ebots
        self.wind = self.environment.wind_at(self.position)
        self.current = self.environment.current_at(self.position)
        if self.buoy is not None:
            thrust = self.buoy_controller.thrust(
                wish_velocity[b], estimate.velocity[b], estimate.heading[b], self.max_thrust_n
            )
            self.buoy.active = self.active[b]
            self.buoy.step(thrust, dt, self.wind[b], self.current[b], self.max_thrust_n)
            self.position[b], self.velocity[b], self.heading[b] = (
                self.buoy.position_m,
                self.buoy.velocity_mps,
                self.buoy.heading_rad,
            )
        if self.ebot is not None:
            wheels = self.ebot_controller.wheels(wish_velocity[e], wish_heading[e], estimate.heading[e])
            self.ebot.active = self.active[e]
            self.ebot.step(wheels, dt, world)
            self.position[e], self.velocity[e], self.heading[e] = (
                self.ebot.position_m,
                self.ebot.velocity_mps,
                self.ebot.heading_rad,
            )
            self.wall_contacts = self.ebot.wall_contacts
            self.robot_contacts = self.ebot.robot_contacts
        self.environment.step(dt)
        self.t += dt
        self._sense()

    def _sense(self) -> None:
        """Sample the sensors at the new time and feed the estimators."""
        if self.buoy is not None:
            d = self.buoy
            readings = self.buoy_sensors.sample(
                self.t, d.position_m, d.velocity_mps, d.acceleration_mps2, d.heading_rad, d.yaw_rate_radps
            )
            self._estimate_buoys(readings)
        if self.ebot is not None:
            d = self.ebot
            readings = self.ebot_sensors.sample(
                self.t,
                d.position_m,
                d.velocity_mps,
                d.acceleration_mps2,
                d.heading_rad,
                d.yaw_rate_radps,
                d.wheel_travel_m,
            )
            if readings.encoders is not None:
                r = readings.encoders
                self.ebot_estimator.update_encoders(r.agents, r.t_s, r.ticks)
            if readings.compass is not None:
                self.ebot_estimator.update_compass(readings.compass.agents, readings.compass.heading_rad)

    def _estimate_buoys(self, readings: SensorReadings) -> None:
        if readings.gps is not None:
            fix = readings.gps
            x, y = self.frame.to_local(fix.lat_deg, fix.lon_deg)
            self.buoy_estimator.update_gps(fix.agents, fix.t_s, np.column_stack((x, y)), fix.velocity_mps)
        if readings.compass is not None:
            self.buoy_estimator.update_compass(readings.compass.agents, readings.compass.heading_rad)

    def range_finders(self, rows: NDArray[np.int_], world: World) -> FloatArray:
        """The sonar echoes of the kinematic model, with range noise."""
        return noisy_ranges(super().range_finders(rows, world), self.rng, self.range_spec)

    def light_sensors(self, rows: NDArray[np.int_], world: World) -> FloatArray:
        """The light readings of the kinematic model, with noise."""
        return noisy_light(super().light_sensors(rows, world), self.rng, self.light_spec)

    def environment_at(self) -> tuple[FloatArray, FloatArray]:
        """(wind, current) at each body, m/s, as last applied."""
        return self.wind, self.current
