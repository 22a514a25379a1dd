"""Byte links to an autopilot: UDP (in/out), TCP and serial ports.

    link = open_link("udpin:0.0.0.0:14550")        # listen; replies go to the last sender
    link = open_link("udpout:192.168.1.10:14550")  # send to an address; replies come back to our port
    link = open_link("tcp:127.0.0.1:5760")         # connect (e.g. to SITL)
    link = open_link("/dev/ttyUSB0", baud=57600)   # serial (pyserial); also COM3 on Windows

Every link has `write(data)`, `read(max_bytes=4096, timeout_s=0.0) -> bytes` (waits at most timeout_s,
returns b"" when nothing came) and `close()`, and is a context manager. Errors opening or using a link
are `LinkError`s naming the connection string.
"""

from __future__ import annotations

import re
import select
import socket
import sys

import serial

__all__ = ["Link", "LinkError", "SerialLink", "TcpLink", "UdpLink", "open_link", "parse_connection_string"]


class LinkError(OSError):
    """A link could not be opened or used; the message names the connection string."""


if sys.platform != "win32":
    import termios

    # pyserial lets termios.error (not an OSError) escape when a port that has gone away is flushed.
    _SERIAL_ERRORS: tuple[type[BaseException], ...] = (serial.SerialException, OSError, termios.error)
else:  # pragma: no cover - Windows
    _SERIAL_ERRORS = (serial.SerialException, OSError)


def parse_connection_string(connection: str) -> tuple[str, str, int | None]:
    """(kind, host or device path, port): kind is "udpin", "udpout", "tcp" or "serial"."""
    if not isinstance(connection, str) or not connection.strip():
        raise LinkError(f"empty connection string {connection!r}")
    text = connection.strip()
    if text.startswith("/") or re.fullmatch(r"COM\d+", text, flags=re.IGNORECASE):
        return "serial", text, None
    parts = text.split(":")
    if len(parts) != 3 or parts[0] not in ("udpin", "udpout", "tcp"):
        raise LinkError(
            f"bad connection string {connection!r}: expected udpin:HOST:PORT, udpout:HOST:PORT, tcp:HOST:PORT "
            "or a serial device path"
        )
    kind, host, port_text = parts
    if not host:
        raise LinkError(f"bad connection string {connection!r}: no host")
    try:
        port = int(port_text)
    except ValueError:
        raise LinkError(f"bad connection string {connection!r}: port {port_text!r} is not a number") from None
    if not 0 <= port <= 65535 or (port == 0 and kind != "udpin"):
        raise LinkError(f"bad connection string {connection!r}: port {port} out of range")
    return kind, host, port


class Link:
    """Common interface: write, read, close; context manager."""

    connection: str

    def write(self, data: bytes) -> None:  # pragma: no cover - interface
        raise NotImplementedError

    def read(self, max_bytes: int = 4096, timeout_s: float = 0.0) -> bytes:  # pragma: no cover - interface
        raise NotImplementedError

    def close(self) -> None:  # pragma: no cover - interface
        raise NotImplementedError

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _wait_readable(sock: socket.socket, timeout_s: float) -> bool:
    ready, _, _ = select.select([sock], [], [], max(0.0, float(timeout_s)))
    return bool(ready)


class UdpLink(Link):
    """udpin binds HOST:PORT and answers whoever sent last; udpout sends to HOST:PORT from an ephemeral port."""

    def __init__(self, connection: str, kind: str, host: str, port: int) -> None:
        self.connection = connection
        self.kind = kind
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            if kind == "udpin":
                self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                self.sock.bind((host, port))
                self.peer: tuple[str, int] | None = None
            else:
                self.peer = (socket.gethostbyname(host), port)
        except OSError as exc:
            self.sock.close()
            raise LinkError(f"cannot open {connection!r}: {exc}") from exc

    @property
    def local_address(self) -> tuple[str, int]:
        return self.sock.getsockname()

    def write(self, data: bytes) -> None:
        if self.peer is None:
            return  # udpin: nobody has spoken to us yet, so there is no one to answer
        try:
            self.sock.sendto(bytes(data), self.peer)
        except OSError as exc:
            raise LinkError(f"cannot write to {self.connection!r}: {exc}") from exc

    def read(self, max_bytes: int = 4096, timeout_s: float = 0.0) -> bytes:
        try:
            if not _wait_readable(self.sock, timeout_s):
                return b""
            data, sender = self.sock.recvfrom(max(max_bytes, 65535))
        except ConnectionRefusedError:
            return b""  # an ICMP "port unreachable" from an earlier send: nothing to read
        except OSError as exc:
            raise LinkError(f"cannot read from {self.connection!r}: {exc}") from exc
        if self.kind == "udpin":
            self.peer = sender
        return data[:max_bytes] if len(data) > max_bytes else data

    def close(self) -> None:
        self.sock.close()


class TcpLink(Link):
    """A TCP client connection."""

    def __init__(self, connection: str, host: str, port: int, connect_timeout_s: float = 5.0) -> None:
        self.connection = connection
        try:
            self.sock = socket.create_connection((host, port), timeout=connect_timeout_s)
        except OSError as exc:
            raise LinkError(f"cannot open {connection!r}: {exc}") from exc
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)

    def write(self, data: bytes) -> None:
        try:
            self.sock.sendall(bytes(data))
        except OSError as exc:
            raise LinkError(f"cannot write to {self.connection!r}: {exc}") from exc

    def read(self, max_bytes: int = 4096, timeout_s: float = 0.0) -> bytes:
        try:
            if not _wait_readable(self.sock, timeout_s):
                return b""
            data = self.sock.recv(max_bytes)
        except OSError as exc:
            raise LinkError(f"cannot read from {self.connection!r}: {exc}") from exc
        if not data:
            raise LinkError(f"{self.connection!r}: connection closed by the peer")
        return data

    def close(self) -> None:
        self.sock.close()


class SerialLink(Link):
    """A serial port (pyserial), 8N1 at `baud`."""

    def __init__(self, connection: str, device: str, baud: int) -> None:
        self.connection = connection
        try:
            self.port = serial.Serial(device, baudrate=baud, timeout=0, write_timeout=1.0)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise LinkError(f"cannot open serial port {device!r} at {baud} baud: {exc}") from exc

    def write(self, data: bytes) -> None:
        try:
            self.port.write(bytes(data))
            self.port.flush()
        except _SERIAL_ERRORS as exc:
            raise LinkError(f"cannot write to {self.connection!r}: {exc}") from exc

    def read(self, max_bytes: int = 4096, timeout_s: float = 0.0) -> bytes:
        try:
            self.port.timeout = max(0.0, float(timeout_s))
            first = self.port.read(1)
            if not first:
                return b""
            self.port.timeout = 0
            return first + self.port.read(max(0, max_bytes - 1))
        except _SERIAL_ERRORS as exc:
            raise LinkError(f"cannot read from {self.connection!r}: {exc}") from exc

    def close(self) -> None:
        self.port.close()


def open_link(connection_string: str, baud: int = 115200) -> Link:
    """Open a link from a connection string (see the module docstring); raises LinkError."""
    kind, where, port = parse_connection_string(connection_string)
    if kind == "serial":
        return SerialLink(connection_string, where, baud)
    assert port is not None
    if kind == "tcp":
        return TcpLink(connection_string, where, port)
    return UdpLink(connection_string, kind, where, port)
