"""The paper's aggregation experiment (DESIGN.md experiment 4) run as a mission script over MAVLink.

Start a fleet whose ground-station port is left to this script, then run the script:

    bob-sitl fleet aggregation --processes --external-gcs --agents 10 --speed 2 --duration 1400
    python examples/mission_aggregation.py --vessels 10

It talks to the vessels' autonomy processes only through MAVLink
(`bob_autonomy.ground.mission.MissionClient` on UDP 14600): discovers them by heartbeat,
sets the BoB rule with p0 = 50 m fleet-wide and starts it, switches p0 to 5 m
and waits until the convex hull of the positions the vessels report has shrunk
by the wanted factor, then sets p0 back to 50 m and waits until the swarm has
spread again. It prints what it measured and exits 0 when the criterion held,
1 when it did not (a MissionError explains a vessel that stopped answering).
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np
from scipy.spatial import ConvexHull, QhullError

from bob_autonomy.core.geodesy import LocalFrame
from bob_autonomy.ground.mission import MissionClient, MissionError


def hull_area_m2(client: MissionClient, vessels: list[int]) -> float:
    """Area (m2) of the convex hull of the vessels' reported positions (0 with fewer than 3)."""
    reported = client.positions()
    points = [(reported[v].lat_deg, reported[v].lon_deg) for v in vessels if v in reported]
    if len(points) < 3:
        return 0.0
    frame = LocalFrame(*points[0])
    x, y = frame.to_local(np.array([p[0] for p in points]), np.array([p[1] for p in points]))
    try:
        return float(ConvexHull(np.column_stack((x, y))).volume)
    except QhullError:  # all in a line
        return 0.0


def run(args: argparse.Namespace) -> dict:
    """The experiment; returns the measured figures and whether the criterion held."""
    with MissionClient(args.connection, timeout_s=2.0, retries=5) as client:
        vessels = client.discover(args.vessels, timeout_s=args.discover_timeout)
        client.set_params({"BOB_BEHAVIOR": 0, "BOB_H": 0, "BOB_P0_M": args.far_p0}, vessels)
        client.start(vessels)
        client.wait_until(
            lambda c: len(set(c.positions()) & set(vessels)) == len(vessels), 30.0, "a position from every vessel"
        )
        time.sleep(args.settle)
        start_area = hull_area_m2(client, vessels)
        client.set_param("BOB_P0_M", args.near_p0, vessels)
        switched = time.monotonic()
        target = start_area / args.shrink
        client.wait_until(
            lambda c: hull_area_m2(c, vessels) <= target,
            args.timeout,
            f"hull area below {target:.0f} m2",
            describe=lambda c: f"hull area {hull_area_m2(c, vessels):.0f} m2",
        )
        aggregated_after = time.monotonic() - switched
        aggregated_area = hull_area_m2(client, vessels)
        client.set_param("BOB_P0_M", args.far_p0, vessels)
        client.wait_until(
            lambda c: hull_area_m2(c, vessels) >= args.spread * aggregated_area,
            args.timeout,
            "the swarm spreading again",
            describe=lambda c: f"hull area {hull_area_m2(c, vessels):.0f} m2",
        )
        client.stop(vessels)
        return {
            "vessels": vessels,
            "start_area_m2": round(start_area, 1),
            "aggregated_area_m2": round(aggregated_area, 1),
            "aggregation_wall_s": round(aggregated_after, 1),
            "spread_area_m2": round(hull_area_m2(client, vessels), 1),
            "passed": True,
        }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--connection", default="udpin:127.0.0.1:14600", help="where the vessels' GCS links arrive")
    parser.add_argument("--vessels", type=int, required=True, help="how many vessels to wait for")
    parser.add_argument("--far-p0", type=float, default=50.0, help="p0 while spread, m")
    parser.add_argument("--near-p0", type=float, default=5.0, help="p0 while aggregating, m")
    parser.add_argument("--shrink", type=float, default=50.0, help="the hull area must fall by this factor")
    parser.add_argument("--spread", type=float, default=5.0, help="then grow again by this factor")
    parser.add_argument("--settle", type=float, default=5.0, help="wall s at p0 = far before switching")
    parser.add_argument("--timeout", type=float, default=900.0, help="wall s to wait for each phase")
    parser.add_argument("--discover-timeout", type=float, default=60.0, help="wall s to find the vessels")
    args = parser.parse_args(argv)
    try:
        result = run(args)
    except MissionError as error:
        print(f"mission failed: {error}", file=sys.stderr)
        return 1
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
