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

import math
import time
from collections.abc import Callable, Iterable, Sequence

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from bob_autonomy.core.geodesy import LocalFrame
from bob_autonomy.ground.mission_link import MissionError, MissionTimeoutError, VesselPosition, float32, result_name
from bob_autonomy.ground.mission_transfer import MissionTransfer
from bob_autonomy.ground.params import BEHAVIOR_NAMES, PARAMS, LatLon, ParamError, validate_latlon

__all__ = ["MissionClient", "MissionError", "MissionTimeoutError", "VesselPosition"]

_SPECS = {spec.name: spec for spec in PARAMS}


class MissionClient(MissionTransfer):
    """A ground-station endpoint for mission scripts (see the module docstring).

    connection: "udpin:HOST:PORT" (listen; vessels send to it) or "udpout:HOST:PORT" (also send there).
    system_id / component_id: ours (255 / MAV_COMP_ID_MISSIONPLANNER 190). signing_key: 32 bytes or None.
    timeout_s: wait for each answer (s); retries: further tries before a vessel is reported as failed.
    target_component: the vessels' autonomy component (191).
    """

    # -- parameters ----------------------------------------------------------------------------------------

    def set_param(self, name: str, value: float, vessels: Iterable[int] | None = None) -> dict[int, float]:
        """Set a parameter on the vessels (None: all found); checks it against the declared range first
        (ParamError), then verifies each vessel's PARAM_VALUE echo. Returns {system id: value in force}."""
        return {sid: values[name] for sid, values in self.set_params({name: value}, vessels).items()}

    def set_params(self, values: dict[str, float], vessels: Iterable[int] | None = None) -> dict[int, dict[str, float]]:
        """Set several parameters on the vessels (None: all found) in one round trip: every value is checked
        against its declared range first (ParamError, nothing sent), then each vessel is sent all the
        PARAM_SETs in the order given without waiting between them, and is done when it has echoed every value
        in a PARAM_VALUE. A retry sends a vessel only the parameters it has not echoed yet. Returns
        {system id: {name: value in force}}.

        One round trip rather than one per parameter: a behaviour switch of nine parameters reaches a fleet in
        the time of one answer, and a lost echo costs one retry of the whole set, not one per parameter.
        """
        checked: dict[str, tuple[float | int, float, int]] = {}  # name -> (value sent, float32 echo, MAV type)
        for name, value in values.items():
            spec = _SPECS.get(name)
            if spec is None:
                raise ParamError(f"unknown parameter {name!r}; known: {', '.join(_SPECS)}")
            value_sent = spec.check(value)
            checked[name] = (value_sent, float32(value_sent), spec.mav_type)
        if not checked:
            return {}
        targets = self._targets(vessels)
        unechoed = {sid: list(checked) for sid in targets}  # in the order given
        echoed: dict[int, dict[str, float]] = {sid: {} for sid in targets}

        def send(pending: list[int], attempt: int) -> None:
            for sid in pending:
                for name in unechoed[sid]:
                    value_sent, _, mav_type = checked[name]
                    message = self.codec.mav.param_set_encode(
                        sid, self.target_component, name.encode("ascii"), float(value_sent), mav_type
                    )
                    self._send(message, [sid])

        start = float(self.clock())

        def match(sid: int, msg) -> tuple[str, object] | None:
            if msg.get_type() != "PARAM_VALUE" or msg.param_id not in unechoed[sid]:
                return None
            name = msg.param_id
            if msg.param_value == checked[name][1]:
                unechoed[sid].remove(name)
                echoed[sid][name] = msg.param_value
                return ("ok", echoed[sid]) if not unechoed[sid] else None
            # The vessel says why it refused in a STATUSTEXT sent just before the PARAM_VALUE.
            for t, _severity, text in reversed(self.statustexts(sid)):
                if t >= start and name in text:
                    return "fail", f"refused ({text}); {name} is {msg.param_value:g}"
            return "wait", f"{name} is still {msg.param_value:g}"

        what = "cannot set " + ", ".join(f"{name} = {value!r}" for name, value in values.items())
        return self._exchange(what, targets, send, match)  # type: ignore[return-value]

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
        label = what or result_name("MAV_CMD", command)

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
            return "fail", result_name("MAV_RESULT", msg.result)

        try:
            self._exchange(f"{label} failed", targets, send, match)
        except MissionError as exc:
            raise self._explained(exc) from None

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
            return "fail", result_name("MAV_RESULT", msg.result)

        try:
            self._exchange(f"cannot set the goal to {lat}, {lon}", targets, send, match)
        except MissionError as exc:
            raise self._explained(exc) from None

    def set_leader(self, leader_system_id: int, vessels: Iterable[int] | None = None) -> None:
        """Follow the vessel with this system id (0 = none): MAV_CMD_DO_FOLLOW param1."""
        self.command(mavlink.MAV_CMD_DO_FOLLOW, (leader_system_id,), vessels, what=f"follow {leader_system_id}")

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
