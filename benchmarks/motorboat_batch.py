"""The 45 motorboat MPC solves of one lockstep step: one `MotorboatMpc.solve()` per boat, or the fleet's solves in
one mapped call each of the QP data, the DAQP conic and the plan speeds (`MotorboatMpcBatch`, what a lockstep
motorboat fleet uses).

Both paths get the same seeded sequence of random states (desired velocity up to 2 m/s, velocity over ground,
drift, heading, yaw rate; a tenth of the boats wished too slowly to move, so they hold), each path with its own
45 controllers, so that each step's commands become the next step's previous ones and each plan the next
linearisation point, as in a fleet. The two are timed step by step, alternating, and their commands are
checked equal (throttle, steering, status). Prints one JSON line: median ms per step of each, and the ratio.

    python benchmarks/motorboat_batch.py [--steps 200] [--boats 45] [--seed 5]
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import time

import numpy as np

from bob_autonomy.control.motorboat_control import MotorboatMpc
from bob_autonomy.control.motorboat_mpc_batch import MotorboatMpcBatch


def states(steps: int, boats: int, seed: int) -> list[tuple[np.ndarray, ...]]:
    """Per step: desired (n, 2), velocity (n, 2), water (n, 2) m/s, heading (n,) rad, yaw rate (n,) rad/s,
    throttle available (n,)."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(steps):
        moving = rng.random((boats, 1)) >= 0.1
        desired = rng.uniform(-2.0, 2.0, (boats, 2)) * np.where(moving, 1.0, 0.02)
        out.append((desired, rng.uniform(-1.5, 1.5, (boats, 2)), rng.normal(0.0, 0.2, (boats, 2)),
                    rng.uniform(-math.pi, math.pi, boats), rng.normal(0.0, 0.3, boats), np.ones(boats)))  # fmt: skip
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--boats", type=int, default=45)
    parser.add_argument("--seed", type=int, default=5)
    args = parser.parse_args()
    alone = [MotorboatMpc(time_budget_s=math.inf) for _ in range(args.boats)]
    batch = MotorboatMpcBatch([MotorboatMpc(time_budget_s=math.inf) for _ in range(args.boats)])
    one_by_one, mapped = [], []
    for k, (desired, velocity, water, heading, rate, throttle) in enumerate(states(args.steps, args.boats, args.seed)):
        t_s = 0.5 * k
        start = time.perf_counter()
        expected = [
            mpc.solve(desired[i], velocity[i], water[i], heading[i], rate[i], max_throttle=throttle[i], t_s=t_s)
            for i, mpc in enumerate(alone)
        ]
        one_by_one.append(time.perf_counter() - start)
        start = time.perf_counter()
        got = batch.solve(desired, velocity, water, heading, rate, throttle, t_s)
        mapped.append(time.perf_counter() - start)
        same = all((g.throttle, g.steering, g.status) == (e.throttle, e.steering, e.status)
                   for g, e in zip(got, expected, strict=True))  # fmt: skip
        if not same:
            raise SystemExit(f"step {k}: the mapped commands differ from the per-boat ones")
    alone_ms, mapped_ms = 1e3 * statistics.median(one_by_one), 1e3 * statistics.median(mapped)
    print(
        json.dumps(
            {
                "boats": args.boats,
                "steps": args.steps,
                "one_by_one_ms_per_step": round(alone_ms, 3),
                "mapped_ms_per_step": round(mapped_ms, 3),
                "mapped_over_one_by_one": round(mapped_ms / alone_ms, 3),
                "mapped_calls": batch.calls,
                "commands_equal": True,
            }
        )
    )


if __name__ == "__main__":
    main()
