"""Microseconds per prediction and per update of the buoy and eBot EKFs (bob_autonomy.ekf), one vessel.

Each call is timed on its own (time.perf_counter_ns) inside a realistic
stream: every 0.02 s a buoy predicts with an accelerometer reading (with and,
separately, without a thrust command: with one, the prediction also fuses the
drag-balance pseudo-measurement), then takes a GPS fix (position + ground
velocity) and a compass reading at that same time (so an update's time is the
update alone, no prediction to its time). An eBot reads its encoders every
0.1 s, then takes a compass reading and a position fix. Reported: the median
over --calls calls of each, one JSON line.

    python benchmarks/ekf_step.py [--calls 5000] [--seed 1]
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import statistics
import time

import numpy as np

from bob_autonomy.ekf import BuoyEkf, EbotEkf


def timed(call, *args) -> float:
    """Microseconds one call takes."""
    start = time.perf_counter_ns()
    call(*args)
    return (time.perf_counter_ns() - start) / 1000.0


def buoy(calls: int, rng: np.random.Generator, thrust: bool) -> dict[str, float]:
    f = BuoyEkf(position_m=[0.0, 0.0], heading_rad=0.3)
    times: dict[str, list[float]] = {"predict": [], "update_gps": [], "update_compass": []}
    for k in range(calls + 100):  # the first 100 rounds warm up
        t = 0.02 * k
        accel = 0.05 * rng.standard_normal(2)
        cmd = np.array([10.0 * math.cos(0.05 * t), 10.0 * math.sin(0.05 * t)]) if thrust else None
        us_predict = timed(f.predict, t, accel, cmd)
        position, velocity, heading = f.estimate(t)
        xy = position + 0.5 * rng.standard_normal(2)
        us_gps = timed(f.update_gps, t, xy, velocity + 0.05 * rng.standard_normal(2))
        us_compass = timed(f.update_compass, t, heading + 0.02 * rng.standard_normal())
        if k >= 100:
            times["predict"].append(us_predict)
            times["update_gps"].append(us_gps)
            times["update_compass"].append(us_compass)
    assert f.gated + f.rejected + f.failures < calls // 100, "the benchmark stream should be clean"
    return {name: statistics.median(v) for name, v in times.items()}


def ebot(calls: int, rng: np.random.Generator) -> dict[str, float]:
    metres_per_tick = 2.0 * math.pi * 0.03 / 360
    f = EbotEkf([0.0, 0.0], 0.0, 0.1, metres_per_tick)
    times: dict[str, list[float]] = {"predict_encoders": [], "update_compass": [], "update_position": []}
    travel = np.zeros(2)
    for k in range(calls + 100):
        t = 0.1 * k
        travel += np.array([0.019, 0.021]) + 0.001 * rng.standard_normal(2)
        ticks = np.floor(travel / metres_per_tick).astype(np.int64)
        us_enc = timed(f.update_encoders, t, ticks)
        position, _, heading = f.estimate()
        us_compass = timed(f.update_compass, t, heading + 0.02 * rng.standard_normal())
        us_position = timed(f.update_position, t, position + 0.05 * rng.standard_normal(2), 0.1)
        if k >= 100:
            times["predict_encoders"].append(us_enc)
            times["update_compass"].append(us_compass)
            times["update_position"].append(us_position)
    return {name: statistics.median(v) for name, v in times.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--calls", type=int, default=5000, help="timed calls of each kind")
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    rng = np.random.default_rng(args.seed)
    with_thrust = buoy(args.calls, rng, thrust=True)
    accel_only = buoy(args.calls, rng, thrust=False)
    result = {
        "benchmark": "ekf_step",
        "unit": "us_per_call_median",
        "calls": args.calls,
        "buoy": {
            "predict_accel_us": round(accel_only["predict"], 1),
            "predict_accel_thrust_us": round(with_thrust["predict"], 1),
            "update_gps_pos_vel_us": round(with_thrust["update_gps"], 1),
            "update_compass_us": round(with_thrust["update_compass"], 1),
        },
        "ebot": {name + "_us": round(v, 1) for name, v in ebot(args.calls, rng).items()},
        "python": platform.python_version(),
    }
    print(json.dumps(result))


if __name__ == "__main__":
    main()
