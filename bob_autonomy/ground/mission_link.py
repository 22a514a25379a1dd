"""The link under `MissionClient` (bob_autonomy.ground.mission): one UDP socket for the whole fleet, a receiver
thread that keeps each vessel's heartbeat, position and STATUSTEXTs and sends our HEARTBEAT, and the sending
of a message to chosen vessels. Also the errors and the position record the client reports with."""

from __future__ import annotations

import contextlib
import logging
import math
import queue
import select
import socket
import struct
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from typing import Self

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from bob_autonomy.ground.gcs import COMPONENT_ID, MavlinkCodec
from bob_autonomy.ground.gcs_codec import ALLOWED_UNSIGNED
from firmware_bridge.links import LinkError, parse_connection_string

__all__ = ["FleetLink", "MissionError", "MissionTimeoutError", "VesselPosition"]

logger = logging.getLogger("bob_autonomy.ground.mission")

_UDP_MAX = 65535
RECEIVE_BUFFER_BYTES = 4 << 20  # asked of the kernel for the socket (it grants up to net.core.rmem_max)
SO_RXQ_OVFL = getattr(socket, "SO_RXQ_OVFL", 40)  # Linux: each datagram carries the socket's drop count
_DROPS = struct.Struct("=I")


class MissionError(RuntimeError):
    """A request failed on some vessels. `failures` maps system id -> reason; the message lists them all."""

    def __init__(self, what: str, failures: dict[int, str] | None = None) -> None:
        self.what = what
        self.failures = dict(failures or {})
        detail = "; ".join(f"vessel {sid}: {why}" for sid, why in sorted(self.failures.items()))
        super().__init__(f"{what}: {detail}" if detail else what)


class MissionTimeoutError(MissionError):
    """A wait (`discover`, `wait_until`, `wait_all_within`) ran out of time."""


@dataclass(frozen=True)
class VesselPosition:
    """A vessel's position as its autonomy component reported it: WGS-84 lat/lon (deg), ground velocity
    (m/s, east and north), heading (rad from east, counter-clockwise; None if unknown) and when we got
    it (`t_s`, the client's clock)."""

    system_id: int
    lat_deg: float
    lon_deg: float
    v_east_mps: float
    v_north_mps: float
    heading_rad: float | None
    t_s: float


@dataclass
class _Vessel:
    system_id: int
    address: tuple[str, int]
    last_heartbeat_s: float
    behavior_running: bool = False
    behavior_index: int = 0
    statustexts: deque = field(default_factory=lambda: deque(maxlen=100))
    chunks: dict[int, dict[int, str]] = field(default_factory=dict)


def float32(x: float) -> float:
    """x rounded to the nearest float32, as a PARAM_VALUE carries it (to compare an echo with what was set)."""
    return struct.unpack("<f", struct.pack("<f", float(x)))[0]


def result_name(enum: str, value: int) -> str:
    """The name of `value` in MAVLink enum `enum` (e.g. MAV_RESULT_DENIED), or "ENUM value" if unknown."""
    entry = mavlink.enums[enum].get(value)
    return entry.name if entry is not None else f"{enum} {value}"


class FleetLink:
    """A ground-station endpoint on one UDP socket: the fleet it has heard and how to reach each vessel.

    connection: "udpin:HOST:PORT" (listen; vessels send to it) or "udpout:HOST:PORT" (also send there).
    system_id / component_id: ours (255 / MAV_COMP_ID_MISSIONPLANNER 190). signing_key: 32 bytes or None.
    timeout_s: wait for each answer (s); retries: further tries before a vessel is reported as failed.
    target_component: the vessels' autonomy component (191).
    """

    def __init__(
        self,
        connection: str = "udpin:0.0.0.0:14550",
        *,
        system_id: int = 255,
        component_id: int = mavlink.MAV_COMP_ID_MISSIONPLANNER,
        signing_key: bytes | None = None,
        timeout_s: float = 1.0,
        retries: int = 3,
        heartbeat_period_s: float = 1.0,
        target_component: int = COMPONENT_ID,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        kind, host, port = parse_connection_string(connection)
        if kind not in ("udpin", "udpout"):
            raise LinkError(f"MissionClient needs udpin:HOST:PORT or udpout:HOST:PORT, not {connection!r}")
        assert port is not None
        self.connection = connection
        self.timeout_s = float(timeout_s)
        self.retries = int(retries)
        self.heartbeat_period_s = float(heartbeat_period_s)
        self.target_component = int(target_component)
        self.clock = clock
        self.codec = MavlinkCodec(system_id, component_id, signing_key=signing_key)
        self.counters = self.codec.counters
        self._default_peer: tuple[str, int] | None = None
        self.kernel_drops = 0  # datagrams the kernel dropped because our receive buffer was full (Linux)
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            # A fleet's routed telemetry (about 70 datagrams per simulated s per vessel) fills the default buffer
            # in well under a second when this thread is held up (2,000 datagrams/s at 5 vessels and 5x speed).
            self._sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RECEIVE_BUFFER_BYTES)
            with contextlib.suppress(OSError):  # not on every kernel: kernel_drops then stays 0
                self._sock.setsockopt(socket.SOL_SOCKET, SO_RXQ_OVFL, 1)
            if kind == "udpin":
                self._sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                self._sock.bind((host, port))
            else:
                self._default_peer = (socket.gethostbyname(host), port)
                self._sock.bind(("0.0.0.0", 0))
        except OSError as exc:
            self._sock.close()
            raise LinkError(f"cannot open {connection!r}: {exc}") from exc
        self._lock = threading.RLock()  # vessels, positions, listeners, the codec
        self._vessels: dict[int, _Vessel] = {}
        self._positions: dict[int, VesselPosition] = {}
        self._listeners: list[queue.Queue] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"MissionClient {connection}", daemon=True)
        self._thread.start()

    # -- lifetime ------------------------------------------------------------------------------------------

    @property
    def local_address(self) -> tuple[str, int]:
        """The (host, port) our socket is bound to."""
        return self._sock.getsockname()

    def close(self) -> None:
        """Stop the receiver thread and close the socket."""
        self._stop.set()
        if self._thread.is_alive() and threading.current_thread() is not self._thread:
            self._thread.join(timeout=2.0)
        self._sock.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- the receiver thread -------------------------------------------------------------------------------

    def _run(self) -> None:
        next_heartbeat = 0.0
        while not self._stop.is_set():
            try:
                now = float(self.clock())
                if now >= next_heartbeat:
                    next_heartbeat = now + self.heartbeat_period_s
                    self._send_heartbeat()
                ready, _, _ = select.select([self._sock], [], [], 0.02)
                if ready:
                    self._read_waiting()
            except (ConnectionRefusedError, ConnectionResetError):
                continue  # an ICMP "port unreachable" from an earlier send
            except (OSError, ValueError):
                if self._stop.is_set():
                    return
                logger.exception("MissionClient receive loop")
                time.sleep(0.05)
            except Exception:  # never let the thread die on a bad message
                logger.exception("MissionClient receive loop")

    def _read_waiting(self, most: int = 256) -> None:
        """Read the datagrams waiting (up to `most`) before the next select: a fleet routes all its telemetry
        here, and a thread that woke once per datagram fell behind under load until the kernel dropped echoes."""
        for _ in range(most):
            try:
                data, ancillary, _flags, sender = self._sock.recvmsg(_UDP_MAX, 64, socket.MSG_DONTWAIT)
            except BlockingIOError:
                return
            for level, kind, value in ancillary:
                if level == socket.SOL_SOCKET and kind == SO_RXQ_OVFL and len(value) >= _DROPS.size:
                    self.kernel_drops = _DROPS.unpack_from(value)[0]
            self._on_datagram(data, sender)

    def _on_datagram(self, data: bytes, sender: tuple[str, int]) -> None:
        with self._lock:
            messages = self.codec.decode(data, datagram=True)
            now = float(self.clock())
            for msg in messages:
                self._track(msg, sender, now)
            listeners = list(self._listeners)
        for msg in messages:
            for q in listeners:
                q.put(msg)

    def _track(self, msg, sender: tuple[str, int], now: float) -> None:
        sid = msg.get_srcSystem()
        if msg.get_srcComponent() != self.target_component:
            return
        if self.codec.signing_key is not None and msg.get_msgId() in ALLOWED_UNSIGNED:
            return  # let through unsigned (radio status): it proves nothing of who sent it, so it moves nothing
        vessel = self._vessels.get(sid)
        kind = msg.get_type()
        if vessel is None:
            if kind != "HEARTBEAT":
                return
            vessel = self._vessels[sid] = _Vessel(sid, sender, now)
            logger.info("vessel %d found at %s:%d", sid, *sender)
        vessel.address = sender
        if kind == "HEARTBEAT":
            vessel.last_heartbeat_s = now
            vessel.behavior_running = bool(msg.custom_mode & 1)
            vessel.behavior_index = (msg.custom_mode >> 8) & 0xFF
        elif kind == "GLOBAL_POSITION_INT":
            heading = None if msg.hdg == 65535 else math.radians(90.0 - msg.hdg / 100.0)
            if heading is not None:
                heading = math.atan2(math.sin(heading), math.cos(heading))
            self._positions[sid] = VesselPosition(
                sid, msg.lat / 1e7, msg.lon / 1e7, msg.vy / 100.0, msg.vx / 100.0, heading, now
            )
        elif kind == "STATUSTEXT":
            text = msg.text
            if msg.id:  # one chunk of a long text: keep until the last (shorter than 50 characters) arrives
                parts = vessel.chunks.setdefault(msg.id, {})
                parts[msg.chunk_seq] = text
                if len(text) >= 50:
                    if len(vessel.chunks) > 8:
                        vessel.chunks.pop(next(iter(vessel.chunks)))
                    return
                text = "".join(parts[k] for k in sorted(parts))
                del vessel.chunks[msg.id]
            vessel.statustexts.append((now, msg.severity, text))
            logger.info("vessel %d: %s", sid, text)

    def _send_heartbeat(self) -> None:
        message = self.codec.mav.heartbeat_encode(
            mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, mavlink.MAV_STATE_ACTIVE
        )
        self._send(message, None)

    # -- sending -------------------------------------------------------------------------------------------

    def _addresses(self, vessels: Iterable[int] | None) -> list[tuple[str, int]]:
        with self._lock:
            if vessels is None:
                found = {v.address for v in self._vessels.values()}
                if self._default_peer is not None:
                    found.add(self._default_peer)
                return sorted(found)
            out = []
            for sid in vessels:
                vessel = self._vessels.get(sid)
                if vessel is not None:
                    out.append(vessel.address)
                elif self._default_peer is not None:
                    out.append(self._default_peer)
            return sorted(set(out))

    def _send(self, message, vessels: Iterable[int] | None) -> None:
        """Pack once and send to the given vessels' addresses (None: every known address)."""
        with self._lock:
            data = self.codec.pack(message)
        for address in self._addresses(vessels):
            try:
                self._sock.sendto(data, address)
            except OSError as exc:
                logger.warning("cannot send to %s:%d: %s", address[0], address[1], exc)

    @contextlib.contextmanager
    def _listen(self) -> Iterator[queue.Queue]:
        q: queue.Queue = queue.Queue()
        with self._lock:
            self._listeners.append(q)
        try:
            yield q
        finally:
            with self._lock:
                self._listeners.remove(q)

    def _for_us(self, msg) -> bool:
        """Whether a reply is addressed to this ground station (its system and component, or 0): a vessel routes
        its autopilot's answers to its own commands to the ground station too, from the same system id."""
        system, component = getattr(msg, "target_system", 0), getattr(msg, "target_component", 0)
        return system in (0, self.codec.system_id) and component in (0, self.codec.mav.srcComponent)

    # -- the fleet ------------------------------------------------------------------------------------------

    @property
    def vessels(self) -> list[int]:
        """System ids of the vessels heard so far (HEARTBEAT from their component 191), sorted."""
        with self._lock:
            return sorted(self._vessels)

    def _targets(self, vessels: Iterable[int] | None) -> list[int]:
        if vessels is None:
            found = self.vessels
            if not found:
                raise MissionError("no vessels known: call discover() first")
            return found
        targets = sorted({int(v) for v in vessels})
        if not targets:
            raise MissionError("an empty list of vessels")
        with self._lock:
            unknown = [sid for sid in targets if sid not in self._vessels]
        if unknown and self._default_peer is None:
            raise MissionError("unknown vessels", dict.fromkeys(unknown, "never heard (no HEARTBEAT)"))
        return targets

    def discover(self, min_vessels: int = 1, timeout_s: float = 10.0) -> list[int]:
        """Wait until at least `min_vessels` vessels have sent a HEARTBEAT from their autonomy component;
        return all vessels heard (sorted system ids). MissionTimeoutError names those found when too few came."""
        deadline = time.monotonic() + float(timeout_s)
        while True:
            found = self.vessels
            if len(found) >= min_vessels:
                return found
            if time.monotonic() >= deadline:
                raise MissionTimeoutError(
                    f"found {len(found)} of {min_vessels} vessels in {timeout_s:g} s "
                    f"({', '.join(map(str, found)) or 'none'}) on {self.connection}"
                )
            time.sleep(0.02)

    def statustexts(self, system_id: int) -> list[tuple[float, int, str]]:
        """The last (up to 100) STATUSTEXTs of a vessel: (time received, severity, text)."""
        with self._lock:
            vessel = self._vessels.get(system_id)
            return list(vessel.statustexts) if vessel is not None else []

    def behavior_running(self) -> dict[int, bool]:
        """Whether each vessel's behaviour runs, from its last HEARTBEAT (custom_mode bit 0)."""
        with self._lock:
            return {sid: v.behavior_running for sid, v in self._vessels.items()}

    def positions(self) -> dict[int, VesselPosition]:
        """The latest reported position of each vessel that reported one."""
        with self._lock:
            return dict(self._positions)
