"""Simulated seconds per wall-clock second of the 45-buoy `aggregation` scenario at physics fidelity.

Dynamics, wind and gusts, sensors, the vessels' estimators and controllers,
the lossy radio and the behaviours, all in the loop; recording and figures
excluded. Prints one JSON line (and the kinematic figure as a baseline).

    python benchmarks/aggregation_speed.py [--seconds 300]
"""

from __future__ import annotations

import argparse
import json
import time

from sitl.fleet import LockstepFleet
from sitl.scenario import load_scenario


def realtime_factor(fidelity: str, simulated_s: float) -> tuple[float, float]:
    """(simulated seconds per wall second, wall ms per step)."""
    scenario = load_scenario("aggregation").with_overrides(fidelity=fidelity)
    fleet = LockstepFleet(scenario)
    steps = round(simulated_s / scenario.dt_s)
    start = time.perf_counter()
    for _ in range(steps):
        fleet.step()
    wall = time.perf_counter() - start
    return simulated_s / wall, 1000.0 * wall / steps


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=300.0, help="simulated seconds to time")
    args = parser.parse_args()
    physics, physics_ms = realtime_factor("physics", args.seconds)
    kinematic, kinematic_ms = realtime_factor("kinematic", args.seconds)
    print(
        json.dumps(
            {
                "scenario": "aggregation",
                "agents": 45,
                "simulated_s": args.seconds,
                "physics_sim_s_per_wall_s": round(physics, 1),
                "physics_ms_per_step": round(physics_ms, 3),
                "kinematic_sim_s_per_wall_s": round(kinematic, 1),
                "kinematic_ms_per_step": round(kinematic_ms, 3),
                "physics_cost_ratio": round(kinematic / physics, 2),
            }
        )
    )


if __name__ == "__main__":
    main()
