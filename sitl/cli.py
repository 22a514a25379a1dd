"""The `bob-sitl` command: list and run scenarios, sweep them, run them as a fleet of processes.

Exit status: 0 when every criterion passed, 1 when one failed, 2 for a bad
scenario, option or output directory (one message naming the file or option
and the key), 130 when a run or sweep is interrupted (Ctrl-C or SIGTERM; nothing
is written).
Runs larger than `sitl.budget`'s limits are refused before they start unless
`--force` is given.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import signal
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

from sitl.budget import MAX_AGENT_STEPS, MAX_AGENTS, MAX_TRAJECTORY_ROWS, check_run_size
from sitl.runner import run_to_directory
from sitl.scenario import ScenarioError, load_scenario, packaged_scenarios
from sitl.sweep import run_sweep

FORCE_HELP = (
    f"run even beyond the size limits (at most {MAX_AGENTS:,} agents, {MAX_AGENT_STEPS['kinematic']:,.0f} "
    f"agent-steps kinematic, {MAX_AGENT_STEPS['physics']:,.0f} physics, {MAX_TRAJECTORY_ROWS:,.0f} trajectory rows)"
)


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="bob-sitl", description="BoB autonomy software-in-the-loop simulator")
    sub = parser.add_subparsers(dest="command", required=True)
    sub.add_parser("list", help="list the packaged scenarios")
    run = sub.add_parser("run", help="run a scenario (packaged NAME or a TOML FILE)")
    run.add_argument("scenario", metavar="NAME|FILE")
    run.add_argument("--agents", type=int, help="number of agents (resizes the scenario's main group)")
    run.add_argument("--seed", type=int, help="random seed (default: the scenario's)")
    run.add_argument("--duration", type=float, metavar="SECONDS", help="simulated duration, s")
    run.add_argument("--out", type=Path, metavar="DIR", help="output directory (default: runs/NAME)")
    run.add_argument(
        "--fidelity",
        choices=["kinematic", "physics"],
        help="kinematic bodies and perfect knowledge, or dynamics, sensors and estimates (default: the scenario's)",
    )
    run.add_argument("--estimator", choices=["simple", "ekf"], help="each vessel's pose estimator (physics)")
    run.add_argument("--controller", choices=["simple", "mpc"], help="each vessel's velocity controller (physics)")
    run.add_argument(
        "--link",
        choices=["mavlink", "direct"],
        help="vehicle link (physics): MAVLink bytes through firmware_bridge, or readings handed over directly",
    )
    run.add_argument("--quiet", action="store_true", help="no progress bar")
    run.add_argument("--force", action="store_true", help=FORCE_HELP)
    fleet = sub.add_parser(
        "fleet",
        help="run a scenario as a fleet of processes: simulated vehicles and radio on UDP, one bob-autonomy per vessel",
    )
    fleet.add_argument("scenario", metavar="NAME|FILE")
    fleet.add_argument(
        "--processes", action="store_true", help="one bob-autonomy process per vessel (the only fleet mode so far)"
    )
    fleet.add_argument("--speed", type=float, default=1.0, help="simulated seconds per wall second (default 1)")
    fleet.add_argument("--agents", type=int, help="number of agents (resizes the scenario's main group)")
    fleet.add_argument("--seed", type=int, help="random seed (default: the scenario's)")
    fleet.add_argument("--duration", type=float, metavar="SECONDS", help="simulated duration, s")
    fleet.add_argument("--out", type=Path, metavar="DIR", help="output directory (default: runs/NAME-processes)")
    fleet.add_argument("--estimator", choices=["simple", "ekf"], help="each vessel's pose estimator")
    fleet.add_argument("--controller", choices=["simple", "mpc"], help="each vessel's velocity controller")
    fleet.add_argument(
        "--base-port", type=int, default=5760, help="UDP port of vehicle 0; vehicle i: base + 10 i (ArduPilot SITL)"
    )
    fleet.add_argument("--mesh-port", type=int, default=15000, help="UDP port of the simulated radio medium")
    fleet.add_argument("--gcs-port", type=int, default=14600, help="UDP port the vessels' ground-station links reach")
    fleet.add_argument(
        "--external-gcs",
        action="store_true",
        help="leave --gcs-port to your mission script (bob_autonomy.mission); the scenario may not have events",
    )
    fleet.add_argument("--quiet", action="store_true", help="no progress bar")
    fleet.add_argument("--force", action="store_true", help=FORCE_HELP)
    sweep = sub.add_parser("sweep", help="run a scenario over swarm sizes and seeds; plot metrics against size")
    sweep.add_argument("scenario", metavar="NAME|FILE")
    sweep.add_argument("--agents", type=int, nargs="+", required=True, help="swarm sizes")
    sweep.add_argument("--runs", type=int, default=10, help="seeds per size (1..RUNS)")
    sweep.add_argument("--plot", nargs="+", default=[], metavar="METRIC", help="scalar metrics to plot")
    sweep.add_argument("--out", type=Path, metavar="DIR", help="output directory (default: runs/NAME-sweep)")
    sweep.add_argument("--quiet", action="store_true", help="no progress bar")
    sweep.add_argument("--force", action="store_true", help=FORCE_HELP)
    return parser


def _fail(message: object) -> int:
    print(f"bob-sitl: {message}", file=sys.stderr)
    return 2


@contextlib.contextmanager
def _sigterm_interrupts() -> Iterator[None]:
    """SIGTERM raises KeyboardInterrupt while running, so that the clean-up of a Ctrl-C runs too."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def interrupt(signum: int, frame: object) -> None:
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    if args.command == "list":
        for name, description in packaged_scenarios().items():
            print(f"{name:24s} {description}")
        return 0
    if args.command == "sweep":
        return _sweep(args)
    if args.command == "fleet":
        return _fleet(args)
    return _run(args)


def _run(args: argparse.Namespace) -> int:
    try:
        scenario = load_scenario(args.scenario).with_overrides(
            args.agents, args.seed, args.duration, args.fidelity, args.estimator, args.controller, args.link
        )
        check_run_size(scenario, args.scenario, force=args.force)
    except ScenarioError as error:
        return _fail(error)
    out = args.out or Path("runs") / scenario.name
    try:
        with _sigterm_interrupts():
            result = run_to_directory(scenario, out, progress=not args.quiet, force=args.force)
    except ScenarioError as error:
        return _fail(error)
    except FileExistsError as error:  # the output directory (OutputDirectoryError), its message names it
        return _fail(error)
    except OSError as error:
        return _fail(f"cannot write the outputs to {out}: {error}")
    except KeyboardInterrupt:
        print(f"bob-sitl: interrupted; nothing written to {out}", file=sys.stderr)
        return 130
    summary = {k: v for k, v in result.metrics.items() if not isinstance(v, dict) or k == "criteria"}
    print(json.dumps(summary, indent=2))
    print(f"outputs in {out}/", file=sys.stderr)
    return 0 if result.metrics["passed"] else 1


def _fleet(args: argparse.Namespace) -> int:
    from sitl.process_fleet import ProcessFleetError, ProcessOptions, run_processes_to_directory

    if not args.processes:
        print("bob-sitl: fleet needs --processes (for a fleet in one process use `bob-sitl run`)", file=sys.stderr)
        return 2
    try:
        scenario = load_scenario(args.scenario).with_overrides(
            args.agents, args.seed, args.duration, "physics", args.estimator, args.controller
        )
        check_run_size(scenario, args.scenario, force=args.force)
        options = ProcessOptions(
            speed=args.speed,
            base_port=args.base_port,
            mesh_port=args.mesh_port,
            gcs_port=args.gcs_port,
            external_gcs=args.external_gcs,
        )
    except (ScenarioError, ValueError) as error:
        print(f"bob-sitl: {error}", file=sys.stderr)
        return 2
    out = args.out or Path("runs") / f"{scenario.name}-processes"
    try:
        result = run_processes_to_directory(scenario, out, options, progress=not args.quiet)
    except (ScenarioError, ProcessFleetError, FileExistsError) as error:
        print(f"bob-sitl: {error}", file=sys.stderr)
        return 2
    except OSError as error:  # ports, processes or the outputs
        return _fail(f"the fleet run failed: {error}")
    summary = {k: v for k, v in result.metrics.items() if not isinstance(v, dict) or k in ("criteria", "realtime")}
    print(json.dumps(summary, indent=2))
    print(f"outputs in {out}/", file=sys.stderr)
    return 0 if result.metrics["passed"] else 1


def _sweep(args: argparse.Namespace) -> int:
    if args.runs < 1:
        return _fail(f"--runs must be at least 1, got {args.runs}")
    out = args.out
    try:
        scenario = load_scenario(args.scenario)
        out = out or Path("runs") / f"{scenario.name}-sweep"
        with _sigterm_interrupts():
            rows = run_sweep(
                scenario,
                args.agents,
                range(1, args.runs + 1),
                out,
                args.plot,
                progress=not args.quiet,
                force=args.force,
            )
    except (ScenarioError, FileExistsError) as error:
        return _fail(error)
    except OSError as error:
        return _fail(f"cannot write the outputs to {out}: {error}")
    except KeyboardInterrupt:
        print(f"bob-sitl: interrupted; nothing written to {out}", file=sys.stderr)
        return 130
    print(f"{len(rows)} runs, {sum(r['passed'] for r in rows)} passed their criteria")
    return 0


if __name__ == "__main__":
    sys.exit(main())
