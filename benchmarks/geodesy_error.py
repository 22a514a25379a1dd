"""Error of the local tangent-plane frame (bob_autonomy.core.geodesy) against geographiclib's WGS-84 geodesics.

Points at distances from 10 m to 5 km (log-spaced) in 16 directions from an
origin (default: a Singapore reservoir, lat 1.33, lon 103.92) are placed with
Geodesic.WGS84.Direct; for each, `LocalFrame.to_local` gives (x, y), which is
compared with Geodesic.WGS84.Inverse's distance s12 and initial azimuth azi1
(clockwise from north, converted to our counter-clockwise-from-east bearing).

Position error = |(x, y) - s12 (cos b, sin b)|, b the converted azimuth;
round trip = metres between a point and to_geodetic(to_local(point)). Prints a
summary and one JSON line.

    python benchmarks/geodesy_error.py [--lat 1.33] [--lon 103.92] [--max-distance 5000]
"""

from __future__ import annotations

import argparse
import json
import math

import numpy as np

from bob_autonomy.core.geodesy import WGS84_A_M, WGS84_E2, LocalFrame

try:
    from geographiclib.geodesic import Geodesic
except ImportError as exc:  # pragma: no cover - dev dependency
    raise SystemExit("this benchmark needs geographiclib: pip install -e '.[dev]'") from exc

DIRECTIONS = 16
DISTANCES = 25


def surface_distance_m(lat1: np.ndarray, lon1: np.ndarray, lat2: np.ndarray, lon2: np.ndarray) -> np.ndarray:
    """Small separations (m) from local radii of curvature: good to ~1e-12 m for the round-trip residuals."""
    phi = np.radians(lat1)
    w = 1.0 - WGS84_E2 * np.sin(phi) ** 2
    meridian = WGS84_A_M * (1.0 - WGS84_E2) / w**1.5
    prime = WGS84_A_M / np.sqrt(w)
    dn = np.radians(lat2 - lat1) * meridian
    de = np.radians((lon2 - lon1 + 180.0) % 360.0 - 180.0) * prime * np.cos(phi)
    return np.hypot(dn, de)


def measure(lat0: float, lon0: float, max_distance_m: float) -> dict[str, float]:
    frame = LocalFrame(lat0, lon0)
    geod = Geodesic.WGS84
    distances = np.geomspace(10.0, max_distance_m, DISTANCES)
    azimuths = np.arange(DIRECTIONS) * 360.0 / DIRECTIONS
    lat, lon, s12, azi1 = [], [], [], []
    for d in distances:
        for az in azimuths:
            direct = geod.Direct(lat0, lon0, float(az), float(d))
            inverse = geod.Inverse(lat0, lon0, direct["lat2"], direct["lon2"])
            lat.append(direct["lat2"])
            lon.append(direct["lon2"])
            s12.append(inverse["s12"])
            azi1.append(inverse["azi1"])
    lat, lon, s12, azi1 = map(np.asarray, (lat, lon, s12, azi1))
    x, y = frame.to_local(lat, lon)
    bearing = np.radians(90.0 - azi1)
    position_error = np.hypot(x - s12 * np.cos(bearing), y - s12 * np.sin(bearing))
    distance_error = np.hypot(x, y) - s12
    bearing_error = np.abs(np.mod(np.arctan2(y, x) - bearing + math.pi, 2 * math.pi) - math.pi)
    lat_back, lon_back = frame.to_geodetic(x, y)
    round_trip = surface_distance_m(lat, lon, lat_back, lon_back)
    x_back, y_back = frame.to_local(lat_back, lon_back)
    far = np.isclose(s12, distances[-1])
    sphere_model = distances[-1] ** 3 / (6.0 * WGS84_A_M**2)
    return {
        "origin_lat_deg": lat0,
        "origin_lon_deg": lon0,
        "points": int(lat.size),
        "max_distance_m": float(distances[-1]),
        "max_position_error_m": float(position_error.max()),
        "max_position_error_at_max_distance_m": float(position_error[far].max()),
        "max_distance_error_m": float(np.abs(distance_error).max()),
        "expected_d3_over_6R2_m": float(sphere_model),
        "max_bearing_error_rad": float(bearing_error.max()),
        "max_round_trip_geodetic_m": float(round_trip.max()),
        "max_round_trip_local_m": float(np.hypot(x_back - x, y_back - y).max()),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--lat", type=float, default=1.33)
    parser.add_argument("--lon", type=float, default=103.92)
    parser.add_argument("--max-distance", type=float, default=5000.0)
    args = parser.parse_args()
    result = measure(args.lat, args.lon, args.max_distance)
    print(
        f"origin ({result['origin_lat_deg']}, {result['origin_lon_deg']}), {result['points']} points, "
        f"10 m .. {result['max_distance_m']:.0f} m, {DIRECTIONS} directions"
    )
    print(f"max position error        {result['max_position_error_m']:.3e} m")
    print(
        f"max |distance| error      {result['max_distance_error_m']:.3e} m "
        f"(sphere model d^3/6R^2: {result['expected_d3_over_6R2_m']:.3e} m)"
    )
    print(f"max bearing error         {result['max_bearing_error_rad']:.3e} rad")
    print(f"max round trip (geodetic) {result['max_round_trip_geodetic_m']:.3e} m")
    print(f"max round trip (local)    {result['max_round_trip_local_m']:.3e} m")
    print(json.dumps(result))


if __name__ == "__main__":
    main()
