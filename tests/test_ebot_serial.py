"""The eBot serial protocol client and its MAVLink bridge, over a real pseudo-terminal against the simulated eBot.

Everything here runs in real time (the simulated robot steps with the wall clock), kept short: waits are polls
with deadlines, and motion is checked against what the simulator itself integrated from the commands it got.
"""

from __future__ import annotations

import math
import os
import signal
import socket
import subprocess
import sys
import threading
import time
import tty

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_bridge import commands
from firmware_bridge.decoder import Battery, CommandAck, CompassReading, Heartbeat, ImuReading, TelemetryDecoder
from firmware_bridge.decoder import WheelDistance as WheelDistanceReading
from firmware_bridge.ebot_bridge import EbotMavlinkBridge
from firmware_bridge.ebot_serial import EbotProtocolError, EbotSerial, wheel_command
from firmware_bridge.links import LinkError, open_link
from sitl.vehicles.ebot_serial_sim import EbotSerialSim

pytestmark = [
    pytest.mark.skipif(sys.platform == "win32", reason="pseudo-terminals are POSIX"),
    pytest.mark.xdist_group("realtime"),  # real-time robot simulation: never beside the other real-time tests
]

MAX_WHEEL_MPS = 0.2  # the eBot's (and the simulator's) full wheel speed
SYSTEM_ID = 7


def exact_sim(**kwargs) -> EbotSerialSim:
    """A simulated eBot with noise-free sonars and light sensors."""
    kwargs.setdefault("range_spec", None)
    kwargs.setdefault("light_spec", None)
    return EbotSerialSim(**kwargs)


def wait_for(condition, timeout_s: float = 2.0, poll_s: float = 0.01) -> bool:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if condition():
            return True
        time.sleep(poll_s)
    return bool(condition())


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wheel_lines(sim: EbotSerialSim) -> list[bytes]:
    return [c.line for c in sim.commands() if c.line.startswith(b"8w")]


def commanded_motion(sim: EbotSerialSim) -> tuple[float, float]:
    """(forward distance m, turn rad) the simulator should have driven, from the wheel commands it received and
    when (its own clock), up to now; the truth differs only by wheel slip and step quantization."""
    left = right = 0.0
    t_prev, distance, turn = None, 0.0, 0.0
    for command in [*sim.commands(), None]:
        t = sim.t_s if command is None else command.t_s
        if t_prev is not None:
            distance += 0.5 * (left + right) * MAX_WHEEL_MPS * (t - t_prev)
            turn += (right - left) * MAX_WHEEL_MPS / sim.params.wheel_base_m * (t - t_prev)
        t_prev = t
        if command is None:
            break
        if command.line.startswith(b"8w"):
            left, right = (int(v) / 100.0 - 2.0 for v in command.line[2:-1].split(b";"))
        elif command.line == b"2H\n":
            left = right = 0.0
    return distance, turn


# -- the serial client against the simulated robot -------------------------------------------------------------


def test_handshake_starts_the_robot():
    with exact_sim() as sim, EbotSerial.connect(sim.device_path) as robot:
        assert robot.identity == "eBot-sim 1.0"
        assert sim.started
        lines = [c.line for c in sim.commands()]
        assert lines[:4] == [b"<<1?\n", b"<<1E\n", b"<<1O\n", b"F\n"]


def test_handshake_failures_name_the_port_and_what_came():
    with exact_sim(answer_handshake=False) as sim:
        with pytest.raises(EbotProtocolError) as info:
            EbotSerial.connect(sim.device_path, handshake_timeout_s=0.3)
        message = str(info.value)
        assert sim.device_path in message and "<<1?" in message and "received nothing" in message
    with exact_sim(identity="HELLO 2.1") as sim:
        with pytest.raises(EbotProtocolError, match=r"expected a line starting 'eB'; received b'HELLO 2.1'") as info:
            EbotSerial.connect(sim.device_path, handshake_timeout_s=0.3)
        assert sim.device_path in str(info.value)


def test_silent_port_times_out_queries_without_raising():
    master, slave = os.openpty()
    try:
        tty.setraw(slave)
        with EbotSerial(os.ttyname(slave), reply_timeout_s=0.1) as robot:
            start = time.monotonic()
            assert robot.pose() is None
            assert time.monotonic() - start < 1.0
            assert robot.counters.timeouts == 1
    finally:
        os.close(master)
        os.close(slave)


def test_each_query_parses_to_the_truth():
    with exact_sim(position=(0.6, 2.2), heading_rad=2.5) as sim, EbotSerial.connect(sim.device_path) as robot:
        x, y, heading = sim.pose()
        pose = robot.pose()
        assert pose is not None
        assert (pose.x_m, pose.y_m) == pytest.approx((x, y), abs=1e-3)
        assert pose.heading_rad == pytest.approx(heading, abs=1e-3)

        sonar = robot.sonar()
        truth = sim.sonar_truth_m()
        assert sonar is not None and len(sonar.ranges_m) == 6
        assert np.isfinite(truth).sum() >= 2  # the robot is near a corner: some sonars see walls
        np.testing.assert_allclose(sonar.ranges_m, truth, atol=1e-3)  # NaN (no echo) where the truth is NaN

        light = robot.light()
        assert light is not None
        assert (light.left, light.right) == pytest.approx(tuple(sim.light_truth() * 1000.0), abs=1.0)  # mW/m^2
        assert light.left != light.right  # the two sensors point differently

        imu = robot.imu()
        assert imu is not None
        assert imu.accel_mg == (0.0, 0.0, 1000.0) and imu.gyro_mradps == (0.0, 0.0, 0.0)  # level, at rest
        assert imu.accel_mps2[2] == pytest.approx(9.80665)

        power = robot.power()
        assert power is not None and power.voltage_v == pytest.approx(7.4, abs=1e-3)
        assert robot.counters.garbage == robot.counters.malformed == robot.counters.timeouts == 0


def test_garbage_and_malformed_lines_are_counted_and_skipped():
    with exact_sim() as sim, EbotSerial.connect(sim.device_path) as robot:
        sim.queue_noise([b"\xff\xfe\x00\x13junk\n", b"1;2;x\n", b"12;13\n", b"nan;1;2\n", b"A" * 400 + b"\n"])
        pose = robot.pose()
        assert pose is not None and pose.x_m == pytest.approx(1.0, abs=1e-3)
        assert robot.counters.garbage == 2  # not printable; too long
        assert robot.counters.malformed == 3  # not numbers; two fields for three; NaN
        sim.inject(b"4;5;6\n")  # unsolicited (e.g. a late reply): dropped before the next query
        assert wait_for(lambda: robot.port.in_waiting > 0)
        assert robot.power() is not None and robot.counters.stale_lines == 1
        assert robot.query("2Z", 1) is None and robot.counters.error_replies == 1  # the robot's "?2Z"
        assert robot.sonar() is not None  # and the stream is still in step


def test_wheel_speeds_are_sent_as_s_plus_2_times_100():
    cases = [
        ((1.0, -1.0), b"8w300;100\n"),
        ((0.0, 0.0), b"8w200;200\n"),
        ((0.5, -0.25), b"8w250;175\n"),
        ((0.123, -0.987), b"8w212;101\n"),
        ((math.nan, 3.0), b"8w200;300\n"),  # NaN -> 0; clipped
        ((-7.0, math.inf), b"8w100;200\n"),
    ]
    with exact_sim() as sim, EbotSerial.connect(sim.device_path) as robot:
        for (left, right), expected in cases:
            assert wheel_command(left, right) == expected
            assert robot.set_wheels(left, right) == expected
        robot.halt()
        assert wait_for(lambda: len(wheel_lines(sim)) == len(cases) + 1)
        assert wheel_lines(sim) == [expected for _, expected in cases] + [b"8w200;200\n"]
        assert b"2H\n" in [c.line for c in sim.commands()]
        assert sim.wheel_cmd == (0.0, 0.0)


def test_unplugged_port_raises_a_link_error():
    sim = exact_sim()
    robot = EbotSerial.connect(sim.device_path)
    try:
        sim.close()
        with pytest.raises(LinkError, match=sim.device_path):
            robot.pose()
        with pytest.raises(LinkError, match=sim.device_path):
            robot.set_wheels(0.5, 0.5)
    finally:
        robot.close()


# -- the MAVLink bridge, end to end over UDP ---------------------------------------------------------------------


class BridgeRun:
    """A simulated eBot, the bridge on udpin in a thread, and a MAVLink client on udpout."""

    def __init__(self, sim: EbotSerialSim | None = None, **bridge_kwargs) -> None:
        self.sim = exact_sim() if sim is None else sim
        self.robot = EbotSerial.connect(self.sim.device_path)
        port = free_udp_port()
        self.server = open_link(f"udpin:127.0.0.1:{port}")
        self.client = open_link(f"udpout:127.0.0.1:{port}")
        bridge_kwargs.setdefault("system_id", SYSTEM_ID)
        self.bridge = EbotMavlinkBridge(self.robot, self.server, **bridge_kwargs)
        self.decoder = TelemetryDecoder()
        self.readings: list = []
        self.error: BaseException | None = None
        self.stop = threading.Event()
        self.client.write(commands.heartbeat())  # udpin answers whoever spoke last: speak before it starts
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        try:
            self.bridge.run(self.stop)
        except BaseException as exc:  # handed to the test
            self.error = exc

    def send(self, frame: bytes) -> None:
        self.client.write(frame)

    def pump(self, duration_s: float) -> None:
        """Read telemetry for duration_s."""
        end = time.monotonic() + duration_s
        while time.monotonic() < end:
            data = self.client.read(65535, timeout_s=max(0.0, min(0.02, end - time.monotonic())))
            if data:
                self.readings.extend(self.decoder.feed(data))

    def latest(self, kind):
        found = [r for r in self.readings if isinstance(r, kind)]
        return found[-1] if found else None

    def arm(self) -> None:
        self.send(commands.command_long_arm(True, target_system=SYSTEM_ID))
        end = time.monotonic() + 2.0
        while time.monotonic() < end and not any(isinstance(r, CommandAck) for r in self.readings):
            self.pump(0.02)
        ack = self.latest(CommandAck)
        assert ack is not None and ack.command == mavlink.MAV_CMD_COMPONENT_ARM_DISARM
        assert ack.result == mavlink.MAV_RESULT_ACCEPTED

    def drive(self, left_mps: float, right_mps: float, duration_s: float, period_s: float = 0.1) -> None:
        end = time.monotonic() + duration_s
        while time.monotonic() < end:
            self.send(commands.rc_override_for_wheels(left_mps, right_mps, MAX_WHEEL_MPS, target_system=SYSTEM_ID))
            self.pump(min(period_s, max(0.0, end - time.monotonic())))

    def close(self) -> None:
        self.stop.set()
        self.thread.join(timeout=3.0)
        self.client.close()
        self.server.close()
        self.robot.close()
        self.sim.close()

    def __enter__(self) -> BridgeRun:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def test_rc_override_and_manual_control_come_out_as_the_same_wheel_commands():
    wheel_cases = [(0.1, 0.1), (0.2, -0.2), (0.05, 0.15), (-0.2, -0.1), (0.0, 0.0), (0.13, 0.07)]
    manual_cases = [(0.5, 0.0), (0.25, -0.5), (-1.0, 0.3)]
    with BridgeRun(failsafe_s=5.0) as run:
        run.send(commands.rc_override_for_wheels(0.1, 0.1, MAX_WHEEL_MPS, target_system=SYSTEM_ID))
        run.pump(0.2)
        assert wheel_lines(run.sim) == [] and run.bridge.counters.refused == 1  # not armed yet
        run.arm()
        expected = []
        for left, right in wheel_cases:
            run.send(commands.rc_override_for_wheels(left, right, MAX_WHEEL_MPS, target_system=SYSTEM_ID))
            expected.append(wheel_command(left / MAX_WHEEL_MPS, right / MAX_WHEEL_MPS))
            assert wait_for(lambda: len(wheel_lines(run.sim)) >= len(expected))
        for throttle, steering in manual_cases:
            run.send(commands.manual_control(throttle, steering, target_system=SYSTEM_ID))
            expected.append(wheel_command(throttle + steering, throttle - steering))
            assert wait_for(lambda: len(wheel_lines(run.sim)) >= len(expected))
        run.send(commands.rc_override_for_wheels(0.2, 0.2, MAX_WHEEL_MPS, target_system=SYSTEM_ID + 1))  # not us
        run.send(b"\xfd\x09\x00garbage" + b"\x00" * 20)  # noise on the MAVLink side: counted, not raised
        run.pump(0.2)
        assert wheel_lines(run.sim) == expected
        assert run.bridge.counters.ignored == 1 and run.bridge.decoder.counters.skipped_bytes > 0
        assert run.error is None


def test_bridge_drives_forward_and_turns_with_the_right_sign():
    with BridgeRun() as run:
        run.arm()
        x0, y0, h0 = run.sim.pose()
        run.drive(0.1, 0.1, 1.5)  # 0.1 m/s forward for 1.5 s
        run.send(commands.rc_override_for_wheels(0.0, 0.0, MAX_WHEEL_MPS, target_system=SYSTEM_ID))
        assert wait_for(lambda: run.sim.wheel_cmd == (0.0, 0.0))
        run.pump(0.3)  # telemetry of the stopped robot
        x1, y1, h1 = run.sim.pose()
        distance, turn = commanded_motion(run.sim)
        assert 0.12 < distance < 0.2  # about 1.5 s at 0.1 m/s, whatever the scheduling
        forward = (x1 - x0) * math.cos(h0) + (y1 - y0) * math.sin(h0)
        assert forward == pytest.approx(distance, rel=0.1, abs=0.005)
        assert abs(h1 - h0) < 0.1
        wheels = run.latest(WheelDistanceReading)
        assert wheels is not None
        np.testing.assert_allclose(wheels.distance_m[0], [forward, forward], atol=0.01)

        run.drive(-0.1, 0.1, 0.5)  # left back, right forward: counter-clockwise, heading grows
        run.send(commands.rc_override_for_wheels(0.0, 0.0, MAX_WHEEL_MPS, target_system=SYSTEM_ID))
        assert wait_for(lambda: run.sim.wheel_cmd == (0.0, 0.0))
        _, _, h2 = run.sim.pose()
        _, turn_total = commanded_motion(run.sim)
        ccw = turn_total - turn
        assert ccw > 0.5  # 2 rad/s for about 0.5 s
        assert math.remainder(h2 - h1, 2 * math.pi) == pytest.approx(ccw, rel=0.1, abs=0.05)

        run.drive(0.1, -0.1, 0.3)  # and clockwise
        run.send(commands.rc_override_for_wheels(0.0, 0.0, MAX_WHEEL_MPS, target_system=SYSTEM_ID))
        assert wait_for(lambda: run.sim.wheel_cmd == (0.0, 0.0))
        _, _, h3 = run.sim.pose()
        assert math.remainder(h3 - h2, 2 * math.pi) < -0.3
        assert run.error is None


def test_telemetry_decodes_to_the_truth():
    sim = exact_sim(position=(0.5, 2.0), heading_rad=2.0)
    with BridgeRun(sim) as run:
        raw: list = []
        parser = mavlink.MAVLink(None)
        wanted = {"HEARTBEAT", "ATTITUDE", "SCALED_IMU", "SYS_STATUS", "DISTANCE_SENSOR"}
        end = time.monotonic() + 3.0
        while time.monotonic() < end and not wanted <= {m.get_type() for m in raw}:
            data = run.client.read(65535, timeout_s=0.02)
            if data:
                run.readings.extend(run.decoder.feed(data))
                raw.extend(parser.parse_buffer(data) or [])
        for _ in range(20):
            data = run.client.read(65535, timeout_s=0.02)
            raw.extend(parser.parse_buffer(data) or [])
            run.readings.extend(run.decoder.feed(data))
        _, _, heading = sim.pose()

        beat = run.latest(Heartbeat)
        assert beat is not None and beat.system == SYSTEM_ID
        assert beat.mav_type == mavlink.MAV_TYPE_GROUND_ROVER and beat.autopilot == mavlink.MAV_AUTOPILOT_GENERIC
        assert not beat.armed

        compass = run.latest(CompassReading)
        assert compass is not None
        assert math.remainder(compass.heading_rad[0] - heading, 2 * math.pi) == pytest.approx(0.0, abs=math.radians(2))

        imu = run.latest(ImuReading)
        assert imu is not None
        np.testing.assert_allclose(imu.accel_body_mps2[0], [0.0, 0.0], atol=0.05)
        assert imu.gyro_z_radps[0] == pytest.approx(0.0, abs=0.01)
        scaled = [m for m in raw if m.get_type() == "SCALED_IMU"][-1]
        assert scaled.zacc == -1000  # z down: gravity reads -1 g at rest

        battery = run.latest(Battery)
        assert battery is not None and battery.voltage_v[0] == pytest.approx(7.4, abs=0.01)

        sonars = {m.id: m for m in raw if m.get_type() == "DISTANCE_SENSOR"}
        assert sorted(sonars) == [0, 1, 2, 3, 4, 5]
        for i, truth in enumerate(sim.sonar_truth_m()):
            reported = sonars[i].current_distance
            if math.isfinite(truth):
                assert reported == pytest.approx(truth * 100.0, abs=1.0)
            else:
                assert reported > sonars[i].max_distance  # no echo
        assert sonars[0].orientation == mavlink.MAV_SENSOR_ROTATION_NONE
        assert sonars[3].orientation == mavlink.MAV_SENSOR_ROTATION_YAW_180
        assert sonars[1].orientation == mavlink.MAV_SENSOR_ROTATION_CUSTOM  # 60 deg left
        assert math.degrees(2 * math.atan2(sonars[1].quaternion[3], sonars[1].quaternion[0])) == pytest.approx(-60)
        assert run.error is None


def test_failsafe_halts_the_robot_after_command_loss():
    with BridgeRun(failsafe_s=0.3) as run:
        run.arm()
        run.drive(0.1, 0.1, 0.2)
        run.send(commands.rc_override_for_wheels(0.1, 0.1, MAX_WHEEL_MPS, target_system=SYSTEM_ID))
        lost = time.monotonic()  # the last command is on its way
        assert wait_for(lambda: run.sim.wheel_cmd == (0.5, 0.5))
        assert wait_for(lambda: run.sim.wheel_cmd == (0.0, 0.0), timeout_s=2.0)
        assert 0.25 < time.monotonic() - lost < 1.5
        assert b"2H\n" in [c.line for c in run.sim.commands()]
        assert run.bridge.failsafe_active and run.bridge.counters.failsafes == 1
        x0, y0, _ = run.sim.pose()
        time.sleep(0.2)
        x1, y1, _ = run.sim.pose()
        assert math.hypot(x1 - x0, y1 - y0) < 1e-6  # it stays stopped
        run.drive(0.1, 0.1, 0.15)  # and a fresh command drives again
        assert wait_for(lambda: run.sim.wheel_cmd == (0.5, 0.5)) and not run.bridge.failsafe_active


def test_closing_the_pty_mid_run_ends_the_bridge_with_a_clear_error():
    with BridgeRun() as run:
        run.pump(0.2)
        start = time.monotonic()
        run.sim.close()
        run.thread.join(timeout=3.0)
        assert not run.thread.is_alive() and time.monotonic() - start < 2.0
        assert isinstance(run.error, LinkError)
        assert run.sim.device_path in str(run.error)


def test_command_line_runs_the_bridge_and_halts_on_sigterm():
    port = free_udp_port()
    with exact_sim() as sim:
        process = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "firmware_bridge.ebot_bridge",
                "--serial",
                sim.device_path,
                "--mavlink",
                f"udpin:127.0.0.1:{port}",
                "--system-id",
                str(SYSTEM_ID),
            ],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
        )
        try:
            assert wait_for(lambda: any(c.line == b"2P\n" for c in sim.commands()), timeout_s=10.0)
            process.send_signal(signal.SIGTERM)
            _, stderr = process.communicate(timeout=5.0)
        finally:
            if process.poll() is None:
                process.kill()
                process.wait()
        assert process.returncode == 0, stderr.decode()
        assert b"robot halted" in stderr
        assert [c.line for c in sim.commands()][-2:] == [b"2H\n", b"8w200;200\n"]
