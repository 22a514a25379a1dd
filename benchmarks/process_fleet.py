"""Process fleets at speed 1: how fast 45 (optionally 100) `bob-autonomy` processes start, keep time and stop.

Runs the `aggregation` scenario without its events (45 buoys, wind and current, lossy radio; every vessel a
separate `bob-autonomy run` process with MAVLink, EKF and MPC) as a process fleet in real time, and prints a
JSON line per run:

    start_s            wall s from the fleet's start until every vehicle was armed and the pre-roll done
    late_fraction      share of physics steps that began more than half a step late (and max_lag_s)
    mpc_fallbacks      MPC fallbacks in the vessels' logs ("MPC fallback"), over_budget those over the time budget;
                       mpc_fallbacks_counted: the vessels' own counts (their stop summaries)
    latency_p99_ms     the vessels' control-step compute latency, p99 (median and max over vessels)
    stop_s_max/median  wall s from SIGTERM to each process's exit; killed: processes that had to be SIGKILLed
    rss/pss_mib        resident memory per autonomy process at the end (RSS counts shared pages; PSS shares them)
    *_cpu_share        CPU used per wall s (of one core): each vessel's since it started, the fleet process's
    load_before/after  the machine's 1-minute load average (other users included)

    nice -n 10 python benchmarks/process_fleet.py                  # 45 vessels, 90 s
    nice -n 10 python benchmarks/process_fleet.py --hundred        # then 100 vessels too
    nice -n 10 python benchmarks/process_fleet.py --launcher exec  # one interpreter per vessel, as before
    nice -n 10 python benchmarks/process_fleet.py --signal TERM    # stopped by SIGTERM (or INT) after 40 s
    python benchmarks/process_fleet.py --profile-startup --runs 0  # where one process's start-up goes

The vessels run at niceness 10 above the fleet (`--vessel-nice`, as `bob-sitl fleet --vessel-nice 10`): the
simulated world (physics and autopilots, which are separate hardware on a real boat) keeps wall time, and when
the cores are short the vessels lag, as slow on-board computers would (their latency_p99_ms says by how much).
On a 2-core host 45 vessels need about 1.7 cores by themselves; at the same priority as the world, 98-99 % of
the world's steps began late. `--vessel-nice 0` measures that.

Heavy: run alone, under nice, one at a time (2 cores shared).
"""

from __future__ import annotations

import argparse
import cProfile
import io
import json
import os
import pstats
import re
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from sitl.experiments.scenario import load_scenario
from sitl.fleets.process_fleet import ProcessOptions, run_processes_to_directory

STOPPED = re.compile(r"stopped cleanly: (\{.*\})")


def vessel_log_figures(out: Path) -> dict[str, object]:
    """MPC fallbacks and control-step latencies read from the vessels' logs."""
    fallbacks = over_budget = counted = 0
    p99 = []
    for log in sorted(out.glob("vessel-*.log")):
        for line in log.read_text(errors="replace").splitlines():
            if "MPC fallback" in line:
                fallbacks += 1
                over_budget += "time budget" in line
            elif (match := STOPPED.search(line)) is not None:
                summary = json.loads(match.group(1))
                counted += summary.get("mpc_fallbacks", 0)
                if "compute_latency_s_p99" in summary:
                    p99.append(summary["compute_latency_s_p99"])
    return {
        "mpc_fallbacks": fallbacks,
        "over_budget": over_budget,
        "mpc_fallbacks_counted": counted,  # the vessels' own count (mpc_fallbacks in their stop summaries)
        "latency_p99_ms_median": round(1e3 * statistics.median(p99), 2) if p99 else None,
        "latency_p99_ms_max": round(1e3 * max(p99), 2) if p99 else None,
    }


def run_fleet(
    agents: int,
    duration_s: float,
    launcher: str,
    base_port: int,
    keep: Path | None = None,
    vessel_nice: int = 0,
    stop_signal: str | None = None,
    signal_after_s: float = 40.0,
) -> dict[str, object]:
    """One process fleet of `agents` buoys for duration_s at speed 1 (or until `stop_signal`, INT or TERM, is
    sent to this process signal_after_s wall s after the start); its figures (outputs kept in `keep`)."""
    scenario = load_scenario("aggregation").with_overrides(agents, None, duration_s, "physics")
    scenario = scenario.model_copy(update={"events": []})
    options = ProcessOptions(
        speed=1.0,
        base_port=base_port,
        mesh_port=base_port - 100,
        gcs_port=base_port - 99,
        fork_server=launcher == "fork-server",
        arm_timeout_s=180.0,
        vessel_nice=vessel_nice,
    )
    load_before = os.getloadavg()[0]
    if stop_signal is not None:  # as Ctrl-C or `kill` would: the fleet stops early and still writes its outputs
        timer = threading.Timer(signal_after_s, os.kill, (os.getpid(), signal.Signals[f"SIG{stop_signal}"]))
        timer.daemon = True
        timer.start()
    with tempfile.TemporaryDirectory(prefix="process-fleet-") as tmp:
        out = Path(tmp) / "run" if keep is None else keep / f"{launcher}-{agents}"
        wall = time.monotonic()
        result = run_processes_to_directory(scenario, out, options)
        wall = time.monotonic() - wall
        logs = vessel_log_figures(out)
    m = result.metrics
    processes, realtime, memory = m["processes"], m["realtime"], m["processes"]["memory"]
    return {
        "agents": agents,
        "duration_s": duration_s,
        "launcher": processes["launcher"],
        "stopped_by": f"SIG{stop_signal}" if stop_signal else "end",
        "interrupted_at_s": m.get("interrupted_at_s"),
        "vessel_nice": vessel_nice,
        "start_s": processes["startup_wall_s"],
        "late_fraction": realtime["late_fraction"],
        "max_lag_s": realtime["max_lag_s"],
        "steps": realtime["steps"],
        **logs,
        "stop_s_max": processes["stop_s_max"],
        "stop_s_median": processes["stop_s_median"],
        "killed": processes["killed"],
        "exit_codes_nonzero": sum(1 for c in processes["exit_codes"] if c != 0),
        "rss_mib_median": memory.get("rss_mib_median"),
        "rss_mib_max": memory.get("rss_mib_max"),
        "pss_mib_median": memory.get("pss_mib_median"),
        "pss_mib_max": memory.get("pss_mib_max"),
        "vessel_cpu_share_median": memory.get("cpu_share_median"),
        "vessel_cpu_share_max": memory.get("cpu_share_max"),
        "fleet_cpu_share": processes.get("fleet_cpu_share"),
        "wall_s": round(wall, 1),
        "load_before": round(load_before, 2),
        "load_after": round(os.getloadavg()[0], 2),
    }


def profile_startup(top: int = 8) -> dict[str, object]:
    """Where one autonomy process's start-up goes: `python -X importtime` of bob_autonomy.cli (the modules
    with the largest cumulative import time, ms) and a cProfile of building its Vessel (MPC included)."""
    text = subprocess.run(
        [sys.executable, "-X", "importtime", "-c", "import bob_autonomy.cli"],
        capture_output=True,
        text=True,
        check=True,
    ).stderr
    rows = []
    for line in text.splitlines():
        parts = line.split("|")
        if len(parts) == 3 and parts[1].strip().isdigit():
            rows.append((int(parts[1]), parts[2].rstrip()))
    total = next((us for us, name in rows if name.strip() == "bob_autonomy.cli"), None)
    tops = {}
    for us, name in sorted(rows, reverse=True):
        if name.strip() not in tops and len(name) - len(name.lstrip()) <= 9:  # the top levels of the tree
            tops[name.strip()] = round(us / 1e3, 1)
        if len(tops) >= top:
            break
    from bob_autonomy.cli import _apply_config_file, _parser, config_from_args
    from bob_autonomy.onboard.vessel import Vessel

    argv = ["run", "--vehicle", "udpout:127.0.0.1:9", "--system-id", "1", "--behavior", "bob-rule"]
    argv += ["--origin", "1.3405,103.956", "--mesh", "udpout:127.0.0.1:9", "--dt", "0.1"]
    config = config_from_args(_apply_config_file(_parser(), argv))
    profiler = cProfile.Profile()
    start = time.perf_counter()
    profiler.enable()
    vessel = Vessel(config)
    profiler.disable()
    build_s = time.perf_counter() - start
    vessel.vehicle_link.close()
    stream = io.StringIO()
    stats = pstats.Stats(profiler, stream=stream).sort_stats("cumulative")
    inner = {
        f"{Path(f).name}:{name}": round(1e3 * cum, 1)
        for (f, _, name), (_, _, _, cum, _) in stats.stats.items()  # type: ignore[attr-defined]
        if name in ("__init__", "_build", "_buoy_qp_functions", "_warm_up", "behavior") and "bob_autonomy" in f
    }
    return {
        "import_ms": None if total is None else round(total / 1e3, 1),
        "largest_imports_ms": tops,
        "vessel_build_ms": round(1e3 * build_s, 1),
        "vessel_build_parts_ms": dict(sorted(inner.items(), key=lambda kv: -kv[1])[:6]),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--agents", type=int, default=45)
    parser.add_argument("--hundred", action="store_true", help="also run 100 vessels")
    parser.add_argument("--duration", type=float, default=90.0, help="simulated s (speed 1: wall s)")
    parser.add_argument("--launcher", choices=["fork-server", "exec"], default="fork-server")
    parser.add_argument("--runs", type=int, default=1, help="fleets of --agents to run (0: none)")
    parser.add_argument("--base-port", type=int, default=27600, help="vehicle 0's UDP port (mesh: base - 100)")
    parser.add_argument("--vessel-nice", type=int, default=10, help="the vessels' niceness above the fleet's")
    parser.add_argument("--signal", choices=["INT", "TERM"], help="stop the fleet with this signal instead")
    parser.add_argument("--signal-after", type=float, default=40.0, help="wall s after the start, for --signal")
    parser.add_argument("--keep", type=Path, help="keep each run's outputs in this directory")
    parser.add_argument("--profile-startup", action="store_true", help="print where one start-up goes")
    args = parser.parse_args()
    if args.profile_startup:
        print(json.dumps({"profile_startup": profile_startup()}), flush=True)
    sizes = [args.agents] * args.runs + ([100] if args.hundred else [])
    for agents in sizes:
        figures = run_fleet(
            agents, args.duration, args.launcher, args.base_port, args.keep, args.vessel_nice, args.signal,
            args.signal_after,
        )  # fmt: skip
        print(json.dumps(figures), flush=True)


if __name__ == "__main__":
    main()
