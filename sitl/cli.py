"""The `bob-sitl` command: list and run scenarios, sweep them, reproduce the paper, run them as a fleet of processes.

Exit status: 0 when every criterion passed (a sweep: when it finished; a reproduction: when every
criterion passed at 9 of 10 seeds), 1 when one failed, 2 for a bad scenario, option, output
directory or Dask cluster (one message naming the file or option and the key), 130 when a run,
sweep or reproduction is interrupted (Ctrl-C or SIGTERM; a run writes nothing, a sweep or a
reproduction keeps its finished runs for --resume).
Runs larger than `sitl.fleets.budget`'s limits are refused before they start unless
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

from sitl.experiments.distributed import ClusterError
from sitl.experiments.runner import run_to_directory
from sitl.experiments.scenario import ScenarioError, load_scenario, packaged_scenarios
from sitl.experiments.sweep import parse_param, partial_path, read_partial, run_sweep
from sitl.fleets.budget import MAX_AGENT_STEPS, MAX_AGENTS, MAX_TRAJECTORY_ROWS, check_run_size
from sitl.vehicles.vessel_shards import VesselProcessError

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
    run.add_argument(
        "--vessel-processes",
        type=_positive_int,
        default=1,
        metavar="N",
        help="physics: run the buoys' estimators, controllers and MAVLink links in N processes "
        "(the same results, sooner on N cores; default 1)",
    )
    run.add_argument(
        "--animate",
        action="store_true",
        help="also write an animation of the run (animation.mp4 with ffmpeg, else animation.gif)",
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
        help="leave --gcs-port to your mission script (bob_autonomy.ground.mission); the scenario may not have events",
    )
    fleet.add_argument(
        "--vessel-nice",
        type=int,
        default=0,
        metavar="N",
        help="niceness 0..19 of the autonomy processes above the fleet's: with more vessels than the cores can run, "
        "the world keeps wall time and the vessels lag (default 0)",
    )
    fleet.add_argument("--quiet", action="store_true", help="no progress bar")
    fleet.add_argument("--force", action="store_true", help=FORCE_HELP)
    sweep = sub.add_parser(
        "sweep", help="run a scenario over swarm sizes, parameter values and seeds; plot metrics against one of them"
    )
    sweep.add_argument("scenario", metavar="NAME|FILE")
    sweep.add_argument("--agents", type=int, nargs="+", help="swarm sizes (default: the scenario's)")
    sweep.add_argument(
        "--param",
        action="append",
        default=[],
        metavar="PATH=V1,V2,...",
        help="sweep a scenario value: a dotted path (network.range_m, groups.0.params.p0, "
        "environment.wind.speed_mps) and its values; repeatable: the runs are the product",
    )
    sweep.add_argument("--runs", type=int, default=10, help="seeds per size and values (1..RUNS)")
    sweep.add_argument("--duration", type=float, metavar="SECONDS", help="simulated duration of each run, s")
    sweep.add_argument("--plot", nargs="+", default=[], metavar="METRIC", help="scalar metrics to plot")
    sweep.add_argument("--x", metavar="PATH", help="the plot's axis: agents or a --param path")
    sweep.add_argument("--out", type=Path, metavar="DIR", help="output directory (default: runs/NAME-sweep)")
    _execution_options(sweep)
    sweep.add_argument("--quiet", action="store_true", help="no progress bar")
    sweep.add_argument("--force", action="store_true", help=FORCE_HELP)
    reproduce = sub.add_parser(
        "reproduce", help="run the paper's experiments over many seeds; report each criterion's pass rate"
    )
    reproduce.add_argument(
        "experiments", nargs="*", metavar="EXPERIMENT", help="names or DESIGN.md numbers (default: all)"
    )
    reproduce.add_argument("--seeds", type=int, required=True, metavar="N", help="seeds per experiment")
    reproduce.add_argument("--first-seed", type=int, default=1, metavar="S", help="seeds S..S+N-1 (default 1)")
    reproduce.add_argument("--out", type=Path, metavar="DIR", help="output directory (default: runs/reproduce)")
    reproduce.add_argument(
        "--duration", type=float, metavar="SECONDS", help="cap every experiment's duration (smoke tests only)"
    )
    _execution_options(reproduce)
    reproduce.add_argument("--quiet", action="store_true", help="no progress bar")
    reproduce.add_argument("--force", action="store_true", help=FORCE_HELP)
    return parser


def _execution_options(parser: argparse.ArgumentParser) -> None:
    where = parser.add_mutually_exclusive_group()
    where.add_argument("--workers", type=int, metavar="N", help="run on a local Dask cluster of N processes")
    where.add_argument(
        "--scheduler", metavar="ADDRESS", help="run on an existing Dask cluster (e.g. tcp://10.0.0.5:8786)"
    )
    parser.add_argument(
        "--resume", action="store_true", help="continue an interrupted run: its finished runs are skipped"
    )


def _positive_int(text: str) -> int:
    """argparse type: a whole number of at least 1."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"{value} is not at least 1")
    return value


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
    if args.command == "reproduce":
        return _reproduce(args)
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
            result = run_to_directory(
                scenario, out, progress=not args.quiet, force=args.force, vessel_processes=args.vessel_processes
            )
    except ScenarioError as error:
        return _fail(error)
    except FileExistsError as error:  # the output directory (OutputDirectoryError), its message names it
        return _fail(error)
    except VesselProcessError as error:
        return _fail(f"{error}\nnothing written to {out}")
    except OSError as error:
        return _fail(f"cannot write the outputs to {out}: {error}")
    except KeyboardInterrupt:
        print(f"bob-sitl: interrupted; nothing written to {out}", file=sys.stderr)
        return 130
    if args.animate:
        from sitl.experiments.animate import write_animation

        try:
            with _sigterm_interrupts():
                movie = write_animation(result.fleet, result.recorder, out)
        except (OSError, ValueError) as error:
            return _fail(f"the run's outputs are in {out}/, but the animation could not be written: {error}")
        except KeyboardInterrupt:
            print(f"bob-sitl: interrupted; the run's outputs are in {out}/, without the animation", file=sys.stderr)
            return 130
        print(f"animation: {movie}", file=sys.stderr)
    summary = {k: v for k, v in result.metrics.items() if not isinstance(v, dict) or k == "criteria"}
    print(json.dumps(summary, indent=2))
    print(f"outputs in {out}/", file=sys.stderr)
    return 0 if result.metrics["passed"] else 1


def _fleet(args: argparse.Namespace) -> int:
    from sitl.fleets.process_fleet import ProcessFleetError, ProcessOptions, run_processes_to_directory

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
            vessel_nice=args.vessel_nice,
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
        params = [parse_param(text) for text in args.param]
        scenario = load_scenario(args.scenario).with_overrides(duration_s=args.duration)
        out = out or Path("runs") / f"{scenario.name}-sweep"
        with _sigterm_interrupts(), _keeps_partial(out):
            rows = run_sweep(
                scenario,
                args.agents,
                range(1, args.runs + 1),
                out,
                args.plot,
                progress=not args.quiet,
                force=args.force,
                params=params,
                x=args.x,
                workers=args.workers,
                scheduler=args.scheduler,
                resume=args.resume,
            )
    except (ScenarioError, FileExistsError, ClusterError) as error:
        return _fail(error)
    except OSError as error:
        return _fail(f"cannot write the outputs to {out}: {error}")
    except KeyboardInterrupt:
        return 130
    print(f"{len(rows)} runs, {sum(bool(r['passed']) for r in rows)} passed their criteria; outputs in {out}/")
    return 0


def _reproduce(args: argparse.Namespace) -> int:
    from sitl.experiments.reproduce import PASS_RATE, reproduce, reproduced

    if args.seeds < 1:
        return _fail(f"--seeds must be at least 1, got {args.seeds}")
    if args.first_seed < 0:
        return _fail(f"--first-seed must be at least 0, got {args.first_seed}")
    out = args.out or Path("runs") / "reproduce"
    try:
        with _sigterm_interrupts(), _keeps_partial(out):
            report = reproduce(
                args.experiments,
                range(args.first_seed, args.first_seed + args.seeds),
                out,
                duration_s=args.duration,
                workers=args.workers,
                scheduler=args.scheduler,
                resume=args.resume,
                progress=not args.quiet,
                force=args.force,
            )
    except (ScenarioError, FileExistsError, ClusterError) as error:
        return _fail(error)
    except OSError as error:
        return _fail(f"cannot write the outputs to {out}: {error}")
    except KeyboardInterrupt:
        return 130
    short = [r for r in report if r["item"] == "criterion" and r["pass_rate"] < PASS_RATE - 1e-12]
    for r in short:
        print(f"{r['experiment']}: {r['name']} passed at {r['passed']} of {r['runs']} seeds", file=sys.stderr)
    print(f"report in {out}/report.md")
    return 0 if reproduced(report) else 1


@contextlib.contextmanager
def _keeps_partial(out: Path) -> Iterator[None]:
    """On an interrupt or a failed run, say what was kept of the finished runs and how to go on."""
    try:
        yield
    except KeyboardInterrupt:
        kept = len(read_partial(partial_path(out)))
        if kept:
            print(
                f"bob-sitl: interrupted; {kept} finished run(s) kept in {partial_path(out)}: the same command "
                "with --resume continues",
                file=sys.stderr,
            )
        else:
            print(f"bob-sitl: interrupted; nothing written to {out}", file=sys.stderr)
        raise
    except (ScenarioError, FileExistsError):
        raise  # before the first run: nothing to keep
    except Exception as error:
        kept = len(read_partial(partial_path(out)))
        if kept:
            what = "a Dask worker differs" if isinstance(error, ClusterError) else "a run failed"
            print(f"bob-sitl: {what}; {kept} finished run(s) kept in {partial_path(out)}", file=sys.stderr)
        raise


if __name__ == "__main__":
    sys.exit(main())
