"""Simulated seconds per wall-clock second of the 45-buoy `aggregation` scenario at physics fidelity.

Dynamics, wind and gusts, sensors, the vessels' estimators and controllers,
the lossy radio and the behaviours, all in the loop; recording and figures
excluded. Prints one JSON line (and the kinematic figure as a baseline).

    python benchmarks/aggregation_speed.py [--seconds 300] [--profile]

--profile also prints where a physics step's time goes (cProfile over a further
run; the profiler's own overhead inflates every figure about twofold, the shares
are what to read).
"""

from __future__ import annotations

import argparse
import cProfile
import json
import pstats
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


# Where a physics step goes: (label, file suffix, function name) of the stages, read from the profile's
# cumulative times. "MAVLink up" includes the estimator's fusion of what was decoded only through `feed`.
STAGES = (
    ("step, total", "sitl/fleet.py", "step"),
    ("MAVLink up: vehicles encode telemetry, vessels decode it", "sitl/vehicle_transport.py", "up"),
    ("- vehicles' telemetry streams (schedule, build, pack)", "sitl/mavlink_vehicle.py", "stream"),
    ("- vessels' decoders (frame, check, decode, convert)", "firmware_bridge/decoder.py", "feed"),
    ("MAVLink down: RC override encoded, decoded and applied", "sitl/vehicle_transport.py", "down"),
    ("estimator (EKF bank)", "bob_autonomy/pipeline.py", "feed"),
    ("controller (MPC)", "bob_autonomy/pipeline.py", "thrust"),
    ("dynamics and environment", "sitl/vehicle_physics.py", "step"),
    ("sensors", "sitl/vehicle_physics.py", "sense"),
    ("radio and behaviours", "sitl/medium.py", "broadcast"),
)


def profile_summary(simulated_s: float) -> dict[str, float]:
    """Milliseconds per step (under the profiler) of each stage of STAGES, physics fidelity."""
    fleet = LockstepFleet(load_scenario("aggregation").with_overrides(fidelity="physics"))
    steps = round(simulated_s / fleet.scenario.dt_s)
    profiler = cProfile.Profile()
    profiler.enable()
    for _ in range(steps):
        fleet.step()
    profiler.disable()
    cumulative = {}
    for (path, _line, name), (_cc, _nc, _tt, ct, _callers) in pstats.Stats(profiler).stats.items():
        for label, suffix, function in STAGES:
            if name == function and path.endswith(suffix):
                cumulative[label] = cumulative.get(label, 0.0) + ct
    return {label: round(1000.0 * cumulative.get(label, 0.0) / steps, 2) for label, _, _ in STAGES}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=300.0, help="simulated seconds to time")
    parser.add_argument("--profile", action="store_true", help="also print where a step's time goes")
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
    if args.profile:
        print(json.dumps({"profiled_ms_per_step": profile_summary(min(args.seconds, 60.0))}, indent=1))


if __name__ == "__main__":
    main()
