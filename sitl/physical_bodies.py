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

from bob_autonomy.ekf import BuoyEkfBank, EbotEkfBank
from bob_autonomy.geodesy import LocalFrame
from bob_autonomy.mpc import BuoyMpc, DiffDriveMpc
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
        estimator: str = "simple",
        controller: str = "simple",
        dt_s: float = 0.1,
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
        self.use_ekf, self.use_mpc = estimator == "ekf", controller == "mpc"
        wheel_base, per_tick = self.ebot_params.wheel_base_m, encoders.metres_per_tick
        # eBots start from a known pose (the paper's robots are told theirs) and dead-reckon from there.
        if self.use_ekf:
            self.buoy_estimator = BuoyEkfBank(b.size)
            self.ebot_estimator = EbotEkfBank(self.position[e], self.heading[e], wheel_base, per_tick)
        else:
            self.buoy_estimator = AlphaBetaBuoyEstimator(b.size)
            self.ebot_estimator = OdometryEstimator(self.position[e], self.heading[e], wheel_base, per_tick)
        self.buoy_controller = BuoyVelocityController()
        self.ebot_controller = DiffDriveController(wheel_base, self.ebot_params.max_wheel_speed_mps)
        self.buoy_mpcs = [BuoyMpc(dt_s=dt_s) for _ in range(b.size)] if self.use_mpc else []
        self.ebot_mpcs = (
            [DiffDriveMpc(wheel_base, self.ebot_params.max_wheel_speed_mps, dt_s=dt_s) for _ in range(e.size)]
            if self.use_mpc
            else []
        )
        self.thrust_world_n = np.zeros((b.size, 2))  # last command, world frame (the EKF's known input)
        self.mpc_fallbacks = 0
        self.t = -PRE_ROLL_S
        self.wind = np.zeros_like(self.position)
        self.current = np.zeros_like(self.position)
        while self.t < -1e-9:
            self.apply(np.zeros((len(self), 2)), np.full(len(self), np.nan), 0.1, World())

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
        estimate = self._estimate()
        b, e = self.buoys, self.ebots
        self.wind = self.environment.wind_at(self.position)
        self.current = self.environment.current_at(self.position)
        if self.buoy is not None:
            thrust = self._buoy_thrust(wish_velocity[b], estimate, pre_roll=self.t < 0.0)
            self.buoy.active = self.active[b]
            self.buoy.step(thrust, dt, self.wind[b], self.current[b], self.max_thrust_n)
            self.position[b], self.velocity[b], self.heading[b] = (
                self.buoy.position_m,
                self.buoy.velocity_mps,
                self.buoy.heading_rad,
            )
        if self.ebot is not None:
            wheels = self._ebot_wheels(wish_velocity[e], wish_heading[e], estimate.heading[e])
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

    def _buoy_thrust(self, wish: FloatArray, estimate: PoseEstimate, pre_roll: bool) -> FloatArray:
        """Body-frame thrust (N) for every buoy from its controller; world thrust kept for the EKF."""
        b = self.buoys
        velocity, heading = estimate.velocity[b], estimate.heading[b]
        if self.use_mpc and not pre_roll:
            water = self.buoy_estimator.drift() if self.use_ekf else np.zeros_like(velocity)
            results = [
                mpc.solve(wish[k], velocity[k], water[k], heading[k], self.max_thrust_n[k])
                for k, mpc in enumerate(self.buoy_mpcs)
            ]
            self.mpc_fallbacks = sum(m.fallbacks for m in self.buoy_mpcs)
            self.thrust_world_n = np.array([r.thrust_world_n for r in results]).reshape(-1, 2)
            return np.array([r.thrust_body_n for r in results]).reshape(-1, 2)
        body = self.buoy_controller.thrust(wish, velocity, heading, self.max_thrust_n)
        c, s = np.cos(np.nan_to_num(heading)), np.sin(np.nan_to_num(heading))
        self.thrust_world_n = np.column_stack((c * body[:, 0] - s * body[:, 1], s * body[:, 0] + c * body[:, 1]))
        return body

    def _ebot_wheels(self, wish: FloatArray, wish_heading: FloatArray, heading: FloatArray) -> FloatArray:
        """Wheel speeds (m/s) for every eBot from its controller."""
        simple = self.ebot_controller.wheels(wish, wish_heading, heading)
        if not self.use_mpc or self.t < 0.0:
            return simple
        # The MPC tracks a velocity vector; turning in place to a wished heading stays the simple controller's.
        turning = ~np.isnan(wish_heading) & (np.hypot(wish[:, 0], wish[:, 1]) < 1e-6)
        wheels = np.array([mpc.solve(wish[k], heading[k]).wheels_mps for k, mpc in enumerate(self.ebot_mpcs)])
        self.mpc_fallbacks = sum(m.fallbacks for m in self.ebot_mpcs)
        return np.where(turning[:, None], simple, wheels.reshape(-1, 2))

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
                self._compass(self.ebot_estimator, readings)

    def _compass(self, estimator, readings: SensorReadings) -> None:
        """Feed compass readings (the EKFs take their measurement times)."""
        c = readings.compass
        if self.use_ekf:
            estimator.update_compass(c.agents, c.heading_rad, c.t_s)
        else:
            estimator.update_compass(c.agents, c.heading_rad)

    def _estimate_buoys(self, readings: SensorReadings) -> None:
        if self.use_ekf and readings.imu is not None:
            # The accelerometer drives the prediction; the commanded thrust makes the drift observable.
            imu = readings.imu
            self.buoy_estimator.predict(imu.agents, imu.t_s, imu.accel_body_mps2, self.thrust_world_n[imu.agents])
            self.buoy_estimator.update_gyro(imu.agents, imu.t_s, imu.gyro_z_radps)
        if readings.gps is not None:
            fix = readings.gps
            x, y = self.frame.to_local(fix.lat_deg, fix.lon_deg)
            self.buoy_estimator.update_gps(fix.agents, fix.t_s, np.column_stack((x, y)), fix.velocity_mps)
        if readings.compass is not None:
            self._compass(self.buoy_estimator, readings)

    def range_finders(self, rows: NDArray[np.int_], world: World) -> FloatArray:
        """The sonar echoes of the kinematic model, with range noise."""
        return noisy_ranges(super().range_finders(rows, world), self.rng, self.range_spec)

    def light_sensors(self, rows: NDArray[np.int_], world: World) -> FloatArray:
        """The light readings of the kinematic model, with noise."""
        return noisy_light(super().light_sensors(rows, world), self.rng, self.light_spec)

    def environment_at(self) -> tuple[FloatArray, FloatArray]:
        """(wind, current) at each body, m/s, as last applied."""
        return self.wind, self.current
