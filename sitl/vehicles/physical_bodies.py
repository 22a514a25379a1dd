"""Bodies at physics fidelity: dynamics, wind and current, sensors, and the vessel's own estimator and controller.

The behaviour sees only what the vessel believes: the pose its estimator makes
of the simulated sensors' readings. Its wish goes through the vessel's velocity
controller (autonomy code, `bob_autonomy`) into thrust or wheel commands, which
the simulated dynamics apply. The physics (dynamics, environment, sensors and
truth) is `sitl.vehicles.vehicle_physics.VehiclePhysics`, shared with the process fleet;
truth stays there, for the metrics and the recording. Same interface as the
kinematic bodies, so the lockstep fleet runs either.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from bob_autonomy.control.motorboat_control import MotorboatModel
from bob_autonomy.core.geodesy import LocalFrame
from bob_autonomy.estimation.simple_estimator import PoseEstimate
from bob_autonomy.onboard.pipeline import EbotPipeline, MotorboatPipeline
from sitl.vehicles.autopilot_params import parameter_default
from sitl.vehicles.bodies import BODY_SPECS, EBOT_SONAR_ANGLES_RAD, KinematicBodies
from sitl.vehicles.bodies import EBOT as EBOT_KIND
from sitl.vehicles.mavlink_vehicle import EBOT, MOTORBOAT
from sitl.vehicles.motorboat import MotorboatParams
from sitl.vehicles.sensors import noisy_light, noisy_ranges
from sitl.vehicles.vehicle_physics import PRE_ROLL_S, VehiclePhysics
from sitl.vehicles.vehicle_transport import DirectTransport, MavlinkTransport
from sitl.vehicles.vessel_shards import BuoyShard, BuoyShardSpec, ShardedBuoys
from sitl.world.environment import Environment
from sitl.world.world import FloatArray, World


def _truth(name: str) -> property:
    """An attribute of the physics (ground truth), readable and assignable through the bodies."""

    def get(self: PhysicalBodies):
        return getattr(self.physics, name)

    def set_(self: PhysicalBodies, value) -> None:
        setattr(self.physics, name, value)

    return property(get, set_, doc=f"`physics.{name}` (ground truth)")


class PhysicalBodies(KinematicBodies):
    """Truth from the dynamics; `believed()` from each vessel's estimator; commands from its controller."""

    position = _truth("position")
    velocity = _truth("velocity")
    heading = _truth("heading")
    active = _truth("active")
    wind = _truth("wind")
    current = _truth("current")
    wall_contacts = _truth("wall_contacts")
    robot_contacts = _truth("robot_contacts")
    t = _truth("t")

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
        motorboat_params: list[MotorboatParams] | None = None,
        vessel_processes: int = 1,
    ) -> None:
        self.physics = VehiclePhysics(
            kinds, position, heading, environment, frame, rng, thrust_fraction, sensor_specs, t0_s=-PRE_ROLL_S,
            motorboat_params=motorboat_params,
        )  # fmt: skip
        super().__init__(kinds, position, heading)  # truth attributes go to the physics (same values)
        p = self.physics
        self.environment, self.rng, self.frame, self.dt_s = environment, rng, frame, dt_s
        self.buoy_params, self.ebot_params, self.buoy, self.ebot = p.buoy_params, p.ebot_params, p.buoy, p.ebot
        self.max_thrust_n = p.max_thrust_n
        self.range_spec, self.light_spec = p.range_spec, p.light_spec
        self.buoy_sensors, self.ebot_sensors = p.buoy_sensors, p.ebot_sensors
        b, e = self.buoys, self.ebots
        wheel_base, per_tick = self.ebot_params.wheel_base_m, p.metres_per_tick
        # Simulated time: an MPC solve is never too slow for it, so a loaded machine cannot change a run.
        options = {"estimator": estimator, "controller": controller, "dt_s": dt_s, "mpc_time_budget_s": math.inf}
        # The buoys' vessel side (estimators, controllers, MAVLink links with their autopilots), in this process or
        # spread over `vessel_processes` (sitl.vehicles.vessel_shards; the same results). In this process its
        # pipeline and link are `buoy_vessels` and `buoy_link`; spread, those are None.
        spec = BuoyShardSpec(0, self.max_thrust_n, frame, self.buoy_params.max_thrust_n, options, link, self.t)
        self.buoy_side: BuoyShard | ShardedBuoys
        if vessel_processes > 1 and b.size > 1:
            self.buoy_side = ShardedBuoys(spec, vessel_processes)
            self.buoy_vessels, self.buoy_link = None, None
        else:
            self.buoy_side = BuoyShard(spec)
            self.buoy_vessels, self.buoy_link = self.buoy_side.pipeline, self.buoy_side.link
        # eBots start from a known pose (the paper's robots are told theirs) and dead-reckon from there. Over MAVLink
        # the simulated autopilot (a skid-steer rover) slews their throttle as it does a boat's, and they plan with it.
        ebot_slew = parameter_default(EBOT, "MOT_SLEWRATE") / 100.0 if link == "mavlink" else 0.0
        self.ebot_vessels = EbotPipeline(
            self.position[e],
            self.heading[e],
            wheel_base,
            self.ebot_params.max_wheel_speed_mps,
            per_tick,
            throttle_slew_per_s=ebot_slew,
            **options,
        )
        # Motorboats: each vessel knows its boat's top speed and turning radius (a real one reads SPEED_MAX and
        # TURN_RADIUS from its autopilot) and estimates as a buoy does.
        m = self.motorboats
        boats = p.motorboat_params
        self.max_speed[m] = [q.top_speed_mps for q in boats]
        self.turning_radius[m] = [q.turning_radius_m for q in boats]
        # Over MAVLink the simulated autopilot slews the throttle (MOT_SLEWRATE), and the vessel plans with the
        # slew it reads (bob_autonomy.onboard.autopilot.AutopilotProfile.throttle_slew_per_s); the direct link has none.
        slew = parameter_default(MOTORBOAT, "MOT_SLEWRATE") / 100.0 if link == "mavlink" else 0.0
        models = [MotorboatModel.for_top_speed(q.top_speed_mps, q.turning_radius_m, slew) for q in boats]
        self.motorboat_vessels = MotorboatPipeline(m.size, frame, models, p.motorboat_thrust_fraction, **options)
        self.link = link
        self._mavlink_light: tuple | None = None  # (t, rows, light) decoded with this step's range finders
        if link == "mavlink":

            def clock() -> float:  # the vessels stamp readings with the simulated time
                return self.t

            self.ebot_link = MavlinkTransport(
                EBOT,
                e.size,
                self.ebot_params.max_wheel_speed_mps,
                clock,
                first_system_id=b.size + 1,
                metres_per_tick=per_tick,
            )
            self.motorboat_link = MavlinkTransport(
                MOTORBOAT, m.size, 1.0, clock, first_system_id=b.size + e.size + 1, metres_per_tick=per_tick
            )
        elif link == "direct":
            self.ebot_link = self.motorboat_link = DirectTransport()
        else:
            raise ValueError(f"unknown vehicle link {link!r}; choose direct or mavlink")
        while self.t < -1e-9:
            self.apply(np.zeros((len(self), 2)), np.full(len(self), np.nan), 0.1, World())

    def close(self) -> None:
        """Stop the vessel worker processes, if any (a run's end; also done when the bodies are collected)."""
        self.buoy_side.close()

    @property
    def mpc_fallbacks(self) -> int:
        return self.buoy_side.status()[0] + self.ebot_vessels.mpc_fallbacks + self.motorboat_vessels.mpc_fallbacks

    def link_counters(self) -> dict[str, int]:
        """MAVLink counters of the vehicles and vessels (empty for the direct link)."""
        totals: dict[str, int] = {}
        counted = [t.counters() for t in {id(t): t for t in (self.ebot_link, self.motorboat_link)}.values()]
        for counters in (self.buoy_side.status()[1], *counted):
            for name, value in counters.items():
                totals[name] = totals.get(name, 0) + value
        if self.motorboats.size:  # wishes a motorboat could not follow (turn in place, move sideways): said, counted
            totals["motorboat_sideways_wishes"] = self.motorboat_vessels.sideways_wishes
        return totals

    def believed(self) -> tuple[FloatArray, FloatArray, FloatArray]:
        """(position, heading, velocity) each vessel believes it has (estimates, not truth)."""
        estimate = self._estimate()
        return estimate.position, estimate.heading, estimate.velocity

    def _estimate(self) -> PoseEstimate:
        n = len(self)
        out = PoseEstimate(np.full((n, 2), np.nan), np.zeros((n, 2)), np.full(n, np.nan))
        pairs = ((self.buoys, self.buoy_side), (self.ebots, self.ebot_vessels))
        for rows, vessels in (*pairs, (self.motorboats, self.motorboat_vessels)):
            if rows.size:
                e = vessels.estimate(self.t)
                out.position[rows], out.velocity[rows], out.heading[rows] = e.position, e.velocity, e.heading
        return out

    def apply(self, wish_velocity: FloatArray, wish_heading: FloatArray, dt: float, world: World) -> None:
        """One control step: the vessels' controllers, the link, dynamics, environment, sensors, estimators."""
        b, e, m = self.buoys, self.ebots, self.motorboats
        idle = self.t < 0.0
        thrust = np.zeros((b.size, 2))
        wheels = np.zeros((e.size, 2))
        boats = None
        if b.size:
            thrust = self.buoy_side.command(wish_velocity[b], self.t, idle)
        if e.size:
            wheels = self.ebot_vessels.wheels(wish_velocity[e], wish_heading[e], self.t, idle=idle)
            wheels = self.ebot_link.down(wheels, self.t)
        if m.size:
            if not idle:
                self.motorboat_vessels.check_wish(wish_velocity[m], wish_heading[m])
            boats = self.motorboat_vessels.commands(wish_velocity[m], self.t, idle=idle)
            boats = self.motorboat_link.down(boats, self.t)
        self.physics.step(thrust, wheels, dt, world, boats)
        self._sense()

    def _sense(self) -> None:
        """Sample the sensors at the new time; the readings go up the link to the vessels' estimators."""
        readings = self.physics.sense()
        if "buoy" in readings:
            self.buoy_side.sense(readings["buoy"], self.t)
        if "ebot" in readings:
            self.ebot_vessels.feed(self.ebot_link.up(readings["ebot"], self.t))
        if "motorboat" in readings:
            self.motorboat_vessels.feed(self.motorboat_link.up(readings["motorboat"], self.t))

    def range_finders(self, rows: NDArray[np.int_], world: World) -> FloatArray:
        """The sonar echoes of the kinematic model, with range noise. Over the MAVLink link they travel as
        DISTANCE_SENSOR (with the light readings) and each vessel places them with its own heading estimate."""
        offsets = noisy_ranges(super().range_finders(rows, world), self.rng, self.range_spec)
        if self.link != "mavlink":
            return offsets
        light = noisy_light(super().light_sensors(rows, world), self.rng, self.light_spec)
        index = np.searchsorted(self.ebots, rows)
        heading = self.ebot_vessels.estimate(self.t).heading[index]
        ranges = np.hypot(offsets[..., 0], offsets[..., 1])
        obstacles, seen_light = self.ebot_link.senses(
            index, ranges, light, heading, self.t, EBOT_SONAR_ANGLES_RAD, BODY_SPECS[EBOT_KIND].range_max_m
        )
        self._mavlink_light = (self.t, rows.copy(), seen_light)
        return obstacles

    def light_sensors(self, rows: NDArray[np.int_], world: World) -> FloatArray:
        """The light readings of the kinematic model, with noise (over MAVLink: as the vessels decoded them
        with this step's range finders)."""
        cached = self._mavlink_light
        if self.link == "mavlink" and cached is not None and cached[0] == self.t and np.array_equal(cached[1], rows):
            return cached[2]
        return noisy_light(super().light_sensors(rows, world), self.rng, self.light_spec)

    def environment_at(self) -> tuple[FloatArray, FloatArray]:
        """(wind, current) at each body, m/s, as last applied."""
        return self.wind, self.current
