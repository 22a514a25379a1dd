"""Starting and stopping a process fleet (sitl.fleets.process_fleet): the vehicle server, the radio relay and one
`bob-autonomy` process per vessel (forked from a pre-loaded server, or executed), their logs, and their stop
on SIGINT or at the end with each one's time to stop reported."""

from __future__ import annotations

import contextlib
import json
import sys
import time

import numpy as np

from firmware_bridge.tlog import TlogWriter
from sitl.experiments.scenario import ScenarioError
from sitl.fleets.process_events import behavior_parameters
from sitl.fleets.process_supervision import (
    ForkServer,
    Process,
    SupervisionError,
    memory_summary,
    start_exec,
    stop_all,
)
from sitl.radio.mesh_security import write_fleet_key
from sitl.radio.radio_relay import RadioRelay
from sitl.vehicles.bodies import BODY_KINDS
from sitl.vehicles.vehicle_server import VehicleServer

AUTONOMY_COMMAND = (sys.executable, "-m", "bob_autonomy.cli")  # `bob-autonomy`, with this interpreter


class ProcessFleetError(RuntimeError):
    """The process fleet could not run (a port taken, a vessel that never armed); the message says which."""


class ProcessLifecycle:
    """Start and stop of the fleet's processes, mixed into ProcessFleet (which holds the state they use)."""

    def start(self) -> None:
        """Bind the vehicles, the relay (and the GCS), start the autonomy processes."""
        o, s = self.options, self.scenario
        if any(e.action == "set-behavior" for e in s.events) and o.external_gcs:
            raise ScenarioError(
                f"{s.name}: its set-behavior events are sent by the fleet's own ground station (MAVLink parameters "
                "on --gcs-port); with --external-gcs your mission script owns that port: remove the events "
                "(the script can send them) or drop --external-gcs"
            )
        self.needs_gcs = any(e.action == "set-behavior" for e in s.events)
        if s.network.security.faults:
            raise ScenarioError(f"{s.name}: [network.security] faults are simulated by lockstep runs only")
        self.mesh_key_file = write_fleet_key(s, self.out)  # every vessel gets --mesh-key when the fleet has a key
        self._check_events()
        names = {v: k for k, v in BODY_KINDS.items()}
        kinds = [names[int(k)] for k in self.bodies.kind]
        full = {"buoy": self.bodies.buoy_params.max_thrust_n, "ebot": self.bodies.max_wheel_speed_mps, "motorboat": 1.0}
        limits = [full[k] for k in kinds]
        # A motorboat's autopilot says how fast it goes and how tight it turns (ArduPilot's TURN_RADIUS: 0..10 m).
        boats = iter(self.bodies.motorboat_params)
        own: list[dict[str, float] | None] = []
        for kind in kinds:
            boat = next(boats) if kind == "motorboat" else None
            mine = {"SPEED_MAX": boat.top_speed_mps, "TURN_RADIUS": min(boat.turning_radius_m, 10.0)} if boat else None
            own.append(mine)
        # Every autopilot is set up with the simulated GPS's lag, as an operator sets GPS1_DELAY_MS (0..250 ms) for
        # the receiver fitted: the vessels read it and date their fixes by it.
        gps = s.sensors.specs().get("gps")
        lag = None if gps is None else {"GPS1_DELAY_MS": min(250, round(1000 * gps.latency_s))}
        self.tlog = TlogWriter(self.out / "vehicles.tlog")
        try:
            self.server = VehicleServer(
                kinds,
                limits,
                own_params=own,
                vehicle_params=lag,
                host=o.host,
                base_port=o.base_port,
                metres_per_tick=self.bodies.metres_per_tick,
                failsafe_s=o.failsafe_s,
                tlog=self.tlog,
            )
            net = s.network
            self.medium = RadioRelay(
                self.n,
                lambda: self.bodies.position,
                lambda: self.bodies.active,
                channel=net.channel(),
                range_m=net.range_m,
                broadcast_period_s=net.broadcast_period_s,
                rng=np.random.default_rng([s.seed, 1]),
                clock=self._sim_now,
                host=o.host,
                port=o.mesh_port,
                memory_fields=self.memory_fields,
                intruders=net.security.intruders,
            )
        except OSError as error:
            raise ProcessFleetError(str(error)) from error
        if self.needs_gcs:  # a ground station only when the scenario's events need one (see _launch)
            from bob_autonomy.ground.mission import MissionClient

            try:
                self.mission = MissionClient(f"udpin:{o.host}:{o.gcs_port}")
            except OSError as error:
                raise ProcessFleetError(f"{error}; choose another --gcs-port") from error
        if o.fork_server and tuple(o.autonomy) == AUTONOMY_COMMAND:
            log = open(self.out / "fork-server.out", "wb")  # noqa: SIM115 - closed in stop_processes()
            self._logs.append(log)
            try:
                self.forks = ForkServer(o.autonomy, log)
            except SupervisionError as error:
                raise ProcessFleetError(str(error)) from error
        for i in range(self.n):
            self._launch(i, kinds[i])

    def _check_events(self) -> None:
        """Every set-behavior event must be expressible as MAVLink parameters (checked before anything starts)."""
        for event in self.scenario.events:
            if event.action != "set-behavior":
                continue
            groups = [event.group] if event.group else self.group_names
            for g in groups:
                behavior_parameters(self.choices[self.group_names.index(g)], event.choice, self.frame)

    def _launch(self, i: int, kind: str) -> None:
        o, s = self.options, self.scenario
        assert self.server is not None
        choice = self.choices[self.group_of[i]]
        group = s.groups[self.group_of[i]]
        command = [
            *o.autonomy,
            "run",
            "--vehicle", f"udpout:{o.host}:{self.server.ports[i]}",
            "--system-id", str(i + 1),
            "--kind", kind,
            "--mesh", f"udpout:{o.host}:{o.mesh_port}",
            "--behavior-json", json.dumps(choice.model_dump()),
            "--origin", f"{s.origin.lat_deg!r},{s.origin.lon_deg!r}",
            "--time-scale", repr(float(o.speed)),
            "--dt", repr(float(self.dt)),
            "--estimator", s.vessel.estimator,
            "--controller", s.vessel.controller,
            "--memory-fields", json.dumps(self.memory_fields),
            "--log-file", str(self.out / f"vessel-{i + 1:02d}.log"),
        ]  # fmt: skip
        if kind == "ebot":
            x, y = self.start_position[i]
            command += ["--start-x", repr(float(x)), "--start-y", repr(float(y))]
            command += ["--start-heading", repr(float(self.start_heading[i]))]
        if group.thrust_fraction != 1.0:
            command += ["--max-thrust-fraction", repr(float(group.thrust_fraction))]
        command += ["--broadcast-period", repr(float(s.network.broadcast_period_s))]
        command += ["--neighbor-expiry", repr(float(s.network.expiry_s))]
        if self.needs_gcs or o.external_gcs:
            # Each vessel routes all its vehicle's telemetry to its ground station (mavlink-router's job): where
            # nobody listens that was a third of a vessel's CPU and the fleet's MissionClient decoding it all.
            command += ["--gcs", f"udpout:{o.host}:{o.gcs_port}"]
        if self.mesh_key_file is not None:
            command += ["--mesh-key", str(self.mesh_key_file)]
        output = self.out / f"vessel-{i + 1:02d}.out"
        try:
            if self.forks is not None:
                process: Process = self.forks.spawn(command[len(o.autonomy) :], output, o.vessel_nice)
            else:
                out = open(output, "wb")  # noqa: SIM115 - closed in stop_processes()
                self._logs.append(out)
                process = start_exec(command, out, o.vessel_nice)
        except (OSError, SupervisionError) as error:
            raise ProcessFleetError(f"cannot start the autonomy of vessel {i + 1}: {error}") from error
        self.processes.append(process)
        self.exit_codes.append(None)

    def _log_tail(self, i: int, lines: int = 15) -> str:
        text = []
        for name in (f"vessel-{i + 1:02d}.out", f"vessel-{i + 1:02d}.log"):
            path = self.out / name
            if path.exists():
                tail = path.read_text(errors="replace").splitlines()[-lines:]
                text.append(f"--- {name} ---\n" + ("\n".join(tail) if tail else "(empty)"))
        return "\n".join(text)

    def request_stop(self) -> None:
        """Ask the run to end at the next step (safe from a signal handler)."""
        self._stop.set()

    def stop_processes(self) -> None:
        """Note the processes' memory; SIGTERM to every autonomy process group; serve their last (neutral)
        commands for up to stop_timeout_s; SIGKILL what is left; reap them all; note how long each took."""
        self._watch_processes()
        self.memory = memory_summary(self.processes)
        wall = time.monotonic() - self._wall0
        self.fleet_cpu_share = (time.process_time() - self._cpu0) / wall if self._wall0 and wall > 0 else None

        def serve(wait_s: float) -> None:
            if self.server is not None:
                self.server.serve(wait_s, self.bodies.t)
            else:
                time.sleep(wait_s)

        self.stop_report = stop_all(self.processes, self.options.stop_timeout_s, serve)
        self.killed = self.stop_report.killed
        self.exit_codes = [p.returncode for p in self.processes]
        if self.forks is not None:
            self.forks.close()
        for log in self._logs:
            log.close()

    def close(self) -> None:
        """Stop the processes, then close every socket and the telemetry log."""
        try:
            self.stop_processes()
        finally:
            for thing in (self.mission, self.server, self.medium, self.tlog):
                if thing is not None:
                    with contextlib.suppress(Exception):
                        thing.close()
