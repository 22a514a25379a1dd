"""The autonomy process as a MAVLink component of its vessel (MAV_COMP_ID_ONBOARD_COMPUTER, 191).

Transport-agnostic: `GcsComponent.receive(data)` takes whatever bytes a link delivered, `outgoing()` returns
the frames to send, `tick()` is called often (say at 10 Hz or more) for the 1 Hz HEARTBEAT, position
reports and protocol timeouts. The process wires it to a UDP link, drains `pending_autopilot` (arm, disarm,
mode changes it must pass on to the autopilot) and reads `behavior_running`, `goals`, `fence` and `params`.

Protocols (docs/gcs-protocol.md has the tables):

- parameters: PARAM_REQUEST_LIST, PARAM_REQUEST_READ (by id or index), PARAM_SET, each answered with
  PARAM_VALUE (index, count, the value actually in force; INT32 values are sent C-cast to float, as
  ArduPilot does). A refused PARAM_SET is answered with the unchanged value and a STATUSTEXT saying why.
- COMMAND_LONG / COMMAND_INT, answered with COMMAND_ACK: MISSION_START, DO_PAUSE_CONTINUE, arm / disarm and
  DO_SET_MODE (handed to the process: IN_PROGRESS, then the autopilot's own answer), DO_REPOSITION /
  NAV_WAYPOINT (goal), DO_FOLLOW (leader), USER_1 (behaviour), DO_FENCE_ENABLE, REQUEST_MESSAGE /
  REQUEST_AUTOPILOT_CAPABILITIES; others MAV_RESULT_UNSUPPORTED.
- missions: upload (MISSION_COUNT, then our MISSION_REQUEST_INT, answered by MISSION_ITEM_INT or the legacy
  MISSION_ITEM) and download (MISSION_REQUEST_LIST, MISSION_REQUEST_INT or MISSION_REQUEST) of the goal
  waypoints (MISSION), a geofence inclusion polygon (FENCE) and one rally point (RALLY); MISSION_CLEAR_ALL.
- STATUSTEXT for events (`notify`), chunked beyond 50 characters.

Messages are handled when their target system is ours or 0 (broadcast: the whole fleet) and their target
component ours or 0; others are counted (`counters.ignored_other_target`) and dropped.

Signing (`MavlinkCodec`, in `bob_autonomy.ground.gcs_codec`): with a key, every frame we send is MAVLink 2 signed,
and a received frame is accepted only if it is signed with the key and newer than the last one of its stream;
unsigned (`unsigned_rejected`), wrongly signed (`bad_signature`) and replayed or stale (`replay_rejected`)
frames are counted and dropped. Without a key everything well-formed is accepted.

Every value a handler uses is checked first (`bob_autonomy.ground.gcs_checks`: finite, within the field's range; NaN
only where MAVLink lets it mean "default", in a parameter the command does not use). A message with a bad
value changes nothing: it is refused the way its protocol refuses (COMMAND_ACK MAV_RESULT_DENIED, the
PARAM_VALUE in force, MISSION_ACK MAV_MISSION_INVALID_PARAMn / NO_SPACE / INVALID_SEQUENCE, or no answer to a
PARAM_REQUEST_READ), with a STATUSTEXT saying which field and why, counted in `counters.out_of_range` and
logged (the first ten, then at most one line every 10 s). What goes to the autopilot (`AutopilotCommand`) is
finite by construction.

Nothing raises out of `receive`: noise, truncated frames, bad checksums and exceptions in the handlers are
counted (`counters.malformed`, `counters.handler_errors`).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Sequence

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from bob_autonomy.core.geodesy import LocalFrame
from bob_autonomy.ground.gcs_codec import (
    GcsCounters,
    MavlinkCodec,
    SigningKeyError,
    load_signing_key,
    passphrase_to_key,
    signing_timestamp,
)
from bob_autonomy.ground.gcs_commands import AutopilotCommand, CommandProtocol
from bob_autonomy.ground.gcs_mission import MissionProtocol, Upload
from bob_autonomy.ground.gcs_params import ParameterProtocol
from bob_autonomy.ground.params import FAILSAFE_ACTIONS, LatLon, ParameterStore

__all__ = [
    "COMPONENT_ID",
    "AutopilotCommand",
    "GcsComponent",
    "GcsCounters",
    "MavlinkCodec",
    "SigningKeyError",
    "load_signing_key",
    "passphrase_to_key",
    "signing_timestamp",
]

logger = logging.getLogger(__name__)

COMPONENT_ID = mavlink.MAV_COMP_ID_ONBOARD_COMPUTER  # 191
STATUSTEXT_LEN = 50
MAX_OUTGOING = 10_000  # frames held for outgoing() at most
SECURITY_LOG_PERIOD_S = 60.0  # clock s: how often tick() logs the rejected-input counters when they changed

CAPABILITIES = (
    mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_FLOAT
    | mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_INT
    | mavlink.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
    | mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_C_CAST
    | mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2
    | mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_FENCE
    | mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_RALLY
)


# -- the component ----------------------------------------------------------------------------------------------


class GcsComponent(ParameterProtocol, CommandProtocol, MissionProtocol):
    """The autonomy process's MAVLink component (see the module docstring).

    system_id: the vessel's MAVLink system id (the autopilot's). params: the ParameterStore it serves.
    component_id: 191 (MAV_COMP_ID_ONBOARD_COMPUTER). signing_key: 32 bytes, or None for no signing.
    clock: monotonic seconds for periods and timeouts; wall_clock: Unix seconds for signing timestamps.
    heartbeat_period_s: HEARTBEAT period (1 s). mission_timeout_s / mission_retries: how long to wait for a
    requested mission item before asking again, and how many times, before the upload is cancelled.

    State the process reads: `behavior_running` (bool), `goals` and `fence` (lists of (lat, lon) deg),
    `params`, `pending_autopilot` (AutopilotCommand list; `take_autopilot_commands()` drains it),
    `gcs_lost` (BOB_GCS_FS_S elapsed without a ground-station HEARTBEAT, after one was heard),
    `counters` (`counters.security()`: the rejected-input counters, logged every minute when they changed).
    """

    def __init__(
        self,
        system_id: int,
        params: ParameterStore,
        *,
        component_id: int = COMPONENT_ID,
        signing_key: bytes | None = None,
        clock: Callable[[], float] = time.monotonic,
        wall_clock: Callable[[], float] = time.time,
        heartbeat_period_s: float = 1.0,
        mission_timeout_s: float = 1.5,
        mission_retries: int = 5,
    ) -> None:
        self.params = params
        self.clock = clock
        self.counters = GcsCounters()
        self.codec = MavlinkCodec(
            system_id, component_id, signing_key=signing_key, wall_clock=wall_clock, counters=self.counters
        )
        self.system_id = system_id
        self.component_id = component_id
        self.heartbeat_period_s = float(heartbeat_period_s)
        self.mission_timeout_s = float(mission_timeout_s)
        self.mission_retries = int(mission_retries)
        self.behavior_running = False
        self.pending_autopilot: list[AutopilotCommand] = []
        self.to_autopilot: list[bytes] = []  # ground-station frames routed on to the vehicle
        self.gcs_lost = False
        self.last_gcs_heartbeat_s: float | None = None
        self._out: list[bytes] = []
        self._t0 = float(clock())
        self._last_heartbeat_s: float | None = None
        self._position: tuple[float, ...] | None = None
        self._last_position_s: float | None = None
        self._upload: Upload | None = None
        self._last_upload: tuple[tuple[int, int], int, int, int] | None = None  # peer, type, count, result
        self._statustext_id = 0
        self._last_refusal_log_s = -math.inf
        self._security_logged = self.counters.security()
        self._last_security_log_s = float(clock())
        if params.load_problem:
            self.notify(mavlink.MAV_SEVERITY_WARNING, params.load_problem)

    # -- public interface ----------------------------------------------------------------------------------

    @property
    def goals(self) -> list[LatLon]:
        """Goal waypoints (lat, lon) in degrees, in order (mission upload or set-goal command)."""
        return self.params.goals

    @property
    def fence(self) -> list[LatLon]:
        """Geofence inclusion polygon (lat, lon) in degrees; empty when none was uploaded."""
        return self.params.fence

    @property
    def fence_enabled(self) -> bool:
        """BOB_FENCE_EN is 1 and a polygon of at least 3 vertices is set."""
        return bool(self.params.get("BOB_FENCE_EN")) and len(self.fence) >= 3

    def receive(self, data: bytes, *, datagram: bool = False) -> int:
        """Handle received bytes (any chunking; `datagram=True` when `data` is one whole UDP datagram).
        Never raises: bad input and handler failures are counted. Returns how many frames passed the checks
        with the link's credentials (signed with the key when there is one): only then may the process
        make the sender a peer of its link (`Link.confirm_peer`)."""
        before = self.counters.authenticated
        for msg in self.codec.decode(data, datagram=datagram):
            if self._for_autopilot(msg):
                self.to_autopilot.append(bytes(msg.get_msgbuf()))
            try:
                self._handle(msg)
            except Exception:
                self.counters.handler_errors += 1
                logger.exception("error handling %s", msg.get_type())
        return self.counters.authenticated - before

    def _for_autopilot(self, msg: mavlink.MAVLink_message) -> bool:
        """Whether a frame that passed the checks goes on to the vehicle, as mavlink-router routes: everything
        addressed to this vessel's system (or to all) but not to this component alone, and everything without a
        target (a ground station's HEARTBEAT, which the autopilot's GCS failsafe listens for)."""
        if msg.get_srcSystem() == self.system_id and msg.get_srcComponent() == self.component_id:
            return False  # our own frame come back
        if msg.get_msgId() == mavlink.MAVLINK_MSG_ID_REQUEST_DATA_STREAM:
            # The process owns the stream rates of its port: ArduPilot resets every interval of a stream group to
            # the rate asked (GCS_Common.cpp handle_request_data_stream), so MAVProxy's 4 Hz would starve the
            # estimator. MAVProxy does not forward this message to its own outputs either.
            return False
        target = getattr(msg, "target_system", None)
        if target is None:
            return True
        return target in (0, self.system_id) and getattr(msg, "target_component", 0) != self.component_id

    def take_for_autopilot(self) -> list[bytes]:
        """Frames from ground stations for the vehicle (see `_for_autopilot`), oldest first, as received."""
        out, self.to_autopilot = self.to_autopilot, []
        return out

    def outgoing(self) -> list[bytes]:
        """The frames to send since the last call (each one MAVLink frame), oldest first."""
        out, self._out = self._out, []
        return out

    def tick(self) -> None:
        """Periodic work: HEARTBEAT (every heartbeat_period_s), GLOBAL_POSITION_INT (at BOB_POS_HZ, once a
        position was reported), mission upload timeouts, the ground-station failsafe."""
        now = float(self.clock())
        if self._last_heartbeat_s is None or now - self._last_heartbeat_s >= self.heartbeat_period_s:
            self._last_heartbeat_s = now
            self._send_heartbeat()
        rate = float(self.params.get("BOB_POS_HZ"))
        if (
            self._position is not None
            and rate > 0
            and (self._last_position_s is None or now - self._last_position_s >= 1.0 / rate)
        ):
            self._last_position_s = now
            self._send_position()
        self._check_upload_timeout(now)
        self._check_gcs_failsafe(now)
        if now - self._last_security_log_s >= SECURITY_LOG_PERIOD_S:
            self._last_security_log_s = now
            self.log_counters(only_if_changed=True)

    def log_counters(self, *, only_if_changed: bool = False) -> dict[str, int]:
        """Log the counters of rejected input (`GcsCounters.SECURITY`: unsigned, bad signature, replay,
        malformed, out of range) as one line (a warning when any is not zero); tick() does it every
        SECURITY_LOG_PERIOD_S when they changed. Returns them."""
        current = self.counters.security()
        if only_if_changed and current == self._security_logged:
            return current
        self._security_logged = current
        text = ", ".join(f"{name} {value}" for name, value in current.items())
        level = logging.WARNING if any(current.values()) else logging.INFO
        logger.log(level, "ground-station input rejected since start (system %d): %s", self.system_id, text)
        return current

    def notify(self, severity: int, text: str) -> None:
        """Report an event with STATUSTEXT (MAV_SEVERITY_*; 0 emergency .. 7 debug); text longer than 50
        characters goes in chunks that share an id. Also logged."""
        logger.log(_LOG_LEVEL.get(severity, logging.INFO), "%s", text)
        self._statustext(severity, text)

    def _statustext(self, severity: int, text: str) -> None:
        data = text.encode("ascii", errors="replace")
        if len(data) <= STATUSTEXT_LEN:
            self._queue(self.codec.mav.statustext_encode(severity, data, 0, 0))
            return
        self._statustext_id = self._statustext_id % 65535 + 1
        chunks = [data[i : i + STATUSTEXT_LEN] for i in range(0, len(data), STATUSTEXT_LEN)]
        if len(chunks[-1]) == STATUSTEXT_LEN:
            chunks.append(b"")  # a full last chunk is followed by an empty one to mark the end
        for seq, chunk in enumerate(chunks[:256]):
            self._queue(self.codec.mav.statustext_encode(severity, chunk, self._statustext_id, seq))

    def report_position(
        self,
        lat_deg: float,
        lon_deg: float,
        v_east_mps: float = 0.0,
        v_north_mps: float = 0.0,
        heading_rad: float | None = None,
        alt_m: float = 0.0,
    ) -> None:
        """The process's estimate of the vessel's position (WGS-84 deg), ground velocity (m/s, east and
        north) and heading (rad from east, counter-clockwise; None if unknown); sent as
        GLOBAL_POSITION_INT from this component at BOB_POS_HZ by `tick`."""
        self._position = (float(lat_deg), float(lon_deg), float(v_east_mps), float(v_north_mps),
                          heading_rad, float(alt_m))  # fmt: skip

    def take_autopilot_commands(self) -> list[AutopilotCommand]:
        """Drain `pending_autopilot`."""
        out, self.pending_autopilot = self.pending_autopilot, []
        return out

    def fence_contains(self, lat_deg: float, lon_deg: float) -> bool | None:
        """Whether the point is inside the fence polygon; None when no fence is set (or fewer than 3
        vertices). Computed in a local tangent plane at the first vertex (fine over a few km)."""
        fence = self.fence
        if len(fence) < 3:
            return None
        return point_in_polygon((lat_deg, lon_deg), fence)

    # -- dispatch ------------------------------------------------------------------------------------------

    def _queue(self, message: mavlink.MAVLink_message) -> None:
        if len(self._out) >= MAX_OUTGOING:  # nobody drains outgoing(): drop the oldest rather than grow
            del self._out[0]
            self.counters.dropped_outgoing += 1
        self._out.append(self.codec.pack(message))

    def _handle(self, msg: mavlink.MAVLink_message) -> None:
        kind = msg.get_type()
        if kind == "HEARTBEAT":
            if msg.type == mavlink.MAV_TYPE_GCS:
                self._gcs_heartbeat()
            return
        handler = _HANDLERS.get(kind)
        if handler is None:
            self.counters.ignored_message += 1
            return
        if msg.target_system not in (0, self.system_id) or msg.target_component not in (0, self.component_id):
            self.counters.ignored_other_target += 1
            return
        handler(self, msg)

    def _gcs_heartbeat(self) -> None:
        self.last_gcs_heartbeat_s = float(self.clock())
        if self.gcs_lost:
            self.gcs_lost = False
            self.notify(mavlink.MAV_SEVERITY_NOTICE, "ground station link regained")

    def _check_gcs_failsafe(self, now: float) -> None:
        timeout = float(self.params.get("BOB_GCS_FS_S"))
        if self.gcs_lost or timeout <= 0 or self.last_gcs_heartbeat_s is None:
            return
        if now - self.last_gcs_heartbeat_s > timeout:
            self.gcs_lost = True
            action = FAILSAFE_ACTIONS.get(int(self.params.get("BOB_GCS_FS_ACT")), "?")
            self.notify(mavlink.MAV_SEVERITY_CRITICAL, f"ground station lost for {timeout:g} s: {action}")

    # -- telemetry -----------------------------------------------------------------------------------------

    def _time_boot_ms(self) -> int:
        return int((float(self.clock()) - self._t0) * 1000) & 0xFFFFFFFF

    def _send_heartbeat(self) -> None:
        index = int(self.params.get("BOB_BEHAVIOR"))
        custom_mode = (1 if self.behavior_running else 0) | (index << 8)
        status = mavlink.MAV_STATE_ACTIVE if self.behavior_running else mavlink.MAV_STATE_STANDBY
        # base_mode 0: not an autopilot, so no mode flag. MAVSDK (4.1, SystemImpl::process_heartbeat) takes the
        # flight mode from any component's HEARTBEAT with CUSTOM_MODE_ENABLED, and read ours as Rover ACRO.
        self._queue(
            self.codec.mav.heartbeat_encode(
                mavlink.MAV_TYPE_ONBOARD_CONTROLLER,
                mavlink.MAV_AUTOPILOT_INVALID,
                0,
                custom_mode,
                status,
            )
        )

    def _send_position(self) -> None:
        assert self._position is not None
        lat, lon, ve, vn, heading, alt = self._position
        if not (math.isfinite(lat) and math.isfinite(lon)):
            return
        if heading is None or not math.isfinite(heading):
            hdg = 65535
        else:
            hdg = round((90.0 - math.degrees(heading)) * 100.0) % 36000  # cdeg from north, clockwise
        self._queue(
            self.codec.mav.global_position_int_encode(
                self._time_boot_ms(),
                _clamp_int32(round(lat * 1e7)),
                _clamp_int32(round(lon * 1e7)),
                _clamp_int32(round(alt * 1000)),
                _clamp_int32(round(alt * 1000)),
                _cm_s(vn),
                _cm_s(ve),
                0,
                hdg,
            )
        )

    def _send_autopilot_version(self) -> None:
        zeros8 = [0] * 8
        self._queue(self.codec.mav.autopilot_version_encode(CAPABILITIES, 0, 0, 0, 0, zeros8, zeros8, zeros8, 0, 0, 0))


_HANDLERS: dict[str, Callable[[GcsComponent, object], None]] = {
    "PARAM_REQUEST_LIST": GcsComponent._param_request_list,
    "PARAM_REQUEST_READ": GcsComponent._param_request_read,
    "PARAM_SET": GcsComponent._param_set,
    "COMMAND_LONG": GcsComponent._command_long,
    "COMMAND_INT": GcsComponent._command_int,
    "MISSION_COUNT": GcsComponent._mission_count,
    "MISSION_ITEM_INT": GcsComponent._mission_item,
    "MISSION_ITEM": GcsComponent._mission_item,
    "MISSION_REQUEST_LIST": GcsComponent._mission_request_list,
    "MISSION_REQUEST_INT": GcsComponent._mission_request,
    "MISSION_REQUEST": GcsComponent._mission_request,
    "MISSION_ACK": GcsComponent._mission_ack_in,
    "MISSION_CLEAR_ALL": GcsComponent._mission_clear_all,
}

_LOG_LEVEL = {0: logging.CRITICAL, 1: logging.CRITICAL, 2: logging.CRITICAL, 3: logging.ERROR,
              4: logging.WARNING, 5: logging.INFO, 6: logging.INFO, 7: logging.DEBUG}  # fmt: skip


def _clamp_int32(v: int) -> int:
    return max(-(2**31), min(2**31 - 1, int(v)))


def _cm_s(v_mps: float) -> int:
    if not math.isfinite(v_mps):
        return 0
    return max(-32768, min(32767, round(v_mps * 100.0)))


def point_in_polygon(point: Sequence[float], polygon: Sequence[Sequence[float]]) -> bool:
    """Whether (lat, lon) (deg) lies inside the polygon of (lat, lon) vertices (even-odd rule, in a local
    tangent plane at the first vertex)."""
    frame = LocalFrame(float(polygon[0][0]), float(polygon[0][1]))
    px, py = (float(v) for v in frame.to_local(point[0], point[1]))
    xs, ys = frame.to_local([p[0] for p in polygon], [p[1] for p in polygon])
    inside = False
    n = len(polygon)
    for i in range(n):
        x1, y1, x2, y2 = float(xs[i]), float(ys[i]), float(xs[(i + 1) % n]), float(ys[(i + 1) % n])
        if (y1 > py) != (y2 > py) and px < x1 + (py - y1) * (x2 - x1) / (y2 - y1):
            inside = not inside
    return inside
