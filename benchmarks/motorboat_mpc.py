"""Cost of one motorboat MPC call beside the buoy MPC's, both in closed loop with the SITL's truth dynamics.

Both controllers drive their simulated vessel (`sitl.vehicles.motorboat.MotorboatDynamics`, 2 m/s top speed and 3 m
turning radius; `sitl.vehicles.dynamics.BuoyDynamics`) for --steps control steps of 0.5 s over the same seeded
sequence of random desired velocities (a new one every 10-30 s, up to 0.8 m/s, in any direction: the boat
must turn around for many of them) and currents that change every 60 s, the drift known to the controller.
Timed: the whole `solve()` call from Python (wall time median and p99, and the thread's CPU time, which tells
a slow call from a preempted one); the QP alone (`solve_time_s`); fallbacks; and how well each tracks
(median |v - v_desired| over ground once 10 s have passed since the wish changed).

Prints a readable report and, last, one JSON line.

    python benchmarks/motorboat_mpc.py [--steps 2000] [--seed 7]
"""

from __future__ import annotations

import argparse
import json
import math
import time

import numpy as np

from bob_autonomy.control.motorboat_control import MotorboatModel, MotorboatMpc
from bob_autonomy.control.mpc import BuoyMpc
from sitl.vehicles.dynamics import BuoyDynamics, BuoyParams
from sitl.vehicles.motorboat import MotorboatDynamics, params_for

DT_S = 0.5


def sequence(steps: int, seed: int) -> list[tuple[np.ndarray, np.ndarray, bool]]:
    """Per step: (desired velocity, current (m/s, world), whether the wish has held for 10 s)."""
    rng = np.random.default_rng(seed)
    out, desired, current, since, next_desired = [], np.zeros(2), np.zeros(2), 0, 0
    for k in range(steps):
        if k >= next_desired:
            speed, angle = rng.uniform(0.2, 0.8), rng.uniform(-math.pi, math.pi)
            desired = speed * np.array((math.cos(angle), math.sin(angle)))
            next_desired, since = k + int(rng.integers(20, 61)), k
        if k % 120 == 0:
            current = rng.uniform(-0.15, 0.15, 2)
        out.append((desired.copy(), current.copy(), (k - since) * DT_S >= 10.0))
    return out


def _stats(values: list[float]) -> dict[str, float]:
    ordered = sorted(values)
    return {
        "median_ms": 1e3 * ordered[len(ordered) // 2],
        "p99_ms": 1e3 * ordered[min(len(ordered) - 1, int(0.99 * len(ordered)))],
    }


def run_motorboat(seq) -> dict:
    boat = MotorboatDynamics(params_for(2.0, 3.0), np.zeros((1, 2)), np.zeros(1), np.random.default_rng(1))
    mpc = MotorboatMpc(MotorboatModel.for_top_speed(2.0, 3.0), time_budget_s=math.inf)
    wall, cpu, qp, errors = [], [], [], []
    for desired, current, settled in seq:
        w0, c0 = time.perf_counter(), time.thread_time()
        cmd = mpc.solve(desired, boat.velocity_mps[0], current, boat.heading_rad[0], boat.yaw_rate_radps[0])
        wall.append(time.perf_counter() - w0)
        cpu.append(time.thread_time() - c0)
        if cmd.solve_time_s:
            qp.append(cmd.solve_time_s)
        boat.step(np.array([[cmd.throttle, cmd.steering]]), DT_S, current_mps=current[None])
        if settled:
            errors.append(float(np.hypot(*(boat.velocity_mps[0] - desired))))
    return {"call": _stats(wall), "cpu": _stats(cpu), "qp": _stats(qp), "solves": mpc.solves,
            "fallbacks": mpc.fallbacks, "tracking_error_median_mps": float(np.median(errors))}  # fmt: skip


def run_buoy(seq) -> dict:
    params = BuoyParams()
    buoy = BuoyDynamics(params, np.zeros((1, 2)), np.zeros(1), np.random.default_rng(1))
    mpc = BuoyMpc(dt_s=DT_S, time_budget_s=math.inf)
    wall, cpu, qp, errors = [], [], [], []
    for desired, current, settled in seq:
        w0, c0 = time.perf_counter(), time.thread_time()
        result = mpc.solve(desired, buoy.velocity_mps[0], current, buoy.heading_rad[0], params.max_thrust_n)
        wall.append(time.perf_counter() - w0)
        cpu.append(time.thread_time() - c0)
        qp.append(result.solve_time_s)
        buoy.step(result.thrust_body_n[None], DT_S, current_mps=current[None])
        if settled:
            errors.append(float(np.hypot(*(buoy.velocity_mps[0] - desired))))
    return {"call": _stats(wall), "cpu": _stats(cpu), "qp": _stats(qp), "solves": mpc.solves,
            "fallbacks": mpc.fallbacks, "tracking_error_median_mps": float(np.median(errors))}  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=2000)
    parser.add_argument("--seed", type=int, default=7)
    args = parser.parse_args()
    seq = sequence(args.steps, args.seed)
    results = {"motorboat": run_motorboat(seq), "buoy": run_buoy(seq)}
    print(f"{args.steps} control steps of {DT_S} s, seed {args.seed}; times in ms (median / p99)")
    for name, r in results.items():
        print(
            f"  {name:9s} solve() call {r['call']['median_ms']:.3f} / {r['call']['p99_ms']:.3f}"
            f"  (CPU {r['cpu']['median_ms']:.3f} / {r['cpu']['p99_ms']:.3f})"
            f"  QP {r['qp']['median_ms']:.3f} / {r['qp']['p99_ms']:.3f}"
            f"  fallbacks {r['fallbacks']} of {r['solves']}"
            f"  tracking error (median, settled) {r['tracking_error_median_mps']:.3f} m/s"
        )
    print(json.dumps({"steps": args.steps, "seed": args.seed, **results}))


if __name__ == "__main__":
    main()
