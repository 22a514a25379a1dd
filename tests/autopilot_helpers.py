"""Helpers for the simulated-autopilot tests: a ground station that packs real MAVLink 2 frames, pymavlink's own
parser on what the vehicle sends, and a sensor feed at fixed rates."""

from __future__ import annotations

import math

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sitl.vehicles.mavlink_vehicle import SimulatedVehicle

ORIGIN = (1.3405, 103.9560)
m = mavlink


class Gcs:
    """Frames from a ground station (system 255 by default, component 190)."""

    def __init__(self, system: int = 255, component: int = 190) -> None:
        self.mav = mavlink.MAVLink(None, srcSystem=system, srcComponent=component)

    def pack(self, message) -> bytes:
        data = bytes(message.pack(self.mav))
        self.mav.seq = (self.mav.seq + 1) % 256
        return data

    def long(self, command: int, *params: float, target: int = 1, component: int = 1) -> bytes:
        values = [float(p) for p in params] + [0.0] * (7 - len(params))
        return self.pack(self.mav.command_long_encode(target, component, command, 0, *values))

    def override(self, channels: dict[int, int], target: int = 1) -> bytes:
        raw = [65535] * 8 + [0] * 10
        for ch, pwm in channels.items():
            raw[ch - 1] = pwm
        return self.pack(self.mav.rc_channels_override_encode(target, 1, *raw))

    def heartbeat(self) -> bytes:
        return self.pack(self.mav.heartbeat_encode(m.MAV_TYPE_GCS, m.MAV_AUTOPILOT_INVALID, 0, 0, 0))


def parse(data: bytes) -> list:
    """Every message in `data`, by pymavlink's own parser (CRCs checked); fails the test on a bad frame."""
    parser = mavlink.MAVLink(None)
    messages = parser.parse_buffer(bytes(data)) or []
    assert parser.total_receive_errors == 0, "the vehicle sent a frame pymavlink cannot parse"
    return messages


def of_type(messages: list, name: str) -> list:
    return [msg for msg in messages if msg.get_type() == name]


def acks(data: bytes) -> list:
    return of_type(parse(data), "COMMAND_ACK")


def texts(messages: list) -> list[str]:
    return [msg.text for msg in of_type(messages, "STATUSTEXT")]


def run(
    vehicle: SimulatedVehicle,
    t0: float,
    t1: float,
    *,
    dt: float = 0.05,
    gps_hz: float = 5.0,
    compass_hz: float = 10.0,
    imu_hz: float = 20.0,
    gps: bool = True,
    position=ORIGIN,
    every_step=None,
) -> list:
    """Feed the vehicle sensor readings at fixed rates from t0 to t1 (s) and return every message it streams
    (`every_step(t)` may return bytes to send it first)."""
    out = bytearray()
    steps = round((t1 - t0) / dt)
    for k in range(steps):
        t = t0 + k * dt
        if every_step is not None:
            data = every_step(t)
            if data:
                out += vehicle.receive(data, t)
        if gps and _on(t, gps_hz, dt):
            vehicle.observe("gps", t, position[0], position[1], (0.3, 0.4))
        if _on(t, compass_hz, dt):
            vehicle.observe("compass", t, 0.5)
        if _on(t, imu_hz, dt):
            vehicle.observe("imu", t, (0.1, 0.0), 0.02)
        vehicle.actuator(t)
        out += vehicle.stream(t)
    return parse(bytes(out))


def _on(t: float, hz: float, dt: float) -> bool:
    period = 1.0 / hz
    return math.isclose(t / period, round(t / period), abs_tol=dt / period / 4) if hz * dt <= 1 else True


def count(messages: list, name: str) -> int:
    return len(of_type(messages, name))
