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
from bob_autonomy.pipeline import BuoyPipeline, EbotPipeline
from bob_autonomy.simple_estimator import PoseEstimate
from sitl.bodies import KinematicBodies
from sitl.dynamics import BuoyDynamics, BuoyParams, DiffDriveDynamics, DiffDriveParams
from sitl.environment import Environment
from sitl.mavlink_vehicle import BUOY, EBOT
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
from sitl.vehicle_transport import DirectTransport, MavlinkTransport
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
        link: str = "direct",
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
        self.dt_s = dt_s
        wheel_base, per_tick = self.ebot_params.wheel_base_m, encoders.metres_per_tick
        options = {"estimator": estimator, "controller": controller, "dt_s": dt_s}
        self.buoy_vessels = BuoyPipeline(b.size, frame, self.max_thrust_n, **options)
        # eBots start from a known pose (the paper's robots are told theirs) and dead-reckon from there.
        self.ebot_vessels = EbotPipeline(
            self.position[e], self.heading[e], wheel_base, self.ebot_params.max_wheel_speed_mps, per_tick, **options
        )
        self.link = link
        self.t = -PRE_ROLL_S
        if link == "mavlink":

            def clock() -> float:  # the vessels stamp readings with the simulated time
                return self.t

            self.buoy_link = MavlinkTransport(BUOY, b.size, self.buoy_params.max_thrust_n, clock)
            self.ebot_link = MavlinkTransport(
                EBOT,
                e.size,
                self.ebot_params.max_wheel_speed_mps,
                clock,
                first_system_id=b.size + 1,
                metres_per_tick=per_tick,
            )
        elif link == "direct":
            self.buoy_link = self.ebot_link = DirectTransport()
        else:
            raise ValueError(f"unknown vehicle link {link!r}; choose direct or mavlink")
        self.wind = np.zeros_like(self.position)
        self.current = np.zeros_like(self.position)
        while self.t < -1e-9:
            self.apply(np.zeros((len(self), 2)), np.full(len(self), np.nan), 0.1, World())

    @property
    def mpc_fallbacks(self) -> int:
        return self.buoy_vessels.mpc_fallbacks + self.ebot_vessels.mpc_fallbacks

    def link_counters(self) -> dict[str, int]:
        """MAVLink counters of the vehicles and vessels (empty for the direct link)."""
        totals: dict[str, int] = {}
        for transport in {id(t): t for t in (self.buoy_link, self.ebot_link)}.values():
            for name, value in transport.counters().items():
                totals[name] = totals.get(name, 0) + value
        return totals

    def believed(self) -> tuple[FloatArray, FloatArray, FloatArray]:
        """(position, heading, velocity) each vessel believes it has (estimates, not truth)."""
        estimate = self._estimate()
        return estimate.position, estimate.heading, estimate.velocity

    def _estimate(self) -> PoseEstimate:
        n = len(self)
        out = PoseEstimate(np.full((n, 2), np.nan), np.zeros((n, 2)), np.full(n, np.nan))
        for rows, vessels in ((self.buoys, self.buoy_vessels), (self.ebots, self.ebot_vessels)):
            if rows.size:
                e = vessels.estimate(self.t)
                out.position[rows], out.velocity[rows], out.heading[rows] = e.position, e.velocity, e.heading
        return out

    def apply(self, wish_velocity: FloatArray, wish_heading: FloatArray, dt: float, world: World) -> None:
        """One control step: the vessels' controllers, the link, dynamics, environment, sensors, estimators."""
        b, e = self.buoys, self.ebots
        idle = self.t < 0.0
        self.wind = self.environment.wind_at(self.position)
        self.current = self.environment.current_at(self.position)
        if self.buoy is not None:
            thrust = self.buoy_link.down(self.buoy_vessels.thrust(wish_velocity[b], self.t, idle=idle), self.t)
            self.buoy.active = self.active[b]
            self.buoy.step(thrust, dt, self.wind[b], self.current[b], self.max_thrust_n)
            self.position[b], self.velocity[b], self.heading[b] = (
                self.buoy.position_m,
                self.buoy.velocity_mps,
                self.buoy.heading_rad,
            )
        if self.ebot is not None:
            wheels = self.ebot_vessels.wheels(wish_velocity[e], wish_heading[e], self.t, idle=idle)
            wheels = self.ebot_link.down(wheels, self.t)
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
        """Sample the sensors at the new time; the readings go up the link to the vessels' estimators."""
        if self.buoy is not None:
            d = self.buoy
            readings = self.buoy_sensors.sample(
                self.t, d.position_m, d.velocity_mps, d.acceleration_mps2, d.heading_rad, d.yaw_rate_radps
            )
            self.buoy_vessels.feed(self.buoy_link.up(readings, self.t))
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
            self.ebot_vessels.feed(self.ebot_link.up(readings, self.t))

    def range_finders(self, rows: NDArray[np.int_], world: World) -> FloatArray:
        """The sonar echoes of the kinematic model, with range noise."""
        return noisy_ranges(super().range_finders(rows, world), self.rng, self.range_spec)

    def light_sensors(self, rows: NDArray[np.int_], world: World) -> FloatArray:
        """The light readings of the kinematic model, with noise."""
        return noisy_light(super().light_sensors(rows, world), self.rng, self.light_spec)

    def environment_at(self) -> tuple[FloatArray, FloatArray]:
        """(wind, current) at each body, m/s, as last applied."""
        return self.wind, self.current
