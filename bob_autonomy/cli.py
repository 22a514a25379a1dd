"""The `bob-autonomy` command: the on-vessel autonomy process.

    bob-autonomy behaviors                      # the behaviours and their parameters
    bob-autonomy run --vehicle udpout:127.0.0.1:5760 --system-id 1 --behavior bob-rule --param p0=5 \\
        --mesh udpout:127.0.0.1:15000 --origin 1.3405,103.9560

`run` drives one MAVLink vehicle until SIGTERM or Ctrl-C, then leaves its
actuators at zero. Exit status: 0 after a clean stop, 2 for a bad command line
or configuration, 3 when the vehicle cannot be driven.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import logging.handlers
import signal
import sys
import tomllib

from behaviors.registry import BEHAVIORS
from bob_autonomy.behavior_config import BehaviorChoice
from bob_autonomy.vessel import VehicleError, Vessel, VesselConfig
from firmware_bridge.links import LinkError


def _describe_behaviors() -> str:
    lines = []
    for name, cls in sorted(BEHAVIORS.items()):
        doc = (cls.__doc__ or "").strip().splitlines()[0]
        lines.append(f"{name}: {doc}")
        for f in dataclasses.fields(cls):
            default = f.default if f.default is not dataclasses.MISSING else f.default_factory()
            lines.append(f"    {f.name} = {default!r}")
    return "\n".join(lines)


def _param(text: str) -> tuple[str, object]:
    """KEY=VALUE with VALUE in TOML syntax (5, 0.5, true, [10, 20], "name")."""
    key, sep, value = text.partition("=")
    if not sep or not key.strip():
        raise argparse.ArgumentTypeError(f"expected KEY=VALUE, got {text!r}")
    try:
        parsed = tomllib.loads(f"v = {value}")["v"]
    except tomllib.TOMLDecodeError:
        parsed = value  # a bare word: a string
    return key.strip(), parsed


def _latlon(text: str) -> tuple[float, float]:
    try:
        lat, lon = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected LAT,LON in degrees, got {text!r}") from None
    if not (-90 <= lat <= 90 and -180 <= lon <= 180):
        raise argparse.ArgumentTypeError(f"LAT,LON out of range: {text!r}")
    return lat, lon


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="bob-autonomy", description="BoB autonomy: the on-vessel agent process")
    sub = parser.add_subparsers(dest="command", required=True)
    sub.add_parser("behaviors", help="list the behaviours and their parameters")
    run = sub.add_parser("run", help="drive one MAVLink vehicle as an agent of the swarm")
    run.add_argument("--vehicle", required=True, help="vehicle connection: udpout:H:P, udpin:H:P, tcp:H:P or a device")
    run.add_argument("--baud", type=int, default=115200, help="serial baud rate")
    run.add_argument("--system-id", type=int, required=True, help="the vehicle's MAVLink system id (agent = id - 1)")
    run.add_argument("--kind", choices=["buoy", "ebot"], default="buoy")
    run.add_argument("--mesh", help="swarm mesh link, e.g. udpout:127.0.0.1:15000 (none: the agent acts alone)")
    behavior = run.add_mutually_exclusive_group(required=True)
    behavior.add_argument("--behavior", help="behaviour name (see `bob-autonomy behaviors`)")
    behavior.add_argument("--behavior-json", help='{"behavior": NAME, "params": {...}, "avoid_obstacles": false}')
    run.add_argument("--param", type=_param, action="append", default=[], metavar="KEY=VALUE")
    run.add_argument("--avoid-obstacles", action="store_true", help="wrap the behaviour in obstacle avoidance")
    run.add_argument("--memory-fields", default="[]", help="JSON list: the swarm's broadcast memory fields, in order")
    run.add_argument("--origin", type=_latlon, required=True, help="the swarm's shared origin LAT,LON (deg)")
    run.add_argument("--time-scale", type=float, default=1.0, help="clock speed-up (simulation only)")
    run.add_argument("--dt", type=float, default=0.1, help="control period, s")
    run.add_argument("--broadcast-period", type=float, default=0.1, help="state broadcast period, s")
    run.add_argument("--neighbor-expiry", type=float, default=1.0, help="forget neighbours not heard for this long, s")
    run.add_argument("--estimator", choices=["simple", "ekf"], default="simple")
    run.add_argument("--controller", choices=["mpc", "simple"], default="mpc")
    run.add_argument("--start-x", type=float, default=0.0, help="known start position x (eBots), m")
    run.add_argument("--start-y", type=float, default=0.0, help="known start position y (eBots), m")
    run.add_argument("--start-heading", type=float, default=0.0, help="known start heading (eBots), rad")
    run.add_argument("--max-thrust-fraction", type=float, default=1.0, help="usable share of the nominal thrust")
    run.add_argument("--duration", type=float, help="stop after this many clock seconds")
    run.add_argument("--log-file", help="log here (rotated at 5 MB, 3 kept) instead of stderr")
    run.add_argument("--verbose", action="store_true")
    return parser


def _setup_logging(path: str | None, verbose: bool) -> None:
    handler: logging.Handler
    if path:
        handler = logging.handlers.RotatingFileHandler(path, maxBytes=5_000_000, backupCount=3)
    else:
        handler = logging.StreamHandler()
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    logging.basicConfig(level=logging.DEBUG if verbose else logging.INFO, handlers=[handler], force=True)


def config_from_args(args: argparse.Namespace) -> VesselConfig:
    """A VesselConfig from the `run` arguments (ValueError saying what is wrong)."""
    if args.behavior_json:
        try:
            data = json.loads(args.behavior_json)
        except json.JSONDecodeError as error:
            raise ValueError(f"--behavior-json is not JSON: {error}") from None
    else:
        data = {"behavior": args.behavior, "params": dict(args.param), "avoid_obstacles": args.avoid_obstacles}
    try:
        choice = BehaviorChoice.model_validate(data)
        fields = json.loads(args.memory_fields)
    except Exception as error:  # pydantic or JSON: one clear line
        raise ValueError(f"bad behaviour configuration: {error}") from None
    if not isinstance(fields, list) or not all(isinstance(f, str) for f in fields):
        raise ValueError(f"--memory-fields must be a JSON list of names, got {args.memory_fields!r}")
    return VesselConfig(
        vehicle=args.vehicle,
        baud=args.baud,
        system_id=args.system_id,
        kind=args.kind,
        mesh=args.mesh,
        behavior=choice,
        memory_fields=tuple(fields),
        origin=args.origin,
        time_scale=args.time_scale,
        dt_s=args.dt,
        broadcast_period_s=args.broadcast_period,
        neighbor_expiry_s=args.neighbor_expiry,
        estimator=args.estimator,
        controller=args.controller,
        start_pose=(args.start_x, args.start_y, args.start_heading),
        max_thrust_fraction=args.max_thrust_fraction,
    )


def _run(args: argparse.Namespace) -> int:
    _setup_logging(args.log_file, args.verbose)
    log = logging.getLogger("bob-autonomy")
    try:
        config = config_from_args(args)
        vessel = Vessel(config)
    except (ValueError, LinkError) as error:
        print(f"bob-autonomy: {error}", file=sys.stderr)
        log.error("%s", error)
        return 2
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: vessel.stop())
    log.info("vessel %d (%s) running %s on %s", config.system_id, config.kind, config.behavior.behavior, config.vehicle)
    try:
        stats = vessel.run(args.duration)
    except VehicleError as error:
        vessel.shutdown()
        print(f"bob-autonomy: {error}", file=sys.stderr)
        log.error("%s", error)
        return 3
    log.info("stopped cleanly: %s", json.dumps(stats.summary()))
    return 0


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    if args.command == "behaviors":
        print(_describe_behaviors())
        return 0
    return _run(args)


if __name__ == "__main__":
    sys.exit(main())
