"""WGS-84 latitude/longitude <-> the swarm's local frame (x east, y north, metres from a shared origin).

Method
------
Forward (`LocalFrame.to_local`): the point (latitude, longitude, height 0) is
converted exactly to Earth-centred Earth-fixed (ECEF) coordinates on the WGS-84
ellipsoid; the origin's ECEF position is subtracted and the difference is
rotated into the East-North-Up (ENU) axes of the origin. x and y are the east
and north components; the up component (about -d^2 / (2 R): -2 m at 5 km) is
dropped.

Inverse (`LocalFrame.to_geodetic`): the point of the ellipsoid whose east and
north components are (x, y) lies on the line origin + x E + y N + u U; u is the
root nearest zero of the quadratic that puts that line on the ellipsoid
(closed form, no iteration). Its ECEF position is converted to latitude by
Bowring's method (two iterations, well below a micrometre for points near the
surface) and to longitude with atan2. A round trip returns the point to about
1e-9 m.

Assumptions
-----------
- Every point is on the ellipsoid surface (height 0), origin included. Water
  level is close enough to it for a swarm: a point actually 30 m above the
  ellipsoid moves horizontally by only about 30 m * d / R (2 cm at 5 km).
- The tangent plane is not a map projection. (x, y) are the east and north
  components of the straight-line chord from the origin to the point, i.e.
  the point projected along the origin's vertical onto the tangent plane. Its
  length is shorter than the along-surface geodesic distance d by about
  d^3 / (6 R^2): d^3 / (24 R^2) because the chord cuts under the curved
  surface, plus d^3 / (8 R^2) because the chord's vertical component is
  dropped; 0.5 mm at 5 km, 4 mm at 10 km, 0.5 m at 50 km. The bearing atan2(y, x)
  matches the geodesic's initial azimuth to about 1e-8 rad at 5 km. For the
  few kilometres a swarm spans this is far below GPS noise; for areas of
  tens of kilometres or more, use a proper projection.
- Longitude is taken modulo 360 degrees; `to_geodetic` returns it in
  [-180, 180). At the poles longitude is degenerate; the frame still works
  (the origin's east axis is the one for the given origin longitude).

numpy only: usable on a vessel and in the simulator alike.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]

WGS84_A_M = 6378137.0  # semi-major axis
WGS84_F = 1.0 / 298.257223563  # flattening
WGS84_B_M = WGS84_A_M * (1.0 - WGS84_F)  # semi-minor axis
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)  # first eccentricity squared
WGS84_EP2 = WGS84_E2 / (1.0 - WGS84_E2)  # second eccentricity squared

_BOWRING_ITERATIONS = 2


def _checked(value: ArrayLike, name: str, *, latitude: bool = False) -> FloatArray:
    """value as a float array; ValueError naming the first NaN, infinite or (latitude) out-of-range entry."""
    array = np.asarray(value, dtype=float)
    bad = ~np.isfinite(array)
    if latitude:
        with np.errstate(invalid="ignore"):
            bad |= np.abs(array) > 90.0
    if np.any(bad):
        first = float(array[bad].ravel()[0])
        limits = " within [-90, 90]" if latitude else ""
        count = int(np.count_nonzero(bad))
        more = f" ({count} bad values)" if count > 1 else ""
        raise ValueError(f"{name} must be finite{limits}; got {first!r}{more}")
    return array


def geodetic_to_ecef(lat_deg: ArrayLike, lon_deg: ArrayLike, height_m: ArrayLike = 0.0) -> FloatArray:
    """(..., 3) ECEF coordinates (m) of WGS-84 latitude, longitude (deg) and ellipsoidal height (m)."""
    lat = np.radians(np.asarray(lat_deg, dtype=float))
    lon = np.radians(np.asarray(lon_deg, dtype=float))
    h = np.asarray(height_m, dtype=float)
    sin_lat, cos_lat = np.sin(lat), np.cos(lat)
    n = WGS84_A_M / np.sqrt(1.0 - WGS84_E2 * sin_lat**2)  # prime vertical radius of curvature
    return np.stack(
        np.broadcast_arrays(
            (n + h) * cos_lat * np.cos(lon),
            (n + h) * cos_lat * np.sin(lon),
            (n * (1.0 - WGS84_E2) + h) * sin_lat,
        ),
        axis=-1,
    )


def ecef_to_geodetic(ecef_m: ArrayLike) -> tuple[FloatArray, FloatArray, FloatArray]:
    """WGS-84 latitude, longitude (deg, longitude in [-180, 180)) and height (m) of (..., 3) ECEF points.

    Bowring's method: the parametric latitude beta starts at atan2(a Z, b p) and
    the geodetic latitude is refined twice; for points within a few kilometres of
    the surface the error is far below a micrometre. Height from the stable
    formula h = p cos(phi) + Z sin(phi) - a sqrt(1 - e^2 sin^2(phi)).
    """
    ecef = np.asarray(ecef_m, dtype=float)
    x, y, z = ecef[..., 0], ecef[..., 1], ecef[..., 2]
    p = np.hypot(x, y)
    beta = np.arctan2(WGS84_A_M * z, WGS84_B_M * p)
    for _ in range(_BOWRING_ITERATIONS):
        lat = np.arctan2(
            z + WGS84_EP2 * WGS84_B_M * np.sin(beta) ** 3,
            p - WGS84_E2 * WGS84_A_M * np.cos(beta) ** 3,
        )
        beta = np.arctan2((1.0 - WGS84_F) * np.sin(lat), np.cos(lat))
    sin_lat = np.sin(lat)
    height = p * np.cos(lat) + z * sin_lat - WGS84_A_M * np.sqrt(1.0 - WGS84_E2 * sin_lat**2)
    lon_deg = _wrap_lon(np.degrees(np.arctan2(y, x)))
    return np.degrees(lat), lon_deg, height


def _wrap_lon(lon_deg: FloatArray) -> FloatArray:
    return np.mod(lon_deg + 180.0, 360.0) - 180.0


def _scalar_or_array(a: FloatArray) -> FloatArray:
    return a[()] if a.ndim == 0 else a


@dataclass(frozen=True)
class LocalFrame:
    """The swarm's local tangent-plane frame at a WGS-84 origin (degrees); see the module docstring.

    `to_local` and `to_geodetic` broadcast their two arguments against each
    other (scalars give numpy scalars, arrays give arrays of the broadcast shape).
    """

    origin_lat_deg: float
    origin_lon_deg: float

    def __post_init__(self) -> None:
        _checked(self.origin_lat_deg, "origin_lat_deg", latitude=True)
        _checked(self.origin_lon_deg, "origin_lon_deg")

    @cached_property
    def _basis(self) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """Origin ECEF (m) and its unit east, north and up vectors."""
        lat, lon = np.radians(self.origin_lat_deg), np.radians(self.origin_lon_deg)
        sl, cl, so, co = np.sin(lat), np.cos(lat), np.sin(lon), np.cos(lon)
        east = np.array([-so, co, 0.0])
        north = np.array([-sl * co, -sl * so, cl])
        up = np.array([cl * co, cl * so, sl])
        return geodetic_to_ecef(self.origin_lat_deg, self.origin_lon_deg), east, north, up

    def to_local(self, lat_deg: ArrayLike, lon_deg: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """(x east, y north) in metres of surface points given by WGS-84 latitude and longitude (deg)."""
        lat = _checked(lat_deg, "lat_deg", latitude=True)
        lon = _checked(lon_deg, "lon_deg")
        origin, east, north, _ = self._basis
        delta = geodetic_to_ecef(lat, lon) - origin
        return _scalar_or_array(delta @ east), _scalar_or_array(delta @ north)

    def to_geodetic(self, x_east_m: ArrayLike, y_north_m: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """WGS-84 (latitude, longitude) in degrees of the surface points with local coordinates (x, y) in metres.

        Raises ValueError for non-finite input or for (x, y) so far from the
        origin that no point of the ellipsoid's near side projects there.
        """
        x = _checked(x_east_m, "x_east_m")
        y = _checked(y_north_m, "y_north_m")
        x, y = np.broadcast_arrays(x, y)
        origin, east, north, up = self._basis
        # Scale the ellipsoid to the unit sphere: D = diag(1/a^2, 1/a^2, 1/b^2).
        d = np.array([1.0 / WGS84_A_M**2, 1.0 / WGS84_A_M**2, 1.0 / WGS84_B_M**2])
        start = origin + x[..., None] * east + y[..., None] * north  # on the tangent plane
        qa = np.dot(up * d, up)
        qb = start @ (up * d)
        qc = np.einsum("...i,...i->...", start * d, start) - 1.0
        discriminant = qb * qb - qa * qc
        if np.any(discriminant < 0.0):
            worst = float(np.max(np.hypot(x, y)[discriminant < 0.0]))
            raise ValueError(f"(x_east_m, y_north_m) at {worst!r} m from the origin is beyond the ellipsoid's horizon")
        # The root nearest zero (the near side), computed without cancellation.
        q = -(qb + np.copysign(np.sqrt(discriminant), qb))
        with np.errstate(divide="ignore", invalid="ignore"):
            far, near = q / qa, qc / q
        u = np.where(np.abs(near) <= np.abs(far), near, far)  # near is NaN only if q = qc = 0, i.e. far = 0
        lat, lon, _ = ecef_to_geodetic(start + u[..., None] * up)
        return _scalar_or_array(lat), _scalar_or_array(lon)
