"""The simulated autopilot's mission protocol, as ArduPilot Rover serves it.

Sources: libraries/GCS_MAVLink/MissionItemProtocol.cpp (the transfer state machine),
MissionItemProtocol_Waypoints.cpp (the mission), GCS_Common.cpp `handle_mission_*` (dispatch by mission type),
libraries/AP_Mission/AP_Mission.cpp (item checks and what is stored).

- Item 0 is always home: readable whenever home is set, never overwritten by an upload (AP_Mission `replace_cmd`
  index 0, `read_cmd_from_storage`). The count includes it.
- Upload: MISSION_COUNT (more than MAX_ITEMS: MAV_MISSION_NO_SPACE and "Only N items are supported"; while
  someone else uploads: MAV_MISSION_DENIED) truncates the stored mission to the count, then the vehicle asks for
  each item with MISSION_REQUEST (ArduPilot sends the legacy MISSION_REQUEST, `queued_request_send`), again after
  1 s of silence; 8 s without an item ends the upload with MISSION_ACK MAV_MISSION_OPERATION_CANCELLED and
  "Mission upload timeout". A wrong seq gets MAV_MISSION_INVALID_SEQUENCE, an item from another sender
  MAV_MISSION_DENIED (the upload goes on); an item that fails AP_Mission's checks (NaN/inf params:
  MAV_MISSION_INVALID_PARAMn; bad lat/lon/alt: INVALID_PARAM5_X/6_Y/7; an unsupported command: UNSUPPORTED; an
  unsupported frame: UNSUPPORTED_FRAME) is answered with that error and ends the upload. The last item is
  answered MISSION_ACK ACCEPTED and "Flight plan received". MISSION_ITEM (float) is converted (x, y * 1e7) with the
  warning "got MISSION_ITEM; GCS should send MISSION_ITEM_INT"; an item outside an upload: MAV_MISSION_ERROR.
- Download: MISSION_REQUEST_LIST -> MISSION_COUNT; MISSION_REQUEST_INT -> MISSION_ITEM_INT; the legacy
  MISSION_REQUEST -> MISSION_ITEM (and "got MISSION_REQUEST; use MISSION_REQUEST_INT!"); a seq past the end:
  MISSION_COUNT then MISSION_ACK INVALID_SEQUENCE. Items come back as AP_Mission stores them: frame
  MAV_FRAME_GLOBAL or GLOBAL_RELATIVE_ALT, only the params the command keeps (`mission_cmd_to_mavlink_int`).
- MISSION_CLEAR_ALL: MISSION_ACK ACCEPTED (DENIED while someone else uploads).
- Fence and rally: this simulated Rover has no fence or rally store, so it answers as an ArduPilot without them
  (GCS_Common.cpp: no protocol for the type): MISSION_ACK MAV_MISSION_UNSUPPORTED to COUNT, REQUEST_LIST,
  CLEAR_ALL and items; no answer to REQUEST(_INT). AUTOPILOT_VERSION does not claim MISSION_FENCE / RALLY.
The simulator stores missions but does not drive them (no AUTO mode).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

from pymavlink.dialects.v20 import ardupilotmega as mavlink

m = mavlink
MAX_ITEMS = 700  # the simulator's storage (ArduPilot: its storage size / 15 bytes per item)
UPLOAD_TIMEOUT_S = 8.0  # MissionItemProtocol.h upload_timeout_ms
REQUEST_RESEND_S = 1.0  # MissionItemProtocol::update wp_recv_timeout_ms
LOCATION_ALT_MAX_M = 83000  # libraries/AP_Common/Location.h
# Commands the simulator stores, and which params AP_Mission keeps for each (mission_cmd_to_mavlink_int).
KEPT_PARAMS = {
    m.MAV_CMD_NAV_WAYPOINT: (1,),
    m.MAV_CMD_NAV_LOITER_UNLIM: (3,),
    m.MAV_CMD_NAV_LOITER_TIME: (1, 3),
    m.MAV_CMD_NAV_RETURN_TO_LAUNCH: (),
    m.MAV_CMD_NAV_SPLINE_WAYPOINT: (1,),
    m.MAV_CMD_CONDITION_DELAY: (1,),
    m.MAV_CMD_CONDITION_DISTANCE: (1,),
    m.MAV_CMD_DO_JUMP: (1, 2),
    m.MAV_CMD_DO_CHANGE_SPEED: (1, 2, 3),
    m.MAV_CMD_DO_SET_HOME: (1,),
}
WITH_LOCATION = {m.MAV_CMD_NAV_WAYPOINT, m.MAV_CMD_NAV_LOITER_UNLIM, m.MAV_CMD_NAV_LOITER_TIME,
                 m.MAV_CMD_NAV_SPLINE_WAYPOINT, m.MAV_CMD_DO_SET_HOME}  # fmt: skip
ABSOLUTE_FRAMES = {m.MAV_FRAME_MISSION, m.MAV_FRAME_GLOBAL, m.MAV_FRAME_GLOBAL_INT}
RELATIVE_FRAMES = {m.MAV_FRAME_GLOBAL_RELATIVE_ALT, m.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT}
# AP_Mission::sanity_check_params: which params may be NaN (param4 for these).
NAN_PARAM4_OK = {m.MAV_CMD_NAV_WAYPOINT, m.MAV_CMD_NAV_LOITER_UNLIM, m.MAV_CMD_NAV_LAND, m.MAV_CMD_NAV_TAKEOFF}


@dataclass(frozen=True)
class StoredItem:
    """A mission item as AP_Mission keeps it."""

    command: int
    params: tuple[float, float, float, float]
    x: int
    y: int
    z: float
    frame: int


def check_item(item) -> tuple[int, StoredItem | None]:
    """AP_Mission::mavlink_int_to_mission_cmd for the commands the simulator stores: (MAV_MISSION_RESULT, item)."""
    params = [float(item.param1), float(item.param2), float(item.param3), float(item.param4)]
    errors = (m.MAV_MISSION_INVALID_PARAM1, m.MAV_MISSION_INVALID_PARAM2, m.MAV_MISSION_INVALID_PARAM3,
              m.MAV_MISSION_INVALID_PARAM4)  # fmt: skip
    for k, value in enumerate(params):
        nan_ok = k == 3 and item.command in NAN_PARAM4_OK
        if math.isinf(value) or (math.isnan(value) and not nan_ok):
            return errors[k], None
    command = int(item.command)
    if command in (0, 1):
        return m.MAV_MISSION_INVALID, None
    if command not in KEPT_PARAMS:
        return m.MAV_MISSION_UNSUPPORTED, None
    kept = tuple(params[k - 1] if k in KEPT_PARAMS[command] else 0.0 for k in (1, 2, 3, 4))
    if command in (m.MAV_CMD_NAV_WAYPOINT, m.MAV_CMD_NAV_SPLINE_WAYPOINT, m.MAV_CMD_NAV_LOITER_TIME):
        kept = (float(min(65535, max(0, int(kept[0])))), *kept[1:])  # stored as a uint16 (cmd.p1)
    if command == m.MAV_CMD_NAV_LOITER_TIME:
        kept = (kept[0], 0.0, -1.0 if params[2] < 0 else 1.0, 0.0)
    if command not in WITH_LOCATION:
        return m.MAV_MISSION_ACCEPTED, StoredItem(command, kept, 0, 0, 0.0, m.MAV_FRAME_GLOBAL)
    x, y, z = int(item.x), int(item.y), float(item.z)
    if abs(x) > 900_000_000:
        return m.MAV_MISSION_INVALID_PARAM5_X, None
    if abs(y) > 1_800_000_000:
        return m.MAV_MISSION_INVALID_PARAM6_Y, None
    if not math.isfinite(z) or abs(z) >= LOCATION_ALT_MAX_M:
        return m.MAV_MISSION_INVALID_PARAM7, None
    if item.frame in ABSOLUTE_FRAMES:
        frame = m.MAV_FRAME_GLOBAL
    elif item.frame in RELATIVE_FRAMES:
        frame = m.MAV_FRAME_GLOBAL_RELATIVE_ALT
    else:
        return m.MAV_MISSION_UNSUPPORTED_FRAME, None
    return m.MAV_MISSION_ACCEPTED, StoredItem(command, kept, x, y, round(z * 100) / 100.0, frame)


class _AsInt:
    """A MISSION_ITEM (float x, y) seen as MISSION_ITEM_INT (AP_Mission convert_MISSION_ITEM_to_MISSION_ITEM_INT)."""

    def __init__(self, msg) -> None:
        for name in ("param1", "param2", "param3", "param4", "z", "seq", "command", "frame", "current"):
            setattr(self, name, getattr(msg, name))
        self.mission_type = getattr(msg, "mission_type", 0)
        self.bad = None
        x, y = float(msg.x), float(msg.y)
        if msg.command in WITH_LOCATION:
            if not (math.isfinite(x) and abs(x) <= 90):
                self.bad = m.MAV_MISSION_INVALID_PARAM5_X
            elif not (math.isfinite(y) and abs(y) <= 180):
                self.bad = m.MAV_MISSION_INVALID_PARAM6_Y
            else:
                self.x, self.y = round(x * 1e7), round(y * 1e7)
        else:
            self.x = int(x) if math.isfinite(x) and abs(x) < 2**31 else 0
            self.y = int(y) if math.isfinite(y) and abs(y) < 2**31 else 0


class MissionStore:
    """One vehicle's stored mission and the upload in progress.

    home(): (lat degE7, lon degE7, alt m) or None; pack / mav: the vehicle's encoder; text(severity, str) queues a
    STATUSTEXT.
    """

    def __init__(self, home: Callable[[], tuple[int, int, float] | None], pack: Callable, mav, text) -> None:
        self.home, self.pack, self.mav, self.text = home, pack, mav, text
        self.items: list[StoredItem] = []  # items 1..n (0 is home)
        self.receiving = False
        self.upload_to: tuple[int, int] = (0, 0)
        self.next_seq = self.last_seq = 0
        self.last_receive_s = self.last_request_s = -math.inf
        self.errors = 0  # items or requests answered with an error
        self._item_warned = self._request_warned = False

    def count(self) -> int:
        return 1 + len(self.items) if (self.items or self.home() is not None) else 0

    def _ack(self, to: tuple[int, int], result: int, mission_type: int = 0) -> bytes:
        if result != m.MAV_MISSION_ACCEPTED:
            self.errors += 1
        return self.pack(self.mav.mission_ack_encode(to[0], to[1], result, mission_type))

    def _request(self) -> bytes:
        return self.pack(self.mav.mission_request_encode(*self.upload_to, self.next_seq, 0))

    def handle(self, msg, sender: tuple[int, int], t_s: float) -> bytes:
        """Answer one mission message (already known to be for this vehicle)."""
        name = msg.get_type()
        mission_type = int(getattr(msg, "mission_type", 0))
        if mission_type != m.MAV_MISSION_TYPE_MISSION:
            if name in ("MISSION_REQUEST_INT", "MISSION_REQUEST"):
                return b""
            return self._ack(sender, m.MAV_MISSION_UNSUPPORTED, mission_type)
        if name == "MISSION_COUNT":
            return self._count(int(msg.count), sender, t_s)
        if name in ("MISSION_ITEM_INT", "MISSION_ITEM"):
            return self._item(msg, sender, t_s)
        if name == "MISSION_REQUEST_LIST":
            if self.receiving:
                return self._ack(sender, m.MAV_MISSION_DENIED)
            return self.pack(self.mav.mission_count_encode(sender[0], sender[1], self.count(), 0))
        if name in ("MISSION_REQUEST_INT", "MISSION_REQUEST"):
            return self._download(msg, name, sender)
        if name == "MISSION_CLEAR_ALL":
            if self.receiving and sender != self.upload_to:
                return self._ack(sender, m.MAV_MISSION_DENIED)
            self.receiving = False
            self.items = []
            return self._ack(sender, m.MAV_MISSION_ACCEPTED)
        return b""

    def _count(self, count: int, sender: tuple[int, int], t_s: float) -> bytes:
        if self.receiving and sender != self.upload_to:
            return self._ack(sender, m.MAV_MISSION_DENIED)
        self.receiving = False
        if count > MAX_ITEMS:
            self.text(m.MAV_SEVERITY_WARNING, f"Only {MAX_ITEMS} items are supported")
            return self._ack(sender, m.MAV_MISSION_NO_SPACE)
        del self.items[max(0, count - 1) :]  # AP_Mission::truncate(count)
        if count == 0:
            self.text(m.MAV_SEVERITY_INFO, "Flight plan received")
            return self._ack(sender, m.MAV_MISSION_ACCEPTED)
        self.receiving, self.upload_to = True, sender
        self.next_seq, self.last_seq = 0, count - 1
        self.last_receive_s = self.last_request_s = t_s
        return self._request()

    def _item(self, msg, sender: tuple[int, int], t_s: float) -> bytes:
        item = msg
        if msg.get_type() == "MISSION_ITEM":
            item = _AsInt(msg)
            if item.bad is not None:
                return self._ack(sender, item.bad)
            if not self._item_warned:
                self._item_warned = True
                self.text(m.MAV_SEVERITY_WARNING, "got MISSION_ITEM; GCS should send MISSION_ITEM_INT")
        if int(item.current) == 2:  # a guided-mode target: the simulator does not navigate
            return self._ack(sender, m.MAV_MISSION_ERROR)
        if not self.receiving:
            return self._ack(sender, m.MAV_MISSION_ERROR)
        if int(item.seq) != self.next_seq:
            return self._ack(sender, m.MAV_MISSION_INVALID_SEQUENCE)
        if sender != self.upload_to:
            return self._ack(sender, m.MAV_MISSION_DENIED)
        result, stored = check_item(item)
        if result != m.MAV_MISSION_ACCEPTED:
            self.receiving = False
            return self._ack(sender, result)
        seq = int(item.seq)
        if seq >= 1:  # item 0 is home: accepted, not stored
            if seq - 1 < len(self.items):
                self.items[seq - 1] = stored
            else:
                self.items.append(stored)
        self.last_receive_s = t_s
        self.next_seq += 1
        if self.next_seq > self.last_seq:
            self.receiving = False
            self.text(m.MAV_SEVERITY_INFO, "Flight plan received")
            return self._ack(sender, m.MAV_MISSION_ACCEPTED)
        self.last_request_s = t_s
        return self._request()

    def _download(self, msg, name: str, sender: tuple[int, int]) -> bytes:
        if name == "MISSION_REQUEST_INT" and self.receiving:
            return self._ack(sender, m.MAV_MISSION_DENIED)
        seq = int(msg.seq)
        home = self.home()
        if seq != 0 and seq >= self.count():
            reply = b""
            if name == "MISSION_REQUEST_INT":
                reply = self.pack(self.mav.mission_count_encode(sender[0], sender[1], self.count(), 0))
            return reply + self._ack(sender, m.MAV_MISSION_INVALID_SEQUENCE)
        if seq == 0:
            lat, lon, alt = home if home is not None else (0, 0, 0.0)
            stored = StoredItem(m.MAV_CMD_NAV_WAYPOINT, (0.0, 0.0, 0.0, 0.0), lat, lon, alt, m.MAV_FRAME_GLOBAL)
        else:
            stored = self.items[seq - 1]
        p = stored.params
        if name == "MISSION_REQUEST_INT":
            message = self.mav.mission_item_int_encode(sender[0], sender[1], seq, stored.frame, stored.command, 0, 1,
                                                       *p, stored.x, stored.y, stored.z, 0)  # fmt: skip
            return self.pack(message)
        if not self._request_warned:
            self._request_warned = True
            self.text(m.MAV_SEVERITY_WARNING, "got MISSION_REQUEST; use MISSION_REQUEST_INT!")
        located = stored.command in WITH_LOCATION or seq == 0
        x, y = (stored.x * 1e-7, stored.y * 1e-7) if located else (stored.x, stored.y)
        message = self.mav.mission_item_encode(sender[0], sender[1], seq, stored.frame, stored.command, 0, 1, *p,
                                               x, y, stored.z, 0)  # fmt: skip
        return self.pack(message)

    def tick(self, t_s: float) -> bytes:
        """Resend the pending MISSION_REQUEST after 1 s; give the upload up after 8 s without an item."""
        if not self.receiving:
            return b""
        if t_s - self.last_receive_s > UPLOAD_TIMEOUT_S:
            self.receiving = False
            self.text(m.MAV_SEVERITY_WARNING, "Mission upload timeout")
            return self._ack(self.upload_to, m.MAV_MISSION_OPERATION_CANCELLED)
        if t_s - self.last_request_s > REQUEST_RESEND_S:
            self.last_request_s = t_s
            return self._request()
        return b""
