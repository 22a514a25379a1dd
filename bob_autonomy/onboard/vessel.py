"""The on-vessel autonomy process: one agent driving one MAVLink vehicle, talking to its swarm over a mesh.

Each control period (dt_s): drain the vehicle link (telemetry decoded by
firmware_bridge, fused by the estimator) and the ground-station link (the
MAVLink component of `bob_autonomy.ground.gcs`: parameters, commands, missions),
step the agent (listen to the mesh, run the behaviour the parameters select on
the estimate, broadcast the state at the mesh rate), pass the wish through the
supervisor (start/stop, geofence, ground-station loss), turn it into an
actuator command (MPC or proportional) and send it as RC_CHANNELS_OVERRIDE. A
HEARTBEAT goes to the vehicle every second. If the vehicle goes silent the
vessel commands neutral and raises an alarm (logged, counted, STATUSTEXT); one
bad message never stops the loop. On stop the thrusters or wheels are left at
zero. Every MAVLink frame in or out can be logged to a .tlog.
"""

from __future__ import annotations

import json
import logging
import math
import statistics
import threading
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from behaviors.base import Senses
from behaviors.collision_avoidance import collision_layer
from bob_autonomy.control.motorboat_control import MotorboatModel
from bob_autonomy.control.velocity_control import BuoyModel
from bob_autonomy.core.agent import Agent
from bob_autonomy.core.behavior_config import BehaviorChoice
from bob_autonomy.core.clock import ScaledWallClock
from bob_autonomy.core.geodesy import LocalFrame
from bob_autonomy.core.interfaces import AgentState, Pose
from bob_autonomy.ground.gcs import GcsComponent, load_signing_key
from bob_autonomy.ground.params import ParameterStore
from bob_autonomy.ground.supervisor import Supervisor, behavior_params
from bob_autonomy.network.mesh import LinkMesh
from bob_autonomy.onboard.autopilot import MOTORBOAT, AutopilotSession
from bob_autonomy.onboard.autopilot_start import AutopilotStarter, AutopilotStartError, NoHeartbeatError, StartOptions
from bob_autonomy.onboard.pipeline import BuoyPipeline, EbotPipeline
from bob_autonomy.onboard.senses import EbotSenses
from bob_autonomy.onboard.vehicle_link import BUOY, EBOT, VehicleLink
from bob_autonomy.onboard.vessel_driving import AutopilotDriving
from bob_autonomy.onboard.vessel_links import VesselLinks
from bob_autonomy.onboard.vessel_pipelines import buoy_pipeline, ebot_pipeline, motorboat_pipeline
from firmware_bridge.commands import heartbeat
from firmware_bridge.links import Link, ReopeningLink, UdpBroadcastLink, open_link, parse_connection_string
from firmware_bridge.tlog import TlogWriter

logger = logging.getLogger(__name__)


class VehicleError(RuntimeError):
    """The vehicle cannot be driven (never answered, refused to arm); the message says which and why."""


ON_STOP_ACTIONS = ("neutral", "hold", "disarm")
STOP_LINGER_S = 0.6  # wall seconds of neutral commands, read while sent, before the links close
RESTART_RETRY_S = 10.0  # wall seconds between start-ups of a restarted autopilot that would not come into service
# A buoy or motorboat that had a position and has had no GPS fix for this long (s) is held at neutral: its estimate
# only drifts without fixes, and the autopilot, in MANUAL, would drive on whatever we send.
GPS_LOST_S = 5.0
POSE_WAIT_S = 5.0  # vessel-clock s after the start-up without a position or a heading before the vessel says so


@dataclass(frozen=True)
class EbotConfig:
    """What the autonomy knows of an eBot: wheel base m, top wheel speed m/s, encoder travel per tick m, and the
    bearing of each sonar from the forward axis (deg, counter-clockwise)."""

    wheel_base_m: float = 0.1
    max_wheel_speed_mps: float = 0.2
    metres_per_tick: float = 2.0 * math.pi * 0.03 / 360
    sonar_angles_deg: tuple[float, ...] = (0.0, 60.0, 120.0, 180.0, -120.0, -60.0)  # by DISTANCE_SENSOR id


@dataclass(frozen=True)
class VesselConfig:
    """Everything one autonomy process needs (units: m, s, rad, deg for latitude and longitude)."""

    vehicle: str
    system_id: int
    behavior: BehaviorChoice
    origin: tuple[float, float]
    kind: str = BUOY
    mesh: str | None = None
    mesh_baud: int = 115200  # a serial mesh's (an XBee's) baud rate
    memory_fields: tuple[str, ...] = ()
    time_scale: float = 1.0
    dt_s: float = 0.1
    broadcast_period_s: float = 0.1
    neighbor_expiry_s: float = 1.0
    estimator: str = "ekf"
    controller: str = "mpc"
    start_pose: tuple[float, float, float] = (0.0, 0.0, 0.0)
    max_thrust_fraction: float = 1.0
    heartbeat_timeout_s: float = 3.0
    arm_timeout_s: float = 10.0
    baud: int = 57600  # the vehicle link's, on a serial port: ArduPilot's TELEM ports' factory rate (SERIALn_BAUD 57)
    ebot: EbotConfig = field(default_factory=EbotConfig)
    gcs: str | None = None
    gcs_baud: int = 57600  # a serial ground-station link's (a SiK telemetry radio's factory rate)
    params_file: str | None = None
    signing_key_file: str | None = None
    mesh_key_file: str | None = None  # the swarm's fleet key (bob_autonomy.network.mesh_auth; may be the signing key)
    autostart: bool = True
    tlog: str | None = None
    autopilot: StartOptions = field(default_factory=StartOptions)
    on_stop: str = "neutral"
    # An autopilot that restarts under us (brownout, watchdog, reboot command) comes back disarmed: set it up and
    # arm it again (True), or hold at neutral until someone arms it (False).
    recover_after_reboot: bool = True
    top_speed_mps: float | None = None
    # The lag from a GPS measurement to the autopilot reading it, s: fixes are fused that much before the time the
    # autopilot stamps them. None: the autopilot's GPS1_DELAY_MS when set, else 0.
    gps_lag_s: float | None = None

    @property
    def agent_id(self) -> int:
        return self.system_id - 1


def _lasting_link(connection: str, baud: int) -> ReopeningLink:
    """A link that comes back after a failure: a serial port or TCP connection reopened, a UDP socket kept."""
    udp = parse_connection_string(connection)[0].startswith("udp")
    return ReopeningLink(lambda: open_link(connection, baud), keep_open=udp)


class ThrottledMesh:
    """A mesh that sends at most one state per `period_s` (the radio's budget); receiving is unthrottled."""

    def __init__(self, inner: LinkMesh, period_s: float) -> None:
        self.inner, self.period_s = inner, period_s
        self._next_s = -math.inf

    def broadcast(self, state: AgentState) -> None:
        if state.t >= self._next_s:
            self._next_s = state.t + self.period_s - 1e-9
            self.inner.broadcast(state)

    def receive(self) -> list[AgentState]:
        return self.inner.receive()


class SilentMesh:
    """No radio: the agent acts alone."""

    def broadcast(self, state: AgentState) -> None:
        pass

    def receive(self) -> list[AgentState]:
        return []


class MavlinkBody:
    """The Body of an agent whose vehicle is reached over MAVLink: pose from the vessel's own estimator, senses
    from the decoded range and light telemetry (eBots; buoys sense neither)."""

    def __init__(
        self, pipeline: BuoyPipeline | EbotPipeline, clock: ScaledWallClock, sensing: EbotSenses | None = None
    ) -> None:
        self.pipeline, self.clock, self.sensing = pipeline, clock, sensing
        self.wish_velocity = np.zeros(2)
        self.wish_heading = math.nan

    def pose(self) -> Pose:
        e = self.pipeline.estimate(self.clock.now())
        return Pose(*e.position[0], float(e.heading[0]), *e.velocity[0])

    def senses(self) -> Senses:
        if self.sensing is None:
            return Senses(obstacles=np.full((1, 0, 2), np.nan), light=np.full((1, 2), np.nan))
        now = self.clock.now()
        return self.sensing.senses(float(self.pipeline.estimate(now).heading[0]), now)

    def command(self, velocity_mps: np.ndarray, heading_rad: float) -> None:
        self.wish_velocity = np.nan_to_num(np.asarray(velocity_mps, dtype=float).reshape(2))
        self.wish_heading = float(heading_rad)


@dataclass
class VesselStats:
    """Counters and timings of one autonomy process (latencies in wall seconds)."""

    ticks: int = 0
    commands: int = 0
    readings: int = 0
    link_errors: int = 0
    reading_errors: int = 0
    step_errors: int = 0
    silent_alarms: int = 0
    link_reopens: int = 0  # the vehicle link lost (TCP closed, serial port gone) and opened again
    autopilot_reboots: int = 0  # the autopilot's clock since boot went back: it restarted under us
    restarts: int = 0  # start-ups run again after a reboot (bob_autonomy.onboard.autopilot_start)
    gps_outages: int = 0  # times the GPS fixes stopped for GPS_LOST_S while driving
    routed_to_gcs: int = 0
    routed_to_vehicle: int = 0
    estimator_resets: int = 0
    mpc_fallbacks: int = 0  # control steps whose MPC fell back to the proportional command (bob_autonomy.control.mpc)
    # Behaviour updates whose wish collision avoidance changed, of those it saw (behaviors.collision_avoidance; the
    # behaviour in use at the end: a rebuild from new parameters starts them again).
    collision_interventions: int = 0
    collision_updates: int = 0
    # IMU readings levelled with the hull's attitude, and those that came with none near them (taken as level);
    # fixes from an offset antenna that came with no attitude to move them by (bob_autonomy.estimation.tilt).
    imu_levelled: int = 0
    imu_unlevelled: int = 0
    antenna_unplaced: int = 0
    compute_latency_s: list[float] = field(default_factory=list)
    telemetry_to_command_s: list[float] = field(default_factory=list)
    gcs: dict[str, int] = field(default_factory=dict)  # the GCS component's rejected-input counters, at the end
    # The vehicle link's decoder counters at the end (bad_crc, malformed, no_fix, repeated_fix, ...; those not 0).
    vehicle_link: dict[str, int] = field(default_factory=dict)

    def summary(self) -> dict[str, float]:
        out: dict[str, float] = {k: v for k, v in vars(self).items() if isinstance(v, int)}
        out.update({f"gcs_{name}": value for name, value in self.gcs.items()})
        out.update({f"vehicle_link_{name}": value for name, value in self.vehicle_link.items()})
        for name in ("compute_latency_s", "telemetry_to_command_s"):
            values = sorted(getattr(self, name))
            if values:
                out[f"{name}_median"] = statistics.median(values)
                out[f"{name}_p99"] = values[min(len(values) - 1, int(0.99 * len(values)))]
        return out


class Vessel(VesselLinks, AutopilotDriving):
    """One autonomy process: vehicle link, estimator and controller, agent and mesh. `run()` until `stop()`."""

    def __init__(self, config: VesselConfig, clock: ScaledWallClock | None = None) -> None:
        self.config = config
        self.clock = clock or ScaledWallClock(config.time_scale)
        c = config
        if c.on_stop not in ON_STOP_ACTIONS:
            raise ValueError(f"on_stop must be one of {', '.join(ON_STOP_ACTIONS)}, got {c.on_stop!r}")
        for role, connection in (("vehicle", c.vehicle), ("ground-station", c.gcs)):
            if connection and parse_connection_string(connection)[0] == "udpbcast":
                raise ValueError(
                    f"{role} link {connection!r}: udpbcast is for the swarm's mesh only (--mesh); a {role} link "
                    "talks to one peer: use udpout:HOST:PORT, udpin:HOST:PORT, tcp:HOST:PORT or a serial device"
                )
        if c.kind == BUOY:
            model = BuoyModel() if c.top_speed_mps is None else BuoyModel.for_top_speed(c.top_speed_mps)
            self.max_actuator = model.max_thrust_n
            self.pipeline: BuoyPipeline | EbotPipeline = buoy_pipeline(c, model)
        elif c.kind == EBOT:
            self.max_actuator = c.top_speed_mps or c.ebot.max_wheel_speed_mps
            self.pipeline = ebot_pipeline(c, self.max_actuator)
        elif c.kind == MOTORBOAT:
            self.max_actuator = 1.0  # (throttle, steering), each in [-1, 1]
            self.pipeline = motorboat_pipeline(c, MotorboatModel.for_top_speed(c.top_speed_mps or 2.0))
        else:
            raise ValueError(f"unknown vehicle kind {c.kind!r}; choose buoy, motorboat or ebot")
        self.frame = LocalFrame(*c.origin)
        fresh = c.params_file is None or not Path(c.params_file).exists()
        self.params = ParameterStore(c.params_file)
        if fresh or self.params.load_problem:  # a new vessel (or one whose file was set aside as corrupt)
            # starts from its configured behaviour; later the stored parameters rule
            self.params.set_many(behavior_params(c.behavior, self.frame))
            goal = c.behavior.params.get("goal")
            if goal is not None:
                self.params.set_goals([tuple(float(v) for v in self.frame.to_geodetic(goal[0], goal[1]))])
        key = load_signing_key(c.signing_key_file) if c.signing_key_file else None
        self.gcs = GcsComponent(c.system_id, self.params, signing_key=key, clock=self.clock.now)
        self.gcs.behavior_running = c.autostart
        self.supervisor = Supervisor(self.params, c.behavior, self.frame)
        self.tlog = TlogWriter(c.tlog) if c.tlog else None
        self.vehicle_link: Link = open_link(c.vehicle, c.baud)
        telemetry_kind = BUOY if c.kind == MOTORBOAT else c.kind  # a motorboat's telemetry is a buoy's
        self.vehicle = VehicleLink(
            c.system_id,
            telemetry_kind,
            self.max_actuator,
            self.clock.now,
            heartbeat_timeout_s=c.heartbeat_timeout_s,
            gps_lag_s=c.gps_lag_s or 0.0,
        )
        self.autopilot = AutopilotSession(
            c.system_id, c.kind, self.vehicle.encoder, self.clock.now, estimator=c.estimator
        )
        self.vehicle.decoder.message_hook = self._vehicle_message
        # A radio shaken loose from its USB socket (an XBee, a SiK telemetry radio), or an IP radio's interface down,
        # comes back by itself (firmware_bridge.links.ReopeningLink).
        self.gcs_link = _lasting_link(c.gcs, c.gcs_baud) if c.gcs else None
        self.mesh_link = _lasting_link(c.mesh, c.mesh_baud) if c.mesh else None
        mesh_key = load_signing_key(c.mesh_key_file) if c.mesh_key_file else None  # same file format
        if isinstance(self.mesh_link and self.mesh_link.link, UdpBroadcastLink) and mesh_key is None:
            logger.warning(
                "mesh %s is open: any host on that network can broadcast as a member of the swarm; give the "
                "fleet key with --mesh-key (docs/mesh.md)",
                c.mesh,
            )
        network = (
            ThrottledMesh(
                LinkMesh(self.mesh_link, c.agent_id, c.memory_fields, self.clock.now, key=mesh_key),
                c.broadcast_period_s,
            )
            if self.mesh_link is not None
            else SilentMesh()
        )
        self.network = network
        self.sensing = EbotSenses(np.radians(c.ebot.sonar_angles_deg)) if c.kind == EBOT else None
        self.body = MavlinkBody(self.pipeline, self.clock, self.sensing)
        self.agent = Agent(c.agent_id, self.body, network, self.supervisor.behavior(), self.clock, c.neighbor_expiry_s)
        self._hearing_problem: str | None = None  # the last one said
        self._say_hearing_problem()
        self.stats = VesselStats()
        self._stop = threading.Event()
        self._next_heartbeat_s = -math.inf
        self._last_reading_wall_s: float | None = None
        self._alarm = False
        self.pose_known = False
        self._obeying = True
        self._from_vehicle: list[bytes] = []  # the vehicle's frames waiting for the next ground-station write
        self._forwarded = []  # a ground station's commands passed on to the autopilot, not yet answered
        self._hold_heading = False
        self._heading_ref: float | None = None
        self._ignoring_since: float | None = None
        self._ignoring_warned = False
        self._link_lost_at: float | None = None
        self._next_reopen_at = 0.0
        self._armed_seen: bool | None = None
        self._reboots_seen = 0
        self._param_changes_seen = 0
        self._thrust_fraction_asked = c.max_thrust_fraction  # --max-thrust-fraction: MOT_THR_MAX may only lower it
        self._restart_due: float | None = None  # wall clock (time.monotonic) of the next start-up after a reboot
        self._gps_lost = False
        self._pose_wait_said = False  # said that the vessel holds still for want of a position or a heading
        self._driving_since = -math.inf  # clock s: when the (last) start-up ended; the first fix is due after it

    # -- link ------------------------------------------------------------------------------------------

    def _report_position(self, now: float) -> None:
        """The estimate to the ground station, once it holds a position (an EKF without a fix says (0, 0): a ground
        station would show the vessel at the frame's origin), its heading once a compass set it (else unknown);
        after a filter reset the last report stands."""
        e = self.pipeline.estimate(now)
        if self.pipeline.position_known(now).all():
            lat, lon = self.frame.to_geodetic(e.position[0, 0], e.position[0, 1])
            vx, vy = e.velocity[0]
            heading = float(e.heading[0]) if self.pipeline.heading_known(now).all() else None
            self.gcs.report_position(float(lat), float(lon), float(vx), float(vy), heading)

    def _check_estimate(self, now: float) -> None:
        """A diverged estimate (non-finite, or far from the newest GPS fix) is reset and reported; the vessel is
        held at neutral until a fix sets the estimate again."""
        if not isinstance(self.pipeline, BuoyPipeline) or not self.pipeline.diverged(now).any():
            return
        e = self.pipeline.estimate(now)
        self.pipeline.reset()
        self.pose_known = False
        self.stats.estimator_resets += 1
        text = (
            f"vessel {self.config.system_id}: position estimate diverged ({e.position[0, 0]:.3g}, "
            f"{e.position[0, 1]:.3g}) m against the GPS fix; filter reset ({self.stats.estimator_resets} so far)"
        )
        self._say(mavlink.MAV_SEVERITY_ERROR, text)

    def _heartbeat(self, now: float) -> None:
        if now >= self._next_heartbeat_s:
            self._next_heartbeat_s = now + self.config.time_scale  # one wall second
            self._send(heartbeat(encoder=self.autopilot.encoder))

    # -- start -----------------------------------------------------------------------------------------

    def _say_hearing_problem(self) -> None:
        """Warn (once per distinct reason) when the behaviour avoids collisions on broadcasts too slow for it."""
        layer = collision_layer(self.agent.behavior) if self.mesh_link is not None else None
        problem = layer.hearing_problem(self.config.broadcast_period_s) if layer is not None else None
        if problem and problem != self._hearing_problem:
            logger.warning("vessel %d: %s (--broadcast-period)", self.config.system_id, problem)
        self._hearing_problem = problem

    def _say_pose_wait(self, now: float, position: bool, heading: bool) -> None:
        """Say once when the vessel has held still for POSE_WAIT_S after its start-up for want of a GPS fix or a
        compass heading (ATTITUDE) in its estimate, naming which, and say when it has both and drives."""
        if position and heading:
            if self._pose_wait_said:
                self._say(mavlink.MAV_SEVERITY_NOTICE, f"vessel {self.config.system_id}: position and heading known")
            self._pose_wait_said = False
            return
        waited = now - self._driving_since
        if self._pose_wait_said or waited < POSE_WAIT_S:
            return
        wanted = [what for what, known in (("GPS fix", position), ("compass heading (ATTITUDE)", heading)) if not known]
        text = f"vessel {self.config.system_id}: holding still, no {' and no '.join(wanted)} {waited:.0f} s after start"
        self._say(mavlink.MAV_SEVERITY_WARNING, text)
        self._pose_wait_said = True

    def _place_fixes(self, autopilot_lag_s: float | None) -> None:
        """Say how GPS fixes are timed: ArduPilot's stamp (the time it read the fix) on our clock, less the GPS's
        lag, which is the setting's, or else the autopilot's GPS1_DELAY_MS (autopilot_lag_s, s), or else 0."""
        decoder = self.vehicle.decoder
        if self.config.gps_lag_s is None and autopilot_lag_s is not None:
            decoder.gps_lag_s = autopilot_lag_s
            source = "the autopilot's GPS1_DELAY_MS"
        else:
            source = "gps_lag_s" if self.config.gps_lag_s is not None else "GPS1_DELAY_MS not set: set it or gps_lag_s"
        logger.info("GPS fixes fused at the autopilot's fix time less a lag of %.3f s (%s)", decoder.gps_lag_s, source)

    def arm(self) -> None:
        """Bring the autopilot into service (`bob_autonomy.onboard.autopilot_start`): streams, parameters, mode, ready,
        armed. Raises VehicleError saying what is wrong and what to change."""
        c = self.config
        options = replace(
            c.autopilot, heartbeat_timeout_s=c.arm_timeout_s, arm_timeout_s=c.arm_timeout_s, control_period_s=c.dt_s
        )
        starter = AutopilotStarter(
            self.autopilot, self._send, self._pump_and_serve, self._stop.is_set, self.gcs.notify, options
        )
        try:
            profile = starter.run()
        except NoHeartbeatError as error:
            raise VehicleError(f"vehicle {c.system_id} on {c.vehicle!r}: {error}{self._baud_hint()}") from None
        except AutopilotStartError as error:
            raise VehicleError(f"vehicle {c.system_id} on {c.vehicle!r}: {error}") from None
        if profile is None:
            return
        self._place_fixes(profile.gps_lag_s)
        speed = profile.top_speed_mps
        on_ground = profile.known and profile.frame_class != 2  # FRAME_CLASS 2: a boat
        boat = c.kind in (BUOY, MOTORBOAT)
        capped = boat and profile.throttle_ceiling < self._thrust_fraction_asked
        if boat:  # (at a start-up after a reboot too: the ceiling may have changed meanwhile)
            fraction = min(self._thrust_fraction_asked, profile.throttle_ceiling)
            self.config = c = replace(c, max_thrust_fraction=fraction)
        if capped:
            # MOT_THR_MAX clips the throttle: plan with no more (a buoy's lateral is not clipped; kept within it too).
            logger.info(
                "throttle limited to %.0f %% by MOT_THR_MAX: the controller plans with that",
                100 * c.max_thrust_fraction,
            )
        if c.kind == BUOY and ((c.top_speed_mps is None and speed is not None) or on_ground or capped):
            # The autopilot knows how fast full throttle goes and whether it floats; the estimator and the MPC
            # model that vehicle.
            top = c.top_speed_mps or speed
            model = BuoyModel() if top is None else BuoyModel.for_top_speed(top)
            self.pipeline = self.body.pipeline = buoy_pipeline(self.config, model, on_ground=on_ground)
            logger.info(
                "vessel model: top speed %s m/s at full throttle, %s", top, "on the ground" if on_ground else "afloat"
            )
        if c.kind == MOTORBOAT:
            # The autopilot says how fast full throttle goes (SPEED_MAX or CRUISE_*), how tight it turns
            # (TURN_RADIUS) and how fast it lets the throttle change (MOT_SLEWRATE): the MPC plans with that boat.
            top = min(max(c.top_speed_mps or speed or 2.0, 0.1), 50.0)  # what MotorboatModel takes
            model = MotorboatModel.for_top_speed(top, profile.turn_radius_m, profile.throttle_slew_per_s)
            self.pipeline = self.body.pipeline = motorboat_pipeline(self.config, model)
            radius, slew = model.turning_radius_m, 100 * model.throttle_slew_per_s
            logger.info(
                "motorboat model: %.2f m/s at full throttle, turning radius %.2f m, throttle slew %.0f %%/s",
                top, radius, slew,
            )  # fmt: skip
        if c.kind == EBOT:
            # A skid-steer autopilot slews the throttle (MOT_SLEWRATE) as a boat's does: the MPC plans with the slew
            # it read. An autopilot that has no such parameter (the eBot's serial bridge sets the wheels at once) is
            # planned for without one.
            slew = profile.throttle_slew_per_s if profile.get("MOT_SLEWRATE") is not None else 0.0
            rebuild = slew > 0.0
            if c.top_speed_mps is None and speed is not None:
                # Wheels at full throttle move this fast (an eBot's 0.2 m/s is not a rover's): commands scale to it.
                self.max_actuator, rebuild = speed, True
                logger.info("vessel model: wheel speed %.2f m/s at full throttle (from the autopilot)", speed)
            if rebuild:
                self.pipeline = self.body.pipeline = ebot_pipeline(self.config, self.max_actuator, slew)
                logger.info("wheel control: throttle slew %.0f %%/s", 100 * slew)
        if boat and isinstance(self.pipeline, BuoyPipeline):  # a pipeline kept from before a reboot too
            self.pipeline.limit_throttle(c.max_thrust_fraction)
        if c.kind == BUOY and profile.lateral_capable:
            self._hold_heading = True
        self._place_antenna(profile.gps_antenna_m)
        logger.info("vehicle %d in service: %s", c.system_id, profile.frame_name)

    def _place_antenna(self, antenna_m: tuple[float, float, float] | None) -> None:
        """Fixes moved from the GPS antenna to the IMU (buoys, motorboats) by the offset the autopilot's EKF uses."""
        if antenna_m is None or not isinstance(self.pipeline, BuoyPipeline):
            return
        self.pipeline.antenna_frd_m[:] = antenna_m
        logger.info("GPS antenna %.2f m forward, %.2f m right, %.2f m down of the IMU (GPS1_POS less INS_POS1): "
                    "fixes are moved to the IMU with the attitude", *antenna_m)  # fmt: skip

    # -- the loop --------------------------------------------------------------------------------------

    def tick(self) -> None:
        """One control step (see the module docstring)."""
        now = self.clock.now()
        self.stats.ticks += 1
        self._heartbeat(now)
        self._check_estimate(now)
        try:
            self._report_position(now)
        except Exception:  # a report is never worth the process: count it and go on
            self.stats.step_errors += 1
            logger.exception("position report failed (%d so far)", self.stats.step_errors)
        self.serve_gcs()
        self._watch_autopilot(now)
        if self.vehicle.silent():
            if not self._alarm:
                self.stats.silent_alarms += 1
                text = f"ALARM: vehicle {self.config.system_id} silent for {self.vehicle.watch.silent_for_s():.1f} s"
                logger.error("%s: commanding neutral", text)
                self.gcs.notify(mavlink.MAV_SEVERITY_ALERT, text)
            self._alarm = True
            self._send(self._override(np.zeros(2)))
            return
        if self._alarm:
            self._say(mavlink.MAV_SEVERITY_NOTICE, f"vehicle {self.config.system_id} heard again")
            self._alarm = False
            self._request_streams()  # a restarted autopilot streams its defaults only (and its clock tells)
        if self._restart_due is not None:
            if time.monotonic() >= self._restart_due:
                self._restart()
            self._send(self._override(np.zeros(2)))
            return
        if self.autopilot.armed is False or self._gps_outage(now):
            self._send(self._override(np.zeros(2)))  # disarmed, or blind: neutral until that ends
            return
        start = time.perf_counter()
        if not self.pose_known:
            position = bool(self.pipeline.position_known(now).all())
            heading = bool(self.pipeline.heading_known(now).all())
            self.pose_known = position and heading
            self._say_pose_wait(now, position, heading)
            if not self.pose_known:
                self._send(self._override(np.zeros(2)))  # waiting for a position and a heading: hold still
                return
        if not self._obeying:
            self._send(self._override(np.zeros(2)))  # not in our mode: neutral until it is again
            return
        try:
            behavior = self.supervisor.behavior()
            if behavior is not self.agent.behavior:
                self.agent.behavior = behavior
                self._say_hearing_problem()
            self.agent.step()
            position = self.pipeline.estimate(now).position[0]
            velocity = self.supervisor.velocity(
                position, self.body.wish_velocity, self.gcs.behavior_running, self.gcs.gcs_lost
            )
            wish = velocity[None, :]
            if isinstance(self.pipeline, BuoyPipeline):
                actuator = self.pipeline.thrust(wish, now)[0]
            else:
                actuator = self.pipeline.wheels(wish, np.array([self.body.wish_heading]), now)[0]
        except Exception:  # one bad step must not kill the vessel: count it, stop the actuators, go on
            self.stats.step_errors += 1
            logger.exception("control step failed (%d so far); commanding neutral", self.stats.step_errors)
            actuator = np.zeros(2)
        self._send(self._override(actuator, hold_heading=True))
        done = time.perf_counter()
        self.stats.commands += 1
        self.stats.compute_latency_s.append(done - start)
        if self._last_reading_wall_s is not None:
            self.stats.telemetry_to_command_s.append(done - self._last_reading_wall_s)

    def _gps_outage(self, now: float) -> bool:
        """True while a buoy or motorboat driving on a position has had no GPS fix for GPS_LOST_S (the autopilot's
        GPS failed, lost its satellites or its antenna; counted from the end of the start-up before the first fix);
        said when it begins and when fixes come back."""
        if not isinstance(self.pipeline, BuoyPipeline) or not self.pose_known:
            return False
        age = now - max(float(self.pipeline.last_fix_t[0]), self._driving_since)
        lost = age > GPS_LOST_S
        if lost != self._gps_lost:
            self._gps_lost = lost
            system, a = self.config.system_id, self.autopilot
            if lost:
                self.stats.gps_outages += 1
                text = (
                    f"vehicle {system}: no GPS fix for {age:.1f} s (the autopilot reports fix type {a.fix_type}, "
                    f"{a.satellites} satellites): neutral until fixes come back"
                )
                self._say(mavlink.MAV_SEVERITY_CRITICAL, text)
            else:
                text = f"vehicle {system}: GPS fixes back: driving"
                self._say(mavlink.MAV_SEVERITY_NOTICE, text)
        return lost

    def _restart(self) -> None:
        """Bring a restarted autopilot into service again (`arm`'s start-up); if it will not come, say so and try
        again RESTART_RETRY_S later, at neutral meanwhile."""
        self.stats.restarts += 1
        try:
            self.arm()
        except VehicleError as error:
            self._restart_due = time.monotonic() + RESTART_RETRY_S
            text = f"{error}; trying again in {RESTART_RETRY_S:g} s"
            self._say(mavlink.MAV_SEVERITY_ERROR, text)
            return
        self._restart_due = None
        if self._stop.is_set():
            return  # asked to stop during the start-up: not back in service
        self._driving_since = self.clock.now()
        self._armed_seen = self.autopilot.armed
        self.pose_known = False  # the estimator may have been rebuilt for what the autopilot now says
        text = f"vehicle {self.config.system_id} back in service after its autopilot restarted"
        self._say(mavlink.MAV_SEVERITY_NOTICE, text)

    def run(self, duration_s: float | None = None) -> VesselStats:
        """Arm, then run control steps every dt_s (clock seconds) until `stop()` or `duration_s` has passed."""
        self.arm()
        self._driving_since = self.clock.now()
        if self.vehicle.last_heartbeat is None:
            self.vehicle.watch.restart()  # the arming handshake was the start-up; silence counts from here
        end = math.inf if duration_s is None else self.clock.now() + duration_s
        next_tick = self.clock.now()
        while not self._stop.is_set() and self.clock.now() < end:
            # Read telemetry as it arrives until the tick is due, then act on everything heard.
            while not self._stop.is_set():
                wait = self.clock.wall_seconds(next_tick - self.clock.now())
                if wait <= 0:
                    break
                self._pump_and_serve(min(wait, 0.05))  # the router passes frames on between ticks too
            self.pump(0.0)
            self.tick()
            next_tick += self.config.dt_s
            if next_tick < self.clock.now():  # fell behind: skip the missed ticks rather than burst
                next_tick = self.clock.now()
        self.shutdown()
        return self.stats

    def stop(self) -> None:
        """Ask `run()` to finish (safe from a signal handler or another thread)."""
        self._stop.set()

    def _linger(self, seconds: float, frame: bytes | None) -> None:
        """Send `frame` every control period for `seconds` (wall) while reading the link, so that the autopilot
        has applied it before we close (ArduPilot SITL drops unparsed bytes when a TCP peer closes, issue #18)."""
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            if frame is not None:
                self._send(frame)
            self.pump(min(self.config.dt_s, max(0.0, end - time.monotonic())))

    def shutdown(self) -> None:
        """Leave the vehicle at neutral (then in HOLD or disarmed if configured), hand the RC channels back,
        and close the links."""
        neutral = self._override(np.zeros(2))
        self._linger(STOP_LINGER_S, neutral)
        if self.config.on_stop == "hold":
            self._send(self.autopilot.set_mode("HOLD"))
            self._linger(0.3, neutral)
        elif self.config.on_stop == "disarm":
            self._send(self.autopilot.arm(False))
            self._linger(0.3, neutral)
        self._send(self.autopilot.release())
        self._linger(0.2, None)
        for link in (self.vehicle_link, self.mesh_link, self.gcs_link):
            if link is not None:
                link.close()
        if self.tlog is not None:
            self.tlog.close()
        self.stats.gcs = self.gcs.log_counters()
        counters = vars(self.vehicle.decoder.counters).items()
        self.stats.vehicle_link = {k: v for k, v in counters if isinstance(v, int) and not isinstance(v, bool) and v}
        self.stats.mpc_fallbacks = sum(getattr(m, "fallbacks", 0) for m in getattr(self.pipeline, "mpcs", ()))
        if isinstance(self.pipeline, BuoyPipeline):
            tilt = self.pipeline.tilt
            self.stats.imu_levelled, self.stats.imu_unlevelled = tilt.levelled, tilt.unlevelled
            self.stats.antenna_unplaced = self.pipeline.antenna_unplaced
        layer = collision_layer(self.agent.behavior) if hasattr(self, "agent") else None
        if layer is not None:
            self.stats.collision_interventions, self.stats.collision_updates = layer.interventions, layer.updates
        # One JSON line that process fleets read back (sitl.fleets.vessel_logs) for metrics.json.
        logger.info("vessel %d stopped: %s", self.config.system_id, json.dumps(self.stats.summary()))
        if isinstance(self.network, ThrottledMesh):  # what the mesh refused, and why (docs/mesh.md)
            mesh = {**self.network.inner.counters(), "implausible": self.agent.neighbors.counters()}
            mesh.update(link_lost=self.mesh_link.losses, link_reopened=self.mesh_link.reopens)
            logger.info("vessel %d mesh: %s", self.config.system_id, json.dumps(mesh))
