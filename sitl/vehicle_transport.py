"""How readings reach the vessels' autonomy and commands reach the simulated vehicles in a lockstep run.

`DirectTransport` hands the sensor readings over as objects and applies the
commands as they are (the behaviour-study fast path). `MavlinkTransport` is the
full stack without sockets: each vehicle is a `SimulatedVehicle` that encodes
its readings as MAVLink telemetry bytes, which the vessel's `VehicleLink`
(autonomy code) decodes; the vessel's commands go down as RC_CHANNELS_OVERRIDE
bytes that the vehicle decodes and applies, with its failsafe. Nothing passes
but bytes.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Callable

import numpy as np

from bob_autonomy.vehicle_link import VehicleLink
from firmware_bridge.readings import SensorReadings
from sitl.mavlink_vehicle import SimulatedVehicle

FloatArray = np.ndarray


class DirectTransport:
    """Readings and commands passed through untouched."""

    def down(self, commands: FloatArray, t_s: float) -> FloatArray:
        return commands

    def up(self, readings: SensorReadings, t_s: float) -> SensorReadings:
        return readings

    def counters(self) -> dict[str, int]:
        return {}


class MavlinkTransport:
    """n vehicles of one kind ("buoy" or "ebot"), system ids first_system_id.., talking MAVLink 2 bytes.

    max_actuator: full-scale thrust (N) or wheel speed (m/s) that RC 1900 us stands for. metres_per_tick:
    wheel travel per encoder tick (eBots report wheel travel in metres, as ArduPilot does). clock: the
    simulated time (s) the vessels stamp readings with.
    """

    def __init__(
        self,
        kind: str,
        n: int,
        max_actuator: float,
        clock: Callable[[], float],
        *,
        first_system_id: int = 1,
        metres_per_tick: float = 1.0,
        failsafe_s: float = 1.0,
    ) -> None:
        self.metres_per_tick = metres_per_tick
        self.vehicles = [
            SimulatedVehicle(first_system_id + k, kind, max_actuator, failsafe_s=failsafe_s, armed=True)
            for k in range(n)
        ]
        self.links = [VehicleLink(first_system_id + k, kind, max_actuator, clock, agent=k) for k in range(n)]

    def down(self, commands: FloatArray, t_s: float) -> FloatArray:
        """Encode each vessel's command, let its vehicle decode it; returns what the vehicles apply (n, 2)."""
        applied = np.zeros((len(self.vehicles), 2))
        for k, (link, vehicle) in enumerate(zip(self.links, self.vehicles, strict=True)):
            replies = vehicle.receive(link.command(commands[k]), t_s)
            if replies:
                link.receive(replies)
            applied[k] = vehicle.actuator(t_s)
        return applied

    def up(self, readings: SensorReadings, t_s: float) -> list[object]:
        """Encode each vehicle's new readings (and its 1 Hz housekeeping) as telemetry; returns the readings the
        vessels decode from it."""
        frames: dict[int, bytearray] = defaultdict(bytearray)
        for k, vehicle in enumerate(self.vehicles):
            frames[k] += vehicle.housekeeping(t_s)
        if readings.imu is not None:
            m = readings.imu
            for i, k in enumerate(m.agents):
                frames[k] += self.vehicles[k].telemetry.scaled_imu(t_s, m.accel_body_mps2[i], m.gyro_z_radps[i])
        if readings.gps is not None:
            g = readings.gps
            for i, k in enumerate(g.agents):
                velocity = None if g.velocity_mps is None else g.velocity_mps[i]
                frames[k] += self.vehicles[k].telemetry.gps_raw_int(t_s, g.lat_deg[i], g.lon_deg[i], velocity)
        if readings.compass is not None:
            c = readings.compass
            for i, k in enumerate(c.agents):
                frames[k] += self.vehicles[k].telemetry.attitude(t_s, c.heading_rad[i])
        if readings.encoders is not None:
            e = readings.encoders
            for i, k in enumerate(e.agents):
                frames[k] += self.vehicles[k].telemetry.wheel_distance(t_s, e.ticks[i] * self.metres_per_tick)
        decoded: list[object] = []
        for k in sorted(frames):
            decoded += self.links[k].receive(bytes(frames[k]))
        return decoded

    def counters(self) -> dict[str, int]:
        """Totals over the vehicles and the vessels' decoders."""
        totals = defaultdict(int)
        for vehicle in self.vehicles:
            for name, value in vars(vehicle.counters).items():
                totals[f"vehicle_{name}"] += value
        for link in self.links:
            c = link.decoder.counters
            for name in ("decoded", "bad_crc", "malformed", "unknown", "skipped_bytes"):
                totals[f"vessel_{name}"] += getattr(c, name)
        return dict(totals)
