"""LocalFrame (bob_autonomy/core/geodesy.py): WGS-84 latitude/longitude <-> local x east, y north (m)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from numpy.testing import assert_allclose

from bob_autonomy.core.geodesy import LocalFrame

LAT0, LON0 = 1.33, 103.92  # a Singapore reservoir
A = 6378137.0  # WGS-84 semi-major axis (m)
F = 1.0 / 298.257223563  # WGS-84 flattening
E2 = F * (2.0 - F)


def metres_between(lat1, lon1, lat2, lon2) -> np.ndarray:
    """Separation (m) of two nearby points from the local radii of curvature (for tiny residuals)."""
    phi = np.radians(lat1)
    w = 1.0 - E2 * np.sin(phi) ** 2
    north = np.radians(np.asarray(lat2) - lat1) * A * (1.0 - E2) / w**1.5
    east = np.radians((np.asarray(lon2) - lon1 + 180.0) % 360.0 - 180.0) * A / np.sqrt(w) * np.cos(phi)
    return np.hypot(north, east)


@pytest.fixture
def frame() -> LocalFrame:
    return LocalFrame(LAT0, LON0)


def test_origin_maps_to_zero(frame: LocalFrame) -> None:
    x, y = frame.to_local(LAT0, LON0)
    assert abs(x) < 1e-9 and abs(y) < 1e-9
    lat, lon = frame.to_geodetic(0.0, 0.0)
    assert_allclose([lat, lon], [LAT0, LON0], rtol=0, atol=1e-12)


def test_small_step_north_follows_the_meridian_radius(frame: LocalFrame) -> None:
    dlat_deg = 1e-5
    phi = math.radians(LAT0 + dlat_deg / 2)
    meridian_radius = A * (1 - E2) / (1 - E2 * math.sin(phi) ** 2) ** 1.5  # M = a(1-e^2)/(1-e^2 sin^2 phi)^1.5
    expected = meridian_radius * math.radians(dlat_deg)
    assert expected == pytest.approx(1.106, abs=5e-4)
    x, y = frame.to_local(LAT0 + dlat_deg, LON0)
    assert y == pytest.approx(expected, abs=1e-6)
    assert abs(x) < 1e-6


def test_small_step_east_follows_the_parallel(frame: LocalFrame) -> None:
    dlon_deg = 1e-5
    phi = math.radians(LAT0)
    parallel_radius = A / math.sqrt(1 - E2 * math.sin(phi) ** 2) * math.cos(phi)  # N cos(phi)
    x, y = frame.to_local(LAT0, LON0 + dlon_deg)
    assert x == pytest.approx(parallel_radius * math.radians(dlon_deg), abs=1e-6)
    assert abs(y) < 1e-6


@pytest.mark.parametrize(("lat0", "lon0"), [(LAT0, LON0), (-33.86, 151.21), (60.0, -179.99), (89.5, 0.0)])
def test_five_km_agrees_with_geographiclib(lat0: float, lon0: float) -> None:
    geodesic = pytest.importorskip("geographiclib.geodesic").Geodesic.WGS84
    frame = LocalFrame(lat0, lon0)
    azimuths = np.arange(16) * 22.5
    points = [geodesic.Direct(lat0, lon0, float(az), 5000.0) for az in azimuths]
    lat = np.array([p["lat2"] for p in points])
    lon = np.array([p["lon2"] for p in points])
    x, y = frame.to_local(lat, lon)
    for xi, yi, la, lo in zip(x, y, lat, lon, strict=True):
        inverse = geodesic.Inverse(lat0, lon0, la, lo)
        assert math.hypot(xi, yi) == pytest.approx(inverse["s12"], abs=0.01)
        bearing = math.radians(90.0 - inverse["azi1"])  # clockwise from north -> counter-clockwise from east
        difference = (math.atan2(yi, xi) - bearing + math.pi) % (2 * math.pi) - math.pi
        assert abs(difference) < 1e-5


def test_round_trip_is_below_a_micrometre(frame: LocalFrame) -> None:
    rng = np.random.default_rng(3)
    x = rng.uniform(-5000.0, 5000.0, 500)
    y = rng.uniform(-5000.0, 5000.0, 500)
    lat, lon = frame.to_geodetic(x, y)
    x_back, y_back = frame.to_local(lat, lon)
    assert np.max(np.hypot(x_back - x, y_back - y)) < 1e-6
    lat_back, lon_back = frame.to_geodetic(x_back, y_back)
    assert np.max(metres_between(lat, lon, lat_back, lon_back)) < 1e-6


def test_round_trip_near_pole_and_antimeridian() -> None:
    for lat0, lon0, lat, lon in [(89.99, 10.0, 89.98, -170.0), (0.0, 179.999, 0.01, -179.999)]:
        frame = LocalFrame(lat0, lon0)
        lat_back, lon_back = frame.to_geodetic(*frame.to_local(lat, lon))
        assert metres_between(lat, lon, lat_back, lon_back) < 1e-6
        assert -180.0 <= lon_back < 180.0


def test_vectorized_over_arrays_and_broadcasting(frame: LocalFrame) -> None:
    lat = LAT0 + np.linspace(-0.01, 0.01, 12).reshape(3, 4)
    lon = LON0 + np.linspace(0.02, -0.02, 4)
    x, y = frame.to_local(lat, lon)
    assert x.shape == y.shape == (3, 4)
    for i in range(3):
        for j in range(4):
            xi, yi = frame.to_local(lat[i, j], lon[j])
            assert (x[i, j], y[i, j]) == pytest.approx((xi, yi), abs=1e-9)
    lat_back, lon_back = frame.to_geodetic(x, y)
    assert lat_back.shape == lon_back.shape == (3, 4)
    assert_allclose(lat_back, lat, rtol=0, atol=1e-11)
    assert_allclose(lon_back, np.broadcast_to(lon, (3, 4)), rtol=0, atol=1e-11)
    assert np.ndim(frame.to_local(LAT0, LON0)[0]) == 0
    assert frame.to_local([], [])[0].shape == (0,)


@pytest.mark.parametrize(
    ("call", "name", "value"),
    [
        (lambda f: f.to_local(91.0, LON0), "lat_deg", "91.0"),
        (lambda f: f.to_local(-90.5, LON0), "lat_deg", "-90.5"),
        (lambda f: f.to_local(np.array([1.0, np.nan]), LON0), "lat_deg", "nan"),
        (lambda f: f.to_local(LAT0, math.inf), "lon_deg", "inf"),
        (lambda f: f.to_geodetic(np.array([0.0, -math.inf]), 0.0), "x_east_m", "-inf"),
        (lambda f: f.to_geodetic(0.0, math.nan), "y_north_m", "nan"),
        (lambda f: LocalFrame(math.nan, 0.0), "origin_lat_deg", "nan"),
        (lambda f: LocalFrame(95.0, 0.0), "origin_lat_deg", "95.0"),
        (lambda f: LocalFrame(0.0, math.inf), "origin_lon_deg", "inf"),
    ],
)
def test_bad_input_raises_naming_the_value(frame: LocalFrame, call, name: str, value: str) -> None:
    with pytest.raises(ValueError, match=name) as info:
        call(frame)
    assert value in str(info.value)


def test_poles_are_valid_latitudes(frame: LocalFrame) -> None:
    x, y = frame.to_local(np.array([90.0, -90.0]), LON0)
    assert np.all(np.isfinite(x)) and np.all(np.isfinite(y))


def test_beyond_the_horizon_raises(frame: LocalFrame) -> None:
    with pytest.raises(ValueError, match="horizon"):
        frame.to_geodetic(8.0e6, 0.0)
