"""Present an eBot (its own ASCII serial protocol) as a MAVLink ground rover: `EbotMavlinkBridge`, `bob-ebot-bridge`.

    bob-ebot-bridge --serial /dev/rfcomm0 --mavlink udpin:0.0.0.0:14550 --system-id 3

The bridge polls the robot over its serial port (`firmware_bridge.ebot_serial.EbotSerial`) and speaks MAVLink 2
(pymavlink, ardupilotmega dialect) on any link with write(bytes) / read(max_bytes, timeout_s) (`open_link`):

- out: HEARTBEAT (1 Hz; MAV_TYPE_GROUND_ROVER, MAV_AUTOPILOT_GENERIC, armed flag, Rover custom mode), and at
  `rate_hz` ATTITUDE (yaw from the pose heading), SCALED_IMU (mG, mrad/s, body x forward, y right, z down),
  WHEEL_DISTANCE (cumulative metres per wheel, from the robot's own pose), DISTANCE_SENSOR for each of the six
  sonars; at 1 Hz SYS_STATUS (battery voltage) and NAMED_VALUE_FLOAT "light_l", "light_r";
- in: RC_CHANNELS_OVERRIDE and MANUAL_CONTROL, mixed into wheel speeds exactly as
  `commands.rc_override_for_wheels` / `commands.manual_control` encode them (`commands.wheels_from_rc`,
  `commands.wheels_from_manual_control`); COMMAND_LONG arm/disarm and set mode (MANUAL, HOLD), answered with
  COMMAND_ACK.

Failsafe: when no drive command came for `failsafe_s` (default 1 s), the robot is sent `2H` and zero wheels;
so it is on disarming, on HOLD, and when the bridge stops. The full mapping: docs/ebot-serial.md.
Malformed MAVLink bytes are counted (`decoder.counters`), never raised; the robot's port failing raises
`LinkError` out of `run`.
"""

from __future__ import annotations

import argparse
import contextlib
import math
import signal
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Protocol

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_bridge import commands
from firmware_bridge.decoder import TelemetryDecoder, wrap_angle
from firmware_bridge.ebot_serial import EBOT_BAUD, EbotProtocolError, EbotSerial, ImuSample, Pose, wheel_command
from firmware_bridge.links import LinkError, open_link, parse_connection_string

__all__ = ["EBOT_SONAR_ANGLES_DEG", "BridgeCounters", "ByteLink", "EbotMavlinkBridge", "main"]

# Sonar axes, degrees counter-clockwise from forward, in the order `2S` reports them (the simulator's layout,
# sitl.vehicles.bodies.EBOT_SONAR_ANGLES_RAD): front, front-left, rear-left, rear, rear-right, front-right.
EBOT_SONAR_ANGLES_DEG = (0.0, 60.0, 120.0, 180.0, -120.0, -60.0)
SONAR_FOV_RAD = math.radians(60.0)
INT16_MAX = 32767
MODE_MANUAL = commands.ROVER_MODES["MANUAL"]
MODE_HOLD = commands.ROVER_MODES["HOLD"]


class ByteLink(Protocol):
    """What the bridge needs of a MAVLink transport (every `firmware_bridge.links.Link` is one)."""

    def write(self, data: bytes) -> None: ...

    def read(self, max_bytes: int = 4096, timeout_s: float = 0.0) -> bytes: ...


@dataclass
class BridgeCounters:
    """What the bridge has done: drive `commands` taken, commands `ignored` (another target system or component),
    `refused` (disarmed or in HOLD), COMMAND_LONGs `acked`, `failsafes` (halts for command loss),
    `wheel_lines` sent to the robot, telemetry `sent` (frames), `robot_no_reply` (queries with no valid reply),
    `link_write_errors` (MAVLink frames that could not be sent)."""

    commands: int = 0
    ignored: int = 0
    refused: int = 0
    acked: int = 0
    failsafes: int = 0
    wheel_lines: int = 0
    sent: int = 0
    robot_no_reply: int = 0
    link_write_errors: int = 0


def _int16(value: float) -> int:
    return int(max(-INT16_MAX, min(INT16_MAX, round(value))))


def _sensor_orientation(angle_deg: float) -> tuple[int, list[float]]:
    """MAV_SENSOR_ORIENTATION and quaternion (w, x, y, z; body FRD) of a sonar pointing angle_deg CCW from forward.
    MAVLink yaw is clockwise (about z down): a multiple of 45 deg has its own enum value, others are CUSTOM."""
    yaw_cw_deg = (-angle_deg) % 360.0
    half = math.radians(-angle_deg) / 2.0
    quaternion = [math.cos(half), 0.0, 0.0, math.sin(half)]
    steps = yaw_cw_deg / 45.0
    if abs(steps - round(steps)) < 1e-9:
        return mavlink.MAV_SENSOR_ROTATION_NONE + round(steps) % 8, quaternion
    return mavlink.MAV_SENSOR_ROTATION_CUSTOM, quaternion


class EbotMavlinkBridge:
    """One eBot presented as MAVLink system `system_id` (see the module docstring and docs/ebot-serial.md).

    robot: a connected (handshaken) EbotSerial; link: the MAVLink transport; component_id: ours
    (MAV_COMP_ID_AUTOPILOT1); failsafe_s: command silence (s) after which the robot halts; rate_hz: pose, IMU,
    sonar polling and telemetry rate; wheel_base_m: to split the pose's motion into wheel distances (m);
    sonar_angles_deg, sonar_min_m, sonar_max_m: the sonars as DISTANCE_SENSOR reports them; require_arming:
    drive commands are refused until armed (as ArduPilot does); clock: monotonic seconds.
    """

    def __init__(
        self,
        robot: EbotSerial,
        link: ByteLink,
        *,
        system_id: int = 1,
        component_id: int = mavlink.MAV_COMP_ID_AUTOPILOT1,
        failsafe_s: float = 1.0,
        rate_hz: float = 10.0,
        wheel_base_m: float = 0.1,
        sonar_angles_deg: Sequence[float] = EBOT_SONAR_ANGLES_DEG,
        sonar_min_m: float = 0.02,
        sonar_max_m: float = 1.5,
        require_arming: bool = True,
        resend_s: float = 0.25,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if not 1 <= system_id <= 255:
            raise ValueError(f"system_id must be 1..255, got {system_id}")
        if not (failsafe_s > 0 and rate_hz > 0 and wheel_base_m > 0):
            raise ValueError("failsafe_s, rate_hz and wheel_base_m must be positive")
        self.robot = robot
        self.link = link
        self.system_id = int(system_id)
        self.component_id = int(component_id)
        self.failsafe_s = float(failsafe_s)
        self.period_s = 1.0 / float(rate_hz)
        self.wheel_base_m = float(wheel_base_m)
        self.sonar_orientations = [_sensor_orientation(a) for a in sonar_angles_deg]
        self.sonar_min_cm = round(sonar_min_m * 100.0)
        self.sonar_max_cm = round(sonar_max_m * 100.0)
        self.require_arming = require_arming
        self.resend_s = float(resend_s)
        self.clock = clock
        self.counters = BridgeCounters()
        self.decoder = TelemetryDecoder(clock)  # framing and checksums of what comes in; counts what is bad
        self.encoder = commands.Encoder(self.system_id, self.component_id)

        self.armed = not require_arming
        self.custom_mode = MODE_MANUAL
        self.wheels = (0.0, 0.0)  # what the robot was last told, each in [-1, 1]
        self.failsafe_active = False
        self.wheel_distance_m = [0.0, 0.0]
        self.last_pose: Pose | None = None
        self.last_imu: ImuSample | None = None
        self._start_s = float(clock())
        self._last_command_s: float | None = None
        self._last_wheel_send_s = -math.inf
        self._last_wheel_line = b""
        self._next_fast_s = self._start_s
        self._next_slow_s = self._start_s
        self._next_heartbeat_s = self._start_s

    # -- the loop ------------------------------------------------------------------------------------------

    def run(self, stop: threading.Event | None = None, duration_s: float | None = None) -> None:
        """Step until `stop` is set (or duration_s has passed); the robot is halted on the way out. A failing
        robot port raises LinkError; a failing MAVLink link's read raises LinkError too."""
        end = math.inf if duration_s is None else float(self.clock()) + duration_s
        try:
            while not (stop is not None and stop.is_set()) and float(self.clock()) < end:
                self.step()
        finally:
            self.halt_quietly()

    def step(self, max_wait_s: float = 0.02) -> None:
        """Read what came on the MAVLink link (waiting at most max_wait_s or until telemetry is due), act on it,
        apply the failsafe, poll the robot and send the telemetry that is due."""
        now = float(self.clock())
        wait = max(0.0, min(max_wait_s, self._next_fast_s - now, self._next_heartbeat_s - now))
        data = self.link.read(4096, timeout_s=wait)
        if data:
            for message in self.decoder.feed_messages(data):
                self._handle(message)
        now = float(self.clock())
        if (
            not self.failsafe_active
            and self._last_command_s is not None
            and now - self._last_command_s > self.failsafe_s
        ):
            self.failsafe_active = True
            self.counters.failsafes += 1
            self._halt()
        if now >= self._next_heartbeat_s:
            self._next_heartbeat_s = max(self._next_heartbeat_s + 1.0, now)
            self._send(self._heartbeat())
        if now >= self._next_fast_s:
            self._next_fast_s = max(self._next_fast_s + self.period_s, now)
            self._poll_fast()
        if now >= self._next_slow_s:
            self._next_slow_s = max(self._next_slow_s + 1.0, now)
            self._poll_slow()

    def halt_quietly(self) -> None:
        """Halt the robot, ignoring a port that no longer works."""
        with contextlib.suppress(LinkError):
            self._halt()

    # -- commands in ---------------------------------------------------------------------------------------

    def _for_us(self, system: int, component: int | None, *, broadcast_ok: bool) -> bool:
        ok = system == self.system_id or (broadcast_ok and system == 0)
        if component is not None:
            ok = ok and component in (0, self.component_id)
        if not ok:
            self.counters.ignored += 1
        return ok

    def _handle(self, message) -> None:
        kind = message.get_type()
        if kind == "RC_CHANNELS_OVERRIDE":
            if self._for_us(message.target_system, message.target_component, broadcast_ok=False):
                self._drive(*commands.wheels_from_rc(message, 1.0))
        elif kind == "MANUAL_CONTROL":
            if self._for_us(message.target, None, broadcast_ok=False):
                self._drive(*commands.wheels_from_manual_control(message, 1.0))
        elif kind == "COMMAND_LONG" and self._for_us(
            message.target_system, message.target_component, broadcast_ok=True
        ):
            self._command_long(message)

    def _drive(self, left: float, right: float) -> None:
        """A drive command: wheel speeds in [-1, 1] of full speed."""
        now = float(self.clock())
        if (self.require_arming and not self.armed) or self.custom_mode == MODE_HOLD:
            self.counters.refused += 1
            return
        self.counters.commands += 1
        self._last_command_s = now
        self.failsafe_active = False
        line = wheel_command(left, right)
        if line != self._last_wheel_line or now - self._last_wheel_send_s >= self.resend_s:
            self._last_wheel_line = self.robot.set_wheels(left, right)
            self.wheels = self.robot.last_wheels
            self._last_wheel_send_s = now
            self.counters.wheel_lines += 1

    def _halt(self) -> None:
        self.wheels = (0.0, 0.0)
        self._last_wheel_line = wheel_command(0.0, 0.0)
        self._last_wheel_send_s = float(self.clock())
        self.robot.halt()

    def _command_long(self, message) -> None:
        command = message.command
        if command == mavlink.MAV_CMD_COMPONENT_ARM_DISARM:
            arm = message.param1 >= 0.5
            if not arm:
                self._last_command_s = None
                self._halt()
            self.armed = arm or not self.require_arming
            result = mavlink.MAV_RESULT_ACCEPTED
        elif command == mavlink.MAV_CMD_DO_SET_MODE:
            mode = round(message.param2)
            if mode in (MODE_MANUAL, MODE_HOLD):
                self.custom_mode = mode
                if mode == MODE_HOLD:
                    self._last_command_s = None
                    self._halt()
                result = mavlink.MAV_RESULT_ACCEPTED
            else:
                result = mavlink.MAV_RESULT_UNSUPPORTED
        else:
            result = mavlink.MAV_RESULT_UNSUPPORTED
        self.counters.acked += 1
        ack = self.encoder.mav.command_ack_encode(
            command, result, 0, 0, message.get_srcSystem(), message.get_srcComponent()
        )
        self._send(ack)

    # -- telemetry out -----------------------------------------------------------------------------------------

    def _send(self, message) -> None:
        try:
            self.link.write(self.encoder.pack(message))
            self.counters.sent += 1
        except LinkError:
            self.counters.link_write_errors += 1

    def _boot_ms(self) -> int:
        return int((float(self.clock()) - self._start_s) * 1000.0) & 0xFFFFFFFF

    def _heartbeat(self):
        base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | mavlink.MAV_MODE_FLAG_MANUAL_INPUT_ENABLED
        if self.armed:
            base |= mavlink.MAV_MODE_FLAG_SAFETY_ARMED
        state = mavlink.MAV_STATE_ACTIVE if self.armed else mavlink.MAV_STATE_STANDBY
        return self.encoder.mav.heartbeat_encode(
            mavlink.MAV_TYPE_GROUND_ROVER, mavlink.MAV_AUTOPILOT_GENERIC, base, self.custom_mode, state
        )

    def _poll_fast(self) -> None:
        mav = self.encoder.mav
        pose = self.robot.pose()
        imu = self.robot.imu()
        sonar = self.robot.sonar()
        self.counters.robot_no_reply += (pose is None) + (imu is None) + (sonar is None)
        boot_ms = self._boot_ms()
        if imu is not None:
            self.last_imu = imu
            ax, ay, az = imu.accel_mg
            gx, gy, gz = imu.gyro_mradps
            # eBot body x forward, y left, z up -> MAVLink x forward, y right, z down.
            self._send(
                mav.scaled_imu_encode(
                    boot_ms, _int16(ax), _int16(-ay), _int16(-az), _int16(gx), _int16(-gy), _int16(-gz), 0, 0, 0
                )
            )
        if pose is not None:
            self._integrate_wheels(pose)
            rates = (0.0, 0.0, 0.0)
            if self.last_imu is not None:
                gx, gy, gz = self.last_imu.gyro_radps
                rates = (gx, -gy, -gz)
            yaw = wrap_angle(math.pi / 2.0 - pose.heading_rad)  # from north, clockwise
            self._send(mav.attitude_encode(boot_ms, 0.0, 0.0, yaw, *rates))
            distance = [self.wheel_distance_m[0], self.wheel_distance_m[1]] + [0.0] * 14
            self._send(mav.wheel_distance_encode(boot_ms * 1000, 2, distance))
        if sonar is not None:
            for i, (range_m, (orientation, quaternion)) in enumerate(
                zip(sonar.ranges_m, self.sonar_orientations, strict=False)
            ):
                current = self.sonar_max_cm + 1 if not math.isfinite(range_m) else round(range_m * 100.0)
                self._send(
                    mav.distance_sensor_encode(
                        boot_ms,
                        self.sonar_min_cm,
                        self.sonar_max_cm,
                        min(current, 65535),
                        mavlink.MAV_DISTANCE_SENSOR_ULTRASOUND,
                        i,
                        orientation,
                        255,
                        SONAR_FOV_RAD,
                        SONAR_FOV_RAD,
                        quaternion,
                    )
                )

    def _integrate_wheels(self, pose: Pose) -> None:
        """Wheel distances (m) from the robot's own pose: the forward motion along the mid heading, split by the
        heading change over the wheel base (left = ds - dth * b / 2, right = ds + dth * b / 2)."""
        previous, self.last_pose = self.last_pose, pose
        if previous is None:
            return
        turn = wrap_angle(pose.heading_rad - previous.heading_rad)
        mid = previous.heading_rad + 0.5 * turn
        forward = (pose.x_m - previous.x_m) * math.cos(mid) + (pose.y_m - previous.y_m) * math.sin(mid)
        half = 0.5 * turn * self.wheel_base_m
        self.wheel_distance_m[0] += forward - half
        self.wheel_distance_m[1] += forward + half

    def _poll_slow(self) -> None:
        mav = self.encoder.mav
        power = self.robot.power()
        light = self.robot.light()
        self.counters.robot_no_reply += (power is None) + (light is None)
        if power is not None:
            errors = (self.robot.counters.garbage + self.robot.counters.malformed) & 0xFFFF
            millivolts = min(65534, max(0, round(power.voltage_v * 1000.0)))
            self._send(mav.sys_status_encode(0, 0, 0, 0, millivolts, -1, -1, 0, errors, 0, 0, 0, 0))
        if light is not None:
            boot_ms = self._boot_ms()
            self._send(mav.named_value_float_encode(boot_ms, b"light_l", float(light.left)))
            self._send(mav.named_value_float_encode(boot_ms, b"light_r", float(light.right)))


# -- the command ---------------------------------------------------------------------------------------------


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="bob-ebot-bridge",
        description="Present an eBot (its ASCII serial protocol) as a MAVLink ground rover (docs/ebot-serial.md).",
    )
    parser.add_argument("--serial", required=True, help="the eBot's serial device, e.g. /dev/ttyUSB0 or /dev/rfcomm0")
    parser.add_argument("--baud", type=int, default=EBOT_BAUD, help="serial baud rate (default 115200)")
    parser.add_argument(
        "--mavlink",
        default="udpin:0.0.0.0:14550",
        type=_one_peer_link,
        help="MAVLink link: udpin:/udpout:/tcp:HOST:PORT or a device",
    )
    parser.add_argument("--system-id", type=int, default=1, help="our MAVLink system id (default 1)")
    parser.add_argument("--failsafe-s", type=float, default=1.0, help="halt after this long without commands (s)")
    parser.add_argument("--rate-hz", type=float, default=10.0, help="telemetry and polling rate (Hz, default 10)")
    parser.add_argument("--wheel-base-m", type=float, default=0.1, help="wheel base for WHEEL_DISTANCE (m)")
    parser.add_argument("--handshake-timeout-s", type=float, default=3.0, help="handshake timeout (s)")
    parser.add_argument("--no-arming", action="store_true", help="drive without being armed first")
    return parser


def _one_peer_link(connection: str) -> str:
    """argparse type of --mavlink: a link to one peer (a broadcast link would take commands from every host)."""
    try:
        kind = parse_connection_string(connection)[0]
    except LinkError as error:
        raise argparse.ArgumentTypeError(str(error)) from None
    if kind == "udpbcast":
        raise argparse.ArgumentTypeError(f"{connection!r}: udpbcast is for a swarm's mesh, not a vehicle's link")
    return connection


def main(argv: Sequence[str] | None = None) -> int:
    """`bob-ebot-bridge`: exit status 0 after Ctrl-C / SIGTERM (the robot halted), 1 when the robot or the link
    fails, 2 for bad arguments."""
    args = _parser().parse_args(argv)
    stop = threading.Event()

    def request_stop(signum: int, _frame: object) -> None:
        stop.set()

    previous = {sig: signal.signal(sig, request_stop) for sig in (signal.SIGINT, signal.SIGTERM)}
    robot: EbotSerial | None = None
    link = None
    try:
        robot = EbotSerial.connect(args.serial, args.baud, handshake_timeout_s=args.handshake_timeout_s)
        link = open_link(args.mavlink)
        bridge = EbotMavlinkBridge(
            robot,
            link,
            system_id=args.system_id,
            failsafe_s=args.failsafe_s,
            rate_hz=args.rate_hz,
            wheel_base_m=args.wheel_base_m,
            require_arming=not args.no_arming,
        )
        print(
            f"bob-ebot-bridge: {robot.identity!r} on {args.serial} is MAVLink system {args.system_id} on "
            f"{args.mavlink}",
            file=sys.stderr,
        )
        bridge.run(stop)
        print(f"bob-ebot-bridge: stopped, robot halted ({bridge.counters})", file=sys.stderr)
        return 0
    except (LinkError, EbotProtocolError, ValueError) as exc:
        print(f"bob-ebot-bridge: {exc}", file=sys.stderr)
        return 1
    finally:
        if link is not None:
            link.close()
        if robot is not None:
            robot.close()
        for sig, handler in previous.items():
            signal.signal(sig, handler)


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
