"""Byte links to an autopilot: UDP (in/out), TCP and serial ports.

    link = open_link("udpin:0.0.0.0:14550")        # listen; replies go to every live, confirmed peer
    link = open_link("udpout:192.168.1.10:14550")  # send to an address; only that address is heard
    link = open_link("tcp:127.0.0.1:5760")         # connect (e.g. to SITL)
    link = open_link("udpbcast:192.168.1.255:15000")  # a broadcast mesh on an IP radio: send to all, hear all
    link = open_link("/dev/ttyUSB0", baud=57600)   # serial (pyserial); also COM3 on Windows

Every link has `write(data)`, `read(max_bytes=4096, timeout_s=0.0) -> bytes` (waits at most timeout_s,
returns b"" when nothing came) and `close()`, and is a context manager. Errors opening or using a link
are `LinkError`s naming the connection string. `read_from` also says who sent the bytes (a UDP address;
None on a stream), and `confirm_peer(sender)` makes a udpin sender a peer (a no-op elsewhere).

Who a UDP link talks to (issue 17: one datagram must not take a link over):

- udpin: writes go to every *peer*: an address that was confirmed and has been heard from, confirmed,
  within `peer_timeout_s` (10 s). No datagram moves the reply address by itself. A caller that
  authenticates what it reads (`bob_autonomy.ground.gcs`, with MAVLink 2 signing) uses `read_from` and confirms
  a sender only when its frames passed those checks; plain `read` confirms a sender whose datagram holds
  at least one well-formed MAVLink frame (a known message with the right checksum,
  `firmware_bridge.decoder.contains_mavlink_frame`). Datagrams from others are still returned (the caller
  decides what to make of them) and counted in `unconfirmed`.
- udpout: a datagram from any address but the one we send to is dropped and counted in `foreign`.
- udpbcast: a swarm's mesh on an IP radio (Wi-Fi, or a mesh radio that carries Ethernet): every write goes to
  the broadcast address, and every datagram to the port is heard, whoever sent it (our own included). It is
  for the mesh only, whose packets carry their sender's agent id and can be signed with the fleet key
  (`bob_autonomy.network.mesh_auth`); a vehicle or ground-station link must say whom it talks to.
"""

from __future__ import annotations

import contextlib
import logging
import re
import select
import socket
import sys
import time
from collections.abc import Callable

import serial

from firmware_bridge.decoder import contains_mavlink_frame

logger = logging.getLogger(__name__)

__all__ = [
    "PEER_TIMEOUT_S",
    "Link",
    "LinkError",
    "ReopeningLink",
    "SerialLink",
    "TcpLink",
    "UdpBroadcastLink",
    "UdpLink",
    "open_link",
    "parse_connection_string",
]

PEER_TIMEOUT_S = 10.0  # a udpin peer not confirmed again for this long (s) is no longer written to
MAX_FOREIGN_PER_READ = 64  # udpout: foreign datagrams skipped in one read before it returns b""

Address = tuple[str, int]


TCP_WRITE_TIMEOUT_S = 5.0  # a TCP write that cannot go out for this long fails the link


class LinkError(OSError):
    """A link could not be opened or used; the message names the connection string."""


if sys.platform != "win32":
    import termios

    # pyserial lets termios.error (not an OSError) escape when a port that has gone away is flushed.
    _SERIAL_ERRORS: tuple[type[BaseException], ...] = (serial.SerialException, OSError, termios.error)
else:  # pragma: no cover - Windows
    _SERIAL_ERRORS = (serial.SerialException, OSError)


def parse_connection_string(connection: str) -> tuple[str, str, int | None]:
    """(kind, host or device path, port): kind is "udpin", "udpout", "udpbcast", "tcp" or "serial"."""
    if not isinstance(connection, str) or not connection.strip():
        raise LinkError(f"empty connection string {connection!r}")
    text = connection.strip()
    if text.startswith("/") or re.fullmatch(r"COM\d+", text, flags=re.IGNORECASE):
        return "serial", text, None
    parts = text.split(":")
    if len(parts) != 3 or parts[0] not in ("udpin", "udpout", "udpbcast", "tcp"):
        raise LinkError(
            f"bad connection string {connection!r}: expected udpin:HOST:PORT, udpout:HOST:PORT, "
            "udpbcast:BROADCAST_ADDRESS:PORT, tcp:HOST:PORT or a serial device path"
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

    def read_from(self, max_bytes: int = 4096, timeout_s: float = 0.0) -> tuple[bytes, Address | None]:
        """Like `read`, with the sender's address (None on a stream link, which has one peer)."""
        return self.read(max_bytes, timeout_s), None

    def confirm_peer(self, sender: Address | None) -> None:
        """The caller vouches for `sender` (its frames passed the caller's checks): a udpin link writes to it
        from now on. Nothing to do on a link with one fixed peer."""

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
    """udpin binds HOST:PORT and answers its live confirmed peers; udpout sends to HOST:PORT from an ephemeral port
    and hears only HOST:PORT (see the module docstring). clock: monotonic seconds, for peer expiry."""

    def __init__(
        self,
        connection: str,
        kind: str,
        host: str,
        port: int,
        *,
        peer_timeout_s: float = PEER_TIMEOUT_S,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.connection = connection
        self.kind = kind
        self.peer_timeout_s = float(peer_timeout_s)
        self.clock = clock
        self.peers: dict[Address, float] = {}  # udpin: confirmed address -> when last confirmed (clock s)
        self.destination: Address | None = None  # udpout: the one address written to and heard
        self.foreign = 0  # udpout: datagrams from another address, dropped
        self.unconfirmed = 0  # udpin (read): datagrams whose sender did not become a peer
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            if kind == "udpin":
                self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                self.sock.bind((host, port))
            else:
                address = socket.gethostbyname(host)
                # Sending to 0.0.0.0 reaches this host, whose answers come from 127.0.0.1.
                self.destination = ("127.0.0.1" if address == "0.0.0.0" else address, port)
        except OSError as exc:
            self.sock.close()
            raise LinkError(f"cannot open {connection!r}: {exc}") from exc

    @property
    def local_address(self) -> Address:
        return self.sock.getsockname()

    @property
    def peer(self) -> Address | None:
        """udpout: the destination; udpin: the live peer confirmed most recently (None if none)."""
        if self.destination is not None:
            return self.destination
        live = self.live_peers()
        return max(live, key=self.peers.__getitem__) if live else None

    def live_peers(self) -> list[Address]:
        """The addresses written to: udpin peers confirmed within peer_timeout_s (older ones are forgotten),
        or the udpout destination."""
        if self.destination is not None:
            return [self.destination]
        now = float(self.clock())
        for address in [a for a, t in self.peers.items() if now - t > self.peer_timeout_s]:
            del self.peers[address]
        return list(self.peers)

    def confirm_peer(self, sender: Address | None) -> None:
        if self.kind == "udpin" and sender is not None:
            self.peers[(str(sender[0]), int(sender[1]))] = float(self.clock())

    def write(self, data: bytes) -> None:
        """Send `data` to every live peer (udpin: nobody confirmed yet means no one to answer)."""
        errors = []
        peers = self.live_peers()
        for address in peers:
            try:
                self.sock.sendto(bytes(data), address)
            except OSError as exc:
                errors.append(f"{address[0]}:{address[1]}: {exc}")
        if errors and len(errors) == len(peers):
            raise LinkError(f"cannot write to {self.connection!r}: {'; '.join(errors)}")

    def read_from(self, max_bytes: int = 4096, timeout_s: float = 0.0) -> tuple[bytes, Address | None]:
        """One datagram (cut to max_bytes) and its sender, waiting at most timeout_s; (b"", None) if none.
        udpout: datagrams from anywhere but the destination are dropped and counted (`foreign`)."""
        deadline = time.monotonic() + max(0.0, float(timeout_s))
        for _ in range(MAX_FOREIGN_PER_READ):
            try:
                if not _wait_readable(self.sock, deadline - time.monotonic()):
                    return b"", None
                data, sender = self.sock.recvfrom(max(max_bytes, 65535))
            except ConnectionRefusedError:
                return b"", None  # an ICMP "port unreachable" from an earlier send: nothing to read
            except OSError as exc:
                raise LinkError(f"cannot read from {self.connection!r}: {exc}") from exc
            if self.destination is not None and sender != self.destination:
                self.foreign += 1
                continue
            return (data[:max_bytes] if len(data) > max_bytes else data), sender
        return b"", None

    def read(self, max_bytes: int = 4096, timeout_s: float = 0.0) -> bytes:
        """One datagram (see read_from). udpin: a sender not yet a peer becomes one if the datagram holds a
        well-formed MAVLink frame; otherwise it is counted in `unconfirmed`."""
        data, sender = self.read_from(max_bytes, timeout_s)
        if data and self.kind == "udpin":
            if contains_mavlink_frame(data):
                self.confirm_peer(sender)  # a new peer, or a peer still alive
            elif sender not in self.peers:
                self.unconfirmed += 1
        return data

    def close(self) -> None:
        self.sock.close()


class UdpBroadcastLink(Link):
    """udpbcast:ADDRESS:PORT, a broadcast mesh on an IP network (module docstring): bound to PORT on every
    interface, sharing it with other processes on this host (SO_REUSEADDR, and SO_REUSEPORT where the system has
    it: several vessels of a simulated fleet on one machine), writing to ADDRESS:PORT with SO_BROADCAST. ADDRESS
    is the radio subnet's broadcast address (e.g. 192.168.1.255 for 192.168.1.0/24, 255.255.255.255 for the
    local network, 127.255.255.255 for the vessels of one machine). Our own datagrams come back too."""

    def __init__(self, connection: str, address: str, port: int) -> None:
        self.connection = connection
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self.destination = (socket.gethostbyname(address), port)
            self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            if hasattr(socket, "SO_REUSEPORT"):
                self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
            self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_BROADCAST, 1)
            self.sock.bind(("", port))
        except OSError as exc:
            self.sock.close()
            raise LinkError(f"cannot open {connection!r}: {exc}") from exc

    def write(self, data: bytes) -> None:
        try:
            self.sock.sendto(bytes(data), self.destination)
        except OSError as exc:
            raise LinkError(f"cannot write to {self.connection!r}: {exc}") from exc

    def read_from(self, max_bytes: int = 4096, timeout_s: float = 0.0) -> tuple[bytes, Address | None]:
        """One datagram (cut to max_bytes) and its sender, waiting at most timeout_s; (b"", None) if none."""
        try:
            if not _wait_readable(self.sock, timeout_s):
                return b"", None
            data, sender = self.sock.recvfrom(65535)
        except ConnectionRefusedError:
            return b"", None  # an ICMP "port unreachable" from an earlier send: nothing to read
        except OSError as exc:
            raise LinkError(f"cannot read from {self.connection!r}: {exc}") from exc
        return data[:max_bytes], sender

    def read(self, max_bytes: int = 4096, timeout_s: float = 0.0) -> bytes:
        return self.read_from(max_bytes, timeout_s)[0]

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
        self.sock.settimeout(TCP_WRITE_TIMEOUT_S)  # reads wait in select; a write may block this long
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


class ReopeningLink(Link):
    """A link that outlives its port. A serial or TCP link is closed at its first error, then opened again by
    `opener` every `period_s` until it opens (a USB serial adapter shaken loose and plugged in again). A UDP link
    (`keep_open`: its socket outlives an interface going down, and keeps its port, by which a relay or a ground
    station knows it) is kept, and written to again every `period_s` until a write goes out. The write or read
    that failed raises or returns nothing as the link did; until the link is back a read returns nothing (a kept
    UDP link is still read) and a write is dropped (counted in `dropped_writes`), so a loop that writes every
    period is not told at every write. Said once when lost and once when back (logged), counted in `losses` and
    `reopens`. The first open is `opener()` as is: it raises LinkError. Other attributes are the open link's
    (`local_address`, `peers` of a UDP link)."""

    def __init__(
        self,
        opener: Callable[[], Link],
        period_s: float = 1.0,
        clock: Callable[[], float] = time.monotonic,
        *,
        keep_open: bool = False,
    ) -> None:
        self._opener, self.period_s, self.clock, self.keep_open = opener, float(period_s), clock, keep_open
        self.link: Link | None = opener()
        self.connection = self.link.connection
        self.losses = 0
        self.reopens = 0
        self.dropped_writes = 0
        self._lost = False
        self._lost_at = 0.0
        self._next_try = 0.0
        self._closed = False

    def _lose(self, error: OSError) -> None:
        now = float(self.clock())
        self._next_try = now + self.period_s
        if self._lost:
            return  # a retry that failed: still lost, and said so already
        self._lost, self._lost_at = True, now
        self.losses += 1
        if self.keep_open:
            logger.warning("%s failing (%s); trying it again every %g s", self.connection, error, self.period_s)
            return
        with contextlib.suppress(OSError):
            self.link.close()
        self.link = None
        logger.warning("%s lost (%s); reopening it every %g s", self.connection, error, self.period_s)

    def _back(self) -> None:
        if self._lost:
            self._lost = False
            self.reopens += 1
            verb = "works again" if self.keep_open else "reopened"
            logger.warning("%s %s after %.1f s", self.connection, verb, float(self.clock()) - self._lost_at)

    def _usable(self) -> bool:
        """Whether to use the link now: it is not lost, or a retry is due (a closed link opened again first)."""
        if self._closed:
            return False
        if not self._lost:
            return True
        now = float(self.clock())
        if now < self._next_try:
            return False
        self._next_try = now + self.period_s
        if self.link is None:
            try:
                self.link = self._opener()
            except OSError:
                return False
            self._back()
        return True

    def __getattr__(self, name: str):
        link = self.__dict__.get("link")
        if link is None:
            raise AttributeError(f"{type(self).__name__} of {self.__dict__.get('connection')!r} has no {name!r} now")
        return getattr(link, name)

    def write(self, data: bytes) -> None:
        if not self._usable():
            self.dropped_writes += 1
            return
        retrying = self._lost
        try:
            self.link.write(data)
        except OSError as error:
            self._lose(error)
            if retrying:
                self.dropped_writes += 1
                return
            raise
        self._back()

    def read_from(self, max_bytes: int = 4096, timeout_s: float = 0.0) -> tuple[bytes, Address | None]:
        if self._closed or not (self.keep_open or self._usable()):
            return b"", None
        try:
            return self.link.read_from(max_bytes, timeout_s)
        except OSError as error:
            self._lose(error)
            return b"", None

    def read(self, max_bytes: int = 4096, timeout_s: float = 0.0) -> bytes:
        return self.read_from(max_bytes, timeout_s)[0]

    def confirm_peer(self, sender: Address | None) -> None:
        if self.link is not None:
            self.link.confirm_peer(sender)

    def close(self) -> None:
        self._closed = True
        if self.link is not None:
            self.link.close()
            self.link = None


def open_link(connection_string: str, baud: int = 115200, connect_timeout_s: float = 5.0) -> Link:
    """Open a link from a connection string (see the module docstring); raises LinkError. connect_timeout_s: how
    long a TCP connection may take to be accepted or refused, s."""
    kind, where, port = parse_connection_string(connection_string)
    if kind == "serial":
        return SerialLink(connection_string, where, baud)
    assert port is not None
    if kind == "tcp":
        return TcpLink(connection_string, where, port, connect_timeout_s)
    if kind == "udpbcast":
        return UdpBroadcastLink(connection_string, where, port)
    return UdpLink(connection_string, kind, where, port)
