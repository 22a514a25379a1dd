"""Simulated seconds per wall-clock second of the 45-buoy `aggregation` scenario at physics fidelity.

Dynamics, wind and gusts, sensors, the vessels' estimators and controllers,
the lossy radio and the behaviours, all in the loop; recording and figures
excluded. Prints one JSON line (and the kinematic figure as a baseline). The
same physics run over the direct link (no MAVLink) is timed too: its figure is
the most any speed-up of the MAVLink path alone could reach.

    python benchmarks/aggregation_speed.py [--seconds 300] [--profile] [--vessel-processes N]

The physics run is also timed with the buoys' estimators, controllers and MAVLink links spread over N
processes (sitl.vehicles.vessel_shards; default 2 where there are two cores: the same results sooner).

--profile also prints where a physics step's time goes (wall ms per step of
each stage, over a further run of at most 60 simulated s).
"""

from __future__ import annotations

import argparse
import json
import time
from collections import Counter
from collections.abc import Iterator
from contextlib import contextmanager

import psutil  # installed with dask's distributed

from bob_autonomy.onboard.pipeline import BuoyPipeline
from sitl.experiments.scenario import load_scenario
from sitl.fleets.fleet import LockstepFleet
from sitl.radio.medium import BroadcastMedium
from sitl.row_threads import available_cores
from sitl.vehicles import vehicle_transport
from sitl.vehicles.mavlink_vehicle import SimulatedVehicle
from sitl.vehicles.vehicle_physics import VehiclePhysics
from sitl.vehicles.vehicle_transport import MavlinkTransport


def realtime_factor(
    fidelity: str, simulated_s: float, link: str = "mavlink", vessel_processes: int = 1
) -> tuple[float, float, float]:
    """(simulated seconds per wall second, wall ms per step, CPU ms per step). The CPU time (of the fleet process
    and its vessel workers) is the figure to compare across runs on a shared or noisy host, where wall time also
    counts other processes. link: the vehicle link of a physics run ("mavlink", the packaged one, or "direct");
    vessel_processes: the processes the buoys' vessel side is spread over (sitl.vehicles.vessel_shards)."""
    scenario = load_scenario("aggregation").with_overrides(fidelity=fidelity, link=link)
    fleet = LockstepFleet(scenario, vessel_processes=vessel_processes)
    try:
        steps = round(simulated_s / scenario.dt_s)
        start, cpu = time.perf_counter(), _cpu_s(fleet)
        for _ in range(steps):
            fleet.step()
        wall, cpu = time.perf_counter() - start, _cpu_s(fleet) - cpu
    finally:
        fleet.close()
    return simulated_s / wall, 1000.0 * wall / steps, 1000.0 * cpu / steps


def _cpu_s(fleet: LockstepFleet) -> float:
    """CPU seconds used so far by this process and the fleet's vessel worker processes."""
    shards = getattr(fleet.bodies, "buoy_shards", None)
    workers = [] if shards is None else [psutil.Process(process.pid) for process, _ in shards.workers]
    return time.process_time() + sum(w.cpu_times().user + w.cpu_times().system for w in workers)


# Where a physics step goes: (label, class or module, function) of each stage, timed by wrapping it with a clock
# (wall time; cProfile's per-call overhead would inflate the call-heavy MAVLink stages about twofold).
STAGES = (
    ("step, total", LockstepFleet, "step"),
    ("MAVLink up: vehicles encode telemetry, vessels decode it", MavlinkTransport, "up"),
    ("- vehicles' telemetry streams (schedule, build, pack)", SimulatedVehicle, "stream"),
    ("- vessels' decoders, all at once (frame, check, decode, convert)", vehicle_transport, "receive_all"),
    ("- readings merged per kind and round", vehicle_transport, "merge_by_round"),
    ("MAVLink down: RC override encoded, decoded and applied", MavlinkTransport, "down"),
    ("estimator (EKF bank)", BuoyPipeline, "feed"),
    ("controller (MPC)", BuoyPipeline, "thrust"),
    ("dynamics and environment", VehiclePhysics, "step"),
    ("sensors", VehiclePhysics, "sense"),
    ("radio", BroadcastMedium, "broadcast"),
)


@contextmanager
def stage_clocks() -> Iterator[Counter]:
    """Seconds spent in each stage of STAGES while the context is open (the methods wrapped, then restored)."""
    spent: Counter = Counter()
    originals = [(cls, name, getattr(cls, name)) for _, cls, name in STAGES]

    def clocked(label: str, method):
        def run(*args, **kwargs):
            start = time.perf_counter()
            try:
                return method(*args, **kwargs)
            finally:
                spent[label] += time.perf_counter() - start

        return run

    for (label, cls, name), (_, _, method) in zip(STAGES, originals, strict=True):
        setattr(cls, name, clocked(label, method))
    try:
        yield spent
    finally:
        for cls, name, method in originals:
            setattr(cls, name, method)


def stage_summary(simulated_s: float) -> dict[str, float]:
    """Wall milliseconds per step of each stage of STAGES, physics fidelity."""
    fleet = LockstepFleet(load_scenario("aggregation").with_overrides(fidelity="physics"))
    steps = round(simulated_s / fleet.scenario.dt_s)
    with stage_clocks() as spent:
        for _ in range(steps):
            fleet.step()
    return {label: round(1000.0 * spent[label] / steps, 2) for label, _, _ in STAGES}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=300.0, help="simulated seconds to time")
    parser.add_argument("--profile", action="store_true", help="also print where a step's time goes")
    parser.add_argument(
        "--vessel-processes",
        type=int,
        default=min(2, available_cores()),
        metavar="N",
        help="also time the physics run with the buoys' vessel side over N processes (default 2 where there are "
        "2 cores; 1: not)",
    )
    args = parser.parse_args()
    physics, physics_ms, physics_cpu_ms = realtime_factor("physics", args.seconds)
    sharded = None
    if args.vessel_processes > 1:
        sharded = realtime_factor("physics", args.seconds, vessel_processes=args.vessel_processes)
    direct, direct_ms, _ = realtime_factor("physics", args.seconds, link="direct")
    kinematic, kinematic_ms, kinematic_cpu_ms = realtime_factor("kinematic", args.seconds)
    print(
        json.dumps(
            {
                "scenario": "aggregation",
                "agents": 45,
                "simulated_s": args.seconds,
                "physics_sim_s_per_wall_s": round(physics, 1),
                "physics_ms_per_step": round(physics_ms, 3),
                "physics_cpu_ms_per_step": round(physics_cpu_ms, 3),
                "kinematic_sim_s_per_wall_s": round(kinematic, 1),
                "kinematic_ms_per_step": round(kinematic_ms, 3),
                "kinematic_cpu_ms_per_step": round(kinematic_cpu_ms, 3),
                "physics_cost_ratio": round(kinematic / physics, 2),
                "direct_link_sim_s_per_wall_s": round(direct, 1),
                "direct_link_ms_per_step": round(direct_ms, 3),
                "mavlink_share_of_step": round(1.0 - direct_ms / physics_ms, 2),
            }
        )
    )
    if sharded is not None:
        rate, wall_ms, cpu_ms = sharded
        figures = {
            "vessel_processes": args.vessel_processes,
            "physics_sim_s_per_wall_s": round(rate, 1),
            "physics_ms_per_step": round(wall_ms, 3),
            "physics_cpu_ms_per_step_all_processes": round(cpu_ms, 3),
            "speed_up_over_one_process": round(physics_ms / wall_ms, 2),
            "wall_cost_ratio_to_kinematic": round(wall_ms / kinematic_ms, 2),
        }
        print(json.dumps({"physics_over_processes": figures}))
    if args.profile:
        print(json.dumps({"ms_per_step_by_stage": stage_summary(min(args.seconds, 60.0))}, indent=1))


if __name__ == "__main__":
    main()
