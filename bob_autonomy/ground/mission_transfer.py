"""Verified, retried exchanges of `MissionClient` (bob_autonomy.ground.mission) with many vessels at once, and the
mission protocol on top of them: upload (MISSION_COUNT, items on request, MISSION_ACK) and download of goals,
fence and rally point."""

from __future__ import annotations

import queue
import time
from collections.abc import Callable, Iterable, Sequence

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from bob_autonomy.ground.mission_link import FleetLink, MissionError, result_name
from bob_autonomy.ground.params import LatLon, ParamError, validate_latlon


class MissionTransfer(FleetLink):
    """Requests to many vessels verified and retried (`_exchange`), refusals explained, missions moved."""

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
        drops_before = self.kernel_drops
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
        dropped = self.kernel_drops - drops_before
        for sid in pending:
            why = reasons.get(sid) or next((t for s, _, t in reversed(self.statustexts(sid)) if s >= start), None)
            failures[sid] = f"no answer after {self.retries + 1} tries" + (f" (last heard: {why})" if why else "")
            if dropped:
                failures[sid] += f"; our socket dropped {dropped} datagrams meanwhile (its receive buffer was full)"
        if failures:
            raise MissionError(what, failures)
        return results

    def _explained(self, exc: MissionError) -> MissionError:
        """Add each failed vessel's last STATUSTEXT (its reason) to a refusal."""
        failures = dict(exc.failures)
        for sid, why in failures.items():
            texts = self.statustexts(sid)
            if texts and not why.startswith("no answer"):
                failures[sid] = f"{why} ({texts[-1][2]})"
        return type(exc)(exc.what, failures)

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
                            failures[sid] = result_name("MAV_MISSION_RESULT", msg.type)
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
