"""Goal seeking with the BoB rule (eq. 5, H = 1) run as a mission script over MAVLink.

    bob-sitl fleet aggregation --processes --external-gcs --agents 10 --speed 2 --duration 1400
    python examples/mission_goal_seeking.py --vessels 10 --east 150 --north 100

Discovers the vessels by heartbeat, uploads one goal waypoint (given in metres
east and north of the first vessel's reported position, or as --lat/--lon),
sets H = 1 and p0 fleet-wide, starts the behaviour and waits until every vessel
reports a position within --radius of the goal. Prints the time it took; exits
1 (with the reason) if they do not arrive in time.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

from bob_autonomy.core.geodesy import LocalFrame
from bob_autonomy.ground.mission import MissionClient, MissionError


def run(args: argparse.Namespace) -> dict:
    with MissionClient(args.connection, timeout_s=2.0, retries=5) as client:
        vessels = client.discover(args.vessels, timeout_s=args.discover_timeout)
        client.wait_until(lambda c: vessels[0] in c.positions(), 30.0, f"a position from vessel {vessels[0]}")
        if args.lat is not None and args.lon is not None:
            goal = (args.lat, args.lon)
        else:
            first = client.positions()[vessels[0]]
            lat, lon = LocalFrame(first.lat_deg, first.lon_deg).to_geodetic(args.east, args.north)
            goal = (float(lat), float(lon))
        client.set_params({"BOB_BEHAVIOR": 0, "BOB_H": 1, "BOB_P0_M": args.p0, "BOB_LEADER_ID": 0}, vessels)
        client.upload_goals([goal], vessels)
        client.start(vessels)
        started = time.monotonic()
        client.wait_all_within(goal, args.radius, timeout_s=args.timeout)
        return {"vessels": vessels, "goal": goal, "arrived_wall_s": round(time.monotonic() - started, 1)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--connection", default="udpin:127.0.0.1:14600", help="where the vessels' GCS links arrive")
    parser.add_argument("--vessels", type=int, required=True, help="how many vessels to wait for")
    parser.add_argument("--east", type=float, default=100.0, help="goal, m east of the first vessel")
    parser.add_argument("--north", type=float, default=0.0, help="goal, m north of the first vessel")
    parser.add_argument("--lat", type=float, help="goal latitude, deg (with --lon: instead of --east/--north)")
    parser.add_argument("--lon", type=float, help="goal longitude, deg")
    parser.add_argument("--p0", type=float, default=5.0, help="p0, m")
    parser.add_argument("--radius", type=float, default=20.0, help="arrived within this distance of the goal, m")
    parser.add_argument("--timeout", type=float, default=900.0, help="wall s to wait for the arrival")
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
