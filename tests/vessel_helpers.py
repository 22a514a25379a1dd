"""Stand-ins for autonomy-process tests: the simulator's autopilot on a real UDP socket, and a serial port that
can be unplugged and plugged in again."""

from __future__ import annotations

import math
import os
import queue
import socket
import threading
import tty

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from bob_autonomy.core.behavior_config import BehaviorChoice
from bob_autonomy.core.clock import ScaledWallClock
from bob_autonomy.core.geodesy import LocalFrame
from bob_autonomy.onboard.vessel import VesselConfig
from sitl.vehicles.mavlink_vehicle import SimulatedVehicle

ORIGIN = (1.3405, 103.9560)
SCALE = 5.0  # the vessel's and the stand-in vehicle's clocks run 5x wall time


def _without_heartbeats(data: bytes) -> bytes:
    """The MAVLink frames of `data` but its HEARTBEATs."""
    parser = mavlink.MAVLink(None)
    messages = parser.parse_buffer(data) or []
    return b"".join(bytes(m.get_msgbuf()) for m in messages if m.get_type() != "HEARTBEAT")


class StandInVehicle(threading.Thread):
    """SimulatedVehicle on a UDP socket moving a point-mass buoy (1 m/s at full thrust), GPS 5 Hz, compass 10 Hz.
    kind: the autopilot's frame ("buoy", or "motorboat": its first output then moves the point mass 1/45 m/s)."""

    def __init__(self, start_xy=(0.0, 0.0), system_id: int = 1, kind: str = "buoy") -> None:
        super().__init__(daemon=True)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.01)
        self.port = self.sock.getsockname()[1]
        self.vehicle = SimulatedVehicle(system_id, kind, 45.0 if kind == "buoy" else 1.0, failsafe_s=1.0)
        self.frame = LocalFrame(*ORIGIN)
        self.clock = ScaledWallClock(SCALE)
        self.position = np.array(start_xy, dtype=float)
        self.heading = 0.3
        self.peer = None
        self.running = threading.Event()
        self.running.set()
        self.muted = threading.Event()  # set: sends nothing
        self.deaf = threading.Event()  # set: hears nothing (a broken wire from the vessel), still sends
        self.no_fix = threading.Event()  # set: its GPS has no fix (GPS_RAW_INT fix type 1, no satellites)
        self.no_attitude = threading.Event()  # set: it sends no ATTITUDE (no heading)
        self.no_heartbeat = threading.Event()  # set: its HEARTBEATs are lost (a noisy line), the rest comes
        self.from_ground: queue.Queue[bytes] = queue.Queue()  # frames of a ground station on another port
        self.applied: list[np.ndarray] = []

    def run(self) -> None:
        last = self.clock.now()
        next_gps = next_att = last
        while self.running.is_set():
            try:
                data, self.peer = self.sock.recvfrom(65535)
                replies = b"" if self.deaf.is_set() else self.vehicle.receive(data, self.clock.now())
                if replies and not self.muted.is_set():
                    self.sock.sendto(replies, self.peer)
            except TimeoutError:
                pass
            now = self.clock.now()
            while not self.from_ground.empty():  # answered on that port (not here); announcements go to all
                self.vehicle.receive(self.from_ground.get_nowait(), now)
            if now < last:  # rebooted: its clock starts again
                last = next_gps = next_att = now
            thrust = self.vehicle.actuator(now)
            self.applied.append(thrust)
            c, s = math.cos(self.heading), math.sin(self.heading)
            world = np.array([c * thrust[0] - s * thrust[1], s * thrust[0] + c * thrust[1]])
            velocity = world / 45.0
            self.position += velocity * (now - last)
            last = now
            if self.peer is None or self.muted.is_set():
                continue
            out = self.vehicle.housekeeping(now)
            if now >= next_gps:
                next_gps = now + 0.2
                lat, lon = self.frame.to_geodetic(self.position[0], self.position[1])
                if self.no_fix.is_set():
                    out += self.vehicle.telemetry.gps_raw_int(now, 0.0, 0.0, None, fix_type=1, satellites=0)
                else:
                    out += self.vehicle.telemetry.gps_raw_int(now, float(lat), float(lon), velocity)
            if now >= next_att and not self.no_attitude.is_set():
                next_att = now + 0.1
                out += self.vehicle.telemetry.attitude(now, self.heading)
            if out and self.no_heartbeat.is_set():
                out = _without_heartbeats(out)
            if out:
                self.sock.sendto(out, self.peer)

    def reboot(self) -> None:
        """The autopilot restarts (a brownout): a fresh one, disarmed, at its default streams, with its clock since
        boot (time_boot_ms) from zero again; the boat stays where it is."""
        kind = self.vehicle.kind
        self.clock = ScaledWallClock(SCALE)
        self.vehicle = SimulatedVehicle(self.vehicle.system_id, kind, 45.0 if kind == "buoy" else 1.0, failsafe_s=1.0)

    def close(self) -> None:
        self.running.clear()
        self.join(2.0)
        self.sock.close()


class PluggedPty:
    """A serial device on a USB adapter, reached by a stable path (as udev's /dev/serial/by-id/ names it): a
    pseudo-terminal whose `master` is the device's side. `unplug()` closes it under whoever opened the path and
    removes the path; `replug()` brings a new one behind the same path."""

    def __init__(self, path) -> None:
        self.path = path
        self.master: int | None = None
        self.replug()

    def replug(self) -> None:
        master, slave = os.openpty()
        tty.setraw(slave)
        os.symlink(os.ttyname(slave), self.path)
        os.close(slave)  # the vessel opens it by the path
        self.master = master

    def unplug(self) -> None:
        os.close(self.master)
        self.master = None
        os.unlink(self.path)


def ground_station_vessel_config(vehicle_port: int, **overrides) -> VesselConfig:
    """A vessel for a stand-in vehicle on `vehicle_port`, with a ground-station link (udpin on a free port) and its
    behaviour not started, for ground-station tests; `overrides` replace any field."""
    values = dict(
        vehicle=f"udpout:127.0.0.1:{vehicle_port}",
        system_id=1,
        behavior=BehaviorChoice(behavior="bob-rule", params={"p0": 10.0}),
        origin=ORIGIN,
        controller="simple",
        gcs="udpin:127.0.0.1:0",
        autostart=False,
    )
    values.update(overrides)
    return VesselConfig(**values)
