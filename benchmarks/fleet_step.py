"""Whole-swarm steps per second of the lockstep simulator (perimeter defence, open water).

For N = 100, 1,000, 10,000 and 100,000 buoys at constant density (one per
100 m^2), with the radio range chosen for about 10 neighbours each, prints one
JSON line per N. The baseline is the same fleet stepped agent by agent through
`bob_autonomy.Agent` (the on-vessel code path, a Python loop over agents),
measured where it finishes in reasonable time (N <= --baseline-max-agents):
`speedup_vs_agent_loop` is the ratio of the two.

A fleet this big spreads its passes over agents and pairs over threads (`sitl.row_threads`: numpy releases
the GIL in its loops; the results are the same bits). `--threads` sets how many (default: the cores
available); where that splits the work, the same fleet in one thread is measured in the same run, alternating
with the threaded one, and `threads_speedup` is the ratio.

Memory, MiB: `rss_mib` is the resident set with the last fleet of that N still
alive (/proc/self/statm, Linux; absent elsewhere), `peak_rss_mib` the process's
peak so far (resource.getrusage ru_maxrss), so the N are best run smallest first.

Issue #13's target, every agent broadcasting every step (dt 0.1 s): 10,000
agents at 100 steps/s or more, 100,000 at 10 or more (real time):

    python benchmarks/fleet_step.py --agents 10000 100000 --broadcast-period 0.1
    python benchmarks/fleet_step.py [--agents 100 1000 10000 100000] [--broadcast-period 1.0]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import sys
import time

from sitl.experiments.scenario import Scenario, validate_scenario
from sitl.fleets.adapters import AgentFleet
from sitl.fleets.fleet import LockstepFleet
from sitl.row_threads import ONE_THREAD, RowThreads, available_cores

SPACING_M = 10.0  # one agent per SPACING_M^2 of water
NEIGHBOURS = 10
DT_S = 0.1


def open_water_scenario(n_agents: int, broadcast_period_s: float) -> Scenario:
    """N perimeter-defence buoys spread uniformly at constant density, ~10 neighbours in range."""
    side = SPACING_M * math.sqrt(n_agents)
    range_m = SPACING_M * math.sqrt(NEIGHBOURS / math.pi)
    return validate_scenario(
        {
            "name": f"bench-{n_agents}",
            "duration_s": 1000.0,
            "dt_s": DT_S,
            "seed": 1,
            "network": {"range_m": range_m, "broadcast_period_s": broadcast_period_s, "expiry_s": 2.5},
            "groups": [
                {
                    "name": "buoys",
                    "count": n_agents,
                    "body": "buoy",
                    "behavior": "perimeter-defense",
                    "params": {"max_speed": 0.5, "full_speed_at": 1.0},
                    "start": {"box": {"min": [0.0, 0.0], "max": [side, side]}},
                }
            ],
        },
        "benchmark",
    )


def resident_mib() -> float | None:
    """Resident set size of this process now, MiB (/proc/self/statm; None where there is none)."""
    try:
        with open("/proc/self/statm") as statm:
            pages = int(statm.read().split()[1])
    except (OSError, IndexError, ValueError):
        return None
    return pages * os.sysconf("SC_PAGE_SIZE") / 2**20


def peak_resident_mib() -> float:
    """Peak resident set size of this process so far, MiB (ru_maxrss: KiB on Linux, bytes on macOS)."""
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / 2**20 if sys.platform == "darwin" else peak / 2**10


def steps_per_second(make_stepper, steps: int, min_seconds: float) -> tuple[float, float, float | None]:
    """(steps per second, mean neighbours heard, resident MiB with the last fleet alive) over fresh fleets
    of `steps` steps each.

    Each repetition starts a new fleet so the density stays the one asked for
    (perimeter defence in open water disperses for ever); repetitions go on
    until `min_seconds` of stepping have been timed.
    """
    timed, done, neighbours, resident = 0.0, 0, [], None
    while timed < min_seconds:
        stepper = None  # the previous fleet is freed before the next is built
        stepper = make_stepper()
        stepper.step()  # first broadcast
        start = time.perf_counter()
        for _ in range(steps):
            stepper.step()
        timed += time.perf_counter() - start
        done += steps
        fleet = getattr(stepper, "fleet", stepper)
        neighbours.append(fleet.medium.listener.size / fleet.n)
        resident = resident_mib()
    return done / timed, sum(neighbours) / len(neighbours), resident


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--agents", type=int, nargs="+", default=[100, 1000, 10000, 100000])
    parser.add_argument("--broadcast-period", type=float, default=1.0, help="s between state broadcasts")
    parser.add_argument("--baseline-max-agents", type=int, default=1000, help="largest N for the agent loop")
    parser.add_argument("--threads", type=int, default=available_cores(), help="threads of the lockstep fleet")
    args = parser.parse_args()
    threads = RowThreads(args.threads)
    for n in args.agents:
        scenario = open_water_scenario(n, args.broadcast_period)
        split = args.threads > 1 and len(threads.ranges(n, NEIGHBOURS * n)) > 1  # (the behaviour's pairs)
        rates, one_thread = [], []
        for _ in range(2 if split else 1):  # alternating, so that a drift of the host's speed hits both alike
            if split:
                one_thread.append(
                    steps_per_second(lambda s=scenario: LockstepFleet(s, ONE_THREAD), steps=100, min_seconds=1.0)[0]
                )
            rate, neighbours, resident = steps_per_second(
                lambda s=scenario: LockstepFleet(s, threads), steps=100, min_seconds=1.0 if split else 2.0
            )
            rates.append(rate)
        rate = sum(rates) / len(rates)
        row = {
            "agents": n,
            "threads": len(threads.ranges(n, NEIGHBOURS * n)),
            "steps_per_s": round(rate, 1),
            "agent_steps_per_s": round(rate * n),
            "real_time_factor": round(rate * DT_S, 1),
            "dt_s": DT_S,
            "broadcast_period_s": args.broadcast_period,
            "mean_neighbours": round(neighbours, 1),
            "rss_mib": None if resident is None else round(resident),
            "peak_rss_mib": round(peak_resident_mib()),
        }
        if one_thread:
            row["one_thread_steps_per_s"] = round(sum(one_thread) / len(one_thread), 1)
            row["threads_speedup"] = round(rate / row["one_thread_steps_per_s"], 2)
        if n <= args.baseline_max_agents:
            baseline, _, _ = steps_per_second(
                lambda s=scenario: AgentFleet(LockstepFleet(s)), steps=10, min_seconds=1.0
            )
            row["agent_loop_steps_per_s"] = round(baseline, 2)
            row["speedup_vs_agent_loop"] = round(rate / baseline, 1)
        print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
