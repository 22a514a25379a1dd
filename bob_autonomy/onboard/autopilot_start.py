"""Bringing a real ArduPilot autopilot into service for the autonomy, step by step, over a live link.

1. Wait for the autopilot's HEARTBEAT (component 1 of the vehicle's system).
2. Ask for the messages the estimators need (SET_MESSAGE_INTERVAL; REQUEST_DATA_STREAM when the autopilot
   does not acknowledge it), and for AUTOPILOT_VERSION and HOME_POSITION.
3. Read the parameters the autonomy depends on (frame, RC map and calibration, GCS id, override time,
   failsafes, steering type, speeds); stop with a message saying what to change when the vehicle cannot be
   driven as configured; warn about what is unsafe. Steps 1-3 speak as a component of the autopilot's own
   system, which ArduPilot answers even when MAV_OPTIONS bit 0 takes MAVLink only from MAV_GCS_SYSID; from
   then on the process sends as MAV_GCS_SYSID.
4. Send neutral RC overrides for a while (an autopilot without an RC receiver sits in radio failsafe until
   it hears some: "Arm: Radio failsafe on", issue #18), keep them fresh from then on.
5. Set the driving mode (MANUAL) and see the HEARTBEAT report it.
6. Wait until the autopilot is ready (3D GPS fix), saying what it waits for every few seconds.
7. Arm, retrying with backoff (an acceptance heard late, or a HEARTBEAT saying armed, ends it); each refusal
   is reported with ArduPilot's own reasons (the COMMAND_ACK result and its "PreArm: ..." STATUSTEXTs).
   Arming is never forced unless configured.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from bob_autonomy.onboard.autopilot import CORE_PARAMS, AutopilotProfile, AutopilotSession, message_name
from firmware_bridge.commands import ROVER_MODES, heartbeat

logger = logging.getLogger(__name__)

RESULT_WORDS = {
    mavlink.MAV_RESULT_ACCEPTED: "accepted",
    mavlink.MAV_RESULT_TEMPORARILY_REJECTED: "temporarily rejected",
    mavlink.MAV_RESULT_DENIED: "denied",
    mavlink.MAV_RESULT_UNSUPPORTED: "unsupported",
    mavlink.MAV_RESULT_FAILED: "failed (its checks did not pass)",
    mavlink.MAV_RESULT_IN_PROGRESS: "in progress",
}


PARAM_QUIET_S = 0.5  # no PARAM_VALUE for this long after some came: the rest are names the autopilot lacks
# Rounds of parameter requests, each for the names still unread, while a round reads some or the line loses
# frames: on a noisy line (a byte in 100 spoiled, about half the frames lost) two rounds left FRAME_CLASS and
# RC_OVERRIDE_TIME unread. There a request and its answer both get through about half the time, so a name stays
# unread after k rounds with probability 2^-k: 1.6 % at 6 rounds (real Rover SITL, seed 11 of
# tests/ardupilot/test_real_serial.py, left RC_OVERRIDE_TIME unread), 0.02 % at 12. Rounds only go on while names
# are missing, so a clean line still reads all in one. On a clean line a round that reads none ends them: the rest
# are names it lacks.
PARAM_ROUNDS = 12
STREAM_REQUEST_ROUNDS = 3  # rounds of SET_MESSAGE_INTERVAL while some go unanswered


class AutopilotStartError(RuntimeError):
    """The autopilot cannot be brought into service; the message says why and what to change."""


class NoHeartbeatError(AutopilotStartError):
    """Nothing of the autopilot heard at all: a link that carries nothing we can read (wrong port or baud rate)."""


@dataclass(frozen=True)
class StartOptions:
    """How patient and how forceful the start-up is (wall seconds)."""

    mode: str = "MANUAL"
    heartbeat_timeout_s: float = 30.0
    ready_timeout_s: float = 120.0
    arm_timeout_s: float = 30.0
    arm_answer_s: float = 3.0  # how long each arm attempt waits for its answer (a slow radio or busy autopilot)
    force_arm: bool = False
    neutral_lead_s: float = 2.0
    param_timeout_s: float = 6.0
    control_period_s: float = 0.1


class AutopilotStarter:
    """Runs the start-up (module docstring) with the vessel's own link.

    send(bytes) writes to the vehicle; pump(wait_s) reads and decodes what came (feeding `session.handle`);
    stopped() is true when the process is asked to stop; notify(severity, text) tells the ground station.
    """

    def __init__(
        self,
        session: AutopilotSession,
        send: Callable[[bytes], None],
        pump: Callable[[float], None],
        stopped: Callable[[], bool],
        notify: Callable[[int, str], None],
        options: StartOptions | None = None,
    ) -> None:
        self.session, self.send, self.pump, self.stopped, self.notify = session, send, pump, stopped, notify
        self.options = options or StartOptions()
        self._next_beat = 0.0
        self._neutral = False

    # -- small pieces ------------------------------------------------------------------------------------

    def _keep_alive(self) -> None:
        """Our HEARTBEAT every wall second, and neutral overrides every control period once they have begun."""
        now = time.monotonic()
        if now >= self._next_beat:
            self._next_beat = now + 1.0
            self.send(heartbeat(encoder=self.session.encoder))
        if self._neutral:
            self.send(self.session.override(0.0, 0.0, 0.0))

    def _wait(self, seconds: float, done: Callable[[], bool] | None = None) -> bool:
        """Pump and keep alive for `seconds` or until done(); True when done() became true."""
        end = time.monotonic() + seconds
        while time.monotonic() < end and not self.stopped():
            self._keep_alive()
            self.pump(min(self.options.control_period_s, max(0.0, end - time.monotonic())))
            if done is not None and done():
                return True
        return done is not None and done()

    def _say(self, severity: int, text: str) -> None:
        log = logger.error if severity <= mavlink.MAV_SEVERITY_ERROR else logger.warning
        if severity >= mavlink.MAV_SEVERITY_INFO:
            log = logger.info
        log("%s", text)
        self.notify(severity, text)

    # -- the steps -----------------------------------------------------------------------------------------

    def run(self) -> AutopilotProfile | None:
        """Bring the autopilot into service; returns its profile (None when asked to stop meanwhile)."""
        s, o = self.session, self.options
        # Until its MAV_GCS_SYSID is known, speak as a component of the autopilot's own system: ArduPilot takes any
        # packet from its own system whatever MAV_OPTIONS says (GCS_Common.cpp accept_packet), so the queries are
        # answered even by an autopilot that takes MAVLink only from its ground station. `learn` then takes the
        # ground station's id, the only one whose RC overrides and HEARTBEATs count.
        s.encoder.mav.srcSystem = s.target_system
        if not self._wait(o.heartbeat_timeout_s, lambda: s.custom_mode is not None):
            if self.stopped():
                return None
            others = sorted(s.other_autopilots)
            if others:  # the link works: the ids disagree (every ArduPilot leaves the factory as system 1)
                heard = ", ".join(map(str, others))
                raise AutopilotStartError(
                    f"no HEARTBEAT from autopilot system {s.target_system} within {o.heartbeat_timeout_s:g} s, but "
                    f"this link carries autopilot system {heard}: start with --system-id {others[0]}, or set that "
                    f"autopilot's MAV_SYSID to {s.target_system} (each vessel of a swarm needs its own)"
                )
            raise NoHeartbeatError(
                f"no HEARTBEAT from autopilot system {s.target_system} component 1 within {o.heartbeat_timeout_s:g} s:"
                " check the link (port, baud rate) and the autopilot's MAV_SYSID"
            )
        self._request_streams()
        profile = self._read_parameters()
        if self.stopped():
            return None
        self._neutral = True
        self._wait(o.neutral_lead_s)
        lagging = s.lagging_messages(s.clock(), o.neutral_lead_s)
        if lagging:
            how = "by id" if s.intervals_accepted else "by stream group"
            names = ", ".join(message_name(m) for m in lagging)
            logger.info("still slow after the start-up, asked again %s: %s", how, names)
            for frame in s.requests_again(lagging):
                self.send(frame)
        self._set_mode(o.mode)
        self._wait_ready()
        self._arm()
        return profile

    def _request_streams(self) -> None:
        """SET_MESSAGE_INTERVAL for every message wanted, sent again (all of them: a COMMAND_ACK does not say
        which request it answers) while fewer acknowledgements than requests come back, a request or its answer
        lost on a noisy line; REQUEST_DATA_STREAM only from firmware that answers none, or refuses them all."""
        s = self.session
        since = time.monotonic()
        command = mavlink.MAV_CMD_SET_MESSAGE_INTERVAL
        first = s.clock()
        for frame in s.info_requests():
            self.send(frame)
        for attempt in range(STREAM_REQUEST_ROUNDS):
            t0 = s.clock()
            for frame in s.stream_requests():
                self.send(frame)
            self._wait(1.5, lambda t0=t0: len(s.acks_since(command, t0)) >= s.interval_requests)
            answered = len(s.acks_since(command, t0))
            if answered >= s.interval_requests or self.stopped() or (attempt >= 1 and not s.acks_since(command, first)):
                break  # all answered; or none twice: firmware without the command
        results = s.acks_since(command, first)
        refused = [r for r in s.acks_since(command, t0) if r != mavlink.MAV_RESULT_ACCEPTED]  # the last round's
        if refused:
            self._say(
                mavlink.MAV_SEVERITY_WARNING,
                f"autopilot refused {len(refused)} of {s.interval_requests} message-rate requests "
                f"({RESULT_WORDS.get(refused[0], refused[0])}; faster than its loop allows?)",
            )
        if not results or mavlink.MAV_RESULT_ACCEPTED not in results:
            word = "no answer" if not results else RESULT_WORDS.get(results[-1], str(results[-1]))
            self._say(
                mavlink.MAV_SEVERITY_WARNING,
                f"SET_MESSAGE_INTERVAL {word}; asking with REQUEST_DATA_STREAM (older firmware)",
            )
            for frame in s.stream_fallback_requests():
                self.send(frame)
        logger.info("streams requested in %.2f s", time.monotonic() - since)

    def _read_parameters(self) -> AutopilotProfile:
        s, o = self.session, self.options
        per_round = o.param_timeout_s / 4
        for names in (list(CORE_PARAMS), None):
            missing_before, lost_before = math.inf, s.frames_lost
            for _ in range(PARAM_ROUNDS):
                wanted = s.rc_param_names() if names is None else names
                missing = [n for n in wanted if n not in s.params]
                if not missing or self.stopped():
                    break
                if len(missing) >= missing_before and s.frames_lost == lost_before:
                    break  # the last round read none of the rest on a line that lost nothing: names it lacks
                missing_before, lost_before = len(missing), s.frames_lost
                asked = s.clock()
                for frame in s.param_requests(missing):
                    self.send(frame)

                def settled(w=wanted, asked=asked) -> bool:
                    # every name answered, or answers came and then stopped (ArduPilot ignores unknown names)
                    quiet = s.last_param_t > asked and s.clock() - s.last_param_t > PARAM_QUIET_S
                    return all(n in s.params for n in w) or quiet

                self._wait(per_round, settled)
        # Nothing answered yet: give a slow link (seconds each way) one more parameter timeout before the verdict.
        if not (s.params or s.acks) and not self._wait(o.param_timeout_s, lambda: bool(s.params or s.acks)):
            if self.stopped():
                return s.learn()
            raise AutopilotStartError(
                f"autopilot system {s.target_system} is heard (HEARTBEAT) but answered nothing sent to it: no "
                f"COMMAND_ACK to {s.interval_requests} message-rate requests and no PARAM_VALUE to "
                f"{len(CORE_PARAMS)} parameter requests. Check that our bytes reach the autopilot (the serial TX wire "
                "to its RX; a half-duplex or one-way radio) and that its port speaks MAVLink 2 (SERIALn_PROTOCOL 2)"
            )
        profile = s.learn()
        absent = [n for n in ("FRAME_CLASS", "FRAME_TYPE", "RC_OVERRIDE_TIME") if n not in s.params]
        if absent:
            self._say(
                mavlink.MAV_SEVERITY_WARNING,
                f"autopilot did not report {', '.join(absent)}: assuming ArduPilot's defaults",
            )
        problems = profile.problems(s.kind)
        if problems:
            raise AutopilotStartError("cannot drive this vehicle: " + "; ".join(problems))
        for text in profile.warnings(o.control_period_s):
            self._say(mavlink.MAV_SEVERITY_WARNING, text)
        logger.info(
            "autopilot: %s, overrides from system %d, RC map %s, RC_OVERRIDE_TIME %g s, top speed %s",
            profile.frame_name,
            profile.gcs_system_id,
            profile.rc_map,
            profile.override_timeout_s,
            profile.top_speed_mps,
        )
        return profile

    def _set_mode(self, mode: str) -> None:
        s = self.session
        number = ROVER_MODES[mode]
        for attempt in range(5):
            if self.stopped():
                return
            t0 = s.clock()
            self.send(s.set_mode(mode))
            if self._wait(1.0 + attempt, lambda: s.custom_mode == number):
                logger.info("autopilot in %s", mode)
                return
            result = s.take_ack(mavlink.MAV_CMD_DO_SET_MODE, t0)
            if result is not None and result != mavlink.MAV_RESULT_ACCEPTED:
                texts = s.texts_since(t0, ("",))
                raise AutopilotStartError(
                    f"autopilot refused mode {mode}: {RESULT_WORDS.get(result, result)}"
                    + (f" ({'; '.join(texts)})" if texts else "")
                )
        raise AutopilotStartError(
            f"autopilot did not enter {mode} (HEARTBEAT still says {s.mode_name()}); "
            "is something else setting the mode?"
        )

    def _wait_ready(self) -> None:
        s, o = self.session, self.options
        end = time.monotonic() + o.ready_timeout_s
        while not self.stopped():
            why = s.ready()
            if why is None:
                return
            if time.monotonic() >= end:
                raise AutopilotStartError(f"autopilot not ready after {o.ready_timeout_s:g} s: {why}")
            self._say(mavlink.MAV_SEVERITY_INFO, f"autopilot not ready: {why}")
            self._wait(5.0, lambda: s.ready() is None)

    def _arm(self) -> None:
        s, o = self.session, self.options
        command = mavlink.MAV_CMD_COMPONENT_ARM_DISARM
        first = s.clock()
        end = time.monotonic() + o.arm_timeout_s

        def accepted() -> bool:
            # Any attempt's acceptance, however late (an answer can take seconds over a slow telemetry radio or
            # from a busy autopilot), or a HEARTBEAT saying armed: asking again would only repeat the command.
            return s.armed is True or mavlink.MAV_RESULT_ACCEPTED in s.acks_since(command, first)

        backoff = 1.0
        reasons: list[str] = []
        while not self.stopped():
            t0 = s.clock()
            if not accepted():
                self.send(s.arm(True, force=o.force_arm))
                self._wait(o.arm_answer_s, lambda t0=t0: accepted() or s.take_ack(command, t0) is not None)
            if accepted():
                self._wait(1.0, lambda: s.armed is True)
                logger.info("autopilot armed%s", " (forced)" if o.force_arm else "")
                return
            result = s.take_ack(command, t0)
            self._wait(0.3)  # the reasons follow the ACK
            texts = s.texts_since(t0)
            reasons = texts or reasons
            word = f"no answer within {o.arm_answer_s:g} s" if result is None else RESULT_WORDS.get(result, str(result))
            self._say(
                mavlink.MAV_SEVERITY_WARNING,
                f"autopilot refused to arm ({word})" + (f": {'; '.join(texts)}" if texts else ""),
            )
            if time.monotonic() + backoff >= end:
                break
            self._wait(backoff, accepted)
            backoff = min(backoff * 2, 8.0)
        if self.stopped():
            return
        raise AutopilotStartError(
            f"autopilot would not arm within {o.arm_timeout_s:g} s"
            + (f": {'; '.join(reasons)}" if reasons else "")
            + ". Fix what it reports (or, knowingly, start with force_arm)"
        )
