"""A simulated eBot on a pseudo-terminal, speaking the eBot serial protocol (docs/ebot-serial.md).

    sim = EbotSerialSim()                       # opens a pty and starts stepping the robot in real time
    robot = EbotSerial.connect(sim.device_path)  # e.g. /dev/pts/7: any serial client talks to it
    ...
    sim.pose()                                  # ground truth: (x m, y m, heading rad)
    sim.close()                                 # closes the pty: the client's port fails as if unplugged

One robot, stepped by a thread in real time (every `dt_s` of wall time) with the simulator's own parts:
`sitl.vehicles.dynamics.DiffDriveDynamics` (differential drive, wheel limits 0.20 m/s, slip, wall contacts) in a
`sitl.world.world.World` (by default a 4 m x 3 m room with one light), the sonar geometry of
`sitl.vehicles.bodies.KinematicBodies.range_finders` (six sonars, 1.5 m range) and its light sensors, with the noise
models of `sitl.vehicles.sensors` (`noisy_ranges`, `noisy_light`; pass `range_spec=None`, `light_spec=None` for exact
readings). The protocol's wheel speed s in [-1, 1] drives the wheel at s * max_wheel_speed_mps.

What the robot reports (the conventions of docs/ebot-serial.md): `2P` is its true pose (a perfect localizer)
in mm and mrad; `2A` the true acceleration of the last step in the body frame plus gravity on z (mG) and the
yaw rate on gz (mrad/s); `2S` ranges from the robot's centre (mm, 0 = no echo); `2D` irradiance (mW/m^2);
`2V` the battery voltage (mV), which falls slowly while the wheels turn.

Test hooks: `commands()` (every line received, raw bytes, with the simulation time it arrived),
`inject(data)` (write raw bytes to the client), `queue_noise(lines)` (lines sent before the next reply),
`answer_handshake` / `identity` (to make the handshake fail), and the truth accessors.
"""

from __future__ import annotations

import contextlib
import errno
import os
import select
import threading
import time
import tty
from dataclasses import dataclass

import numpy as np

from sitl.vehicles.bodies import EBOT, KinematicBodies
from sitl.vehicles.dynamics import DiffDriveDynamics, DiffDriveParams
from sitl.vehicles.sensors import LightSpec, RangeSpec, noisy_light, noisy_ranges, world_to_body
from sitl.world.world import World, polygon_segments

__all__ = ["EbotSerialSim", "ReceivedCommand", "default_world"]

_DEFAULT_RANGE = RangeSpec()
_DEFAULT_LIGHT = LightSpec()
GRAVITY_MG = 1000.0
STANDARD_GRAVITY_MPS2 = 9.80665


def default_world() -> World:
    """A 4 m x 3 m room (corners (0, 0) and (4, 3), m) with a 20 W light at (3.5, 2.5)."""
    room = np.array([[0.0, 0.0], [4.0, 0.0], [4.0, 3.0], [0.0, 3.0]])
    return World(
        walls=polygon_segments(room),
        rooms=[room],
        light_positions=np.array([[3.5, 2.5]]),
        light_power_w=np.array([20.0]),
    )


@dataclass(frozen=True)
class ReceivedCommand:
    """One line the simulated robot received: its raw bytes (terminator included) and the simulation time (s)."""

    t_s: float
    line: bytes


class EbotSerialSim:
    """A simulated eBot serving the serial protocol on the master side of a pseudo-terminal.

    world: walls and lights (default `default_world()`); position (m), heading_rad: the start pose;
    params: the drive (wheel limit, slip); dt_s: the real-time step (s); seed: the slip and sensor noise;
    range_spec, light_spec: sensor noise (None: exact); voltage_v: the battery at start (V);
    identity: the line answering `<<1?`; answer_handshake: False makes the robot ignore the handshake.
    """

    def __init__(
        self,
        *,
        world: World | None = None,
        position: tuple[float, float] = (1.0, 1.5),
        heading_rad: float = 0.0,
        params: DiffDriveParams | None = None,
        dt_s: float = 0.02,
        seed: int = 0,
        range_spec: RangeSpec | None = _DEFAULT_RANGE,
        light_spec: LightSpec | None = _DEFAULT_LIGHT,
        voltage_v: float = 7.4,
        identity: str = "eBot-sim 1.0",
        answer_handshake: bool = True,
    ) -> None:
        self.world = default_world() if world is None else world
        self.params = DiffDriveParams() if params is None else params
        self.dt_s = float(dt_s)
        self.range_spec, self.light_spec = range_spec, light_spec
        self.identity = identity
        self.answer_handshake = answer_handshake
        self.rng = np.random.default_rng(seed)
        self.dynamics = DiffDriveDynamics(
            self.params, np.array([position], dtype=float), np.array([heading_rad], dtype=float), self.rng
        )
        self.voltage_v = float(voltage_v)
        self.wheel_cmd = (0.0, 0.0)  # the protocol's s per wheel, [-1, 1]
        self.started = False
        self.halts = 0
        self.dropped_bytes = 0  # replies the client did not read in time (pty buffer full)
        self.t_s = 0.0  # simulation time, s
        self._received: list[ReceivedCommand] = []
        self._noise: list[bytes] = []
        self._inbuf = bytearray()
        self._lock = threading.RLock()
        self._closed = threading.Event()

        self.master_fd, self.slave_fd = os.openpty()
        tty.setraw(self.slave_fd)  # no echo, no line editing, no newline translation
        os.set_blocking(self.master_fd, False)
        self.device_path = os.ttyname(self.slave_fd)
        self._thread = threading.Thread(target=self._run, name=f"ebot-sim {self.device_path}", daemon=True)
        self._thread.start()

    # -- truth and test hooks ---------------------------------------------------------------------------------

    def pose(self) -> tuple[float, float, float]:
        """True (x m, y m, heading rad from east CCW in (-pi, pi])."""
        with self._lock:
            x, y = self.dynamics.position_m[0]
            return float(x), float(y), float(self.dynamics.heading_rad[0])

    def wheel_travel_m(self) -> tuple[float, float]:
        """Cumulative (left, right) wheel rim travel, m (before slip)."""
        with self._lock:
            left, right = self.dynamics.wheel_travel_m[0]
            return float(left), float(right)

    def sonar_truth_m(self) -> np.ndarray:
        """(6,) noise-free ranges from the centre, m, NaN where nothing is within 1.5 m."""
        with self._lock:
            return self._sonar_ranges()

    def light_truth(self) -> np.ndarray:
        """(2,) noise-free (left, right) irradiance, W/m^2."""
        with self._lock:
            return self._light()

    def commands(self) -> list[ReceivedCommand]:
        """Every line received so far, in order."""
        with self._lock:
            return list(self._received)

    def inject(self, data: bytes) -> None:
        """Write raw bytes to the client now."""
        with self._lock:
            self._send(bytes(data))

    def queue_noise(self, lines: list[bytes]) -> None:
        """Raw byte strings to send just before the next reply (each is sent as is: include any newline)."""
        with self._lock:
            self._noise.extend(bytes(line) for line in lines)

    def close(self) -> None:
        """Stop the thread and close both ends of the pty (the client's port then fails: EIO)."""
        if self._closed.is_set():
            return
        self._closed.set()
        self._thread.join(timeout=2.0)
        for fd in (self.master_fd, self.slave_fd):
            with contextlib.suppress(OSError):
                os.close(fd)

    def __enter__(self) -> EbotSerialSim:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- the real-time loop -------------------------------------------------------------------------------------

    def _run(self) -> None:
        next_step = time.monotonic() + self.dt_s
        while not self._closed.is_set():
            wait = max(0.0, min(next_step - time.monotonic(), 0.01))
            try:
                ready, _, _ = select.select([self.master_fd], [], [], wait)
                data = os.read(self.master_fd, 4096) if ready else b""
            except OSError as exc:
                if exc.errno in (errno.EAGAIN, errno.EINTR):
                    data = b""
                elif exc.errno == errno.EIO or self._closed.is_set():
                    data = b""  # no client has the slave open (we hold it, so this is rare)
                    time.sleep(0.005)
                else:
                    raise
            if data:
                self._receive(data)
            now = time.monotonic()
            steps = 0
            while now >= next_step and steps < 50:
                with self._lock:
                    self._step()
                next_step += self.dt_s
                steps += 1
            if now - next_step > 1.0:  # starved of CPU for long: do not try to catch up
                next_step = now + self.dt_s

    def _step(self) -> None:
        speeds = np.array([self.wheel_cmd], dtype=float) * self.params.max_wheel_speed_mps
        self.dynamics.step(speeds, self.dt_s, self.world)
        self.t_s += self.dt_s
        # A small drain while the wheels turn: 0.5 mV per second at full speed on both wheels.
        self.voltage_v -= 0.0005 * self.dt_s * (abs(self.wheel_cmd[0]) + abs(self.wheel_cmd[1])) / 2.0

    def _receive(self, data: bytes) -> None:
        self._inbuf.extend(data.replace(b"\r\n", b"\n").replace(b"\r", b"\n"))
        while True:
            end = self._inbuf.find(b"\n")
            if end < 0:
                if len(self._inbuf) > 256:
                    self._inbuf.clear()  # noise: no line is that long
                return
            raw = bytes(self._inbuf[: end + 1])
            del self._inbuf[: end + 1]
            with self._lock:
                self._received.append(ReceivedCommand(self.t_s, raw))
                self._handle(raw[:-1].decode("ascii", errors="replace").strip())

    def _handle(self, command: str) -> None:
        if not command:
            return
        if command.startswith("<<1"):
            if not self.answer_handshake:
                return
            if command == "<<1?":
                self._reply(self.identity)
            elif command == "<<1E":
                self._reply(">>1B")
            elif command == "<<1O":
                pass
            else:
                self._reply("?" + command)
            return
        if command == "F":
            self.started = self.answer_handshake
            return
        if not self.started:
            self._reply("?" + command)
            return
        if command.startswith("8w"):
            self._wheels(command)
        elif command == "2H":
            self.wheel_cmd = (0.0, 0.0)
            self.halts += 1
        elif command in _QUERIES:
            self._reply(_QUERIES[command](self))
        else:
            self._reply("?" + command)

    def _wheels(self, command: str) -> None:
        parts = command[2:].split(";")
        try:
            values = [int(p) for p in parts]
        except ValueError:
            values = []
        if len(values) != 2 or not all(100 <= v <= 300 for v in values):
            self._reply("?" + command)
            return
        self.wheel_cmd = (values[0] / 100.0 - 2.0, values[1] / 100.0 - 2.0)

    def _reply(self, text: str) -> None:
        noise, self._noise = b"".join(self._noise), []
        self._send(noise + text.encode("ascii") + b"\n")

    def _send(self, data: bytes) -> None:
        if self._closed.is_set():
            return
        try:
            written = os.write(self.master_fd, data)
        except OSError:
            written = 0
        self.dropped_bytes += len(data) - written

    # -- sensors (called under the lock) ---------------------------------------------------------------------------

    def _bodies(self) -> KinematicBodies:
        return KinematicBodies(np.array([EBOT]), self.dynamics.position_m.copy(), self.dynamics.heading_rad.copy())

    def _sonar_ranges(self) -> np.ndarray:
        offsets = self._bodies().range_finders(np.array([0]), self.world)[0]  # (6, 2), NaN: no echo
        return np.hypot(offsets[:, 0], offsets[:, 1])

    def _light(self) -> np.ndarray:
        return self._bodies().light_sensors(np.array([0]), self.world)[0]

    def _reply_sonar(self) -> str:
        offsets = self._bodies().range_finders(np.array([0]), self.world)
        if self.range_spec is not None:
            offsets = noisy_ranges(offsets, self.rng, self.range_spec)
        ranges = np.hypot(offsets[0, :, 0], offsets[0, :, 1])
        # 0 = no echo; a real echo is at least 1 mm.
        return ";".join("0" if not np.isfinite(r) else str(max(1, round(r * 1000.0))) for r in ranges)

    def _reply_light(self) -> str:
        light = self._light()[None]
        if self.light_spec is not None:
            light = noisy_light(light, self.rng, self.light_spec)
        return ";".join(str(round(v * 1000.0)) for v in light[0])

    def _reply_imu(self) -> str:
        d = self.dynamics
        body = world_to_body(d.acceleration_mps2[:1], d.heading_rad[:1])[0] / STANDARD_GRAVITY_MPS2 * 1000.0
        gz = d.yaw_rate_radps[0] * 1000.0
        return f"{round(body[0])};{round(body[1])};{round(GRAVITY_MG)};0;0;{round(gz)}"

    def _reply_pose(self) -> str:
        x, y = self.dynamics.position_m[0]
        heading_mrad = round(float(self.dynamics.heading_rad[0]) * 1000.0)  # -3142..3142
        return f"{round(x * 1000.0)};{round(y * 1000.0)};{heading_mrad}"

    def _reply_power(self) -> str:
        return str(round(self.voltage_v * 1000.0))


_QUERIES = {
    "2S": EbotSerialSim._reply_sonar,
    "2D": EbotSerialSim._reply_light,
    "2A": EbotSerialSim._reply_imu,
    "2P": EbotSerialSim._reply_pose,
    "2V": EbotSerialSim._reply_power,
}
