"""Latency inside the autonomy process, from telemetry in to command out, measured on a real process fleet.

Runs N buoys (each its own `bob-autonomy run`, MPC controller) against the simulated vehicles over UDP in
real time, then reads each vessel's statistics from its log:

- compute: from the control tick that takes the drained telemetry (decoded and fused as it arrived) to the
  RC_CHANNELS_OVERRIDE written to the socket: behaviour, supervisor, MPC and encoding (wall s);
- telemetry age: from the arrival of the newest reading acted on to that command (includes waiting for the
  0.1 s control tick, so it is at most about dt plus the compute time).

    python benchmarks/autonomy_latency.py --vessels 5 --duration 30
"""

from __future__ import annotations

import argparse
import json
import re
import tempfile
from pathlib import Path

import numpy as np

from sitl.experiments.scenario import validate_scenario
from sitl.fleets.process_fleet import ProcessOptions, run_processes_to_directory


def scenario(vessels: int, duration_s: float):
    return validate_scenario(
        {
            "name": "latency",
            "duration_s": duration_s,
            "dt_s": 0.1,
            "seed": 1,
            "fidelity": "physics",
            "network": {"range_m": 300.0, "broadcast_period_s": 0.5, "expiry_s": 3.0, "radio": {}},
            "groups": [
                {
                    "name": "buoys",
                    "count": vessels,
                    "body": "buoy",
                    "behavior": "bob-rule",
                    "params": {"p0": 10.0, "H": 0},
                    "start": {"box": {"min": [0.0, 0.0], "max": [60.0, 60.0]}, "min_separation_m": 5.0},
                }
            ],
            "metrics": {"kind": "aggregation"},
        },
        "latency benchmark",
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--vessels", type=int, default=5)
    parser.add_argument("--duration", type=float, default=30.0, help="simulated (= wall) seconds")
    parser.add_argument("--base-port", type=int, default=25760)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "run"
        options = ProcessOptions(speed=1.0, base_port=args.base_port, mesh_port=25000, gcs_port=25001)
        run_processes_to_directory(scenario(args.vessels, args.duration), out, options)
        summaries = []
        for log in sorted(out.glob("vessel-*.log")):
            found = re.findall(r"stopped cleanly: (\{.*\})", log.read_text())
            if found:
                summaries.append(json.loads(found[-1]))
    if not summaries:
        raise SystemExit("no vessel statistics found in the logs")
    print(f"{len(summaries)} vessels, {args.duration:g} s in real time, MPC, 10 Hz control")
    print(f"{'':24s}{'median ms':>12s}{'p99 ms':>12s}")
    for name, label in (("compute_latency_s", "compute"), ("telemetry_to_command_s", "telemetry age")):
        medians = np.array([s[f"{name}_median"] for s in summaries]) * 1e3
        p99 = np.array([s[f"{name}_p99"] for s in summaries]) * 1e3
        print(f"{label:24s}{np.median(medians):12.2f}{np.max(p99):12.2f}   (median of medians, worst p99)")
    ticks = sum(s["commands"] for s in summaries)
    print(f"commands sent: {ticks}; step errors: {sum(s['step_errors'] for s in summaries)}")


if __name__ == "__main__":
    main()
