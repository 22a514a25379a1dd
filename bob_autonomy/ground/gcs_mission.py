"""The mission protocol of the ground-station component (`bob_autonomy.ground.gcs`): upload and download of the goal
waypoints (MAV_MISSION_TYPE_MISSION), a geofence inclusion polygon (FENCE) and one rally point (RALLY).

Upload: MISSION_COUNT, then our MISSION_REQUEST_INT for each item in turn, answered by MISSION_ITEM_INT or the
legacy MISSION_ITEM; a lost item is asked for again (`mission_timeout_s`, `mission_retries`), a duplicate is
ignored, the final MISSION_ACK says again what it said when the last item comes twice. Every item's values are
checked before use (`bob_autonomy.ground.gcs_checks.mission_item_problem`); a bad one ends the upload with a MISSION_ACK
naming the parameter (MAV_MISSION_INVALID_PARAMn) and nothing is stored. Download: MISSION_REQUEST_LIST, then
MISSION_REQUEST_INT or MISSION_REQUEST. MISSION_CLEAR_ALL. See docs/gcs-protocol.md.

`MissionProtocol` is a mixin of `GcsComponent`, which provides the attributes it declares.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from bob_autonomy.ground.gcs_checks import GLOBAL_FRAMES, mission_item_problem
from bob_autonomy.ground.gcs_codec import GcsCounters, MavlinkCodec
from bob_autonomy.ground.params import MAX_FENCE_VERTICES, MAX_GOALS, LatLon, ParamError, ParameterStore

MISSION_TYPES = (mavlink.MAV_MISSION_TYPE_MISSION, mavlink.MAV_MISSION_TYPE_FENCE, mavlink.MAV_MISSION_TYPE_RALLY)
# The one mission command each mission type takes.
MISSION_ITEM_COMMAND = {
    mavlink.MAV_MISSION_TYPE_MISSION: mavlink.MAV_CMD_NAV_WAYPOINT,
    mavlink.MAV_MISSION_TYPE_FENCE: mavlink.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION,
    mavlink.MAV_MISSION_TYPE_RALLY: mavlink.MAV_CMD_NAV_RALLY_POINT,
}
MISSION_CAPACITY = {
    mavlink.MAV_MISSION_TYPE_MISSION: MAX_GOALS,
    mavlink.MAV_MISSION_TYPE_FENCE: MAX_FENCE_VERTICES,
    mavlink.MAV_MISSION_TYPE_RALLY: 1,
}
MISSION_TYPE_NAMES = {
    mavlink.MAV_MISSION_TYPE_MISSION: "mission",
    mavlink.MAV_MISSION_TYPE_FENCE: "fence",
    mavlink.MAV_MISSION_TYPE_RALLY: "rally",
    mavlink.MAV_MISSION_TYPE_ALL: "all missions",
}


@dataclass
class Upload:
    """An upload in progress from one ground station (system, component), or one just finished."""

    peer: tuple[int, int]
    mission_type: int
    count: int
    received: int = 0  # items received so far = the next sequence number wanted
    points: list[LatLon] = field(default_factory=list)  # waypoints, fence vertices or the rally point
    vertex_counts: list[float] = field(default_factory=list)  # param1 of each fence vertex
    return_point: LatLon | None = None  # a fence's MAV_CMD_NAV_FENCE_RETURN_POINT, taken as the rally point
    last_request_s: float = 0.0
    retries: int = 0


class MissionProtocol:
    """The mission protocol's handlers (see the module docstring), mixed into GcsComponent."""

    codec: MavlinkCodec
    counters: GcsCounters
    params: ParameterStore
    clock: Callable[[], float]
    mission_timeout_s: float
    mission_retries: int
    _upload: Upload | None
    _last_upload: tuple[tuple[int, int], int, int, int] | None  # peer, type, count, final result

    # provided by GcsComponent
    def _queue(self, message: mavlink.MAVLink_message) -> None:  # pragma: no cover - interface
        raise NotImplementedError

    def notify(self, severity: int, text: str) -> None:  # pragma: no cover - interface
        raise NotImplementedError

    def _persist_warning(self) -> None:  # pragma: no cover - interface
        raise NotImplementedError

    def _refuse_value(self, text: str) -> None:  # pragma: no cover - interface
        raise NotImplementedError

    def _mission_ack(self, peer: tuple[int, int], mission_type: int, result: int) -> None:
        self._queue(self.codec.mav.mission_ack_encode(peer[0], peer[1], result, mission_type))

    def _request_item(self, up: Upload) -> None:
        # Always MISSION_REQUEST_INT (degE7 positions): QGroundControl, MAVProxy and Mission Planner answer it;
        # a legacy MISSION_ITEM answer (float32 degrees, about 0.4 m steps) is accepted all the same.
        up.last_request_s = float(self.clock())
        self._queue(self.codec.mav.mission_request_int_encode(up.peer[0], up.peer[1], up.received, up.mission_type))

    def _mission_count(self, msg) -> None:
        peer = (msg.get_srcSystem(), msg.get_srcComponent())
        mission_type = msg.mission_type
        count = msg.count
        if mission_type not in MISSION_TYPES:
            self._mission_ack(peer, mission_type, mavlink.MAV_MISSION_UNSUPPORTED)
            return
        if self._upload is not None and self._upload.peer != peer:
            self._mission_ack(peer, mission_type, mavlink.MAV_MISSION_DENIED)  # busy with another upload
            return
        self._upload = None
        if count > MISSION_CAPACITY[mission_type]:
            self._mission_error(peer, mission_type, mavlink.MAV_MISSION_NO_SPACE,
                                f"{count} items, at most {MISSION_CAPACITY[mission_type]}", bad_value=True)  # fmt: skip
            return
        if mission_type == mavlink.MAV_MISSION_TYPE_FENCE and 0 < count < 3:
            self._mission_error(peer, mission_type, mavlink.MAV_MISSION_INVALID, f"a fence needs 3 vertices, {count}",
                                bad_value=True)  # fmt: skip
            return
        if count == 0:
            self._finish_upload(Upload(peer, mission_type, 0))
            return
        self._upload = Upload(peer, mission_type, count)
        self._request_item(self._upload)

    def _mission_item(self, msg) -> None:
        peer = (msg.get_srcSystem(), msg.get_srcComponent())
        up = self._upload
        if up is None or up.peer != peer or msg.mission_type != up.mission_type:
            last = self._last_upload
            if last is not None and last[:2] == (peer, msg.mission_type) and msg.seq == last[2] - 1:
                self._mission_ack(peer, msg.mission_type, last[3])  # our final ACK was lost: say it again
            return
        expected = up.received
        if msg.seq != expected:
            if msg.seq > expected:
                self._request_item(up)  # out of order: ask again for the one we need
            return  # a duplicate of one we have: ignore
        if msg.get_type() == "MISSION_ITEM_INT":
            lat, lon = msg.x / 1e7, msg.y / 1e7
        else:
            lat, lon = float(msg.x), float(msg.y)
        error = self._check_item(up, msg, lat, lon)
        if error is not None:
            result, why, bad_value = error
            self._upload = None  # as ArduPilot does (MissionItemProtocol::handle_mission_item): the upload ends
            self._mission_error(peer, up.mission_type, result, f"item {msg.seq}: {why}", bad_value=bad_value)
            return
        up.received += 1
        up.retries = 0
        if msg.command == mavlink.MAV_CMD_NAV_FENCE_RETURN_POINT:
            up.return_point = (lat, lon)
        else:
            up.points.append((lat, lon))
            up.vertex_counts.append(float(msg.param1))
        if up.received == up.count:
            self._upload = None
            self._finish_upload(up)
        else:
            self._request_item(up)

    def _check_item(self, up: Upload, msg, lat: float, lon: float) -> tuple[int, str, bool] | None:
        """None if the item may be used, else (MAV_MISSION_RESULT, why, whether a value was the problem)."""
        wanted = {MISSION_ITEM_COMMAND[up.mission_type]}
        if up.mission_type == mavlink.MAV_MISSION_TYPE_FENCE:
            wanted.add(mavlink.MAV_CMD_NAV_FENCE_RETURN_POINT)
        if msg.command not in wanted:
            why = f"command {msg.command} not supported here (only {sorted(wanted)})"
            return mavlink.MAV_MISSION_UNSUPPORTED, why, False
        if msg.frame not in GLOBAL_FRAMES:
            return mavlink.MAV_MISSION_UNSUPPORTED_FRAME, f"frame {msg.frame} is not a global frame", False
        params = (msg.param1, msg.param2, msg.param3, msg.param4)
        problem = mission_item_problem(msg.command, params, lat, lon, msg.z)
        return None if problem is None else (*problem, True)

    def _finish_upload(self, up: Upload) -> None:
        try:
            if up.mission_type == mavlink.MAV_MISSION_TYPE_MISSION:
                self.params.set_goals(up.points)
                what = f"{len(up.points)} goal waypoints"
            elif up.mission_type == mavlink.MAV_MISSION_TYPE_FENCE:
                if any(n != len(up.points) for n in up.vertex_counts):
                    self._mission_error(up.peer, up.mission_type, mavlink.MAV_MISSION_UNSUPPORTED,
                                        f"vertex counts {sorted(set(up.vertex_counts))} for {len(up.points)} vertices: "
                                        "only one inclusion polygon is supported")  # fmt: skip
                    return
                self.params.set_fence(up.points)
                if up.return_point is not None:
                    self.params.set_many({"BOB_RALLY_LAT": up.return_point[0], "BOB_RALLY_LON": up.return_point[1]})
                what = f"fence of {len(up.points)} vertices"
            else:
                lat, lon = up.points[0] if up.points else (0.0, 0.0)
                self.params.set_many({"BOB_RALLY_LAT": lat, "BOB_RALLY_LON": lon})
                what = "rally point"
        except ParamError as exc:
            self._mission_error(up.peer, up.mission_type, mavlink.MAV_MISSION_INVALID, str(exc), bad_value=True)
            self._last_upload = (up.peer, up.mission_type, up.count, mavlink.MAV_MISSION_INVALID)
            return
        self.counters.mission_uploads += 1
        self._last_upload = (up.peer, up.mission_type, up.count, mavlink.MAV_MISSION_ACCEPTED)
        self._mission_ack(up.peer, up.mission_type, mavlink.MAV_MISSION_ACCEPTED)
        self._persist_warning()
        self.notify(mavlink.MAV_SEVERITY_INFO, f"received {what}" if up.points else f"{what} cleared")

    def _mission_error(
        self, peer: tuple[int, int], mission_type: int, result: int, why: str, *, bad_value: bool = False
    ) -> None:
        """Refuse an upload with a MISSION_ACK `result` and say why; bad_value: a value was out of range."""
        self.counters.mission_errors += 1
        self._mission_ack(peer, mission_type, result)
        text = f"{MISSION_TYPE_NAMES.get(mission_type, mission_type)} upload refused: {why}"
        if bad_value:
            self._refuse_value(text)
        else:
            self.notify(mavlink.MAV_SEVERITY_WARNING, text)

    def _check_upload_timeout(self, now: float) -> None:
        up = self._upload
        if up is None or now - up.last_request_s < self.mission_timeout_s:
            return
        if up.retries >= self.mission_retries:
            self._upload = None
            self._mission_error(up.peer, up.mission_type, mavlink.MAV_MISSION_OPERATION_CANCELLED,
                                f"no item {up.received} after {up.retries + 1} requests")  # fmt: skip
            return
        up.retries += 1
        self.counters.mission_retries += 1
        self._request_item(up)

    def _mission_points(self, mission_type: int) -> list[LatLon] | None:
        if mission_type == mavlink.MAV_MISSION_TYPE_MISSION:
            return self.goals
        if mission_type == mavlink.MAV_MISSION_TYPE_FENCE:
            return self.fence
        if mission_type == mavlink.MAV_MISSION_TYPE_RALLY:
            lat, lon = float(self.params.get("BOB_RALLY_LAT")), float(self.params.get("BOB_RALLY_LON"))
            return [] if lat == 0 and lon == 0 else [(lat, lon)]
        return None

    def _mission_request_list(self, msg) -> None:
        peer = (msg.get_srcSystem(), msg.get_srcComponent())
        points = self._mission_points(msg.mission_type)
        if points is None:
            self._mission_ack(peer, msg.mission_type, mavlink.MAV_MISSION_UNSUPPORTED)
            return
        self._queue(self.codec.mav.mission_count_encode(peer[0], peer[1], len(points), msg.mission_type))

    def _mission_request(self, msg) -> None:
        peer = (msg.get_srcSystem(), msg.get_srcComponent())
        points = self._mission_points(msg.mission_type)
        if points is None:
            self._mission_ack(peer, msg.mission_type, mavlink.MAV_MISSION_UNSUPPORTED)
            return
        if not 0 <= msg.seq < len(points):
            self._mission_ack(peer, msg.mission_type, mavlink.MAV_MISSION_INVALID_SEQUENCE)
            self._refuse_value(f"{msg.get_type()}: item {msg.seq} of {len(points)}")
            return
        lat, lon = points[msg.seq]
        command = MISSION_ITEM_COMMAND[msg.mission_type]
        param1 = float(len(points)) if msg.mission_type == mavlink.MAV_MISSION_TYPE_FENCE else 0.0
        if msg.get_type() == "MISSION_REQUEST_INT":
            message = self.codec.mav.mission_item_int_encode(
                peer[0], peer[1], msg.seq, mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, command, 0, 1,
                param1, 0.0, 0.0, 0.0, round(lat * 1e7), round(lon * 1e7), 0.0, msg.mission_type,
            )  # fmt: skip
        else:
            message = self.codec.mav.mission_item_encode(
                peer[0], peer[1], msg.seq, mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT, command, 0, 1,
                param1, 0.0, 0.0, 0.0, lat, lon, 0.0, msg.mission_type,
            )  # fmt: skip
        self._queue(message)

    def _mission_ack_in(self, msg) -> None:
        up = self._upload
        peer = (msg.get_srcSystem(), msg.get_srcComponent())
        ours = up is not None and up.peer == peer and msg.mission_type == up.mission_type
        if ours and msg.type != mavlink.MAV_MISSION_ACCEPTED:  # the ground station gave up
            self._upload = None
            self.counters.mission_errors += 1
            self.notify(mavlink.MAV_SEVERITY_WARNING, f"mission upload cancelled by {peer[0]}/{peer[1]}")

    def _mission_clear_all(self, msg) -> None:
        peer = (msg.get_srcSystem(), msg.get_srcComponent())
        mission_type = msg.mission_type
        if mission_type not in (*MISSION_TYPES, mavlink.MAV_MISSION_TYPE_ALL):
            self._mission_ack(peer, mission_type, mavlink.MAV_MISSION_UNSUPPORTED)
            return
        if mission_type in (mavlink.MAV_MISSION_TYPE_MISSION, mavlink.MAV_MISSION_TYPE_ALL):
            self.params.set_goals([])
        if mission_type in (mavlink.MAV_MISSION_TYPE_FENCE, mavlink.MAV_MISSION_TYPE_ALL):
            self.params.set_fence([])
        if mission_type in (mavlink.MAV_MISSION_TYPE_RALLY, mavlink.MAV_MISSION_TYPE_ALL):
            self.params.set_many({"BOB_RALLY_LAT": 0.0, "BOB_RALLY_LON": 0.0})
        self._persist_warning()
        self._mission_ack(peer, mission_type, mavlink.MAV_MISSION_ACCEPTED)
        self.notify(mavlink.MAV_SEVERITY_INFO, f"{MISSION_TYPE_NAMES.get(mission_type, mission_type)} cleared")
