"""A vessel whose autopilot restarts under it, or whose vehicle link closes, or that someone disarms.

The autopilot is the simulator's (`SimulatedVehicle`, on a real UDP socket: tests/vessel_helpers.py), reached
over real TCP through a relay that can close the connection and refuse new ones for a while, as ArduPilot's SITL
does when it reboots (tests/ardupilot/test_real_reboot.py runs the same against ArduPilot itself) and as a
serial port does when its USB adapter is unplugged. Before, the vessel logged a failed read at every pump forever,
never drove again, and took a disarmed vehicle for one it was driving.
"""

from __future__ import annotations

import contextlib
import os
import select
import socket
import threading
import time
from dataclasses import replace

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink
from vessel_helpers import ORIGIN, SCALE, PluggedPty, StandInVehicle

from bob_autonomy.cli import _apply_config_file, _parser, config_from_args
from bob_autonomy.core.behavior_config import BehaviorChoice
from bob_autonomy.core.clock import ScaledWallClock
from bob_autonomy.onboard.autopilot import REBOOT_BACKSTEP_S, AutopilotSession
from bob_autonomy.onboard.vehicle_link import BUOY
from bob_autonomy.onboard.vessel import Vessel, VesselConfig
from firmware_bridge.commands import Encoder

pytestmark = pytest.mark.xdist_group("realtime")


class TcpRelay(threading.Thread):
    """A TCP server on a free port relaying one client's bytes to a UDP endpoint and its replies back. `drop()`
    closes the client and refuses connections until `restore()` (the port stays the same)."""

    def __init__(self, udp_port: int) -> None:
        super().__init__(daemon=True)
        self.target = ("127.0.0.1", udp_port)
        self.udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.udp.bind(("127.0.0.1", 0))
        self.listener = self._listen(0)
        self.port = self.listener.getsockname()[1]
        self.client: socket.socket | None = None
        self.lock = threading.Lock()
        self.running = True
        self.connections = 0

    @staticmethod
    def _listen(port: int) -> socket.socket:
        listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        listener.bind(("127.0.0.1", port))
        listener.listen(1)
        return listener

    def run(self) -> None:
        while self.running:
            with self.lock:
                sockets = [s for s in (self.listener, self.client, self.udp) if s is not None]
            try:
                ready, _, _ = select.select(sockets, [], [], 0.05)
            except (OSError, ValueError):  # a socket closed by drop() while selected
                continue
            with self.lock:
                for sock in ready:
                    self._serve(sock)

    def _serve(self, sock: socket.socket) -> None:
        try:
            if sock is self.listener:
                if self.client is not None:
                    self.client.close()
                self.client, _ = sock.accept()
                self.connections += 1
            elif sock is self.udp:
                data = sock.recv(65535)
                if self.client is not None:
                    self.client.sendall(data)
            elif sock is self.client:
                data = sock.recv(65535)
                if data:
                    self.udp.sendto(data, self.target)
        except OSError:
            pass  # a socket closed under us by drop()

    def drop(self) -> None:
        with self.lock:
            for sock in (self.client, self.listener):
                if sock is not None:
                    sock.close()
            self.client = self.listener = None

    def restore(self) -> None:
        with self.lock:
            self.listener = self._listen(self.port)

    def close(self) -> None:
        self.running = False
        self.join(2.0)
        self.drop()
        self.udp.close()


@pytest.fixture
def relayed():
    vehicle = StandInVehicle()
    vehicle.start()
    relay = TcpRelay(vehicle.port)
    relay.start()
    yield vehicle, relay
    relay.close()
    vehicle.close()


def _config(port: int, **overrides) -> VesselConfig:
    choice = BehaviorChoice(behavior="bob-rule", params={"goal": [200.0, 0.0], "H": 1, "p0": 5.0, "max_speed": 1.0})
    options = {"time_scale": SCALE, "controller": "simple", "arm_timeout_s": 5.0, "heartbeat_timeout_s": 3.0}
    options.update(overrides)
    return VesselConfig(vehicle=f"tcp:127.0.0.1:{port}", system_id=1, behavior=choice, origin=ORIGIN, **options)


def _said(vessel: Vessel) -> list[str]:
    """What the vessel tells its ground station (GcsComponent.notify, still sent as STATUSTEXT), as it says it."""
    said: list[str] = []
    notify = vessel.gcs.notify

    def spy(severity: int, text: str) -> None:
        said.append(text)
        notify(severity, text)

    vessel.gcs.notify = spy
    return said


def _run(vessel: Vessel, seconds: float) -> threading.Thread:
    runner = threading.Thread(target=vessel.run, kwargs={"duration_s": seconds}, daemon=True)
    runner.start()
    return runner


def _wait(condition, timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, what
        time.sleep(0.05)


def _restart(vehicle: StandInVehicle, relay: TcpRelay, down_wall_s: float = 1.5) -> None:
    """The autopilot restarts: its connection closes, no one answers for `down_wall_s`, then a fresh autopilot."""
    relay.drop()
    vehicle.reboot()
    time.sleep(down_wall_s)
    relay.restore()


def test_a_restarted_autopilot_is_brought_back_into_service_over_a_reopened_link(relayed) -> None:
    vehicle, relay = relayed
    vessel = Vessel(_config(relay.port), clock=ScaledWallClock(SCALE))
    texts = _said(vessel)
    runner = _run(vessel, 200.0)
    try:
        _wait(lambda: vehicle.vehicle.armed and vessel.stats.commands > 20, 20.0, "the vessel never drove")
        before = vehicle.position[0]
        errors_at_drop = vessel.stats.link_errors
        _restart(vehicle, relay)
        _wait(lambda: vessel.stats.restarts >= 1 and vehicle.vehicle.armed, 20.0, "the new autopilot was never armed")
        moved_from = vehicle.position[0]
        _wait(lambda: vehicle.position[0] > moved_from + 2.0, 20.0, "the vessel never drove after the restart")
    finally:
        vessel.stop()
        runner.join(10.0)
    stats = vessel.stats
    assert before > 0.5 and relay.connections == 2
    assert stats.link_reopens == 1 and stats.autopilot_reboots == 1 and stats.restarts == 1
    # said once, not at every read while the link was down
    assert stats.link_errors - errors_at_drop <= 2
    assert any("link lost" in t for t in texts) and any("link reopened" in t for t in texts)
    assert any("restarted (its clock since boot went from" in t for t in texts)
    assert any("back in service" in t for t in texts)


def test_with_recovery_off_a_restarted_autopilot_is_left_disarmed_at_neutral(relayed) -> None:
    vehicle, relay = relayed
    vessel = Vessel(_config(relay.port, recover_after_reboot=False), clock=ScaledWallClock(SCALE))
    texts = _said(vessel)
    runner = _run(vessel, 200.0)
    try:
        _wait(lambda: vehicle.vehicle.armed and vessel.stats.commands > 20, 20.0, "the vessel never drove")
        _restart(vehicle, relay)
        _wait(lambda: vessel.stats.autopilot_reboots == 1, 20.0, "the restart was never noticed")
        time.sleep(2.0)
        new = vehicle.vehicle
        assert not new.armed and vessel.stats.restarts == 0
        assert new.counters.idle > 0 and new.counters.commands == 0  # it hears our overrides, kept while disarmed
        np.testing.assert_allclose(new.actuator(vehicle.clock.now()), [0.0, 0.0], atol=1e-9)
    finally:
        vessel.stop()
        runner.join(10.0)
    assert any("neutral until it is armed again (no recovery)" in t for t in texts)


def test_a_vehicle_disarmed_by_someone_else_gets_neutral_and_is_not_armed_again(relayed) -> None:
    vehicle, relay = relayed
    vessel = Vessel(_config(relay.port), clock=ScaledWallClock(SCALE))
    texts = _said(vessel)
    runner = _run(vessel, 200.0)
    ground = Encoder(255, mavlink.MAV_COMP_ID_MISSIONPLANNER)  # a ground station's COMMAND_LONG, as bytes
    disarm = ground.pack(ground.mav.command_long_encode(1, 1, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, *[0] * 7))
    arm = ground.pack(ground.mav.command_long_encode(1, 1, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, *[0] * 6))
    try:
        _wait(lambda: vehicle.vehicle.armed and vessel.stats.commands > 20, 20.0, "the vessel never drove")
        vehicle.vehicle.receive(disarm, vehicle.clock.now())
        assert not vehicle.vehicle.armed
        _wait(lambda: any("disarmed" in t for t in texts), 5.0, "the disarm was not noticed")
        time.sleep(1.0)
        assert not vehicle.vehicle.armed, "the vessel armed a vehicle someone had disarmed"
        sent = [channels for _t, channels in list(vessel.autopilot.sent)[-5:]]
        assert all(abs(channels[3] - 1500) <= 1 for channels in sent), f"not neutral while disarmed: {sent}"
        vehicle.vehicle.receive(arm, vehicle.clock.now())
        x = vehicle.position[0]
        _wait(lambda: vehicle.position[0] > x + 1.0, 10.0, "the vessel did not drive once armed again")
    finally:
        vessel.stop()
        runner.join(10.0)
    assert any("armed again: driving" in t for t in texts)
    assert vessel.stats.autopilot_reboots == 0 and vessel.stats.restarts == 0


def test_the_session_counts_a_restart_when_the_autopilots_clock_goes_back() -> None:
    now = [0.0]
    session = AutopilotSession(1, BUOY, Encoder(1, 191), lambda: now[0])
    sender = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)

    def attitude(boot_s: float) -> None:
        message = sender.attitude_encode(round(boot_s * 1000), 0.0, 0.0, 0.5, 0.0, 0.0, 0.0)
        session.handle(mavlink.MAVLink(None).decode(bytearray(message.pack(sender))))

    for boot_s in (100.0, 100.2, 100.4):
        attitude(boot_s)
    attitude(100.4 - 0.9 * REBOOT_BACKSTEP_S)  # two streams slightly out of order: not a restart
    assert session.reboots == 0
    attitude(1.5)
    assert session.reboots == 1 and session.last_reboot == pytest.approx((100.4 - 0.9 * REBOOT_BACKSTEP_S, 1.5))
    attitude(1.7)
    assert session.reboots == 1


class PtyBridge(threading.Thread):
    """A serial port for the vessel: a pseudo-terminal reached through a stable path (as udev's /dev/serial/by-id/
    names a USB adapter), relayed to a UDP endpoint. `unplug()` closes it under the vessel and removes the path;
    `replug()` makes a new pseudo-terminal behind the same path."""

    def __init__(self, udp_port: int, path) -> None:
        super().__init__(daemon=True)
        self.target = ("127.0.0.1", udp_port)
        self.path = path
        self.udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.udp.bind(("127.0.0.1", 0))
        self.lock = threading.Lock()
        self.port = PluggedPty(path)
        self.running = True

    @property
    def master(self) -> int | None:
        return self.port.master

    def replug(self) -> None:
        with self.lock:
            self.port.replug()

    def unplug(self) -> None:
        with self.lock:
            self.port.unplug()

    def run(self) -> None:
        while self.running:
            with self.lock:
                fds = [self.udp] + ([self.master] if self.master is not None else [])
            ready, _, _ = select.select(fds, [], [], 0.05)
            with self.lock:
                try:
                    if self.udp in ready:
                        data = self.udp.recv(65535)
                        if self.master is not None:
                            os.write(self.master, data)
                    if self.master is not None and self.master in ready:
                        self.udp.sendto(os.read(self.master, 65535), self.target)
                except OSError:
                    pass  # nobody has the port open (EIO), or it was just unplugged

    def close(self) -> None:
        self.running = False
        self.join(2.0)
        if self.master is not None:
            self.unplug()
        self.udp.close()


def test_an_unplugged_serial_adapter_is_reopened_by_its_path_when_plugged_in_again(tmp_path) -> None:
    vehicle = StandInVehicle()
    vehicle.start()
    bridge = PtyBridge(vehicle.port, tmp_path / "ttyAUTOPILOT")
    bridge.start()
    config = replace(_config(0), vehicle=str(bridge.path), baud=57600)
    vessel = Vessel(config, clock=ScaledWallClock(SCALE))
    texts = _said(vessel)
    runner = _run(vessel, 200.0)
    try:
        _wait(lambda: vehicle.vehicle.armed and vessel.stats.commands > 20, 20.0, "the vessel never drove")
        bridge.unplug()
        _wait(lambda: any("link lost" in t for t in texts), 5.0, "the unplugged port went unnoticed")
        time.sleep(2.5)  # several reopen attempts fail: the path is gone
        errors_unplugged = vessel.stats.link_errors
        bridge.replug()
        _wait(lambda: vessel.stats.link_reopens == 1, 5.0, "the port was not reopened")
        x = vehicle.position[0]
        _wait(lambda: vehicle.position[0] > x + 1.0, 10.0, "the vessel did not drive after the port came back")
    finally:
        vessel.stop()
        runner.join(10.0)
        bridge.close()
        vehicle.close()
    assert errors_unplugged <= 2  # the loss counted once (a read and a write may both see it), not per attempt
    assert vessel.stats.autopilot_reboots == 0 and vessel.stats.restarts == 0  # the autopilot itself ran on
    assert any("link reopened after" in t for t in texts)


def test_a_vessel_that_loses_its_gps_fixes_holds_at_neutral_until_they_come_back() -> None:
    """The autopilot's GPS loses its fix (GPS_RAW_INT fix type 1, as ArduPilot sends it): in MANUAL the autopilot
    would go on driving whatever we send, on an estimate that only drifts. Before, the vessel drove on."""
    vehicle = StandInVehicle()
    vehicle.start()
    vessel = Vessel(replace(_config(0), vehicle=f"udpout:127.0.0.1:{vehicle.port}"), clock=ScaledWallClock(SCALE))
    texts = _said(vessel)
    runner = _run(vessel, 200.0)
    try:
        _wait(lambda: vehicle.vehicle.armed and vessel.stats.commands > 20, 20.0, "the vessel never drove")
        vehicle.no_fix.set()
        lost_at = vessel.clock.now()
        _wait(lambda: any("no GPS fix" in t for t in texts), 5.0, "the lost fixes went unnoticed")
        noticed = vessel.clock.now()
        noticed_after = noticed - lost_at
        # Counted from the last fix's own time, which may come up to a fix period (0.2 s) before the loss was set.
        since_last_fix = noticed - float(vessel.pipeline.last_fix_t[0])
        time.sleep(0.5)
        sent = [channels for _t, channels in list(vessel.autopilot.sent)[-5:]]
        assert all(abs(channels[3] - 1500) <= 1 and abs(channels[4] - 1500) <= 1 for channels in sent), (sent, texts)
        x = vehicle.position[0]
        time.sleep(0.5)
        assert abs(vehicle.position[0] - x) < 0.05, "the vehicle moved while its vessel was blind"
        vehicle.no_fix.clear()
        _wait(lambda: vehicle.position[0] > x + 1.0, 10.0, "the vessel did not drive once fixes came back")
    finally:
        vessel.stop()
        runner.join(10.0)
        vehicle.close()
    assert since_last_fix >= 5.0 and noticed_after < 7.0  # GPS_LOST_S, vessel-clock seconds
    assert vessel.stats.gps_outages == 1 and sum("GPS fixes back" in t for t in texts) == 1
    assert vessel.autopilot.fix_type == 3


def test_a_vessel_without_a_heading_holds_still_and_says_what_it_lacks() -> None:
    """An autopilot that sends no ATTITUDE: the EKF has a position but no heading (it would say 0 rad, east), and a
    buoy turning its thrust into the body frame by it would push the wrong way. The vessel holds at neutral, says
    after POSE_WAIT_S what it lacks, and drives once headings come."""
    vehicle = StandInVehicle()
    vehicle.no_attitude.set()
    vehicle.start()
    vessel = Vessel(replace(_config(0), vehicle=f"udpout:127.0.0.1:{vehicle.port}"), clock=ScaledWallClock(SCALE))
    texts = _said(vessel)
    runner = _run(vessel, 200.0)
    try:
        _wait(lambda: any("no compass heading" in t for t in texts), 20.0, "the missing heading went unsaid")
        assert vehicle.vehicle.armed and not vessel.pose_known
        assert not any("no GPS fix" in t for t in texts)
        sent = [channels for _t, channels in list(vessel.autopilot.sent)[-5:]]
        assert sent and all(abs(channels[3] - 1500) <= 1 and abs(channels[4] - 1500) <= 1 for channels in sent)
        x = vehicle.position[0]
        vehicle.no_attitude.clear()
        _wait(lambda: vehicle.position[0] > x + 1.0, 10.0, "the vessel did not drive once headings came")
    finally:
        vessel.stop()
        runner.join(10.0)
        vehicle.close()
    assert sum("position and heading known" in t for t in texts) == 1


@pytest.mark.parametrize(("line", "expected"), [("", True), ("recover_after_reboot = false", False)])
def test_recovery_after_a_reboot_is_a_setting_of_the_vessel_config_file(tmp_path, line: str, expected: bool) -> None:
    path = tmp_path / "vessel.toml"
    path.write_text(
        f'vehicle = "tcp:127.0.0.1:5760"\nsystem_id = 1\norigin = "1.0,2.0"\nbehavior = "bob-rule"\n{line}\n'
    )
    args = _apply_config_file(_parser(), ["run", "--config", str(path)])
    assert config_from_args(args).recover_after_reboot is expected
    args = _apply_config_file(_parser(), ["run", "--config", str(path), "--no-recover-after-reboot"])
    assert config_from_args(args).recover_after_reboot is False


def test_a_recovery_setting_that_is_not_a_boolean_is_refused_naming_it(tmp_path) -> None:
    path = tmp_path / "vessel.toml"
    path.write_text('vehicle = "tcp:127.0.0.1:5760"\nsystem_id = 1\norigin = "1.0,2.0"\nrecover_after_reboot = "no"\n')
    with pytest.raises(ValueError, match="setting 'recover_after_reboot' must be true or false, got 'no'"):
        _apply_config_file(_parser(), ["run", "--config", str(path)])


def test_the_gps_lag_is_a_setting_of_the_vessel_config_file_within_0_to_1_s(tmp_path) -> None:
    path = tmp_path / "vessel.toml"
    base = 'vehicle = "tcp:127.0.0.1:5760"\nsystem_id = 1\norigin = "1.0,2.0"\nbehavior = "bob-rule"\n'
    path.write_text(base + "gps_lag = 0.12\n")
    assert config_from_args(_apply_config_file(_parser(), ["run", "--config", str(path)])).gps_lag_s == 0.12
    path.write_text(base)
    assert config_from_args(_apply_config_file(_parser(), ["run", "--config", str(path)])).gps_lag_s is None
    for bad in ("-0.1", "2"):
        with pytest.raises(ValueError, match=rf"--gps-lag {float(bad)}: must be within 0..1 s"):
            _apply_config_file(_parser(), ["run", "--config", str(path), "--gps-lag", bad])


def test_a_telemetry_radio_shaken_loose_is_reopened_and_the_ground_station_hears_the_vessel_again(
    tmp_path, caplog
) -> None:
    """The ground-station link on a serial telemetry radio (a SiK on USB): unplugged, said once and nothing more
    at each loop; plugged in again behind the same path, reopened within a second and heard again."""
    vehicle = StandInVehicle()
    vehicle.start()
    ground = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    ground.bind(("127.0.0.1", 0))
    radio = PtyBridge(ground.getsockname()[1], tmp_path / "ttyRADIO")
    radio.start()
    config = replace(_config(0), vehicle=f"udpout:127.0.0.1:{vehicle.port}", gcs=str(radio.path), gcs_baud=57600)
    vessel = Vessel(config, clock=ScaledWallClock(SCALE))

    def heard(timeout_s: float) -> bool:
        """Whether a frame from the vessel reaches the ground station within timeout_s (anything older dropped)."""
        ground.setblocking(False)
        with contextlib.suppress(BlockingIOError):
            while ground.recv(65535):
                pass
        ground.settimeout(timeout_s)
        try:
            return bool(ground.recv(65535))
        except TimeoutError:
            return False

    runner = _run(vessel, 200.0)
    try:
        _wait(lambda: vehicle.vehicle.armed and vessel.stats.commands > 20, 20.0, "the vessel never drove")
        assert heard(2.0)
        radio.unplug()
        time.sleep(2.0)  # twenty loops, and several attempts to reopen a path that is gone
        assert not heard(0.5)
        errors_unplugged = vessel.stats.link_errors
        radio.replug()
        _wait(lambda: vessel.gcs_link.reopens == 1, 5.0, "the radio was not reopened")
        assert heard(3.0), "the ground station did not hear the vessel again"
        assert vehicle.vehicle.armed  # the vehicle drove on meanwhile
    finally:
        vessel.stop()
        runner.join(10.0)
        radio.close()
        vehicle.close()
        ground.close()
    assert errors_unplugged <= 2  # the loss counted once (a read and a write may both see it), not per loop
    said = [r.getMessage() for r in caplog.records if "ttyRADIO" in r.getMessage()]
    assert len(said) <= 3 and "lost" in said[0] and "reopened after" in said[-1], said
