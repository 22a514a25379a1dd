"""The command protocol of the ground-station component (`bob_autonomy.ground.gcs`): COMMAND_LONG and COMMAND_INT,
each value checked (`bob_autonomy.ground.gcs_checks.command_problem`), run and answered with COMMAND_ACK; arm, disarm
and mode changes become `AutopilotCommand`s for the process to pass on to the autopilot: they are answered
MAV_RESULT_IN_PROGRESS at once, and with the autopilot's own result once it has answered
(`answer_autopilot_command`), so a ground station is never told a vessel armed when its autopilot refused.

`CommandProtocol` is a mixin of `GcsComponent`, which provides the attributes it declares.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from bob_autonomy.ground.gcs_checks import command_problem
from bob_autonomy.ground.gcs_codec import GcsCounters, MavlinkCodec
from bob_autonomy.ground.params import ParamError, ParameterStore, validate_latlon

logger = logging.getLogger("bob_autonomy.ground.gcs")

ARM_FORCE_MAGIC = 21196.0  # param2 of MAV_CMD_COMPONENT_ARM_DISARM that forces it


@dataclass(frozen=True)
class AutopilotCommand:
    """A command for the autopilot that came to us; the process passes it on (e.g. with
    firmware_bridge.commands.command_long_arm / set_mode). `kind` is "arm", "disarm" or "set_mode";
    `force` (arm / disarm with param2 = 21196); `base_mode` and `custom_mode` of DO_SET_MODE (for an
    ArduPilot Rover, custom_mode is the mode number: HOLD 4, AUTO 10, GUIDED 15, ...); `params` the seven
    parameters as received, a NaN of an unused one (MAVLink's "default") as 0; `source` the (system,
    component) that sent it; `t_s` our clock at reception. Every number in it is finite (ValueError if not):
    nothing non-finite can reach the autopilot through it."""

    kind: str
    command: int
    params: tuple[float, ...]
    source: tuple[int, int]
    t_s: float
    force: bool = False
    base_mode: int | None = None
    custom_mode: int | None = None

    def __post_init__(self) -> None:
        numbers = [*self.params, self.t_s, *(v for v in (self.base_mode, self.custom_mode) if v is not None)]
        if not all(math.isfinite(v) for v in numbers):
            raise ValueError(f"{self.kind} command {self.command} with a value that is not finite: {numbers}")


@dataclass
class _Command:
    command: int
    params: tuple[float, float, float, float, float, float, float]
    latlon: tuple[float, float]  # params 5 and 6 read as latitude and longitude, deg
    source: tuple[int, int]


Handler = Callable[["CommandProtocol", _Command], int]


class CommandProtocol:
    """The command protocol's handlers (see the module docstring), mixed into GcsComponent."""

    codec: MavlinkCodec
    counters: GcsCounters
    params: ParameterStore
    clock: Callable[[], float]
    behavior_running: bool
    pending_autopilot: list[AutopilotCommand]
    _position: tuple[float, ...] | None

    # provided by GcsComponent and ParameterProtocol
    def _queue(self, message: mavlink.MAVLink_message) -> None:  # pragma: no cover - interface
        raise NotImplementedError

    def notify(self, severity: int, text: str) -> None:  # pragma: no cover - interface
        raise NotImplementedError

    def _refuse_value(self, text: str) -> None:  # pragma: no cover - interface
        raise NotImplementedError

    def _persist_warning(self) -> None:  # pragma: no cover - interface
        raise NotImplementedError

    def _send_autopilot_version(self) -> None:  # pragma: no cover - interface
        raise NotImplementedError

    def _send_heartbeat(self) -> None:  # pragma: no cover - interface
        raise NotImplementedError

    def _send_position(self) -> None:  # pragma: no cover - interface
        raise NotImplementedError

    def _command_long(self, msg) -> None:
        params = (msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6, msg.param7)
        cmd = _Command(msg.command, params, (msg.param5, msg.param6), (msg.get_srcSystem(), msg.get_srcComponent()))
        self._run_command(cmd)

    def _command_int(self, msg) -> None:
        params = (msg.param1, msg.param2, msg.param3, msg.param4, float(msg.x), float(msg.y), msg.z)
        cmd = _Command(msg.command, params, (msg.x / 1e7, msg.y / 1e7), (msg.get_srcSystem(), msg.get_srcComponent()))
        self._run_command(cmd, msg.frame)

    def _run_command(self, cmd: _Command, frame: int | None = None) -> None:
        """Check the command's values, run its handler, answer with a COMMAND_ACK. frame: COMMAND_INT's."""
        self.counters.commands += 1
        handler = _COMMANDS.get(cmd.command)
        problem = command_problem(cmd.command, cmd.params, cmd.latlon, frame)
        if handler is None:
            self.counters.commands_unsupported += 1
            result = mavlink.MAV_RESULT_UNSUPPORTED
        elif problem is not None:
            self._refuse_value(f"{_command_name(cmd.command)} refused: {problem}")
            result = mavlink.MAV_RESULT_DENIED
        else:
            try:
                result = handler(self, cmd)
            except ParamError as exc:  # a value the parameters' own ranges refuse
                self._refuse_value(f"{_command_name(cmd.command)} refused: {exc}")
                result = mavlink.MAV_RESULT_DENIED
            except Exception:
                self.counters.handler_errors += 1
                logger.exception("command %s failed", cmd.command)
                result = mavlink.MAV_RESULT_FAILED
        if result == mavlink.MAV_RESULT_DENIED:
            self.counters.commands_denied += 1
        self._queue(self.codec.mav.command_ack_encode(cmd.command, result, 0, 0, cmd.source[0], cmd.source[1]))

    def _cmd_mission_start(self, cmd: _Command) -> int:
        self.behavior_running = True
        self.notify(mavlink.MAV_SEVERITY_INFO, f"behaviour {self.params.behavior_name} started")
        return mavlink.MAV_RESULT_ACCEPTED

    def _cmd_pause_continue(self, cmd: _Command) -> int:
        action = cmd.params[0]
        if action == 0:
            self.behavior_running = False
            self.notify(mavlink.MAV_SEVERITY_INFO, f"behaviour {self.params.behavior_name} stopped: hold")
        elif action == 1:
            self.behavior_running = True
            self.notify(mavlink.MAV_SEVERITY_INFO, f"behaviour {self.params.behavior_name} continued")
        else:
            raise ParamError(f"param1 must be 0 (pause) or 1 (continue), got {action!r}")
        return mavlink.MAV_RESULT_ACCEPTED

    def _cmd_forward(self, cmd: _Command) -> int:
        p = tuple(0.0 if math.isnan(v) else float(v) for v in cmd.params)  # NaN: an unused parameter's default
        now = float(self.clock())
        if cmd.command == mavlink.MAV_CMD_COMPONENT_ARM_DISARM:
            if p[0] not in (0.0, 1.0):
                raise ParamError(f"param1 must be 1 (arm) or 0 (disarm), got {p[0]!r}")
            kind = "arm" if p[0] == 1.0 else "disarm"
            command = AutopilotCommand(kind, cmd.command, p, cmd.source, now, force=p[1] == ARM_FORCE_MAGIC)
        else:
            if not all(math.isfinite(v) and 0 <= v < 2**32 and v == int(v) for v in p[:2]):
                raise ParamError(f"base mode {p[0]!r} and custom mode {p[1]!r} must be whole numbers")
            command = AutopilotCommand(
                "set_mode", cmd.command, p, cmd.source, now, base_mode=int(p[0]), custom_mode=int(p[1])
            )
        self.pending_autopilot.append(command)
        return mavlink.MAV_RESULT_IN_PROGRESS  # the autopilot's answer follows (`answer_autopilot_command`)

    def answer_autopilot_command(self, command: AutopilotCommand, result: int) -> None:
        """The final COMMAND_ACK of a command passed on to the autopilot (answered MAV_RESULT_IN_PROGRESS when it
        came), to the station that sent it: the autopilot's own result (MAV_RESULT_*), or MAV_RESULT_FAILED when
        it did not answer. MAVLink's command protocol: an IN_PROGRESS is followed by the final result."""
        if result != mavlink.MAV_RESULT_ACCEPTED:
            self.counters.autopilot_refused += 1
        self._queue(self.codec.mav.command_ack_encode(command.command, int(result), 0, 0, *command.source))

    def _cmd_goal(self, cmd: _Command) -> int:
        lat, lon = validate_latlon(cmd.latlon, "goal")
        self.params.set_goals([(lat, lon)])
        self._persist_warning()
        self.notify(mavlink.MAV_SEVERITY_INFO, f"goal set to {lat:.7f}, {lon:.7f}")
        return mavlink.MAV_RESULT_ACCEPTED

    def _cmd_follow(self, cmd: _Command) -> int:
        leader = self.params.set("BOB_LEADER_ID", cmd.params[0])
        self._persist_warning()
        self.notify(mavlink.MAV_SEVERITY_INFO, f"leader set to {leader}" if leader else "leader cleared")
        return mavlink.MAV_RESULT_ACCEPTED

    def _cmd_behavior(self, cmd: _Command) -> int:
        self.params.set("BOB_BEHAVIOR", cmd.params[0])
        self._persist_warning()
        self.notify(mavlink.MAV_SEVERITY_INFO, f"behaviour set to {self.params.behavior_name}")
        return mavlink.MAV_RESULT_ACCEPTED

    def _cmd_fence_enable(self, cmd: _Command) -> int:
        self.params.set("BOB_FENCE_EN", cmd.params[0])
        self._persist_warning()
        return mavlink.MAV_RESULT_ACCEPTED

    def _cmd_request_message(self, cmd: _Command) -> int:
        wanted = cmd.params[0]
        if wanted == mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION:
            self._send_autopilot_version()
        elif wanted == mavlink.MAVLINK_MSG_ID_HEARTBEAT:
            self._send_heartbeat()
        elif wanted == mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT and self._position is not None:
            self._send_position()
        else:
            return mavlink.MAV_RESULT_DENIED
        return mavlink.MAV_RESULT_ACCEPTED

    def _cmd_capabilities(self, cmd: _Command) -> int:
        self._send_autopilot_version()
        return mavlink.MAV_RESULT_ACCEPTED


_COMMANDS: dict[int, Handler] = {
    mavlink.MAV_CMD_MISSION_START: CommandProtocol._cmd_mission_start,
    mavlink.MAV_CMD_DO_PAUSE_CONTINUE: CommandProtocol._cmd_pause_continue,
    mavlink.MAV_CMD_COMPONENT_ARM_DISARM: CommandProtocol._cmd_forward,
    mavlink.MAV_CMD_DO_SET_MODE: CommandProtocol._cmd_forward,
    mavlink.MAV_CMD_DO_REPOSITION: CommandProtocol._cmd_goal,
    mavlink.MAV_CMD_NAV_WAYPOINT: CommandProtocol._cmd_goal,
    mavlink.MAV_CMD_DO_FOLLOW: CommandProtocol._cmd_follow,
    mavlink.MAV_CMD_USER_1: CommandProtocol._cmd_behavior,
    mavlink.MAV_CMD_DO_FENCE_ENABLE: CommandProtocol._cmd_fence_enable,
    mavlink.MAV_CMD_REQUEST_MESSAGE: CommandProtocol._cmd_request_message,
    mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES: CommandProtocol._cmd_capabilities,
}


def _command_name(command: int) -> str:
    entry = mavlink.enums["MAV_CMD"].get(command)
    return entry.name if entry is not None else f"command {command}"
