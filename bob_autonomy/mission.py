"""A client for mission scripts: find the fleet's autonomy components and drive them over MAVLink.

    with MissionClient("udpin:0.0.0.0:14550", signing_key=load_signing_key("bob.key")) as fleet:
        vessels = fleet.discover(min_vessels=3, timeout_s=10)      # system ids, by HEARTBEAT of component 191
        fleet.set_param("BOB_P0_M", 5.0)                          # every vessel; verified, retried
        fleet.set_behavior("bob-rule", vessels=[2, 3])
        fleet.upload_goals([(45.0001, 7.0002)])
        fleet.upload_fence([(45.0, 7.0), (45.0, 7.01), (45.01, 7.01), (45.01, 7.0)])
        fleet.start()                                              # MAV_CMD_MISSION_START to system 0
        fleet.wait_all_within((45.0001, 7.0002), radius_m=10, timeout_s=600)

One UDP socket serves the whole fleet: many vessels may send to the same port; each is told apart by its
MAVLink system id, and the address its autonomy component (191) last sent from is where it is answered.
With `udpout:HOST:PORT` the client also sends to that address before anyone has spoken (a single vessel,
or a router). A background thread receives, keeps each vessel's heartbeat, position (the component's
GLOBAL_POSITION_INT) and STATUSTEXTs, and sends our own HEARTBEAT (MAV_TYPE_GCS) once a second to every
known vessel, which keeps their ground-station failsafe (BOB_GCS_FS_S) quiet.

Every request is verified and retried (`timeout_s` per try, `retries` more tries); a failure raises
`MissionError` whose `failures` maps each vessel that failed to why (no answer, MAV_RESULT / MAV_MISSION
result names, and the vessel's own STATUSTEXT explaining a refusal).
"""

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
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from bob_autonomy.gcs import COMPONENT_ID, MavlinkCodec
from bob_autonomy.gcs_codec import ALLOWED_UNSIGNED
from bob_autonomy.geodesy import LocalFrame
from bob_autonomy.params import BEHAVIOR_NAMES, PARAMS, LatLon, ParamError, validate_latlon
from firmware_bridge.links import LinkError, parse_connection_string

__all__ = ["MissionClient", "MissionError", "MissionTimeoutError", "VesselPosition"]

logger = logging.getLogger(__name__)

_SPECS = {spec.name: spec for spec in PARAMS}
_UDP_MAX = 65535


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


def _f32(x: float) -> float:
    return struct.unpack("<f", struct.pack("<f", float(x)))[0]


def _result_name(enum: str, value: int) -> str:
    entry = mavlink.enums[enum].get(value)
    return entry.name if entry is not None else f"{enum} {value}"


class MissionClient:
    """A ground-station endpoint for mission scripts (see the module docstring).

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
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
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

    def __enter__(self) -> MissionClient:
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
                    data, sender = self._sock.recvfrom(_UDP_MAX)
                    self._on_datagram(data, sender)
            except (ConnectionRefusedError, ConnectionResetError):
                continue  # an ICMP "port unreachable" from an earlier send
            except (OSError, ValueError):
                if self._stop.is_set():
                    return
                logger.exception("MissionClient receive loop")
                time.sleep(0.05)
            except Exception:  # never let the thread die on a bad message
                logger.exception("MissionClient receive loop")

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
        target = getattr(msg, "target_system", 0)
        return target in (0, self.codec.system_id)

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

    # -- one request to many vessels, verified and retried ------------------------------------------------

    def _exchange(
        self,
        what: str,
        targets: Sequence[int],
        send: Callable[[list[int], int], None],
        match: Callable[[int, object], tuple[str, object] | None],
    ) -> dict[int, object]:
        """send(pending, attempt) sends the request to the vessels still pending; match(sid, msg) returns
        ("ok", value), ("fail", reason) (final), ("wait", reason) (keep waiting, remember why) or None."""
        pending = set(targets)
        results: dict[int, object] = {}
        failures: dict[int, str] = {}
        reasons: dict[int, str] = {}
        start = float(self.clock())
        with self._listen() as q:
            for attempt in range(self.retries + 1):
                send(sorted(pending), attempt)
                deadline = time.monotonic() + self.timeout_s
                while pending:
                    remaining = deadline - time.monotonic()
                    if remaining <= 0:
                        break
                    try:
                        msg = q.get(timeout=remaining)
                    except queue.Empty:
                        break
                    sid = msg.get_srcSystem()
                    if sid not in pending:
                        continue
                    verdict = match(sid, msg)
                    if verdict is None:
                        continue
                    status, value = verdict
                    if status == "ok":
                        results[sid] = value
                        pending.discard(sid)
                    elif status == "fail":
                        failures[sid] = str(value)
                        pending.discard(sid)
                    else:
                        reasons[sid] = str(value)
                if not pending:
                    break
        for sid in pending:
            why = reasons.get(sid) or next((t for s, _, t in reversed(self.statustexts(sid)) if s >= start), None)
            failures[sid] = f"no answer after {self.retries + 1} tries" + (f" (last heard: {why})" if why else "")
        if failures:
            raise MissionError(what, failures)
        return results

    # -- parameters ----------------------------------------------------------------------------------------

    def set_param(self, name: str, value: float, vessels: Iterable[int] | None = None) -> dict[int, float]:
        """Set a parameter on the vessels (None: all found); checks it against the declared range first
        (ParamError), then verifies each vessel's PARAM_VALUE echo. Returns {system id: value in force}."""
        spec = _SPECS.get(name)
        if spec is None:
            raise ParamError(f"unknown parameter {name!r}; known: {', '.join(_SPECS)}")
        checked = spec.check(value)
        wanted = _f32(checked)
        targets = self._targets(vessels)
        encoded = name.encode("ascii")

        def send(pending: list[int], attempt: int) -> None:
            for sid in pending:
                self._send(
                    self.codec.mav.param_set_encode(sid, self.target_component, encoded, float(checked), spec.mav_type),
                    [sid],
                )

        start = float(self.clock())

        def match(sid: int, msg) -> tuple[str, object] | None:
            if msg.get_type() != "PARAM_VALUE" or msg.param_id != name:
                return None
            if msg.param_value == wanted:
                return "ok", msg.param_value
            # The vessel says why it refused in a STATUSTEXT sent just before the PARAM_VALUE.
            for t, _severity, text in reversed(self.statustexts(sid)):
                if t >= start and name in text:
                    return "fail", f"refused ({text}); {name} is {msg.param_value:g}"
            return "wait", f"{name} is still {msg.param_value:g}"

        return self._exchange(f"cannot set {name} = {value!r}", targets, send, match)  # type: ignore[return-value]

    def set_params(self, values: dict[str, float], vessels: Iterable[int] | None = None) -> None:
        """Set several parameters (in the order given) on the vessels."""
        for name, value in values.items():
            self.set_param(name, value, vessels)

    def get_param(self, name: str, vessels: Iterable[int] | None = None) -> dict[int, float]:
        """Read a parameter from the vessels: {system id: value} (INT32 values as whole floats)."""
        if name not in _SPECS:
            raise ParamError(f"unknown parameter {name!r}; known: {', '.join(_SPECS)}")
        targets = self._targets(vessels)

        def send(pending: list[int], attempt: int) -> None:
            for sid in pending:
                self._send(
                    self.codec.mav.param_request_read_encode(sid, self.target_component, name.encode("ascii"), -1),
                    [sid],
                )

        def match(sid: int, msg) -> tuple[str, object] | None:
            if msg.get_type() == "PARAM_VALUE" and msg.param_id == name:
                return "ok", float(msg.param_value)
            return None

        return self._exchange(f"cannot read {name}", targets, send, match)  # type: ignore[return-value]

    def set_behavior(self, behavior: str | int, vessels: Iterable[int] | None = None) -> None:
        """Choose the behaviour (name from BEHAVIOR_NAMES, or its index) through BOB_BEHAVIOR."""
        if isinstance(behavior, str):
            try:
                index = BEHAVIOR_NAMES.index(behavior)
            except ValueError:
                raise ParamError(f"unknown behaviour {behavior!r}; known: {', '.join(BEHAVIOR_NAMES)}") from None
        else:
            index = int(behavior)
        self.set_param("BOB_BEHAVIOR", index, vessels)

    # -- commands ------------------------------------------------------------------------------------------

    def command(
        self,
        command: int,
        params: Sequence[float] = (),
        vessels: Iterable[int] | None = None,
        *,
        broadcast: bool = False,
        what: str | None = None,
    ) -> None:
        """COMMAND_LONG to each vessel, waiting for COMMAND_ACK MAV_RESULT_ACCEPTED (IN_PROGRESS: keep
        waiting). `broadcast`: the first try is one message to target system 0 (the whole fleet), retries go
        to each silent vessel by id."""
        p = [float(v) for v in params] + [0.0] * (7 - len(params))
        targets = self._targets(vessels)
        label = what or _result_name("MAV_CMD", command)

        def send(pending: list[int], attempt: int) -> None:
            if broadcast and attempt == 0:
                self._send(self.codec.mav.command_long_encode(0, 0, command, 0, *p), pending)
                return
            for sid in pending:
                self._send(self.codec.mav.command_long_encode(sid, self.target_component, command, attempt, *p), [sid])

        def match(sid: int, msg) -> tuple[str, object] | None:
            if msg.get_type() != "COMMAND_ACK" or msg.command != command or not self._for_us(msg):
                return None
            if msg.result == mavlink.MAV_RESULT_ACCEPTED:
                return "ok", msg.result
            if msg.result == mavlink.MAV_RESULT_IN_PROGRESS:
                return None
            return "fail", _result_name("MAV_RESULT", msg.result)

        try:
            self._exchange(f"{label} failed", targets, send, match)
        except MissionError as exc:
            raise self._explained(exc) from None

    def _explained(self, exc: MissionError) -> MissionError:
        """Add each failed vessel's last STATUSTEXT (its reason) to a refusal."""
        failures = dict(exc.failures)
        for sid, why in failures.items():
            texts = self.statustexts(sid)
            if texts and not why.startswith("no answer"):
                failures[sid] = f"{why} ({texts[-1][2]})"
        return type(exc)(exc.what, failures)

    def start(self, vessels: Iterable[int] | None = None) -> None:
        """Start the behaviour (MAV_CMD_MISSION_START; to system 0 when vessels is None)."""
        self.command(mavlink.MAV_CMD_MISSION_START, (), vessels, broadcast=vessels is None, what="start")

    def stop(self, vessels: Iterable[int] | None = None) -> None:
        """Stop the behaviour and hold (MAV_CMD_DO_PAUSE_CONTINUE param1 = 0; to system 0 when vessels is None)."""
        self.command(mavlink.MAV_CMD_DO_PAUSE_CONTINUE, (0,), vessels, broadcast=vessels is None, what="stop")

    def set_goal(self, lat_deg: float, lon_deg: float, vessels: Iterable[int] | None = None) -> None:
        """One goal (deg) for the vessels (COMMAND_INT MAV_CMD_DO_REPOSITION, lat/lon in degE7)."""
        lat, lon = validate_latlon((lat_deg, lon_deg), "goal")
        targets = self._targets(vessels)
        command = mavlink.MAV_CMD_DO_REPOSITION

        def send(pending: list[int], attempt: int) -> None:
            for sid in pending:
                message = self.codec.mav.command_int_encode(
                    sid, self.target_component, mavlink.MAV_FRAME_GLOBAL_INT, command, 0, 0,
                    -1.0, 0.0, 0.0, math.nan, round(lat * 1e7), round(lon * 1e7), 0.0,
                )  # fmt: skip
                self._send(message, [sid])

        def match(sid: int, msg) -> tuple[str, object] | None:
            if msg.get_type() != "COMMAND_ACK" or msg.command != command or not self._for_us(msg):
                return None
            if msg.result == mavlink.MAV_RESULT_ACCEPTED:
                return "ok", msg.result
            return "fail", _result_name("MAV_RESULT", msg.result)

        try:
            self._exchange(f"cannot set the goal to {lat}, {lon}", targets, send, match)
        except MissionError as exc:
            raise self._explained(exc) from None

    def set_leader(self, leader_system_id: int, vessels: Iterable[int] | None = None) -> None:
        """Follow the vessel with this system id (0 = none): MAV_CMD_DO_FOLLOW param1."""
        self.command(mavlink.MAV_CMD_DO_FOLLOW, (leader_system_id,), vessels, what=f"follow {leader_system_id}")

    # -- missions ------------------------------------------------------------------------------------------

    def upload_goals(self, points: Sequence[LatLon], vessels: Iterable[int] | None = None) -> None:
        """Upload goal waypoints (lat, lon deg) as a MISSION of NAV_WAYPOINT items (empty list: clear)."""
        self._upload(mavlink.MAV_MISSION_TYPE_MISSION, [validate_latlon(p, "goal") for p in points], vessels)

    def upload_fence(self, polygon: Sequence[LatLon], vessels: Iterable[int] | None = None) -> None:
        """Upload a geofence inclusion polygon (lat, lon deg; at least 3 vertices, or empty to clear)."""
        vertices = [validate_latlon(p, "fence vertex") for p in polygon]
        if 0 < len(vertices) < 3:
            raise ParamError(f"a fence polygon needs at least 3 vertices, got {len(vertices)}")
        self._upload(mavlink.MAV_MISSION_TYPE_FENCE, vertices, vessels)

    def upload_rally(self, point: LatLon, vessels: Iterable[int] | None = None) -> None:
        """Upload the rally point (lat, lon deg)."""
        self._upload(mavlink.MAV_MISSION_TYPE_RALLY, [validate_latlon(point, "rally point")], vessels)

    def _item(self, sid: int, mission_type: int, points: list[LatLon], seq: int):
        lat, lon = points[seq]
        command = {
            mavlink.MAV_MISSION_TYPE_MISSION: mavlink.MAV_CMD_NAV_WAYPOINT,
            mavlink.MAV_MISSION_TYPE_FENCE: mavlink.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION,
            mavlink.MAV_MISSION_TYPE_RALLY: mavlink.MAV_CMD_NAV_RALLY_POINT,
        }[mission_type]
        param1 = float(len(points)) if mission_type == mavlink.MAV_MISSION_TYPE_FENCE else 0.0
        return self.codec.mav.mission_item_int_encode(
            sid, self.target_component, seq, mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, command, 0, 1,
            param1, 0.0, 0.0, 0.0, round(lat * 1e7), round(lon * 1e7), 0.0, mission_type,
        )  # fmt: skip

    def _upload(self, mission_type: int, points: list[LatLon], vessels: Iterable[int] | None) -> None:
        """The mission upload protocol with every target at once: MISSION_COUNT, answer each vessel's
        MISSION_REQUEST(_INT) with the item, until its MISSION_ACK. A vessel silent for 2.5 timeouts (it
        re-requests on its own first) gets MISSION_COUNT again (a restart), up to `retries` times."""
        targets = self._targets(vessels)
        kind = mavlink.enums["MAV_MISSION_TYPE"][mission_type].name
        stall_s = 2.5 * self.timeout_s
        failures: dict[int, str] = {}
        last_heard = dict.fromkeys(targets, time.monotonic())
        restarts = dict.fromkeys(targets, 0)
        pending = set(targets)

        def send_count(sid: int) -> None:
            count = self.codec.mav.mission_count_encode(sid, self.target_component, len(points), mission_type)
            self._send(count, [sid])
            last_heard[sid] = time.monotonic()

        with self._listen() as q:
            for sid in targets:
                send_count(sid)
            while pending:
                try:
                    msg = q.get(timeout=0.05)
                except queue.Empty:
                    msg = None
                if msg is not None and msg.get_srcSystem() in pending and self._for_us(msg):
                    sid = msg.get_srcSystem()
                    kind_in = msg.get_type()
                    if kind_in in ("MISSION_REQUEST_INT", "MISSION_REQUEST") and msg.mission_type == mission_type:
                        last_heard[sid] = time.monotonic()
                        if 0 <= msg.seq < len(points):
                            # MISSION_ITEM_INT even for a legacy MISSION_REQUEST, as MAVProxy does: degE7, not float32
                            self._send(self._item(sid, mission_type, points, msg.seq), [sid])
                    elif kind_in == "MISSION_ACK" and msg.mission_type == mission_type:
                        pending.discard(sid)
                        if msg.type != mavlink.MAV_MISSION_ACCEPTED:
                            failures[sid] = _result_name("MAV_MISSION_RESULT", msg.type)
                now = time.monotonic()
                for sid in sorted(pending):
                    if now - last_heard[sid] > stall_s:
                        if restarts[sid] >= self.retries:
                            pending.discard(sid)
                            failures[sid] = f"no answer after {restarts[sid] + 1} tries"
                        else:
                            restarts[sid] += 1
                            send_count(sid)
        if failures:
            raise self._explained(MissionError(f"{kind} upload of {len(points)} items failed", failures))

    def download(self, mission_type: int, system_id: int) -> list[LatLon]:
        """Download a vessel's goals (MAV_MISSION_TYPE_MISSION), fence (FENCE) or rally point (RALLY)."""
        sid = self._targets([system_id])[0]
        kind = mavlink.enums["MAV_MISSION_TYPE"][mission_type].name

        def single(request, accept: Callable[[object], tuple[str, object] | None], what: str):
            return self._exchange(what, [sid], lambda pending, attempt: self._send(request, [sid]),
                                  lambda s, m: accept(m) if self._for_us(m) else None)[sid]  # fmt: skip

        count = single(
            self.codec.mav.mission_request_list_encode(sid, self.target_component, mission_type),
            lambda m: ("ok", m.count) if m.get_type() == "MISSION_COUNT" and m.mission_type == mission_type else None,
            f"{kind} download: no MISSION_COUNT",
        )
        points: list[LatLon] = []
        for seq in range(int(count)):
            item = single(
                self.codec.mav.mission_request_int_encode(sid, self.target_component, seq, mission_type),
                lambda m, seq=seq: (
                    ("ok", m)
                    if m.get_type() == "MISSION_ITEM_INT" and m.seq == seq and m.mission_type == mission_type
                    else None
                ),
                f"{kind} download: no item {seq}",
            )
            points.append((item.x / 1e7, item.y / 1e7))
        self._send(
            self.codec.mav.mission_ack_encode(sid, self.target_component, mavlink.MAV_MISSION_ACCEPTED, mission_type),
            [sid],
        )
        return points

    # -- waiting -------------------------------------------------------------------------------------------

    def wait_until(
        self, predicate: Callable[[MissionClient], bool], timeout_s: float, what: str = "the condition", *,
        poll_s: float = 0.1, describe: Callable[[MissionClient], str] | None = None,
    ) -> None:  # fmt: skip
        """Call predicate(self) every poll_s until it is true; MissionTimeoutError after timeout_s (s) saying what
        was awaited (and `describe(self)`, when given, for the state at the end)."""
        deadline = time.monotonic() + float(timeout_s)
        while True:
            if predicate(self):
                return
            if time.monotonic() >= deadline:
                detail = f": {describe(self)}" if describe is not None else ""
                raise MissionTimeoutError(f"timed out after {timeout_s:g} s waiting for {what}{detail}")
            time.sleep(poll_s)

    def wait_all_within(
        self, goal: LatLon, radius_m: float, timeout_s: float, vessels: Iterable[int] | None = None
    ) -> dict[int, float]:
        """Wait until every vessel (None: all found) reports a position within radius_m (m) of goal (lat,
        lon deg). Returns their distances (m); MissionTimeoutError lists each vessel still out and how far."""
        lat, lon = validate_latlon(goal, "goal")
        targets = self._targets(vessels)
        frame = LocalFrame(lat, lon)

        def distances() -> dict[int, float | None]:
            positions = self.positions()
            out: dict[int, float | None] = {}
            for sid in targets:
                p = positions.get(sid)
                if p is None:
                    out[sid] = None
                else:
                    x, y = frame.to_local(p.lat_deg, p.lon_deg)
                    out[sid] = float(math.hypot(x, y))
            return out

        try:
            self.wait_until(
                lambda c: all(d is not None and d <= radius_m for d in distances().values()),
                timeout_s,
                f"all of vessels {targets} within {radius_m:g} m of {lat}, {lon}",
            )
        except MissionTimeoutError as exc:
            far = {
                sid: "no position reported" if d is None else f"{d:.1f} m away"
                for sid, d in distances().items()
                if d is None or d > radius_m
            }
            raise MissionTimeoutError(str(exc), far) from None
        return {sid: d for sid, d in distances().items() if d is not None}
