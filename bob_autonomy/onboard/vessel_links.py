"""A vessel's links (bob_autonomy.onboard.vessel): reading and decoding the vehicle, sending to it, serving the ground
station and routing frames between the two, as mavlink-router does on a companion computer."""

from __future__ import annotations

import contextlib
import logging
import time
from typing import TYPE_CHECKING

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from bob_autonomy.ground.gcs import AutopilotCommand, GcsComponent
from bob_autonomy.onboard.autopilot_start import RESULT_WORDS
from bob_autonomy.onboard.senses import EbotSenses
from bob_autonomy.onboard.vehicle_link import VehicleLink
from firmware_bridge.baud_probe import find_mavlink_baud
from firmware_bridge.links import Link, LinkError, SerialLink, TcpLink, open_link, parse_connection_string
from firmware_bridge.tlog import TlogWriter

if TYPE_CHECKING:
    from bob_autonomy.onboard.autopilot import AutopilotSession
    from bob_autonomy.onboard.pipeline import BuoyPipeline, EbotPipeline, MotorboatPipeline
    from bob_autonomy.onboard.vessel import VesselConfig, VesselStats

logger = logging.getLogger("bob_autonomy.onboard.vessel")

MAX_ROUTED_BACKLOG = 2000  # frames; a ground-station link that cannot keep up loses the oldest
FORWARDED_ANSWER_S = 5.0  # s (vessel clock) the autopilot has to answer a ground station's arm or mode command
REASONS_WAIT_S = 1.0  # s (vessel clock) after such a command that a refusal waits for the autopilot's reasons
REOPEN_PERIOD_S = 1.0  # wall seconds between attempts to reopen a lost vehicle link
DATAGRAM_BYTES = 1200  # MAVLink frames per UDP datagram up to this size (one frame may be larger)


def _datagrams(frames: list[bytes]) -> list[bytes]:
    """Whole frames packed into datagrams of at most DATAGRAM_BYTES (a frame is never split)."""
    out: list[bytes] = []
    current = bytearray()
    for frame in frames:
        if current and len(current) + len(frame) > DATAGRAM_BYTES:
            out.append(bytes(current))
            current = bytearray()
        current += frame
    if current:
        out.append(bytes(current))
    return out


class VesselLinks:
    """The vessel's link handling, mixed into Vessel, which provides the attributes declared here."""

    config: VesselConfig
    stats: VesselStats
    tlog: TlogWriter | None
    vehicle_link: Link
    gcs_link: Link | None
    vehicle: VehicleLink
    autopilot: AutopilotSession
    gcs: GcsComponent
    pipeline: BuoyPipeline | EbotPipeline | MotorboatPipeline
    sensing: EbotSenses | None
    _from_vehicle: list[bytes]
    _forwarded: list[tuple[AutopilotCommand, float]]  # passed on to the autopilot, not yet answered: (command, sent)
    _last_reading_wall_s: float | None
    _link_lost_at: float | None  # wall clock (time.monotonic) when the vehicle link was lost; None while it is up
    _next_reopen_at: float

    def _vehicle_message(self, msg) -> None:
        """Every message decoded from the vehicle link: to the tlog, and the autopilot's to the session."""
        if self.tlog is not None:
            self.tlog.write_message(msg)
        self.autopilot.handle(msg)
        if self.autopilot.is_autopilot(msg):
            # Any message of the autopilot shows it and the link alive, not only its 1 Hz HEARTBEAT: on a noisy
            # line (a byte in 100 spoiled) three HEARTBEATs in a row were lost while 40 other messages a second
            # came, and the vessel stopped the boat as if its autopilot had gone silent.
            self.vehicle.watch.beat()
        if self.gcs_link is not None and msg.get_srcSystem() == self.config.system_id:
            # The vehicle's own traffic goes on to the ground station (mavlink-router's job on a companion).
            self._from_vehicle.append(bytes(msg.get_msgbuf()))
            if len(self._from_vehicle) > MAX_ROUTED_BACKLOG:
                del self._from_vehicle[: len(self._from_vehicle) - MAX_ROUTED_BACKLOG]

    def _baud_hint(self) -> str:
        """For a serial vehicle link that carried no HEARTBEAT: that it carried nothing at all, or the baud rate it
        does carry MAVLink at, said as what to change (the port is closed to listen at other rates; the vessel does
        not start), else ""."""
        kind, device, _port = parse_connection_string(self.config.vehicle)
        if kind != "serial":
            return ""
        if self.vehicle.decoder.counters.bytes_fed == 0:
            return (
                ". Not a byte came on this port: check that it is the autopilot's (its TX wired to our RX, a "
                "common ground) and that the autopilot is powered"
            )
        self.vehicle_link.close()
        baud = find_mavlink_baud(device, self.config.baud)
        if baud is None:
            return ""
        # ArduPilot's SERIALn_BAUD is in thousands: 57 for 57,600, 921 for 921,600
        return (
            f". This port carries MAVLink at {baud} baud, not {self.config.baud}: start with --baud {baud} (baud = "
            f"{baud} in the vessel file), or set the autopilot port's SERIALn_BAUD to {self.config.baud // 1000}"
            f" (it is {baud // 1000} now)"
        )

    def _say(self, severity: int, text: str) -> None:
        """Tell the ground station (STATUSTEXT, MAV_SEVERITY_*) and the log: `GcsComponent.notify` does both."""
        self.gcs.notify(severity, text)

    def _send(self, data: bytes) -> None:
        if self.tlog is not None:
            self.tlog.write_frame(data)  # every command is one frame
        if self._link_lost_at is not None:
            return  # nothing to write to until the link is reopened (the autopilot's failsafe has the vehicle)
        try:
            self.vehicle_link.write(data)
        except LinkError as error:
            self._vehicle_link_failed("write", error)

    def _vehicle_link_failed(self, doing: str, error: LinkError) -> None:
        """Count a failed read or write. A TCP connection closed by the autopilot (ArduPilot SITL rebooting) or a
        serial port gone (a USB adapter unplugged, an autopilot losing power) cannot recover by itself: it is
        closed and reopened every REOPEN_PERIOD_S until it opens again; said once, not at every attempt."""
        self.stats.link_errors += 1
        if self._link_lost_at is not None:
            return
        if not isinstance(self.vehicle_link, TcpLink | SerialLink):
            logger.error("vehicle link %s failed (%d so far): %s", doing, self.stats.link_errors, error)
            return
        self._link_lost_at = time.monotonic()
        self._next_reopen_at = self._link_lost_at + REOPEN_PERIOD_S
        with contextlib.suppress(OSError):
            self.vehicle_link.close()
        c = self.config
        text = f"vehicle {c.system_id} link lost ({error}); reopening {c.vehicle} every {REOPEN_PERIOD_S:g} s"
        self._say(mavlink.MAV_SEVERITY_CRITICAL, text)

    def _reopen_vehicle_link(self, wait_wall_s: float) -> bool:
        """Try to reopen a lost vehicle link when an attempt is due (waiting at most `wait_wall_s` for it);
        True once it is open again."""
        now = time.monotonic()
        if now < self._next_reopen_at:
            time.sleep(min(max(0.0, wait_wall_s), self._next_reopen_at - now))
            if time.monotonic() < self._next_reopen_at:
                return False
        self._next_reopen_at = time.monotonic() + REOPEN_PERIOD_S
        try:
            # A host that neither accepts nor refuses must not hold the loop (and the ground station) for long.
            self.vehicle_link = open_link(self.config.vehicle, self.config.baud, connect_timeout_s=REOPEN_PERIOD_S / 2)
        except LinkError as error:
            logger.debug("vehicle link still closed: %s", error)
            return False
        lost_for = time.monotonic() - self._link_lost_at
        self._link_lost_at = None
        self.stats.link_reopens += 1
        text = f"vehicle {self.config.system_id} link reopened after {lost_for:.1f} s"
        self._say(mavlink.MAV_SEVERITY_NOTICE, text)
        return True

    def pump(self, wait_wall_s: float = 0.0) -> None:
        """Read and decode what the vehicle sent, waiting at most `wait_wall_s` for the first bytes."""
        timeout = max(0.0, wait_wall_s)
        if self._link_lost_at is not None and not self._reopen_vehicle_link(timeout):
            return
        while True:
            try:
                data = self.vehicle_link.read(65535, timeout)
            except LinkError as error:
                self._vehicle_link_failed("read", error)
                time.sleep(min(timeout, 0.1))
                return
            if not data:
                return
            timeout = 0.0
            readings = self.vehicle.receive(data)
            if readings:
                self._last_reading_wall_s = time.perf_counter()
                self.stats.readings += len(readings)
                try:
                    self.pipeline.feed(readings)
                    if self.sensing is not None:
                        self.sensing.feed(readings)
                except Exception:  # one bad reading must not stop the vessel: count it, log it, go on
                    self.stats.reading_errors += 1
                    logger.exception("readings could not be fused (%d so far)", self.stats.reading_errors)

    def _answer_forwarded(self) -> None:
        """Give each ground station's arm, disarm or mode command the autopilot's answer (COMMAND_ACK) once it has
        come, or MAV_RESULT_FAILED, said, when none came within FORWARDED_ANSWER_S. A refusal is also said with the
        autopilot's reasons (its "PreArm:" / "Arm:" STATUSTEXTs, which may follow its COMMAND_ACK: waited for up to
        REASONS_WAIT_S)."""
        if not self._forwarded:
            return
        now = float(self.autopilot.clock())
        waiting = []
        for command, sent in self._forwarded:
            result = self.autopilot.take_ack(command.command, sent)
            if result is None or result == mavlink.MAV_RESULT_IN_PROGRESS:
                if now - sent <= FORWARDED_ANSWER_S:
                    waiting.append((command, sent))
                    continue
                result = mavlink.MAV_RESULT_FAILED
                text = f"vehicle {self.config.system_id} did not answer {command.kind} within {FORWARDED_ANSWER_S:g} s"
                self._say(mavlink.MAV_SEVERITY_WARNING, text)
            elif result != mavlink.MAV_RESULT_ACCEPTED:
                reasons = "; ".join(self.autopilot.texts_since(sent))
                if not reasons and now - sent <= REASONS_WAIT_S:
                    waiting.append((command, sent))
                    continue
                word, why = RESULT_WORDS.get(result, f"result {result}"), reasons or "no reason given"
                text = f"vehicle {self.config.system_id} refused {command.kind} ({word}): {why}"
                self._say(mavlink.MAV_SEVERITY_WARNING, text)
            self.gcs.answer_autopilot_command(command, result)
        self._forwarded = waiting

    def _pump_and_serve(self, wait_wall_s: float) -> None:
        """Read the vehicle link and serve the ground station (during the start-up, which the GCS sees)."""
        self.pump(wait_wall_s)
        self.serve_gcs()

    def serve_gcs(self) -> None:
        """Exchange what is due with the ground station(s): read their datagrams, answer, pass on autopilot
        commands (arm, disarm, set mode) to the vehicle."""
        gcs, link = self.gcs, self.gcs_link
        while link is not None:
            try:
                data, sender = link.read_from(65535, 0.0)
            except LinkError as error:
                self.stats.link_errors += 1
                logger.warning("ground-station link read failed: %s", error)
                break
            if not data:
                break
            if gcs.receive(data, datagram=True):  # frames passed the checks (signature when keyed): answer it
                link.confirm_peer(sender)
        for frame in gcs.take_for_autopilot():
            self.stats.routed_to_vehicle += 1
            self._send(frame)
        for command in gcs.take_autopilot_commands():
            if command.kind in ("arm", "disarm"):
                self._send(self.autopilot.arm(command.kind == "arm", force=command.force))
            elif command.kind == "set_mode" and command.custom_mode is not None:
                self._send(self.vehicle.set_mode(int(command.custom_mode)))
            else:  # a mode without a number (none is made so): answered at once, never left in progress
                gcs.answer_autopilot_command(command, mavlink.MAV_RESULT_UNSUPPORTED)
                continue
            self._forwarded.append((command, float(self.autopilot.clock())))
        self._answer_forwarded()
        gcs.tick()
        own = gcs.outgoing()
        if self.tlog is not None:
            for frame in own:
                self.tlog.write_frame(frame)
        routed, self._from_vehicle = self._from_vehicle, []
        self.stats.routed_to_gcs += len(routed)
        if link is None:
            return
        routed = [gcs.codec.sign_routed(frame) for frame in routed]  # signed as our own when the link is keyed
        for datagram in _datagrams(own + routed):
            try:
                link.write(datagram)
            except LinkError as error:
                self.stats.link_errors += 1
                logger.warning("ground-station link write failed: %s", error)
