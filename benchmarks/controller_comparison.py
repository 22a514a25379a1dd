"""Velocity tracking of the buoy controllers in gusty wind and current: simple proportional vs MPC.

Five buoys run a survey line (waypoints at 0.5 m/s) at physics fidelity with a
6 m/s gusty wind and a 0.15 m/s cross current, both with the EKF (whose drift
estimate the MPC feeds forward). Prints a table: RMS of |true velocity -
wished velocity| after the first 20 s, the largest thrust command against its
limit, MPC fallbacks, and the improvement.

    python benchmarks/controller_comparison.py [--duration 300]
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from sitl.experiments.scenario import validate_scenario
from sitl.fleets.fleet import LockstepFleet


def survey(controller: str, duration_s: float) -> dict:
    scenario = validate_scenario(
        {
            "name": f"tracking-{controller}",
            "duration_s": duration_s,
            "dt_s": 0.5,
            "seed": 21,
            "fidelity": "physics",
            "vessel": {"estimator": "ekf", "controller": controller},
            "environment": {
                "wind": {"speed_mps": 6.0, "toward_deg": 45.0, "gust_intensity": 0.3, "gust_time_constant_s": 15.0},
                "current": {"speed_mps": 0.15, "toward_deg": 90.0},
            },
            "groups": [
                {
                    "name": "survey",
                    "count": 5,
                    "body": "buoy",
                    "behavior": "waypoints",
                    "params": {
                        "waypoints": [[300.0, 0.0], [300.0, 100.0], [0.0, 100.0], [0.0, 0.0]],
                        "speed": 0.5,
                        "loop": True,
                    },
                    "start": {"box": {"min": [-20.0, -20.0], "max": [0.0, 0.0]}, "min_separation_m": 5.0},
                }
            ],
        },
        "benchmarks/controller_comparison.py",
    )
    fleet = LockstepFleet(scenario)
    errors, thrust_ratio = [], 0.0
    bodies = fleet.bodies
    while fleet.t < duration_s:
        fleet.apply_events()
        fleet.sync_table()
        wish = fleet.decide(fleet.senses())
        fleet.finish_step(wish)
        thrust = np.hypot(*bodies.buoy_vessels.thrust_world_n.T)
        thrust_ratio = max(thrust_ratio, float((thrust / bodies.max_thrust_n).max()))
        if fleet.t > 20.0:
            errors.append(np.hypot(*(bodies.velocity - wish.velocity).T))
    e = np.concatenate(errors)
    return {
        "controller": controller,
        "tracking_rms_mps": round(float(np.sqrt(np.mean(e**2))), 4),
        "tracking_p95_mps": round(float(np.percentile(e, 95)), 4),
        "max_thrust_over_limit": round(thrust_ratio, 4),
        "mpc_fallbacks": int(bodies.mpc_fallbacks),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=300.0, help="simulated seconds per controller")
    args = parser.parse_args()
    rows = [survey("simple", args.duration), survey("mpc", args.duration)]
    print(f"{'controller':>10} {'RMS (m/s)':>10} {'p95 (m/s)':>10} {'max |T|/limit':>14} {'fallbacks':>10}")
    for r in rows:
        print(
            f"{r['controller']:>10} {r['tracking_rms_mps']:>10.4f} {r['tracking_p95_mps']:>10.4f} "
            f"{r['max_thrust_over_limit']:>14.4f} {r['mpc_fallbacks']:>10d}"
        )
    improvement = 1.0 - rows[1]["tracking_rms_mps"] / rows[0]["tracking_rms_mps"]
    print(f"MPC tracking RMS {100 * improvement:.1f} % lower than the simple controller")
    print(json.dumps({"rows": rows, "mpc_improvement": round(improvement, 4)}))


if __name__ == "__main__":
    main()
