"""The `bob-autonomy` command: the on-vessel autonomy process.

    bob-autonomy behaviors                      # the behaviours and their parameters
    bob-autonomy run --vehicle udpout:127.0.0.1:5760 --system-id 1 --behavior bob-rule --param p0=5 \\
        --mesh udpout:127.0.0.1:15000 --origin 1.3405,103.9560
    bob-autonomy run --config /etc/bob/vessel.toml      # as a service (docs/vessel.toml, docs/bob-autonomy.service)
    bob-autonomy --config /etc/bob/vessel.toml          # the same: `run` is the default command

`run` drives one MAVLink vehicle until SIGTERM or Ctrl-C, then leaves its
actuators at zero. A config file holds the same settings as the options (names
with underscores: `system_id = 3`, `param = ["p0=5"]`); options given on the
command line win. Exit status: 0 after a clean stop, 2 for a bad command line
or configuration, 3 when the vehicle cannot be driven.

A config file that cannot be used (missing, not a regular file, over 1 MiB, not
UTF-8, not TOML, nested too deeply, an unknown setting, a value of the wrong
type, a non-finite number) is reported in one line naming the file and the
setting, with exit status 2, never a traceback. Numbers given as options must
be finite too, and periods and time limits positive.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import logging
import logging.handlers
import math
import os
import select
import signal
import sys
import time
import tomllib
import traceback

from behaviors.registry import BEHAVIORS
from bob_autonomy.core.behavior_config import BehaviorChoice
from bob_autonomy.core.safe_read import (
    MAX_SETTINGS_FILE_BYTES,
    UnreadableFileError,
    describe_parse_error,
    read_small_file,
)
from bob_autonomy.onboard.autopilot_start import StartOptions
from bob_autonomy.onboard.vessel import VehicleError, Vessel, VesselConfig
from firmware_bridge.decoder import MAX_GPS_LAG_S


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
    except Exception as error:  # RecursionError from deep nesting, MemoryError
        raise argparse.ArgumentTypeError(f"{key.strip()}: {describe_parse_error(error)}") from None
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
    run.add_argument("--config", help="TOML file with any of these settings (options given here win)")
    run.add_argument("--vehicle", help="vehicle connection: udpout:H:P, udpin:H:P, tcp:H:P or a device (required)")
    run.add_argument(
        "--baud",
        type=int,
        default=57600,
        help="the vehicle link's serial baud rate (57600: ArduPilot's TELEM ports leave the factory at it)",
    )
    run.add_argument("--system-id", type=int, help="the vehicle's MAVLink system id, agent = id - 1 (required)")
    run.add_argument("--kind", choices=["buoy", "motorboat", "ebot"], default="buoy")
    run.add_argument(
        "--mesh",
        help="swarm mesh link: an XBee's serial port (/dev/ttyUSB1), an IP radio's broadcast "
        "(udpbcast:192.168.1.255:15000) or the simulator's relay (udpout:127.0.0.1:15000); none: the agent acts alone",
    )
    run.add_argument(
        "--mesh-baud", type=int, default=115200, help="the mesh's serial baud rate (an XBee's BD: 7 is 115200)"
    )
    behavior = run.add_mutually_exclusive_group()
    behavior.add_argument("--behavior", help="behaviour name (see `bob-autonomy behaviors`; one of the two required)")
    behavior.add_argument("--behavior-json", help='{"behavior": NAME, "params": {...}, "avoid_obstacles": false}')
    run.add_argument("--param", type=_param, action="append", default=[], metavar="KEY=VALUE")
    run.add_argument("--avoid-obstacles", action="store_true", help="wrap the behaviour in obstacle avoidance")
    run.add_argument("--memory-fields", default="[]", help="JSON list: the swarm's broadcast memory fields, in order")
    run.add_argument("--origin", type=_latlon, help="the swarm's shared origin LAT,LON in deg (required)")
    run.add_argument("--time-scale", type=float, default=1.0, help="clock speed-up (simulation only)")
    run.add_argument("--dt", type=float, default=0.1, help="control period, s")
    run.add_argument("--broadcast-period", type=float, default=0.1, help="state broadcast period, s")
    run.add_argument("--neighbor-expiry", type=float, default=1.0, help="forget neighbours not heard for this long, s")
    run.add_argument("--estimator", choices=["simple", "ekf"], default="ekf")
    run.add_argument("--controller", choices=["mpc", "simple"], default="mpc")
    run.add_argument("--start-x", type=float, default=0.0, help="known start position x (eBots), m")
    run.add_argument("--start-y", type=float, default=0.0, help="known start position y (eBots), m")
    run.add_argument("--start-heading", type=float, default=0.0, help="known start heading (eBots), rad")
    run.add_argument("--max-thrust-fraction", type=float, default=1.0, help="usable share of the nominal thrust")
    run.add_argument(
        "--vehicle-timeout", type=float, default=3.0, help="vehicle lost after this long with no HEARTBEAT, s"
    )
    run.add_argument(
        "--gcs",
        help="ground-station link, e.g. udpout:10.0.0.1:14550, udpin:0.0.0.0:14560 or a telemetry radio's serial port",
    )
    run.add_argument("--gcs-baud", type=int, default=57600, help="a serial ground-station link's baud rate")
    run.add_argument("--params-file", help="persistent parameters (JSON, written atomically); default: in memory")
    run.add_argument("--signing-key", help="MAVLink 2 signing key file (see docs/gcs-protocol.md)")
    run.add_argument("--mesh-key", help="fleet key file: sign and check every mesh packet (docs/mesh.md)")
    run.add_argument("--wait-for-start", action="store_true", help="hold until the GCS sends MISSION_START")
    run.add_argument("--tlog", help="append every MAVLink frame in and out to this .tlog")
    run.add_argument(
        "--on-stop",
        choices=["neutral", "hold", "disarm"],
        default="neutral",
        help="after the neutral commands on stop: leave the mode (neutral), set HOLD, or disarm",
    )
    run.add_argument(
        "--force-arm", action="store_true", help="arm even when the autopilot's checks fail (never on water)"
    )
    run.add_argument(
        "--no-recover-after-reboot",
        dest="recover_after_reboot",
        action="store_false",
        help="when the autopilot restarts under us (brownout, watchdog), stay at neutral instead of setting it up "
        "and arming it again",
    )
    run.add_argument(
        "--arm-timeout", type=float, default=60.0, help="give up when the autopilot will not arm for this long, s"
    )
    run.add_argument(
        "--ready-timeout", type=float, default=120.0, help="wait this long for a GPS fix and passing checks, s"
    )
    run.add_argument(
        "--top-speed", type=float, help="the vessel's speed at full throttle, m/s (default: from the autopilot)"
    )
    run.add_argument(
        "--gps-lag",
        type=float,
        help="GPS lag from measurement to the autopilot reading the fix, s (0-1; default: the autopilot's "
        "GPS1_DELAY_MS, else 0): fixes are fused that much before the autopilot's time stamp",
    )
    run.add_argument("--duration", type=float, help="stop after this many clock seconds")
    run.add_argument("--log-file", help="log here (rotated at 5 MB, 3 kept) instead of stderr")
    run.add_argument("--verbose", action="store_true")
    parser.run_parser = run  # type: ignore[attr-defined] - for --config defaults
    return parser


class _StderrHandler(logging.StreamHandler):
    """A stream handler that writes to whatever sys.stderr is when a record comes, not to the one it was made
    with: the vessel's threads log for as long as it runs, and a caller that swapped stderr and closed its copy
    (a test's capture, a supervisor) must not turn each record into a logging error."""

    def __init__(self) -> None:
        super().__init__(sys.stderr)

    @property
    def stream(self):  # type: ignore[override]
        return sys.stderr

    @stream.setter
    def stream(self, _value: object) -> None:
        pass


def _setup_logging(path: str | None, verbose: bool) -> None:
    handler: logging.Handler = (
        logging.handlers.RotatingFileHandler(path, maxBytes=5_000_000, backupCount=3) if path else _StderrHandler()
    )
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    logging.basicConfig(level=logging.DEBUG if verbose else logging.INFO, handlers=[handler], force=True)


# Options that are periods, rates or limits: a zero or negative value would spin or never stop (s, or a factor).
_POSITIVE = {
    "time_scale",
    "dt",
    "broadcast_period",
    "neighbor_expiry",
    "vehicle_timeout",
    "max_thrust_fraction",
    "arm_timeout",
    "ready_timeout",
    "top_speed",
}


def _read_config(path: str) -> dict[str, object]:
    """The settings of a --config TOML file; ValueError naming the file and what is wrong with it."""
    try:
        raw = read_small_file(path, MAX_SETTINGS_FILE_BYTES)
    except FileNotFoundError:
        raise ValueError(f"config {path!r}: no such file") from None
    except UnreadableFileError as error:
        raise ValueError(f"config {path!r} {error}") from None
    try:
        return tomllib.loads(raw.decode("utf-8"))
    except tomllib.TOMLDecodeError as error:
        raise ValueError(f"config {path!r} is not valid TOML: {error}") from None
    except Exception as error:  # RecursionError (deep nesting), MemoryError, UnicodeDecodeError
        raise ValueError(f"config {path!r} cannot be read: {describe_parse_error(error)}") from None


def _config_value(action: argparse.Action, value: object, where: str) -> object:
    """A config file's `value` for the option of `action`, checked and converted as the option would be."""
    name = action.dest

    def wrong(expected: str) -> ValueError:
        shown = repr(value) if len(repr(value)) <= 60 else repr(value)[:57] + "..."
        return ValueError(f"{where}: setting {name!r} must be {expected}, got {shown}")

    try:
        if isinstance(action, argparse._StoreTrueAction | argparse._StoreFalseAction):  # the setting's value
            if not isinstance(value, bool):
                raise wrong("true or false")
            return value
        if name == "param":
            if not isinstance(value, list) or not all(isinstance(p, str) for p in value):
                raise wrong('a list of "KEY=VALUE" strings')
            return [_param(p) for p in value]
        if name == "origin":
            if isinstance(value, list) and len(value) == 2 and all(_is_number(v) for v in value):
                value = f"{value[0]},{value[1]}"
            if not isinstance(value, str):
                raise wrong('"LAT,LON" in degrees')
            return _latlon(value)
        if action.type is int:
            if isinstance(value, str):
                value = int(value)
            if isinstance(value, bool) or not isinstance(value, int):
                raise wrong("an integer")
        elif action.type is float:
            if isinstance(value, str):
                value = float(value)
            if not _is_number(value) or not math.isfinite(value):  # type: ignore[arg-type]
                raise wrong("a finite number")
            value = float(value)  # type: ignore[arg-type]
            if name in _POSITIVE and value <= 0:
                raise wrong("greater than 0")
        elif not isinstance(value, str):
            raise wrong("a string")
    except (argparse.ArgumentTypeError, ValueError, OverflowError) as error:
        if str(error).startswith(where):
            raise
        raise ValueError(f"{where}: setting {name!r}: {error}") from None
    if action.choices is not None and value not in action.choices:
        raise wrong(f"one of {list(action.choices)}")
    return value


def _is_number(value: object) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def _check_numbers(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Every float option finite; periods, rates and limits positive (ValueError naming the option)."""
    for action in parser._actions:
        value = getattr(args, action.dest, None)
        if action.type is not float or value is None:
            continue
        option = action.option_strings[0]
        if not math.isfinite(value):
            raise ValueError(f"{option} {value}: must be a finite number")
        if action.dest in _POSITIVE and value <= 0:
            raise ValueError(f"{option} {value}: must be greater than 0")
    if args.duration is not None and args.duration < 0:
        raise ValueError(f"--duration {args.duration}: must not be negative")
    if args.gps_lag is not None and not 0 <= args.gps_lag <= MAX_GPS_LAG_S:
        raise ValueError(f"--gps-lag {args.gps_lag}: must be within 0..{MAX_GPS_LAG_S:g} s")
    if args.max_thrust_fraction > 1:
        raise ValueError(f"--max-thrust-fraction {args.max_thrust_fraction}: must be at most 1")


def _apply_config_file(parser: argparse.ArgumentParser, argv: list[str] | None) -> argparse.Namespace:
    """Parse `run` arguments with a --config file's settings as defaults (ValueError naming file and key)."""
    args = parser.parse_args(argv)
    if args.command != "run":
        return args
    run_parser = parser.run_parser  # type: ignore[attr-defined]
    if args.config:
        settings = _read_config(args.config)
        where = f"config {args.config!r}"
        actions = {a.dest: a for a in run_parser._actions if a.dest not in ("help", "config")}
        unknown = sorted(set(settings) - set(actions))
        if unknown:
            raise ValueError(f"{where}: unknown setting(s) {unknown}")
        run_parser.set_defaults(**{k: _config_value(actions[k], v, where) for k, v in settings.items()})
        args = parser.parse_args(argv)
    _check_numbers(run_parser, args)
    return args


def config_from_args(args: argparse.Namespace) -> VesselConfig:
    """A VesselConfig from the `run` arguments (ValueError saying what is wrong)."""
    missing = [
        f"--{name.replace('_', '-')}" for name in ("vehicle", "system_id", "origin") if getattr(args, name) is None
    ]
    if not (args.behavior or args.behavior_json):
        missing.append("--behavior or --behavior-json")
    if missing:
        raise ValueError(f"missing required setting(s): {', '.join(missing)}")
    if args.behavior_json:
        try:
            data = json.loads(args.behavior_json)
        except Exception as error:  # JSONDecodeError, RecursionError (deep nesting), MemoryError
            raise ValueError(f"--behavior-json is not JSON: {describe_parse_error(error)}") from None
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
        mesh_baud=args.mesh_baud,
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
        heartbeat_timeout_s=args.vehicle_timeout,
        gcs=args.gcs,
        gcs_baud=args.gcs_baud,
        params_file=args.params_file,
        signing_key_file=args.signing_key,
        mesh_key_file=args.mesh_key,
        autostart=not args.wait_for_start,
        tlog=args.tlog,
        arm_timeout_s=args.arm_timeout,
        autopilot=StartOptions(force_arm=args.force_arm, ready_timeout_s=args.ready_timeout),
        on_stop=args.on_stop,
        recover_after_reboot=args.recover_after_reboot,
        top_speed_mps=args.top_speed,
        gps_lag_s=args.gps_lag,
    )


def _run(args: argparse.Namespace) -> int:
    try:
        _setup_logging(args.log_file, args.verbose)
    except OSError as error:
        print(f"bob-autonomy: cannot open the log file {args.log_file!r}: {error}", file=sys.stderr)
        return 2
    log = logging.getLogger("bob-autonomy")
    try:
        config = config_from_args(args)
        vessel = Vessel(config)
    except (ValueError, OSError) as error:  # bad settings, a link or key file that cannot be opened
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


def _join_negative_values(argv: list[str]) -> list[str]:
    """`--origin -35.36,149.16` as `--origin=-35.36,149.16`: argparse takes a value that starts with '-' and is
    not a plain number for an option (issue #18)."""
    out: list[str] = []
    k = 0
    while k < len(argv):
        if argv[k] == "--origin" and k + 1 < len(argv) and argv[k + 1][:1] == "-" and argv[k + 1][1:2].isdigit():
            out.append(f"--origin={argv[k + 1]}")
            k += 2
            continue
        out.append(argv[k])
        k += 1
    return out


def _fast_exit(code: int) -> None:
    """End this process now with `code`, after flushing the logs and the standard streams: skips the
    interpreter's teardown (~0.1 s of CPU with numpy, casadi and pymavlink loaded), which 45 autonomy processes
    stopping at once on 2 cores turn into seconds (issue #13: processes killed after their stop timeout)."""
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    os._exit(code)


def _forked_vessel(argv: list[str], out_path: str, nice: int, request_fd: int, reply_fd: int) -> None:
    """In a child of the fork server: its own session, `nice` added to its niceness, standard output and error
    to `out_path`, SIGTERM when the fork server dies, then `bob-autonomy` with `argv`; never returns."""
    code = 1
    try:
        os.close(request_fd)
        os.close(reply_fd)
        os.setsid()
        lower_priority(nice)
        die_with_parent()
        for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGCHLD):
            signal.signal(sig, signal.SIG_DFL)
        null = os.open(os.devnull, os.O_RDONLY)
        out = os.open(out_path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        os.dup2(null, 0)
        os.dup2(out, 1)
        os.dup2(out, 2)
        os.close(null)
        os.close(out)
        sys.stdout.reconfigure(line_buffering=True)  # type: ignore[union-attr]
        sys.argv = ["bob-autonomy", *argv]
        code = main(argv)
    except SystemExit as stop:
        code = stop.code if isinstance(stop.code, int) else 1
    except BaseException:
        traceback.print_exc()
    _fast_exit(code)


def serve_forks(request_fd: int = 0, reply_fd: int = 1) -> int:
    """`bob-autonomy fork-server`: start autonomy processes by forking one interpreter that has already
    imported everything a vessel needs (simulated fleets: 45 `bob-autonomy run` processes on 2 cores each
    spent ~1 s of CPU importing numpy, scipy, casadi, pymavlink and pydantic; forked, they share it).

    Requests, one JSON object a line on `request_fd`: {"argv": [...], "out": PATH, "nice": N} (the arguments
    of `bob-autonomy`, where its standard output and error go, and the niceness to add, 0 if absent).
    Replies, a JSON line each on `reply_fd`: {"pid": N} for every request, in order; {"exit": N, "status":
    CODE, "t": MONOTONIC_S} when a child ends (CODE as subprocess's returncode: negative for a signal; t on
    the system's monotonic clock, s); {"error": TEXT} for a bad request. At end of input: waits for its
    children, then exits 0.
    """
    import bob_autonomy.onboard.vessel  # noqa: F401 - everything a vessel imports, once, before any fork
    from bob_autonomy.control.mpc import BuoyMpc

    BuoyMpc()  # loads casadi's QP plugin library before the forks
    die_with_parent()
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the fleet stops the children; Ctrl-C is the fleet's
    reply_fd = os.dup(reply_fd)
    os.dup2(2, 1)  # a stray print goes to standard error, never into the replies
    children: set[int] = set()
    pending = b""
    reading = True

    def reply(message: dict) -> None:
        data = (json.dumps(message) + "\n").encode()
        while data:
            data = data[os.write(reply_fd, data) :]

    while reading or children:
        if reading:
            ready = select.select([request_fd], [], [], 0.02)[0]
        else:
            ready = []
            time.sleep(0.02)
        while children:
            pid, status = os.waitpid(-1, os.WNOHANG)
            if pid == 0:
                break
            children.discard(pid)
            reply({"exit": pid, "status": os.waitstatus_to_exitcode(status), "t": time.monotonic()})
        if not ready:
            continue
        chunk = os.read(request_fd, 65536)
        reading = bool(chunk)
        pending += chunk
        *lines, pending = pending.split(b"\n")
        for line in lines:
            try:
                request = json.loads(line)
                argv, out = [str(a) for a in request["argv"]], str(request["out"])
                nice = int(request.get("nice", 0))
                if not 0 <= nice <= 19:
                    raise ValueError(f"nice must be 0..19, got {nice}")
            except (ValueError, KeyError, TypeError, AttributeError) as error:
                reply({"error": f"bad request: {error}"})
                continue
            pid = os.fork()
            if pid == 0:
                _forked_vessel(argv, out, nice, request_fd, reply_fd)
            children.add(pid)
            reply({"pid": pid})
    return 0


def lower_priority(nice: int) -> None:
    """Add `nice` (0..19) to this process's niceness, and to its session's scheduling group where Linux groups
    sessions (sched_autogroup: CPU is shared between sessions first, so niceness alone does not count against
    processes of other sessions, such as the simulator that started this one)."""
    if nice:
        os.nice(nice)
        with contextlib.suppress(OSError), open("/proc/self/autogroup", "w") as autogroup:
            autogroup.write(str(nice))


def die_with_parent() -> None:
    """On Linux, ask for SIGTERM when the parent process dies, even by SIGKILL, so that no autonomy process
    outlives the fleet that started it (elsewhere a no-op)."""
    if sys.platform.startswith("linux"):
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG


def main(argv: list[str] | None = None) -> int:
    """`bob-autonomy` with `argv` (default: the command line, and then a `run` ends the process itself)."""
    program = argv is None
    argv = _join_negative_values(list(sys.argv[1:] if argv is None else argv))
    if argv == ["fork-server"]:
        return serve_forks()
    if argv and argv[0].startswith("--") and argv[0] not in ("--help", "-h"):
        argv.insert(0, "run")  # `bob-autonomy --vehicle ... --behavior ...` is `bob-autonomy run ...`
    try:
        args = _apply_config_file(_parser(), argv)
    except ValueError as error:
        print(f"bob-autonomy: {error}", file=sys.stderr)
        return 2
    if args.command == "behaviors":
        print(_describe_behaviors())
        return 0
    code = _run(args)
    if program:  # the process ends here: skip the interpreter's teardown (see _fast_exit)
        _fast_exit(code)
    return code


if __name__ == "__main__":
    sys.exit(main())
