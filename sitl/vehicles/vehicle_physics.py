"""The simulated vehicles' physics: dynamics, wind and current, sensors and ground truth, without any autonomy.

What a vehicle's hardware does, and nothing of what its autonomy does: it applies
actuator commands (buoy: body-frame thrust x forward, y left, N; eBot: left and
right wheel speeds, m/s; motorboat: throttle and steering, each in [-1, 1], see
`sitl.vehicles.motorboat`) for a time step, and its sensors sample the truth into
the typed readings a vessel would receive. The lockstep fleet
(`sitl.vehicles.physical_bodies.PhysicalBodies`) puts every vessel's estimator and
controller between the two in memory; the process fleet (`sitl.fleets.process_fleet`)
puts MAVLink over UDP and one `bob-autonomy` process per vessel there. Truth
(`position`, `velocity`, `heading`, `active`, `wind`, `current`) stays here for
the metrics and the recording.

Every random draw comes from the generators given (dynamics and sensors from
`rng`, gusts from the environment's own), in a fixed order per step (buoy
dynamics, eBot dynamics, motorboat dynamics, gusts, buoy sensors, eBot sensors,
motorboat sensors), so a run with a seed is exactly repeatable; motorboats draw
nothing when there are none, so fleets without them are unchanged.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from bob_autonomy.core.geodesy import LocalFrame
from firmware_bridge.readings import SensorReadings
from sitl.vehicles.bodies import BUOY, EBOT, MOTORBOAT, KinematicBodies
from sitl.vehicles.dynamics import BuoyDynamics, BuoyParams, DiffDriveDynamics, DiffDriveParams
from sitl.vehicles.motorboat import MotorboatDynamics, MotorboatParams
from sitl.vehicles.sensors import (
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
from sitl.world.environment import Environment
from sitl.world.waves import hull_tilt
from sitl.world.world import FloatArray, World

PRE_ROLL_S = 2.0  # sensors and estimators run this long before t = 0, as a vessel powered up before the mission


def _row_index(rows: NDArray[np.intp]) -> NDArray[np.intp] | slice:
    """Sorted distinct rows as an index: a slice when they are contiguous (indexing gives views), else the rows."""
    if rows.size and rows[-1] - rows[0] == rows.size - 1:
        return slice(int(rows[0]), int(rows[-1]) + 1)
    return rows


class VehiclePhysics:
    """N simulated vehicles (buoys and eBots) in one environment: actuators in, truth and sensor readings out.

    kinds (N,): sitl.vehicles.bodies.BUOY or EBOT per vehicle. position (N, 2) m, heading (N,) rad: the start poses.
    environment: wind and current. frame: the local frame the GPS converts positions with. rng: draws the
    dynamics' and the sensors' noise. thrust_fraction (N,): each buoy's thrust limit as a fraction of nominal
    (weak batteries; ignored for eBots). sensor_specs: {"gps", "compass", "imu", "encoders", "ranges",
    "light"} -> spec (defaults for missing ones). t0_s: the simulated time at construction, s.
    motorboat_params: one MotorboatParams per motorboat (in row order; default: sitl.vehicles.motorboat's defaults);
    their
    thrust_fraction applies too (weak batteries).

    Rows: `buoys`, `ebots` and `motorboats` are the fleet rows of each kind, in order; actuator arrays and the
    readings' `agents` are indexed within a kind (row `buoys[k]` is buoy k).
    """

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
        t0_s: float = 0.0,
        motorboat_params: list[MotorboatParams] | None = None,
    ) -> None:
        self.kind = np.asarray(kinds, dtype=int)
        self.position = np.asarray(position, dtype=float).copy()
        self.heading = np.asarray(heading, dtype=float).copy()
        self.velocity = np.zeros_like(self.position)
        n = self.kind.shape[0]
        self.active = np.ones(n, dtype=bool)
        self.buoys = np.flatnonzero(self.kind == BUOY)
        self.ebots = np.flatnonzero(self.kind == EBOT)
        self.environment, self.frame, self.rng = environment, frame, rng
        b, e = self.buoys, self.ebots
        self.buoy_params, self.ebot_params = BuoyParams(), DiffDriveParams()
        self.buoy = BuoyDynamics(self.buoy_params, self.position[b], self.heading[b], rng) if b.size else None
        self.ebot = DiffDriveDynamics(self.ebot_params, self.position[e], self.heading[e], rng) if e.size else None
        self.max_thrust_n = self.buoy_params.max_thrust_n * np.asarray(thrust_fraction, dtype=float)[b]
        self.range_spec: RangeSpec = sensor_specs.get("ranges", RangeSpec())
        self.light_spec: LightSpec = sensor_specs.get("light", LightSpec())
        self.encoder_spec: EncoderSpec = sensor_specs.get("encoders", EncoderSpec())
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
            self.encoder_spec,
        )
        # Motorboats last, so that a fleet without them draws exactly what it did before they existed.
        m = self.motorboats = np.flatnonzero(self.kind == MOTORBOAT)
        self.motorboat_params = list(motorboat_params) if motorboat_params is not None else [MotorboatParams()] * m.size
        if len(self.motorboat_params) != m.size:
            raise ValueError(f"{len(self.motorboat_params)} motorboat parameter sets for {m.size} motorboats")
        self.motorboat_thrust_fraction = np.asarray(thrust_fraction, dtype=float)[m]
        self.motorboat: MotorboatDynamics | None = None
        self.motorboat_sensors: SensorSuite | None = None
        if m.size:
            self.motorboat = MotorboatDynamics(self.motorboat_params, self.position[m], self.heading[m], rng)
            self.motorboat_sensors = SensorSuite(
                m.size,
                frame,
                rng,
                sensor_specs.get("gps", GpsSpec()),
                sensor_specs.get("compass", CompassSpec()),
                sensor_specs.get("imu", ImuSpec()),
                None,
            )
        # The rows of each kind as a slice when they are contiguous (the usual case): views instead of copies.
        self._buoy_rows, self._ebot_rows = _row_index(self.buoys), _row_index(self.ebots)
        self._motorboat_rows = _row_index(m)
        self.t = float(t0_s)
        self.wind = np.zeros_like(self.position)
        self.current = np.zeros_like(self.position)
        self.wall_contacts = 0
        self.robot_contacts = 0

    def __len__(self) -> int:
        return int(self.kind.shape[0])

    @property
    def max_wheel_speed_mps(self) -> float:
        """The eBots' wheel speed limit, m/s (what RC 1900 us stands for)."""
        return self.ebot_params.max_wheel_speed_mps

    @property
    def metres_per_tick(self) -> float:
        """Wheel travel per encoder tick, m."""
        return self.encoder_spec.metres_per_tick

    def step(
        self,
        thrust_body_n: FloatArray,
        wheels_mps: FloatArray,
        dt_s: float,
        world: World,
        motorboat_commands: FloatArray | None = None,
    ) -> None:
        """Apply the actuators for dt_s s: (len(buoys), 2) body-frame thrust, N (x forward, y left; clipped to
        each buoy's limit), (len(ebots), 2) wheel speeds, m/s (left, right) and (len(motorboats), 2) throttle and
        steering (None: neutral). Inactive vehicles do not move.

        Wind and current are taken at the positions before the step and held over it (`wind`, `current`).
        """
        b, e = self._buoy_rows, self._ebot_rows
        self.wind = self.environment.wind_at(self.position)
        self.current = self.environment.current_at(self.position)
        if self.buoy is not None:
            self.buoy.active = self.active[b].copy()
            self.buoy.step(thrust_body_n, dt_s, self.wind[b], self.current[b], self.max_thrust_n)
            self.position[b], self.velocity[b], self.heading[b] = (
                self.buoy.position_m,
                self.buoy.velocity_mps,
                self.buoy.heading_rad,
            )
        if self.ebot is not None:
            self.ebot.active = self.active[e].copy()
            self.ebot.step(wheels_mps, dt_s, world)
            self.position[e], self.velocity[e], self.heading[e] = (
                self.ebot.position_m,
                self.ebot.velocity_mps,
                self.ebot.heading_rad,
            )
            self.wall_contacts = self.ebot.wall_contacts
            self.robot_contacts = self.ebot.robot_contacts
        if self.motorboat is not None:
            m = self._motorboat_rows
            boats = self.motorboat
            boats.active = self.active[m].copy()
            command = np.zeros((self.motorboats.size, 2)) if motorboat_commands is None else motorboat_commands
            boats.step(command, dt_s, self.wind[m], self.current[m], self.motorboat_thrust_fraction)
            self.position[m], self.velocity[m] = boats.position_m, boats.velocity_mps
            self.heading[m] = boats.heading_rad
        self.environment.step(dt_s)
        self.t += dt_s

    def hold(self, dt_s: float) -> None:
        """Let dt_s s pass with every vehicle held still where it is (moored before its release): no dynamics,
        no gusts, no random draws; the sensors go on measuring the unchanged truth (`sense`)."""
        self.wind = self.environment.wind_at(self.position)
        self.current = self.environment.current_at(self.position)
        self.t += dt_s

    def sense(self) -> dict[str, SensorReadings]:
        """Sample the sensors at the current time: {"buoy": ..., "ebot": ..., "motorboat": ...} readings for the kinds
        present.

        The readings' `agents` index vehicles within their kind; times are simulated seconds. Call once per
        step, after `step`.
        """
        out: dict[str, SensorReadings] = {}
        if self.buoy is not None:
            d = self.buoy
            out["buoy"] = self.buoy_sensors.sample(
                self.t, d.position_m, d.velocity_mps, d.acceleration_mps2, d.heading_rad, d.yaw_rate_radps,
                tilt=self._tilt(d),
            )  # fmt: skip
        if self.ebot is not None:
            d = self.ebot
            out["ebot"] = self.ebot_sensors.sample(
                self.t,
                d.position_m,
                d.velocity_mps,
                d.acceleration_mps2,
                d.heading_rad,
                d.yaw_rate_radps,
                d.wheel_travel_m,
            )
        if self.motorboat is not None and self.motorboat_sensors is not None:
            d = self.motorboat
            out["motorboat"] = self.motorboat_sensors.sample(
                self.t, d.position_m, d.velocity_mps, d.acceleration_mps2, d.heading_rad, d.yaw_rate_radps,
                tilt=self._tilt(d),
            )  # fmt: skip
        return out

    def _tilt(self, hulls) -> tuple[FloatArray, FloatArray, FloatArray] | None:
        """The roll, pitch and body rates the waves give floating hulls now (None on flat water)."""
        waves = self.environment.waves
        if not waves.on:
            return None
        return hull_tilt(waves, self.t, hulls.position_m, hulls.heading_rad, hulls.yaw_rate_radps)

    def ebot_senses(self, world: World) -> tuple[FloatArray, FloatArray]:
        """The eBots' noisy sonar ranges (n_ebots, 6) m (NaN: no echo) and light readings (n_ebots, 2) W/m^2,
        from the same geometry and noise models as the lockstep bodies (sitl.vehicles.bodies, sitl.vehicles.sensors)."""
        e = self.ebots
        view = KinematicBodies(self.kind, self.position, self.heading)
        view.active[:] = self.active
        offsets = noisy_ranges(view.range_finders(e, world), self.rng, self.range_spec)
        light = noisy_light(view.light_sensors(e, world), self.rng, self.light_spec)
        return np.hypot(offsets[..., 0], offsets[..., 1]), light

    def stop(self, rows: NDArray[np.intp]) -> None:
        """Deactivate vehicles (fleet rows): they stop and no longer move (a removed vessel)."""
        self.active[np.asarray(rows, dtype=np.intp)] = False
