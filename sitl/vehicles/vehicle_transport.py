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

from bob_autonomy.onboard.autopilot import AutopilotSession
from bob_autonomy.onboard.senses import EbotSenses
from bob_autonomy.onboard.vehicle_link import BUOY, VehicleLink, command_frames, receive_all
from firmware_bridge.commands import rc_override
from firmware_bridge.override_batch import read_overrides
from firmware_bridge.rc_channels import RcMap, ResolutionCarry
from firmware_bridge.readings import SensorReadings
from sitl.vehicles.mavlink_vehicle import MOTORBOAT, SimulatedVehicle, encode_readings, encode_senses, prepend_streams
from sitl.vehicles.reading_batches import merge_by_round

FloatArray = np.ndarray


class DirectTransport:
    """Readings and commands passed through untouched."""

    def down(self, commands: FloatArray, t_s: float) -> FloatArray:
        return commands

    def up(self, readings: SensorReadings, t_s: float) -> SensorReadings:
        return readings

    def counters(self) -> dict[str, int]:
        return {}


DEFAULT_RC_MAP = RcMap()  # ArduPilot's default RC map and calibration, Rover's dead zone


def motorboat_override(
    throttle: float, steering: float, target_system: int, encoder, carry: ResolutionCarry | None = None
) -> bytes:
    """A motorboat's throttle and steering (each in [-1, 1]) as the vessel sends them (AutopilotSession.override
    at ArduPilot's default RC calibration): steering on channel 1, throttle on 3, lateral at TRIM; the steering as
    it is, because on a motorboat frame the autopilot negates it twice in reverse (Rover/mode.cpp get_pilot_input
    with PILOT_STEER_TYPE 0, AP_MotorsUGV::output_regular: AutopilotProfile.steering_flips_in_reverse). carry:
    the throttle's error diffusion over whole percent."""
    if carry is not None:
        throttle = carry(DEFAULT_RC_MAP.throttle, throttle)
    channels = DEFAULT_RC_MAP.channels_for(steering, throttle, 0.0)
    return rc_override(channels, target_system, 1, encoder=encoder)


class MavlinkTransport:
    """n vehicles of one kind ("buoy", "ebot" or "motorboat"), system ids first_system_id.., talking MAVLink 2 bytes.

    max_actuator: full-scale thrust (N) or wheel speed (m/s) that full RC deflection stands for. metres_per_tick:
    wheel travel per encoder tick (eBots report wheel travel in metres, as ArduPilot does). clock: the
    simulated time (s) the vessels stamp readings with; the vehicles boot at its time at construction (a lockstep
    run's pre-roll starts below zero), so their messages carry positive times since boot. streams,
    vehicle_params: as `SimulatedVehicle`'s streams and params. With ArduPilot's stream defaults (1 Hz) each
    vessel asks its vehicle for its messages at the start, with the requests `bob-autonomy` sends
    (`bob_autonomy.onboard.autopilot.AutopilotSession`).
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
        streams: str = "ardupilot",
        vehicle_params: dict[str, float] | None = None,
    ) -> None:
        self.metres_per_tick = metres_per_tick
        self.kind = kind
        boot_s = float(clock())
        self.vehicles = [
            SimulatedVehicle(
                first_system_id + k,
                kind,
                max_actuator,
                failsafe_s=failsafe_s,
                armed=True,
                streams=streams,
                params=vehicle_params,
                boot_s=boot_s,
            )
            for k in range(n)
        ]
        telemetry = BUOY if kind == MOTORBOAT else kind  # a motorboat's telemetry is a buoy's (GPS, compass, IMU)
        self.links = [VehicleLink(first_system_id + k, telemetry, max_actuator, clock, agent=k) for k in range(n)]
        self.sensing: list[EbotSenses] | None = None  # each eBot vessel's range and light readings
        for k, (link, vehicle) in enumerate(zip(self.links, self.vehicles, strict=True)):
            session = AutopilotSession(first_system_id + k, kind, link.encoder, clock)
            replies = vehicle.receive(b"".join(session.stream_requests()), float(clock()))
            if replies:
                link.receive(replies)

    def down(self, commands: FloatArray, t_s: float) -> FloatArray:
        """Encode each vessel's command, let its vehicle decode it; returns what the vehicles apply (n, 2). The
        overrides are encoded and read for all vessels at once (`command_frames`, `read_overrides`: the same
        bytes and the same handling as one at a time)."""
        if self.kind == MOTORBOAT:
            frames = [
                motorboat_override(commands[k, 0], commands[k, 1], link.target_system, link.encoder, link.carry)
                for k, link in enumerate(self.links)
            ]
        else:
            frames = command_frames(self.links, commands)
        read = read_overrides([vehicle.reader for vehicle in self.vehicles], frames)
        applied = np.zeros((len(self.vehicles), 2))
        for k, (vehicle, data, override) in enumerate(zip(self.vehicles, frames, read, strict=True)):
            if override is not None:
                vehicle.receive_override(override[0], override[2], t_s)
            else:
                replies = vehicle.receive(data, t_s)
                if replies:
                    self.links[k].receive(replies)
            applied[k] = vehicle.actuator(t_s)
        return applied

    def up(self, readings: SensorReadings, t_s: float) -> list[object]:
        """Encode each vehicle's new readings (and its 1 Hz housekeeping) as telemetry; returns the readings the
        vessels decode from it."""
        frames = [bytearray() for _ in self.vehicles]
        encode_readings(readings, t_s, self.vehicles, frames, metres_per_tick=self.metres_per_tick)
        prepend_streams(t_s, self.vehicles, frames)
        # Decoded all at once (firmware_bridge.batch_decoder), fused as one batch per kind and round
        # (sitl.vehicles.reading_batches).
        decoded, columns = receive_all(self.links, [bytes(data) for data in frames])
        return merge_by_round(decoded, columns)

    def senses(
        self,
        agents: np.ndarray,
        ranges_m: FloatArray,
        light: FloatArray,
        heading_rad: FloatArray,
        t_s: float,
        sonar_angles_rad: FloatArray,
        max_range_m: float,
    ) -> tuple[FloatArray, FloatArray]:
        """eBots `agents` (this transport's vehicle indices) send their sonar ranges (k, sonars) m and light
        readings (k, 2) as telemetry; each vessel turns what it decodes into its Senses with its own heading
        estimate (k,) rad. Returns obstacles (k, sonars, 2) m (world-aligned offsets) and light (k, 2)."""
        if self.sensing is None:
            self.sensing = [EbotSenses(sonar_angles_rad) for _ in self.vehicles]
        frames = [bytearray() for _ in self.vehicles]
        encode_senses(t_s, self.vehicles, frames, agents, ranges_m, light, max_range_m)
        obstacles = np.full((len(agents), len(sonar_angles_rad), 2), np.nan)
        seen_light = np.full((len(agents), 2), np.nan)
        for j, k in enumerate(agents):
            self.sensing[k].feed(self.links[k].receive(bytes(frames[k])))
            s = self.sensing[k].senses(float(heading_rad[j]), t_s)
            obstacles[j], seen_light[j] = s.obstacles[0], s.light[0]
        return obstacles, seen_light

    def counters(self) -> dict[str, int]:
        """Totals over the vehicles and the vessels' decoders."""
        totals = defaultdict(int)
        for vehicle in self.vehicles:
            for name, value in vars(vehicle.counters).items():
                totals[f"vehicle_{name}"] += value
        for link in self.links:
            c = link.decoder.counters
            for name in ("decoded", "bad_crc", "malformed", "unknown", "skipped_bytes", "no_fix", "repeated_fix"):
                totals[f"vessel_{name}"] += getattr(c, name)
            for name, count in c.by_type.items():
                totals[f"vessel_decoded_{name}"] += count
        return dict(totals)
