"""A fleet of processes: simulated vehicles and radio on UDP, one `bob-autonomy run` process per vessel, in real time.

As deployed, only faster: each vessel's autonomy is its own operating-system
process that reaches its vehicle over MAVLink (UDP, `sitl.vehicles.vehicle_server`) and
its swarm over a mesh (UDP, `sitl.radio.radio_relay`), on a clock running `speed`
times wall time. This process owns the world: the physics of every vehicle
(`sitl.vehicles.vehicle_physics.VehiclePhysics`, stepped every `dt` simulated seconds at
its wall time), their MAVLink endpoints and the radio medium, the scenario's
events, the recording and the metrics.

A run: build the scenario's world, start poses and physics exactly as the
lockstep fleet does (same seeds, same draws); bind the vehicles' ports and the
relay's; start the autonomy processes (each in its own session, output to
`vessel-NN.out`, log to `vessel-NN.log`; forked from one pre-loaded `bob-autonomy
fork-server`, `sitl.fleets.process_supervision`); keep stepping with the actuators held
at zero until every vehicle has been armed by its autonomy (a clear error
naming the vessel and quoting its log if one never is); then run the scenario
for its duration: each step applies what each vehicle was last commanded (its
failsafe included), steps the physics, sends the sensors' telemetry, records a
frame when due; between steps it answers the vehicles' peers and relays mesh
packets. At the end, on Ctrl-C (SIGINT) or SIGTERM: the processes' memory and
CPU share noted, SIGTERM to every autonomy process group, up to `stop_timeout_s`
for them to send their neutral commands and exit (how long each took goes into
metrics.json), SIGKILL for any left, every socket closed; then the outputs of a
lockstep run (trajectory.csv, metrics.json from the same metrics functions,
figures, scenario.toml) plus `vehicles.tlog` and the vessels' logs, all or
nothing (`sitl.experiments.runner.write_atomically`).

What each agent believed (the `est_*` columns) is the pose it last broadcast
on the mesh, carried forward by its broadcast velocity to the frame's time.
"""

from __future__ import annotations

import contextlib
import json
import math
import select
import signal
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from tqdm import tqdm

from firmware_bridge.tlog import TlogWriter
from sitl.experiments.metrics import METRICS, step_watch
from sitl.experiments.plots import write_figures
from sitl.experiments.recorder import Frame, Recorder
from sitl.experiments.run_environment import write_environment
from sitl.experiments.runner import estimation_errors, write_atomically
from sitl.experiments.scenario import BehaviorChoice, Scenario, scenario_to_toml
from sitl.fleets.fleet import LockstepFleet, build_world, initial_poses, motorboat_params
from sitl.fleets.process_events import ProcessEvents, behavior_parameters  # noqa: F401 - re-exported
from sitl.fleets.process_lifecycle import AUTONOMY_COMMAND, ProcessFleetError, ProcessLifecycle
from sitl.fleets.process_supervision import (
    ForkServer,
    Process,
    StopReport,
)
from sitl.fleets.vessel_logs import collision_counters, gcs_counters
from sitl.radio.mesh_security import mesh_log_counters
from sitl.radio.radio_relay import DEFAULT_MESH_PORT, RadioRelay
from sitl.vehicles.bodies import BODY_KINDS
from sitl.vehicles.vehicle_physics import PRE_ROLL_S, VehiclePhysics
from sitl.vehicles.vehicle_server import DEFAULT_BASE_PORT, VehicleServer
from sitl.world.world import FloatArray

DEFAULT_GCS_PORT = 14600  # where the autonomy processes' GCS links point (bob_autonomy.ground.mission.MissionClient)
MAX_STEP_S = 0.1  # the physics steps at most this long, so the sensors keep their rates (GPS 5 Hz, IMU 10 Hz)
LATE_FRACTION = 0.5  # a step that starts more than this fraction of a wall step after its due time is late

# The BoB rule's parameters that MAVLink parameters carry (bob_autonomy.ground.supervisor.behavior_params).


@dataclass(frozen=True)
class ProcessOptions:
    """How to run a fleet of processes.

    speed: simulated seconds per wall second. host: where the vehicles, relay and GCS listen. base_port:
    vehicle i listens on base_port + 10 i. mesh_port: the radio relay. gcs_port: the mission client that
    carries set-behavior events; external_gcs: leave that port to the user's mission script (no events then).
    failsafe_s: simulated seconds
    without a command before a vehicle stops. arm_timeout_s, stop_timeout_s: wall seconds to wait for every
    vehicle to be armed, and for the processes to exit after SIGTERM. autonomy: the command that runs
    `bob-autonomy`. fork_server: start the vessels by forking one pre-loaded `bob-autonomy fork-server`
    (`sitl.fleets.process_supervision`; only with the real `bob-autonomy`: another command is always exec'd).
    vessel_nice: niceness the autonomy processes get above the fleet's (0..19): when they want more CPU than
    there is (100 vessels on 2 cores), the world keeps to wall time and the vessels lag, as slow computers would.
    """

    speed: float = 1.0
    host: str = "127.0.0.1"
    base_port: int = DEFAULT_BASE_PORT
    mesh_port: int = DEFAULT_MESH_PORT
    gcs_port: int = DEFAULT_GCS_PORT
    external_gcs: bool = False
    failsafe_s: float = 1.0
    arm_timeout_s: float = 60.0
    stop_timeout_s: float = 6.0  # a vessel sends neutral for 0.6 s and hands RC back before it exits
    autonomy: tuple[str, ...] = AUTONOMY_COMMAND
    fork_server: bool = True
    vessel_nice: int = 0

    def __post_init__(self) -> None:
        if not 0 <= self.vessel_nice <= 19:
            raise ValueError(f"vessel_nice must be 0..19, got {self.vessel_nice!r}")
        if not (math.isfinite(self.speed) and self.speed > 0):
            raise ValueError(f"speed must be positive, got {self.speed!r}")
        for name in ("base_port", "mesh_port", "gcs_port"):
            if not 1 <= getattr(self, name) <= 65535:
                raise ValueError(f"{name} must be a port number, got {getattr(self, name)!r}")


@dataclass
class RealtimeStats:
    """How well the physics kept to wall time: per step, how late (wall s) it started after its due time, and
    how long its work (actuators, dynamics, sensors, telemetry) took (wall s)."""

    wall_step_s: float
    steps: int = 0
    late: int = 0
    max_lag_s: float = 0.0
    total_lag_s: float = 0.0
    total_work_s: float = 0.0

    def add(self, lag_s: float, work_s: float) -> None:
        """One step that started lag_s wall seconds after its due time and took work_s wall seconds."""
        self.steps += 1
        self.total_work_s += work_s
        self.max_lag_s = max(self.max_lag_s, lag_s)
        self.total_lag_s += lag_s
        if lag_s > LATE_FRACTION * self.wall_step_s:
            self.late += 1

    def summary(self) -> dict:
        return {
            "wall_step_s": self.wall_step_s,
            "steps": self.steps,
            "max_lag_s": round(self.max_lag_s, 6),
            "mean_lag_s": round(self.total_lag_s / max(1, self.steps), 6),
            "late_fraction": round(self.late / max(1, self.steps), 6),
            "late_threshold_s": LATE_FRACTION * self.wall_step_s,
            "mean_step_work_s": round(self.total_work_s / max(1, self.steps), 6),
        }


@dataclass
class ProcessRunResult:
    """What a process-fleet run produced: the fleet at the end, its recording and its metrics."""

    fleet: ProcessFleet
    recorder: Recorder
    metrics: dict = field(default_factory=dict)


class ProcessFleet(ProcessLifecycle, ProcessEvents):
    """The world of a process fleet; see the module docstring. Offers what the metrics and figures read:
    n, scenario, world, bodies, events_log, medium, group_of, group_names, behavior_names(), light_seen(), t."""

    def __init__(self, scenario: Scenario, out: Path, options: ProcessOptions) -> None:
        self.scenario, self.out, self.options = scenario, Path(out), options
        self.rng = np.random.default_rng(scenario.seed)
        self.world = build_world(scenario, self.rng)
        position, heading = initial_poses(scenario, self.world, self.rng)
        kinds = np.concatenate([np.full(g.count, BODY_KINDS[g.body]) for g in scenario.groups])
        thrust = np.concatenate([np.full(g.count, g.thrust_fraction) for g in scenario.groups])
        self.dt = min(scenario.dt_s, MAX_STEP_S)
        self.bodies = VehiclePhysics(
            kinds,
            position,
            heading,
            scenario.environment.build(np.random.default_rng([scenario.seed, 3])),
            scenario.origin.frame(),
            np.random.default_rng([scenario.seed, 2]),
            thrust,
            scenario.sensors.specs(),
            motorboat_params=motorboat_params(scenario),
        )
        self.n = len(self.bodies)
        self.frame = scenario.origin.frame()
        self.start_position, self.start_heading = position.copy(), heading.copy()
        self.group_of = np.concatenate([np.full(g.count, k) for k, g in enumerate(scenario.groups)])
        self.group_names = [g.name for g in scenario.groups]
        self.choices: list[BehaviorChoice] = [BehaviorChoice(**_choice(g)) for g in scenario.groups]
        self.names = [c.build().name for c in self.choices]
        self.assignment = self.group_of.copy()
        self.memory_fields = list(LockstepFleet.memory_fields_of(scenario))
        self.pending = sorted(scenario.events, key=lambda e: e.t_s)
        self.events_log: list[dict] = []
        self.event_errors: list[str] = []
        self.event_delays_s: list[float] = []
        self._event_threads: list[threading.Thread] = []
        self.step_index = 0
        self.t = 0.0
        self.started = False
        self.interrupted = False
        self.realtime = RealtimeStats(self.dt / options.speed)
        self.processes: list[Process] = []
        self.exit_codes: list[int | None] = []
        self.killed = 0
        self.stop_report = StopReport()
        self.memory: dict[str, float | None] = {}
        self.forks: ForkServer | None = None
        self.startup_wall_s: float | None = None
        self.needs_gcs = False
        self._logs: list = []
        self._stop = threading.Event()
        self._k = 0  # physics steps since the physics started (boot)
        self._wall0 = 0.0
        self._cpu0 = 0.0
        self.fleet_cpu_share: float | None = None  # this process's CPU s per wall s up to the stop
        self.mission = None  # the fleet's MissionClient: only for set-behavior events (never with external_gcs)
        self.tlog: TlogWriter | None = None
        self.server: VehicleServer | None = None
        self.medium: RadioRelay | None = None

    # -- what the metrics read -----------------------------------------------------------------------------

    @property
    def active(self) -> NDArray[np.bool_]:
        return self.bodies.active

    def behavior_names(self) -> list[str]:
        """Name of the behaviour each agent runs."""
        return [self.names[k] for k in self.assignment]

    def light_seen(self) -> bool:
        """Whether an active agent has broadcast a light target (memory field `target_light`)."""
        if self.medium is None:
            return False
        for agent, (state, _) in self.medium.latest.items():
            light = state.memory.get("target_light")
            if self.active[agent] and light is not None and np.isfinite(light).any():
                return True
        return False

    def believed(self) -> tuple[FloatArray, FloatArray]:
        """(position (n, 2) m, heading (n,) rad) each agent last broadcast, carried forward to now; NaN if none."""
        position, heading = np.full((self.n, 2), np.nan), np.full(self.n, np.nan)
        if self.medium is not None:
            now = self._sim_now()
            for agent, (state, heard_s) in self.medium.latest.items():
                p = state.pose
                age = max(0.0, now - heard_s)
                position[agent] = (p.x + p.vx * age, p.y + p.vy * age)
                heading[agent] = p.heading
        return position, heading

    # -- time ----------------------------------------------------------------------------------------------

    def _wall_of(self, k: int) -> float:
        """Wall time (time.monotonic) at which physics step k is due."""
        return self._wall0 + k * self.realtime.wall_step_s

    def _sim_now(self) -> float:
        """Simulated time now (s since the physics started): the last step's, plus the wall time since it was
        due, scaled, up to the next step."""
        since = (time.monotonic() - self._wall_of(self._k)) * self.options.speed
        return self.bodies.t + min(max(since, 0.0), self.dt)

    def _serve_until(self, deadline: float) -> None:
        """Answer the vehicles' peers and relay mesh packets until the wall time `deadline`."""
        assert self.server is not None and self.medium is not None
        sockets = [*self.server.sockets(), self.medium.sock]
        while not self._stop.is_set():
            now = time.monotonic()
            wait = deadline - now
            due = self.medium.next_due_s()
            if due is not None:
                wait = min(wait, self._wall_of(self._k) + (due - self.bodies.t) / self.options.speed - now)
            if wait <= 0 and now >= deadline:
                break
            try:
                ready, _, _ = select.select(sockets, [], [], max(0.0, wait))
            except InterruptedError:  # pragma: no cover - PEP 475 retries; kept for other platforms
                continue
            if ready:
                t = self._sim_now()
                self.server.read(t, ready)
                if self.medium.sock in ready:
                    self.medium.read()
            self.medium.flush()

    # -- running -------------------------------------------------------------------------------------------

    def _step(self) -> None:
        """One physics step of dt: the vehicles' actuators (none for removed vehicles), the dynamics, the
        sensors, the telemetry. Before the start the vehicles are held still at their start poses."""
        assert self.server is not None
        b = self.bodies
        actuators = self.server.actuators(b.t)
        if not self.started:
            actuators[:] = 0.0
        actuators[~b.active] = 0.0
        if self.started:
            b.step(actuators[b.buoys], actuators[b.ebots], self.dt, self.world, actuators[b.motorboats])
        else:
            b.hold(self.dt)
        senses = b.ebot_senses(self.world) if b.ebots.size else None
        self.server.send_telemetry(b.t, b.sense(), senses)
        self._k += 1

    def _tick(self) -> None:
        """Wait (serving) for the next step's wall time, then take it; track the lag."""
        deadline = self._wall_of(self._k + 1)
        self._serve_until(deadline)
        if self._stop.is_set():
            return
        begin = time.monotonic()
        self._step()
        if self.started:
            self.realtime.add(max(0.0, begin - deadline), time.monotonic() - begin)

    def wait_armed(self) -> None:
        """Hold the vehicles still at their start poses, sensors running, until every vehicle has been armed by
        its autonomy and PRE_ROLL_S more simulated seconds have passed (the vessels' estimators settle, as in
        the lockstep fleet's pre-roll)."""
        assert self.server is not None
        deadline = time.monotonic() + self.options.arm_timeout_s
        next_check = 0.0
        release_s: float | None = None
        while not self._stop.is_set():
            armed = ready = self.server.armed()
            if self.needs_gcs and self.mission is not None:  # set-behavior events go to vessels the GCS has heard
                ready = armed & np.isin(np.arange(1, self.n + 1), self.mission.vessels)
            if ready.all():
                release_s = self.bodies.t + PRE_ROLL_S if release_s is None else release_s
                if self.bodies.t >= release_s - 1e-9:
                    self.startup_wall_s = time.monotonic() - self._wall0
                    return
            now = time.monotonic()
            if now >= next_check:
                next_check = now + 0.25
                for i, process in enumerate(self.processes):
                    if process.poll() is not None:
                        raise ProcessFleetError(
                            f"the autonomy of vessel {i + 1} (system id {i + 1}, UDP {self.server.ports[i]}) exited "
                            f"with status {process.returncode} before the start\n{self._log_tail(i)}"
                        )
                if now > deadline and not ready.all():
                    i = int(np.flatnonzero(~ready)[0])
                    what = "was not armed" if not armed[i] else "was not heard on the ground-station port"
                    raise ProcessFleetError(
                        f"vessel {i + 1} (system id {i + 1}, UDP {self.server.ports[i]}) {what} within "
                        f"{self.options.arm_timeout_s:g} s; {int((~armed).sum())} of {self.n} vehicles unarmed\n"
                        f"{self._log_tail(i)}"
                    )
            self._tick()
        raise ProcessFleetError("interrupted before every vehicle was armed")

    def run(self, recorder: Recorder, progress: bool = False) -> None:
        """Start everything, wait for the vehicles to be armed, run the scenario's duration (or until stopped)."""
        self._wall0 = time.monotonic()
        self._cpu0 = time.process_time()
        self.start()
        self.wait_armed()
        self.started = True
        steps = round(self.scenario.duration_s / self.dt)
        bar = tqdm(total=steps, desc=self.scenario.name, unit="step", disable=not progress, mininterval=0.5)
        last_check = time.monotonic()
        while not self._stop.is_set():
            self.t = round(self.step_index * self.dt, 9)
            self._apply_events()
            if recorder.due(self.t):
                recorder.record(self._frame())
            recorder.observe_step(self.t, self.bodies.active, self.bodies.position)
            if self.step_index == steps:
                break
            self._tick()
            if self._stop.is_set():
                break
            self.step_index += 1
            bar.update(1)
            if time.monotonic() - last_check > 1.0:
                last_check = time.monotonic()
                self._watch_processes()
        bar.close()
        self.interrupted = self.step_index < steps

    def _watch_processes(self) -> None:
        """Note (once, on stderr and in metrics.json) an autonomy process that has exited during the run."""
        for i, process in enumerate(self.processes):
            if self.exit_codes[i] is None and process.poll() is not None:
                self.exit_codes[i] = process.returncode
                print(
                    f"bob-sitl: the autonomy of vessel {i + 1} exited with status {process.returncode}", file=sys.stderr
                )

    def _frame(self) -> Frame:
        b = self.bodies
        active = b.active.nonzero()[0]
        position, heading = self.believed()
        return Frame(
            t=self.t,
            agents=active,
            position=b.position[active].copy(),
            heading=b.heading[active].copy(),
            velocity=b.velocity[active].copy(),
            behavior=self.behavior_names(),
            light_seen=self.light_seen(),
            wind=b.wind[active].copy(),
            current=b.current[active].copy(),
            estimate=np.column_stack((position[active], heading[active])),
        )

    def metrics(self, recorder: Recorder) -> dict:
        """The scenario's metrics (the same functions as a lockstep run) and the process fleet's own figures."""
        s = self.scenario
        metrics = METRICS[s.metrics.kind](self, recorder, dict(s.metrics.params))
        metrics = {"scenario": s.name, "seed": s.seed, "duration_s": s.duration_s, **metrics}
        metrics["estimation"] = estimation_errors(_finite_estimates(recorder))
        assert self.medium is not None and self.server is not None and self.tlog is not None
        metrics["network"] = self.medium.counters()
        metrics["realtime"] = {"speed": self.options.speed, "dt_s": self.dt, **self.realtime.summary()}
        metrics["vehicles"] = {**self.server.counters(), "tlog_frames": self.tlog.frames}
        metrics["gcs"] = gcs_counters({i + 1: self.out / f"vessel-{i + 1:02d}.log" for i in range(self.n)})
        metrics["mesh"] = mesh_log_counters({i + 1: self.out / f"vessel-{i + 1:02d}.log" for i in range(self.n)})
        avoidance = collision_counters({i + 1: self.out / f"vessel-{i + 1:02d}.log" for i in range(self.n)})
        if avoidance:
            metrics["collision_avoidance"] = avoidance
        metrics["processes"] = {
            "exit_codes": self.exit_codes,
            "killed": self.killed,
            "startup_wall_s": None if self.startup_wall_s is None else round(self.startup_wall_s, 3),
            "launcher": "fork-server" if self.forks is not None else "exec",
            **self.stop_report.summary(),
            "memory": self.memory,
            "fleet_cpu_share": None if self.fleet_cpu_share is None else round(self.fleet_cpu_share, 4),
        }
        if self.event_delays_s:
            metrics["event_delays_s"] = self.event_delays_s
        if self.mission is not None:  # datagrams the ground station's socket lost: answers to events among them
            metrics["gcs_kernel_drops"] = self.mission.kernel_drops
        if self.event_errors:
            metrics["event_errors"] = self.event_errors
        if self.interrupted:
            metrics["interrupted_at_s"] = self.t
            metrics["passed"] = False
        return metrics


def _choice(group) -> dict:
    return {k: getattr(group, k) for k in BehaviorChoice.model_fields}


def _finite_estimates(recorder: Recorder) -> Recorder:
    """The recording restricted, frame by frame, to agents whose belief is known (estimation errors)."""
    frames = []
    for f in recorder.frames:
        if f.estimate is None:
            continue
        ok = np.isfinite(f.estimate).all(axis=1)
        if ok.any():
            frames.append(
                Frame(
                    f.t,
                    f.agents[ok],
                    f.position[ok],
                    f.heading[ok],
                    f.velocity[ok],
                    f.behavior,
                    estimate=f.estimate[ok],
                )
            )
    return Recorder(recorder.period_s, recorder.body_names, frames)


def run_processes_to_directory(
    scenario: Scenario, out: Path, options: ProcessOptions | None = None, progress: bool = False
) -> ProcessRunResult:
    """Run `scenario` as a fleet of processes and write its outputs to `out`, all or nothing.

    Outputs: those of a lockstep run (trajectory.csv, metrics.json, figures, scenario.toml) plus
    vehicles.tlog and vessel-NN.out / vessel-NN.log. Ctrl-C (SIGINT) and SIGTERM end the run early and still
    write them (metrics.json then says `interrupted_at_s` and does not pass). Raises ScenarioError,
    ProcessFleetError or FileExistsError.
    """
    options = options or ProcessOptions()
    out = Path(out)
    if out.exists() and any(out.iterdir()) and not (out / "metrics.json").exists():
        raise FileExistsError(f"{out} exists, is not empty and is not a previous run's output; choose another --out")
    scenario = scenario.with_overrides(fidelity="physics")

    def write(staging: Path) -> ProcessRunResult:
        fleet = ProcessFleet(scenario, staging, options)
        bodies = {g.name: g.body for g in scenario.groups}
        recorder = Recorder(
            scenario.log_period_s,
            [bodies[fleet.group_names[k]] for k in fleet.group_of],
            watch=step_watch(scenario.metrics.kind, fleet),
        )
        with _stop_on_signals(fleet):
            try:
                fleet.run(recorder, progress)
            except KeyboardInterrupt:
                fleet.interrupted = True
            finally:
                fleet.close()
        if not recorder.frames:
            raise ProcessFleetError("the run ended before its first frame was recorded")
        result = ProcessRunResult(fleet, recorder, fleet.metrics(recorder))
        recorder.write_csv(staging / "trajectory.csv")
        result.metrics["figures"] = write_figures(fleet, recorder, result.metrics, staging)
        (staging / "metrics.json").write_text(json.dumps(result.metrics, indent=2) + "\n")
        (staging / "scenario.toml").write_text(scenario_to_toml(scenario))
        write_environment(staging)
        return result

    return write_atomically(out, write)


@contextlib.contextmanager
def _stop_on_signals(fleet: ProcessFleet):
    """While running: SIGINT and SIGTERM ask the fleet to stop cleanly (main thread only; elsewhere no change)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    for sig in previous:
        signal.signal(sig, lambda *_: fleet.request_stop())
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
