"""The simulated vehicles as MAVLink endpoints on UDP, and the telemetry log (.tlog) of everything they exchange.

Vehicle i (0-based) of a fleet is MAVLink system i + 1 and binds UDP
HOST:(base_port + 10 i), base_port 5760 by default: the port numbers of
ArduPilot SITL instances (`sim_vehicle.py -I i` serves SERIAL0 on 5760 + 10 i),
so tools configured for a SITL fleet find the vehicles where they expect them.
Anyone may connect with `udpout:HOST:PORT` (the `bob-autonomy` process,
MAVProxy, QGroundControl): a vehicle answers every peer that sent it a datagram
in the last `PEER_TIMEOUT_S` wall seconds, so several can listen at once.

Each vehicle is a `sitl.vehicles.mavlink_vehicle.SimulatedVehicle`: an ArduPilot Rover
as the autonomy and ground stations see it (streams, parameters, missions,
arming, modes, failsafes; docs/simulated-autopilot.md). Its telemetry is
encoded from the sensor readings of `sitl.vehicles.vehicle_physics.VehiclePhysics`.
With `streams="ardupilot"` (the default) each vehicle streams at Rover's 1 Hz
defaults until asked, as a real autopilot does (bob-autonomy asks at start);
with `streams="sensor-rate"`: HEARTBEAT and SYS_STATUS at 1 Hz (simulated time),
GPS_RAW_INT, ATTITUDE, SCALED_IMU and WHEEL_DISTANCE as the sensors deliver,
and GLOBAL_POSITION_INT with every GPS fix. Replies go to the sender; telemetry and the
vehicle's announcements (STATUSTEXT, PARAM_VALUE echoes, HOME_POSITION) to
every live peer. All frames of one vehicle and one step go out in one datagram
to each peer. Each peer is a link of its own, as each of ArduPilot's MAVLink
channels is: its frames are numbered at send time from its own counter
(`firmware_bridge.frames.renumber`), so a peer sees an unbroken sequence whatever
the vehicle answered the others, and a ground station's loss figure is the link's.
A datagram whose handling raises is counted (`datagram_errors`), logged and
skipped: one bad datagram never ends a fleet.

Every MAVLink frame received or sent is appended to a telemetry log in
MAVProxy's `.tlog` format: per frame, an 8-byte big-endian count of
microseconds since the Unix epoch, then the raw frame. `pymavlink.mavutil.
mavlink_connection(path)` and `mavlogdump.py` read it.
"""

from __future__ import annotations

import logging
import select
import socket
import time
from collections.abc import Sequence

import numpy as np

from firmware_bridge.frames import renumber
from firmware_bridge.readings import SensorReadings
from firmware_bridge.tlog import TlogWriter, split_frames
from sitl.vehicles.bodies import BODY_SPECS
from sitl.vehicles.bodies import EBOT as EBOT_KIND
from sitl.vehicles.mavlink_vehicle import (
    BUOY,
    EBOT,
    MOTORBOAT,
    SimulatedVehicle,
    encode_readings,
    encode_senses,
    prepend_streams,
)

DEFAULT_BASE_PORT = 5760  # ArduPilot SITL instance 0 (SERIAL0)
PORT_STRIDE = 10  # ArduPilot SITL: instance i uses base + 10 i
EBOT_SONAR_RANGE_M = BODY_SPECS[EBOT_KIND].range_max_m
PEER_TIMEOUT_S = 5.0  # wall seconds: a peer that has sent nothing for this long no longer gets telemetry
_UINT16_MAX = 65535
MAX_LOGGED_ERRORS = 20  # per vehicle: the rest are only counted
log = logging.getLogger(__name__)


def vehicle_port(index: int, base_port: int = DEFAULT_BASE_PORT) -> int:
    """The UDP port of vehicle `index` (0-based): base_port + 10 index (ArduPilot's multi-instance rule)."""
    return base_port + PORT_STRIDE * index


class VehicleEndpoint:
    """One simulated vehicle on one bound UDP socket, answering every recent peer."""

    def __init__(self, vehicle: SimulatedVehicle, host: str, port: int, tlog: TlogWriter | None = None) -> None:
        self.vehicle, self.tlog = vehicle, tlog
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self.sock.bind((host, port))
        except OSError as error:
            self.sock.close()
            raise OSError(
                f"cannot bind vehicle {vehicle.system_id} to UDP {host}:{port} ({error}); "
                "is another simulation or SITL running? choose another --base-port"
            ) from error
        self.sock.setblocking(False)
        self.address = self.sock.getsockname()
        self.peers: dict[tuple[str, int], float] = {}  # address -> wall time last heard (time.monotonic)
        self.next_seq: dict[tuple[str, int], int] = {}  # address -> the sequence number of its next frame
        self.bytes_in = self.bytes_out = 0
        self.errors = 0  # datagrams whose handling raised (logged, skipped)

    def fileno(self) -> int:
        return self.sock.fileno()

    def live_peers(self, now_wall_s: float | None = None) -> list[tuple[str, int]]:
        """Peers heard within PEER_TIMEOUT_S wall seconds (older ones are forgotten)."""
        now = time.monotonic() if now_wall_s is None else now_wall_s
        for address in [a for a, heard in self.peers.items() if now - heard > PEER_TIMEOUT_S]:
            del self.peers[address]
            self.next_seq.pop(address, None)
        return list(self.peers)

    def read(self, t_s: float) -> int:
        """Take every datagram waiting: commands to the vehicle (at simulated time t_s), replies to the sender.
        Returns the number of datagrams read."""
        count = 0
        while True:
            try:
                data, sender = self.sock.recvfrom(65535)
            except (BlockingIOError, InterruptedError):
                return count
            except ConnectionRefusedError:  # an ICMP "port unreachable" for an earlier send: that peer is gone
                continue
            count += 1
            self.bytes_in += len(data)
            try:
                self.peers[sender] = time.monotonic()
                if self.tlog is not None:
                    self.tlog.write(data)
                replies = self.vehicle.receive(data, t_s)
                if replies:
                    self._send_to(replies, [sender])
            except Exception as error:  # one bad datagram must never end the fleet (#17): count, log, go on
                self.errors += 1
                if self.errors <= MAX_LOGGED_ERRORS:
                    log.warning(
                        "vehicle %d: datagram of %d bytes from %s:%d not handled (%s: %s); going on",
                        self.vehicle.system_id,
                        len(data),
                        sender[0],
                        sender[1],
                        type(error).__name__,
                        error,
                    )

    def send(self, data: bytes) -> None:
        """Send telemetry to every live peer (logged once)."""
        peers = self.live_peers()
        if data and peers:
            self._send_to(data, peers)

    def _send_to(self, data: bytes, peers: Sequence[tuple[str, int]]) -> None:
        """Send `data` to each peer, numbered on that peer's link; the log gets the first peer's copy."""
        logged = False
        for peer in peers:
            numbered, self.next_seq[peer] = renumber(data, self.next_seq.get(peer, 0))
            try:
                self.sock.sendto(numbered, peer)
                self.bytes_out += len(numbered)
            except (BlockingIOError, ConnectionRefusedError):
                pass  # a full buffer or a vanished peer: telemetry is best effort, as on a radio link
            if self.tlog is not None and not logged:
                self.tlog.write(numbered)
                logged = True

    def close(self) -> None:
        self.sock.close()


class VehicleServer:
    """The vehicles of a fleet on UDP (see the module docstring).

    kinds: "buoy", "ebot" or "motorboat" per vehicle (fleet row order). max_actuators: full-scale thrust (N),
    wheel speed (m/s) or 1 (a motorboat's throttle and steering) per vehicle, what RC 1900 us stands for.
    metres_per_tick: eBot wheel travel per encoder tick, m.
    failsafe_s: simulated seconds without a command after which a vehicle stops its actuators (its
    RC_OVERRIDE_TIME). armed: the vehicles' state at start (False: the autonomy arms them). tlog: where every frame
    is logged (or None). streams: "ardupilot" (ArduPilot Rover's 1 Hz stream defaults until asked;
    sitl/vehicles/mavlink_vehicle.py) or "sensor-rate" (every reading sent as it comes, unasked). vehicle_params:
    autopilot parameter values every vehicle starts with; own_params: each vehicle's own on top (or None), e.g. a
    motorboat's SPEED_MAX and TURN_RADIUS.
    """

    def __init__(
        self,
        kinds: Sequence[str],
        max_actuators: Sequence[float],
        *,
        host: str = "127.0.0.1",
        base_port: int = DEFAULT_BASE_PORT,
        metres_per_tick: float = 1.0,
        failsafe_s: float = 1.0,
        armed: bool = False,
        tlog: TlogWriter | None = None,
        streams: str = "ardupilot",
        vehicle_params: dict[str, float] | None = None,
        own_params: Sequence[dict[str, float] | None] | None = None,
    ) -> None:
        self.kinds = list(kinds)
        own = list(own_params) if own_params is not None else [None] * len(self.kinds)
        self.metres_per_tick = float(metres_per_tick)
        self.tlog = tlog
        self.endpoints: list[VehicleEndpoint] = []
        try:
            for i, (kind, limit, mine) in enumerate(zip(self.kinds, max_actuators, own, strict=True)):
                params = {**(vehicle_params or {}), **(mine or {})}
                vehicle = SimulatedVehicle(
                    i + 1, kind, limit, failsafe_s=failsafe_s, armed=armed, streams=streams, params=params
                )
                self.endpoints.append(VehicleEndpoint(vehicle, host, vehicle_port(i, base_port), tlog))
        except BaseException:
            self.close()
            raise
        # Fleet rows of each kind, in order: sensor readings index vehicles within their kind.
        self.rows = {
            k: np.array([i for i, x in enumerate(self.kinds) if x == k], dtype=np.intp) for k in (BUOY, EBOT, MOTORBOAT)
        }

    def __len__(self) -> int:
        return len(self.endpoints)

    @property
    def vehicles(self) -> list[SimulatedVehicle]:
        return [e.vehicle for e in self.endpoints]

    @property
    def ports(self) -> list[int]:
        return [e.address[1] for e in self.endpoints]

    def sockets(self) -> list[socket.socket]:
        return [e.sock for e in self.endpoints]

    def read(self, t_s: float, ready: Sequence[socket.socket] | None = None) -> int:
        """Read what arrived on the vehicles' sockets (those in `ready`, or all) at simulated time t_s."""
        wanted = None if ready is None else {s.fileno() for s in ready}
        return sum(e.read(t_s) for e in self.endpoints if wanted is None or e.fileno() in wanted)

    def serve(self, wall_s: float, t_s: float) -> None:
        """Answer the vehicles' peers for `wall_s` wall seconds at simulated time t_s (no telemetry)."""
        end = time.monotonic() + wall_s
        while (left := end - time.monotonic()) > 0:
            ready, _, _ = select.select(self.sockets(), [], [], left)
            self.read(t_s, ready)

    def actuators(self, t_s: float) -> np.ndarray:
        """(n, 2) what each vehicle applies at t_s: thrust N (buoys) or wheel speeds m/s (eBots); zero when
        disarmed, holding or in failsafe."""
        return np.array([e.vehicle.actuator(t_s) for e in self.endpoints]).reshape(-1, 2)

    def armed(self) -> np.ndarray:
        """(n,) bool: which vehicles are armed (what their HEARTBEAT says)."""
        return np.array([e.vehicle.armed for e in self.endpoints], dtype=bool)

    def telemetry(
        self, t_s: float, readings: dict[str, SensorReadings], ebot_senses: tuple | None = None
    ) -> list[bytes]:
        """Each vehicle's telemetry frames for this step (housekeeping when due, then its sensors' readings).

        readings: {"buoy": ..., "ebot": ...} as `VehiclePhysics.sense` returns (agents index within a kind).
        """
        frames = [bytearray() for _ in self.endpoints]
        for kind, r in readings.items():
            encode_readings(
                r,
                t_s,
                self.vehicles,
                frames,
                self.rows[kind],
                metres_per_tick=self.metres_per_tick,
                fused_position=True,
            )
        prepend_streams(t_s, self.vehicles, frames)
        if ebot_senses is not None and self.rows[EBOT].size:
            ranges, light = ebot_senses
            encode_senses(t_s, self.vehicles, frames, self.rows[EBOT], ranges, light, EBOT_SONAR_RANGE_M)
        return [bytes(f) for f in frames]

    def send_telemetry(self, t_s: float, readings: dict[str, SensorReadings], ebot_senses: tuple | None = None) -> None:
        """Encode this step's telemetry (and the eBots' (ranges, light), when given) and send each vehicle's to its
        live peers."""
        for endpoint, data in zip(self.endpoints, self.telemetry(t_s, readings, ebot_senses), strict=True):
            endpoint.send(data)

    def counters(self) -> dict[str, int]:
        """Totals over the vehicles: commands applied, refused, failsafe stops, acks; bytes in and out."""
        totals: dict[str, int] = {}
        for e in self.endpoints:
            for name, value in vars(e.vehicle.counters).items():
                totals[name] = totals.get(name, 0) + int(value)
            totals["bytes_in"] = totals.get("bytes_in", 0) + e.bytes_in
            totals["bytes_out"] = totals.get("bytes_out", 0) + e.bytes_out
            totals["datagram_errors"] = totals.get("datagram_errors", 0) + e.errors
        return totals

    def close(self) -> None:
        """Close every socket (the ports are free again)."""
        for e in self.endpoints:
            e.close()


__all__ = [
    "DEFAULT_BASE_PORT",
    "PEER_TIMEOUT_S",
    "PORT_STRIDE",
    "TlogWriter",
    "VehicleEndpoint",
    "VehicleServer",
    "split_frames",
    "vehicle_port",
]
