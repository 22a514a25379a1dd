"""The autonomy's MAVLink conversation with its own vehicle: telemetry in, actuator commands out.

Transport-free (bytes in, bytes out), so that the `bob-autonomy` process (over a
UDP, TCP or serial link) and the lockstep simulator (bytes in memory) run the
very same decoding and command code. Decoding never raises (see
`firmware_bridge.decoder`); a vehicle that stops sending HEARTBEATs is reported
by `silent()`.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from bob_autonomy.core.arrays import finite_pair
from firmware_bridge.batch_decoder import Columns, decode_batch
from firmware_bridge.commands import (
    CHANNEL_LATERAL,
    CHANNEL_STEERING,
    CHANNEL_THROTTLE,
    DEFAULT_RC_RANGE,
    Encoder,
    command_long_arm,
    rc_override,
    rc_override_for_thrust,
    rc_override_for_wheels,
    set_mode,
)
from firmware_bridge.decoder import Battery, CommandAck, Heartbeat, HeartbeatWatch, Reading, TelemetryDecoder
from firmware_bridge.override_batch import carried_units, pwm_table
from firmware_bridge.rc_channels import STEERING_FULL_SCALE, THROTTLE_FULL_SCALE, ResolutionCarry

BUOY, EBOT = "buoy", "ebot"
AUTOPILOT_COMPONENT = 1  # MAV_COMP_ID_AUTOPILOT1: the only component whose telemetry moves the estimate


class VehicleLink:
    """One vehicle (MAVLink system `target_system`) as the autonomy sees it.

    kind: "buoy" (commands are body-frame thrust, N) or "ebot" (wheel speeds, m/s). max_actuator: the
    actuator's full scale (N or m/s), which RC 1900 us stands for. agent: the row its readings carry.
    clock: seconds, stamps readings at reception (a GPS fix when it was taken: `TelemetryDecoder.fix_time`, less
    gps_lag_s). heartbeat_timeout_s: silence after which `silent()` is true.

    Only the vehicle's autopilot is believed: telemetry, heartbeats and acknowledgements from any other
    system id or from a component other than 1 (MAV_COMP_ID_AUTOPILOT1) are dropped and counted
    (`decoder.counters.other_system`, `other_component`).
    """

    def __init__(
        self,
        target_system: int,
        kind: str,
        max_actuator: float,
        clock: Callable[[], float],
        *,
        agent: int = 0,
        heartbeat_timeout_s: float = 3.0,
        encoder: Encoder | None = None,
        gps_lag_s: float = 0.0,
    ) -> None:
        if kind not in (BUOY, EBOT):
            raise ValueError(f"unknown vehicle kind {kind!r}; choose buoy or ebot")
        self.target_system, self.kind, self.max_actuator = target_system, kind, float(max_actuator)
        # Raw GPS only: the autopilot's fused GLOBAL_POSITION_INT would be a second, correlated fix.
        self.decoder = TelemetryDecoder(
            clock,
            agent=agent,
            source_system=target_system,
            source_component=AUTOPILOT_COMPONENT,
            fused_position=False,
            gps_lag_s=gps_lag_s,
        )
        self.watch = HeartbeatWatch(heartbeat_timeout_s, clock, system=target_system)
        self.encoder = encoder if encoder is not None else Encoder()
        self.last_heartbeat: Heartbeat | None = None
        self.battery: Battery | None = None
        self.acks: list[CommandAck] = []
        self.carry = ResolutionCarry()  # commands finer than the autopilot's whole percent, spread over overrides

    def receive(self, data: bytes) -> list[Reading]:
        """Decode bytes from the vehicle; returns the sensor readings (GPS, compass, IMU, wheels) among them."""
        return self._take(self.decoder.feed(data))

    def _take(self, readings: list) -> list:
        """Keep the link's own news (heartbeat, battery, acknowledgements); return the rest, in order."""
        sensors = []
        for reading in readings:
            if isinstance(reading, Heartbeat):  # the autopilot's: the decoder keeps only component 1
                self.watch.beat(reading.t_s)
                self.last_heartbeat = reading
            elif isinstance(reading, Battery):
                self.battery = reading
            elif isinstance(reading, CommandAck):
                self.acks.append(reading)
            else:
                sensors.append(reading)
        return sensors

    def silent(self) -> bool:
        """True when the vehicle has not been heard for longer than the timeout (its HEARTBEAT; a vessel also counts
        every other message of its autopilot)."""
        return self.watch.is_silent()

    @property
    def armed(self) -> bool:
        return bool(self.last_heartbeat is not None and self.last_heartbeat.armed)

    def command(self, actuator: np.ndarray) -> bytes:
        """RC_CHANNELS_OVERRIDE for a thrust (x forward, y left; N) or wheel speeds (left, right; m/s)."""
        a, carry = finite_pair(actuator), self.carry
        if self.kind == BUOY:
            return rc_override_for_thrust(a, self.max_actuator, self.target_system, encoder=self.encoder, carry=carry)
        return rc_override_for_wheels(
            a[0], a[1], self.max_actuator, self.target_system, encoder=self.encoder, carry=carry
        )

    def stop(self) -> bytes:
        """A neutral command: thrusters or wheels at zero."""
        return self.command(np.zeros(2))

    def arm(self, arm: bool = True) -> bytes:
        """COMMAND_LONG arm (or disarm); the vehicle answers with a COMMAND_ACK (see `acks`)."""
        return command_long_arm(arm, self.target_system, encoder=self.encoder)

    def set_mode(self, mode: str | int) -> bytes:
        """COMMAND_LONG set mode (a Rover mode name or number)."""
        return set_mode(mode, self.target_system, encoder=self.encoder)

    def take_ack(self, command: int) -> CommandAck | None:
        """Remove and return the oldest COMMAND_ACK for `command`, if one has arrived."""
        for k, ack in enumerate(self.acks):
            if ack.command == command:
                return self.acks.pop(k)
        return None


def receive_all(links: Sequence[VehicleLink], chunks: Sequence[bytes]) -> tuple[list[list[object]], Columns | None]:
    """links[k].receive(chunks[k]) for every k at once (`firmware_bridge.batch_decoder`): per link its sensor
    readings in order, those of the column-wise types as `Row`s of the returned `Columns` (None when the batch
    was off the fast path and every link decoded its own chunk, giving readings only)."""
    batch = decode_batch([link.decoder for link in links], chunks)
    if batch is None:
        return [link.receive(chunk) if chunk else [] for link, chunk in zip(links, chunks, strict=True)], None
    per_link, columns = batch
    return [link._take(readings) for link, readings in zip(links, per_link, strict=True)], columns


_NEUTRAL_STEERING = DEFAULT_RC_RANGE.pwm_for(0.0, STEERING_FULL_SCALE)


def command_frames(links: Sequence[VehicleLink], actuators: np.ndarray) -> list[bytes]:
    """[links[k].command(actuators[k]) for every k], the same bytes, with the error diffusion and the PWMs
    computed for all links at once (`firmware_bridge.override_batch`); the links must be of one kind. Each frame
    is still packed by its link's encoder (its own sequence number)."""
    if not links:
        return []
    scale = np.array([link.max_actuator for link in links])
    kinds = {link.kind for link in links}
    if len(kinds) != 1 or not (np.all(np.isfinite(scale)) and np.all(scale > 0)):
        return [link.command(a) for link, a in zip(links, actuators, strict=True)]
    a = np.nan_to_num(np.asarray(actuators, dtype=float).reshape(len(links), 2))  # as finite_pair does
    first, second = a[:, 0] / scale, a[:, 1] / scale
    carries = [link.carry for link in links]
    table = pwm_table(DEFAULT_RC_RANGE, THROTTLE_FULL_SCALE)
    if kinds == {BUOY}:  # rc_override_for_thrust: throttle x / max, lateral -y / max, steering neutral
        throttle = carried_units(carries, CHANNEL_THROTTLE, first)
        lateral = carried_units(carries, CHANNEL_LATERAL, -second)
        lateral_pwm = table[lateral.astype(np.intp) + THROTTLE_FULL_SCALE].tolist()
        steering_pwm = [_NEUTRAL_STEERING] * len(links)
    else:  # rc_override_for_wheels: throttle the mean, steering half the difference
        throttle = carried_units(carries, CHANNEL_THROTTLE, (first + second) / 2.0)
        lateral_pwm = None
        steering_pwm = [DEFAULT_RC_RANGE.pwm_for(d, STEERING_FULL_SCALE) for d in ((first - second) / 2.0).tolist()]
    throttle_pwm = table[throttle.astype(np.intp) + THROTTLE_FULL_SCALE].tolist()
    frames = []
    for k, link in enumerate(links):
        channels = {CHANNEL_THROTTLE: throttle_pwm[k], CHANNEL_STEERING: steering_pwm[k]}
        if lateral_pwm is not None:
            channels[CHANNEL_LATERAL] = lateral_pwm[k]
        frames.append(rc_override(channels, link.target_system, 1, encoder=link.encoder))
    return frames
