"""Whole-swarm steps per second of the lockstep simulator (perimeter defence, open water).

For N = 100, 1,000 and 10,000 buoys at constant density (one per 100 m^2),
with the radio range chosen for about 10 neighbours each, prints one JSON line
per N. The baseline is the same fleet stepped agent by agent through
`bob_autonomy.Agent` (the on-vessel code path, a Python loop over agents),
measured where it finishes in reasonable time.

    python benchmarks/fleet_step.py [--agents 100 1000 10000] [--broadcast-period 1.0]
"""

from __future__ import annotations

import argparse
import json
import math
import time

from sitl.adapters import AgentFleet
from sitl.fleet import LockstepFleet
from sitl.scenario import Scenario, validate_scenario

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


def steps_per_second(make_stepper, steps: int, min_seconds: float) -> tuple[float, float]:
    """(steps per second, mean neighbours heard) over fresh fleets of `steps` steps each.

    Each repetition starts a new fleet so the density stays the one asked for
    (perimeter defence in open water disperses for ever); repetitions go on
    until `min_seconds` of stepping have been timed.
    """
    timed, done, neighbours = 0.0, 0, []
    while timed < min_seconds:
        stepper = make_stepper()
        stepper.step()  # first broadcast
        start = time.perf_counter()
        for _ in range(steps):
            stepper.step()
        timed += time.perf_counter() - start
        done += steps
        fleet = getattr(stepper, "fleet", stepper)
        neighbours.append(fleet.medium.listener.size / fleet.n)
    return done / timed, sum(neighbours) / len(neighbours)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--agents", type=int, nargs="+", default=[100, 1000, 10000])
    parser.add_argument("--broadcast-period", type=float, default=1.0, help="s between state broadcasts")
    parser.add_argument("--baseline-max-agents", type=int, default=1000, help="largest N for the agent loop")
    args = parser.parse_args()
    for n in args.agents:
        scenario = open_water_scenario(n, args.broadcast_period)
        rate, neighbours = steps_per_second(lambda s=scenario: LockstepFleet(s), steps=100, min_seconds=2.0)
        row = {
            "agents": n,
            "steps_per_s": round(rate, 1),
            "agent_steps_per_s": round(rate * n),
            "real_time_factor": round(rate * DT_S, 1),
            "dt_s": DT_S,
            "broadcast_period_s": args.broadcast_period,
            "mean_neighbours": round(neighbours, 1),
        }
        if n <= args.baseline_max_agents:
            baseline, _ = steps_per_second(lambda s=scenario: AgentFleet(LockstepFleet(s)), steps=10, min_seconds=1.0)
            row["agent_loop_steps_per_s"] = round(baseline, 2)
            row["speedup_vs_agent_loop"] = round(rate / baseline, 1)
        print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
