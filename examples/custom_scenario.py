"""Build a scenario in Python and run it: a heterogeneous swarm in a room.

Six eBots spread out (perimeter defence) while four align their headings
(heading consensus); everything else is the same machinery `bob-sitl run`
uses. Run:  python examples/custom_scenario.py [OUT_DIR]
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from sitl.experiments.runner import run_to_directory
from sitl.experiments.scenario import validate_scenario

ROOM = [[0.0, 0.0], [10.0, 0.0], [10.0, 8.0], [0.0, 8.0]]
START = {"box": {"min": [4.0, 3.0], "max": [6.0, 5.0]}, "min_separation_m": 0.3}

scenario = validate_scenario(
    {
        "name": "mixed-swarm",
        "description": "Six eBots in perimeter defence and four in heading consensus share one room.",
        "duration_s": 120.0,
        "dt_s": 0.1,
        "seed": 5,
        "world": {"rooms": [{"name": "lab", "polygon": ROOM}]},
        "network": {"range_m": 20.0, "broadcast_period_s": 0.2, "expiry_s": 1.0},
        "groups": [
            {
                "name": "spreaders",
                "count": 6,
                "body": "ebot",
                "behavior": "perimeter-defense",
                "avoid_obstacles": True,
                "start": START,
            },
            {
                "name": "aligners",
                "count": 4,
                "body": "ebot",
                "behavior": "heading-consensus",
                "params": {"cruise_speed": 0.0},
                "start": START,
            },
        ],
    },
    source="examples/custom_scenario.py",
)

if __name__ == "__main__":
    out = Path(sys.argv[1] if len(sys.argv) > 1 else "runs/mixed-swarm")
    result = run_to_directory(scenario, out, progress=True)
    print(json.dumps({k: v for k, v in result.metrics.items() if not isinstance(v, dict)}, indent=2))
    print(f"outputs in {out}/")
