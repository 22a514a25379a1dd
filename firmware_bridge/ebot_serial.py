"""A client of the eBot's own ASCII serial protocol (DESIGN.md, "eBot serial protocol"; docs/ebot-serial.md).

    robot = EbotSerial.connect("/dev/rfcomm0")      # opens the port (115200 baud) and does the handshake
    pose = robot.pose()                             # Pose(x_m, y_m, heading_rad) or None if no valid reply came
    robot.set_wheels(0.5, 0.5)                      # each wheel in [-1, 1] of full speed: sends "8w250;250\\n"
    robot.halt()                                    # "2H\\n" and zero wheels

Conventions (where DESIGN.md is silent; docs/ebot-serial.md has the full table): every command and every
reply is one line of ASCII ending in "\\n" ("\\r\\n" accepted); replies are bare values separated by ";".
Queries answer one line; `<<1O`, `F`, `2H` and `8w` answer nothing; a line starting with "?" is the
robot's error reply.

Robustness: a query returns None (counted in `counters`) when no valid reply comes within `reply_timeout_s`;
lines that are not the expected reply (noise, non-ASCII bytes, wrong field counts, non-numbers) are counted and
skipped, never raised. A port that fails (device unplugged, pty closed) raises `LinkError` naming the port.
A handshake that fails raises `EbotProtocolError` naming the port and what was received.
"""

from __future__ import annotations

import contextlib
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import serial

from firmware_bridge.links import LinkError

__all__ = [
    "EBOT_BAUD",
    "EbotCounters",
    "EbotProtocolError",
    "EbotSerial",
    "ImuSample",
    "LightReading",
    "Pose",
    "Power",
    "SonarRanges",
    "wheel_command",
    "wheel_value",
]

EBOT_BAUD = 115200
SONAR_COUNT = 6
MAX_LINE_BYTES = 256  # a "line" longer than this without a newline is noise
STANDARD_GRAVITY_MPS2 = 9.80665
READ_POLL_S = 0.02  # the longest a read waits before the deadline is checked again

# pyserial's POSIX flush (tcdrain) raises termios.error, which is no OSError, when the device has vanished.
try:
    import termios

    _TERMIOS_ERRORS: tuple[type[BaseException], ...] = (termios.error,)
except ImportError:  # pragma: no cover - Windows
    _TERMIOS_ERRORS = ()

_PORT_ERRORS = (serial.SerialException, OSError, ValueError, *_TERMIOS_ERRORS)


class EbotProtocolError(RuntimeError):
    """The device on the port does not speak the eBot protocol as expected (e.g. the handshake failed)."""


@dataclass(frozen=True)
class SonarRanges:
    """`2S`: six ranges in metres (NaN where the sonar has no echo, reported as 0 mm), in the robot's order
    (docs/ebot-serial.md); t_s is the local reception time (clock of the client, s)."""

    t_s: float
    ranges_m: tuple[float, ...]


@dataclass(frozen=True)
class LightReading:
    """`2D`: the two light sensors (left, right), in the robot's units (the simulator: mW/m^2)."""

    t_s: float
    left: float
    right: float


@dataclass(frozen=True)
class ImuSample:
    """`2A`: accelerometer (x, y, z) in mG and gyro (x, y, z) in mrad/s, robot body frame x forward, y left,
    z up (a level robot at rest reads accel (0, 0, +1000))."""

    t_s: float
    accel_mg: tuple[float, float, float]
    gyro_mradps: tuple[float, float, float]

    @property
    def accel_mps2(self) -> tuple[float, float, float]:
        """Acceleration (specific force) in m/s^2, body frame x forward, y left, z up."""
        g = STANDARD_GRAVITY_MPS2 / 1000.0
        return (self.accel_mg[0] * g, self.accel_mg[1] * g, self.accel_mg[2] * g)

    @property
    def gyro_radps(self) -> tuple[float, float, float]:
        """Angular rates in rad/s about x forward, y left, z up (z positive = counter-clockwise seen from above)."""
        return (self.gyro_mradps[0] / 1000.0, self.gyro_mradps[1] / 1000.0, self.gyro_mradps[2] / 1000.0)


@dataclass(frozen=True)
class Pose:
    """`2P`: the robot's own pose estimate: x, y in metres (its odometry frame; the simulator: x east, y north)
    and heading in rad from the x axis, counter-clockwise, wrapped to (-pi, pi]."""

    t_s: float
    x_m: float
    y_m: float
    heading_rad: float


@dataclass(frozen=True)
class Power:
    """`2V`: the battery voltage in volts."""

    t_s: float
    voltage_v: float


@dataclass
class EbotCounters:
    """What the client has seen: lines received, valid replies, lines skipped as `garbage` (not printable
    ASCII, or over MAX_LINE_BYTES) or `malformed` (ASCII but not the expected reply), `error_replies` (lines
    starting with "?"), `timeouts` (queries with no valid reply in time), `stale_lines` (unsolicited lines
    discarded before a query), `commands` sent."""

    lines: int = 0
    replies: int = 0
    garbage: int = 0
    malformed: int = 0
    error_replies: int = 0
    timeouts: int = 0
    stale_lines: int = 0
    commands: int = 0


def wheel_command(left: float, right: float) -> bytes:
    """The `8w` line for wheel speeds left, right in [-1, 1] of full speed (clipped; NaN/inf -> 0): each sent as
    the integer round((s + 2) * 100), 100..300, e.g. (1, -1) -> b"8w300;100\\n"."""

    return f"8w{wheel_value(left)};{wheel_value(right)}\n".encode("ascii")


def wheel_value(speed: float) -> int:
    """One wheel's speed s in [-1, 1] of full speed (clipped; NaN/inf -> 0) as sent: round((s + 2) * 100)."""
    s = float(speed)
    if not math.isfinite(s):
        s = 0.0
    return round((min(1.0, max(-1.0, s)) + 2.0) * 100.0)


def _wrap(angle_rad: float) -> float:
    return math.pi - (math.pi - angle_rad) % (2.0 * math.pi)


def _printable(line: bytes) -> bool:
    return all(32 <= b < 127 or b == 9 for b in line)


class EbotSerial:
    """One eBot on a serial port (pyserial). Thread-safe: one query at a time.

    device: a serial device path (or anything `serial.serial_for_url` takes); baud: 115200 for an eBot;
    reply_timeout_s: how long a query waits for its reply (s); clock: the time source of the readings' t_s.
    Opening raises LinkError when the port cannot be opened; `handshake` raises EbotProtocolError.
    """

    def __init__(
        self,
        device: str,
        baud: int = EBOT_BAUD,
        *,
        reply_timeout_s: float = 0.3,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.device = device
        self.baud = int(baud)
        self.reply_timeout_s = float(reply_timeout_s)
        self.clock = clock
        self.counters = EbotCounters()
        self.identity: str | None = None
        self.last_wheels: tuple[float, float] = (0.0, 0.0)
        self._lock = threading.RLock()
        self._buf = bytearray()
        self._discarding = False  # inside an over-long line: drop bytes up to its newline
        try:
            self.port = serial.serial_for_url(device, baudrate=self.baud, timeout=READ_POLL_S, write_timeout=1.0)
        except _PORT_ERRORS as exc:
            raise LinkError(f"cannot open eBot serial port {device!r} at {self.baud} baud: {exc}") from exc

    @classmethod
    def connect(
        cls, device: str, baud: int = EBOT_BAUD, *, handshake_timeout_s: float = 2.0, reply_timeout_s: float = 0.3
    ) -> EbotSerial:
        """Open the port and do the handshake; closes the port again if the handshake fails."""
        robot = cls(device, baud, reply_timeout_s=reply_timeout_s)
        try:
            robot.handshake(handshake_timeout_s)
        except BaseException:
            robot.close()
            raise
        return robot

    # -- port I/O ----------------------------------------------------------------------------------------

    def _fail(self, action: str, exc: BaseException) -> LinkError:
        return LinkError(f"eBot serial port {self.device!r}: cannot {action} (device unplugged or closed?): {exc}")

    def _write(self, line: bytes) -> None:
        try:
            self.port.write(line)
            self.port.flush()
        except _PORT_ERRORS as exc:
            raise self._fail("write", exc) from exc
        self.counters.commands += 1

    def _read_chunk(self, wait: bool) -> bytes:
        """What has arrived; when `wait`, first wait up to READ_POLL_S for a byte. (The port's timeout stays at
        READ_POLL_S: changing it reconfigures the port every time.)"""
        try:
            first = b""
            if wait:
                first = self.port.read(1)
                if not first:
                    return b""
            waiting = self.port.in_waiting
            return first + (self.port.read(waiting) if waiting else b"")
        except _PORT_ERRORS as exc:
            raise self._fail("read", exc) from exc

    def _next_line(self, deadline: float) -> bytes | None:
        """The next complete line (without its terminator) before the monotonic deadline, or None."""
        while True:
            newline = self._buf.find(b"\n")
            if newline >= 0:
                line = bytes(self._buf[:newline]).rstrip(b"\r")
                del self._buf[: newline + 1]
                if self._discarding:
                    self._discarding = False
                    continue  # the tail of an over-long line, already counted
                self.counters.lines += 1
                if len(line) > MAX_LINE_BYTES:
                    self.counters.garbage += 1
                    continue
                return line
            if len(self._buf) > MAX_LINE_BYTES:
                self._buf.clear()
                if not self._discarding:
                    self.counters.lines += 1
                    self.counters.garbage += 1
                self._discarding = True
            if time.monotonic() >= deadline:
                return None
            self._buf.extend(self._read_chunk(wait=True))

    def _discard_pending(self) -> None:
        """Drop unsolicited input (e.g. a reply that came after its query timed out), counting its lines."""
        while True:
            chunk = self._read_chunk(wait=False)
            if not chunk:
                break
            self._buf.extend(chunk)
        self.counters.stale_lines += self._buf.count(b"\n")
        self._buf.clear()
        self._discarding = False

    # -- handshake -----------------------------------------------------------------------------------------

    def _expect(self, command: bytes, accept: Callable[[str], bool], wanted: str, deadline: float) -> str:
        self._write(command)
        seen: list[bytes] = []
        while True:
            line = self._next_line(deadline)
            if line is None:
                received = ", ".join(repr(s) for s in seen[-5:]) if seen else "nothing"
                partial = f" (and an unterminated {bytes(self._buf[:40])!r})" if self._buf else ""
                raise EbotProtocolError(
                    f"eBot handshake failed on {self.device!r} at {self.baud} baud: sent {command.strip()!r}, "
                    f"expected {wanted}; received {received}{partial} before the timeout"
                )
            text = line.decode("ascii", errors="replace").strip()
            if _printable(line) and accept(text):
                return text
            seen.append(line)
            self.counters.malformed += 1

    def handshake(self, timeout_s: float = 2.0) -> str:
        """`<<1?` (answered by a line starting "eB", the identity), `<<1E` (answered `>>1B`), then `<<1O` and `F`
        start the robot; finally a `2V` query checks that it answers. Returns the identity line. Raises
        EbotProtocolError (naming the port and what was received) if anything is missing within timeout_s (s)."""
        with self._lock:
            deadline = time.monotonic() + float(timeout_s)
            self._discard_pending()
            self.identity = self._expect(b"<<1?\n", lambda t: t.startswith("eB"), "a line starting 'eB'", deadline)
            self._expect(b"<<1E\n", lambda t: t == ">>1B", "'>>1B'", deadline)
            self._write(b"<<1O\n")
            self._write(b"F\n")
            self._expect(b"2V\n", lambda t: _parse_numbers(t, 1) is not None, "a 2V power reply", deadline)
            self.counters.replies += 1
            return self.identity

    # -- queries -------------------------------------------------------------------------------------------

    def query(self, command: str, count: int) -> tuple[list[float], float] | None:
        """Send a query ("2S", ...), return (its `count` numbers, reception time) or None when no valid reply came
        within reply_timeout_s. Other lines are counted and skipped; an error reply ("?...") ends the wait."""
        with self._lock:
            self._discard_pending()
            self._write(command.encode("ascii") + b"\n")
            deadline = time.monotonic() + self.reply_timeout_s
            while True:
                line = self._next_line(deadline)
                if line is None:
                    self.counters.timeouts += 1
                    return None
                if not _printable(line):
                    self.counters.garbage += 1
                    continue
                text = line.decode("ascii").strip()
                if text.startswith("?"):
                    self.counters.error_replies += 1
                    return None
                values = _parse_numbers(text, count)
                if values is None:
                    self.counters.malformed += 1
                    continue
                self.counters.replies += 1
                return values, float(self.clock())

    def sonar(self) -> SonarRanges | None:
        """`2S`: the six sonar ranges in metres (NaN: no echo), or None."""
        got = self.query("2S", SONAR_COUNT)
        if got is None:
            return None
        values, t_s = got
        if any(v < 0 for v in values):
            self.counters.replies -= 1
            self.counters.malformed += 1
            return None
        return SonarRanges(t_s, tuple(v / 1000.0 if v > 0 else math.nan for v in values))

    def light(self) -> LightReading | None:
        """`2D`: the two light readings (left, right), or None."""
        got = self.query("2D", 2)
        if got is None:
            return None
        (left, right), t_s = got
        return LightReading(t_s, left, right)

    def imu(self) -> ImuSample | None:
        """`2A`: accelerometer (mG) and gyro (mrad/s), body frame x forward, y left, z up; or None."""
        got = self.query("2A", 6)
        if got is None:
            return None
        v, t_s = got
        return ImuSample(t_s, (v[0], v[1], v[2]), (v[3], v[4], v[5]))

    def pose(self) -> Pose | None:
        """`2P`: x, y (sent in mm) in metres and heading (sent in mrad from x, CCW) in rad in (-pi, pi]; or None."""
        got = self.query("2P", 3)
        if got is None:
            return None
        (x_mm, y_mm, heading_mrad), t_s = got
        return Pose(t_s, x_mm / 1000.0, y_mm / 1000.0, _wrap(heading_mrad / 1000.0))

    def power(self) -> Power | None:
        """`2V`: the battery voltage (sent in mV) in volts; or None."""
        got = self.query("2V", 1)
        if got is None:
            return None
        (millivolts,), t_s = got
        if millivolts < 0:
            self.counters.replies -= 1
            self.counters.malformed += 1
            return None
        return Power(t_s, millivolts / 1000.0)

    # -- commands ------------------------------------------------------------------------------------------

    def set_wheels(self, left: float, right: float) -> bytes:
        """Command the wheel speeds, each in [-1, 1] of full speed (clipped; NaN/inf -> 0). Returns the line sent."""
        line = wheel_command(left, right)
        with self._lock:
            self._write(line)
            self.last_wheels = (wheel_value(left) / 100.0 - 2.0, wheel_value(right) / 100.0 - 2.0)
        return line

    def halt(self) -> None:
        """`2H` (the robot halts), then zero wheel speeds, so that it stays halted."""
        with self._lock:
            self._write(b"2H\n")
            self._write(wheel_command(0.0, 0.0))
            self.last_wheels = (0.0, 0.0)

    def close(self) -> None:
        """Close the port (does not halt the robot: call `halt` first while the port works)."""
        with contextlib.suppress(*_PORT_ERRORS):
            self.port.close()

    def __enter__(self) -> EbotSerial:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _parse_numbers(text: str, count: int) -> list[float] | None:
    """Exactly `count` finite numbers separated by ";" (blanks around them allowed), else None."""
    parts = text.split(";")
    if len(parts) != count:
        return None
    values: list[float] = []
    for part in parts:
        part = part.strip()
        if not part or part.lower().lstrip("+-") in ("nan", "inf", "infinity"):
            return None
        try:
            value = float(part)
        except ValueError:
            return None
        if not math.isfinite(value):
            return None
        values.append(value)
    return values
