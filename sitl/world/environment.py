"""Wind and current for the physics fidelity of the simulator.

What: the air and water moving around the buoys. Wind is a mean vector plus
gusts; current is a uniform vector plus an optional gridded field. Both are
looked up at the agents' positions, vectorized over N agents, and handed to
`sitl.vehicles.dynamics.BuoyDynamics.step`.

Why: the paper's buoy experiments ran "in moderate wind", and a buoy that
holds station or aggregates must fight the drift; the estimator estimates that
drift and the MPC treats it as a known disturbance. The simulator therefore
needs a drift that is steady on average but wanders in time (gusts) and may vary
in space (tidal currents around a harbour), with every random draw taken from
one seeded numpy Generator so that a lockstep run is exactly repeatable.

Gust model: a 2-D first-order Gauss-Markov (Ornstein-Uhlenbeck) process,
independent per axis, spatially uniform over the swarm (a swarm of a few hundred
metres sits inside one gust front far more often than not). It is advanced with
the exact discretization of the OU process, so its statistics do not depend on
the step length:
    g <- g * exp(-dt / tau) + sigma * sqrt(1 - exp(-2 dt / tau)) * n,  n ~ N(0, I)
and it starts in its stationary distribution N(0, sigma^2 I).

Frames: x east, y north (m); directions in degrees from east, counter-clockwise;
a `toward_deg` is the direction the air or water moves TOWARDS (not the
meteorological "from" convention).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from sitl.world.waves import WaveSpec

FloatArray = NDArray[np.float64]


def _toward_vector(speed_mps: float, toward_deg: float) -> FloatArray:
    """(2,) velocity (m/s) of the given speed moving towards toward_deg (deg from east, CCW)."""
    angle = math.radians(toward_deg)
    return np.array([speed_mps * math.cos(angle), speed_mps * math.sin(angle)])


def _as_positions(position_m: FloatArray) -> FloatArray:
    """Positions (N, 2) in m as a float array; a single (2,) point becomes (1, 2)."""
    position_m = np.asarray(position_m, dtype=float)
    if position_m.ndim == 1:
        position_m = position_m[None]
    if position_m.ndim != 2 or position_m.shape[1] != 2:
        raise ValueError(f"positions must be (N, 2) in m, got shape {position_m.shape}")
    return position_m


@dataclass(frozen=True)
class WindSpec:
    """Wind over the water.

    speed_mps: mean wind speed, m/s.
    toward_deg: direction the mean wind blows TOWARDS, degrees from east, CCW.
    gust_intensity: dimensionless; the gusts' stationary standard deviation per
        axis is gust_intensity * speed_mps (m/s). Zero: steady wind.
    gust_time_constant_s: correlation time of the gust process, s (the
        autocorrelation at this lag is exp(-1)).
    """

    speed_mps: float = 0.0
    toward_deg: float = 0.0
    gust_intensity: float = 0.0
    gust_time_constant_s: float = 20.0

    def __post_init__(self) -> None:
        if self.speed_mps < 0.0:
            raise ValueError("wind speed_mps must be >= 0 (use toward_deg for the direction)")
        if self.gust_intensity < 0.0:
            raise ValueError("gust_intensity must be >= 0")
        if self.gust_time_constant_s <= 0.0:
            raise ValueError("gust_time_constant_s must be > 0")

    @property
    def mean_mps(self) -> FloatArray:
        """(2,) mean wind velocity, m/s (east, north)."""
        return _toward_vector(self.speed_mps, self.toward_deg)

    @property
    def gust_std_mps(self) -> float:
        """Stationary standard deviation of the gusts per axis, m/s."""
        return self.gust_intensity * self.speed_mps


@dataclass(frozen=True)
class CurrentGrid:
    """A gridded current field, interpolated bilinearly and clamped at the edges.

    Node (i, j) sits at x = x0_m + i * dx_m, y = y0_m + j * dy_m (m). u_mps and
    v_mps are tuples of rows: row j holds the east (u) and north (v) components,
    m/s, at y = y0_m + j * dy_m for every i (so u_mps[j][i]). Outside the grid
    the nearest edge value is used.
    """

    x0_m: float
    y0_m: float
    dx_m: float
    dy_m: float
    u_mps: tuple[tuple[float, ...], ...]
    v_mps: tuple[tuple[float, ...], ...]

    def __post_init__(self) -> None:
        if self.dx_m <= 0.0 or self.dy_m <= 0.0:
            raise ValueError("grid spacings dx_m and dy_m must be > 0")
        u, v = np.asarray(self.u_mps, dtype=float), np.asarray(self.v_mps, dtype=float)
        if u.ndim != 2 or u.size == 0 or u.shape != v.shape:
            raise ValueError(f"u_mps and v_mps must be equal, non-empty tables of rows; got {u.shape} and {v.shape}")

    def sample(self, position_m: FloatArray) -> FloatArray:
        """(N, 2) current (m/s) at positions (N, 2) m, bilinear inside, clamped outside."""
        position_m = _as_positions(position_m)
        table = np.stack((np.asarray(self.u_mps, dtype=float), np.asarray(self.v_mps, dtype=float)), axis=-1)
        ny, nx = table.shape[:2]
        i0, fx = _cell(position_m[:, 0], self.x0_m, self.dx_m, nx)
        j0, fy = _cell(position_m[:, 1], self.y0_m, self.dy_m, ny)
        i1, j1 = np.minimum(i0 + 1, nx - 1), np.minimum(j0 + 1, ny - 1)
        fx, fy = fx[:, None], fy[:, None]
        return (
            table[j0, i0] * (1.0 - fx) * (1.0 - fy)
            + table[j0, i1] * fx * (1.0 - fy)
            + table[j1, i0] * (1.0 - fx) * fy
            + table[j1, i1] * fx * fy
        )


def _cell(coord_m: FloatArray, origin_m: float, spacing_m: float, nodes: int) -> tuple[NDArray[np.int_], FloatArray]:
    """Lower node index and fraction (0..1) along one axis, clamped to the grid."""
    s = np.clip((coord_m - origin_m) / spacing_m, 0.0, nodes - 1)
    i0 = np.minimum(np.floor(s).astype(int), max(nodes - 2, 0))
    return i0, s - i0


@dataclass(frozen=True)
class CurrentSpec:
    """Water current: a uniform part plus an optional gridded field.

    speed_mps: uniform current speed, m/s.
    toward_deg: direction the uniform current flows TOWARDS, degrees from east, CCW.
    grid: optional CurrentGrid added to the uniform part.
    """

    speed_mps: float = 0.0
    toward_deg: float = 0.0
    grid: CurrentGrid | None = None

    def __post_init__(self) -> None:
        if self.speed_mps < 0.0:
            raise ValueError("current speed_mps must be >= 0 (use toward_deg for the direction)")

    @property
    def uniform_mps(self) -> FloatArray:
        """(2,) uniform current velocity, m/s (east, north)."""
        return _toward_vector(self.speed_mps, self.toward_deg)


class Environment:
    """Wind (mean + gust process) and current, sampled at agent positions; the waves that tilt the hulls.

    wind: WindSpec; current: CurrentSpec; rng: numpy Generator, the only
    source of randomness (the gust process starts from its stationary
    distribution, drawn here, and draws two normals per step).
    """

    def __init__(
        self, wind: WindSpec, current: CurrentSpec, rng: np.random.Generator, waves: WaveSpec | None = None
    ) -> None:
        self.wind = wind
        self.current = current
        self.waves = WaveSpec() if waves is None else waves  # swell that tilts the hulls (sitl.world.waves)
        self.rng = rng
        self.time_s = 0.0
        self._mean_wind = wind.mean_mps
        self._uniform_current = current.uniform_mps
        self._gust = wind.gust_std_mps * rng.standard_normal(2)

    @property
    def gust(self) -> FloatArray:
        """(2,) current gust velocity, m/s (east, north), added to the mean wind everywhere."""
        return self._gust.copy()

    def step(self, dt_s: float) -> None:
        """Advance the gust process by dt_s seconds with the exact OU discretization."""
        if dt_s < 0.0:
            raise ValueError("dt_s must be >= 0")
        decay = math.exp(-dt_s / self.wind.gust_time_constant_s)
        noise_std = self.wind.gust_std_mps * math.sqrt(max(0.0, 1.0 - decay * decay))
        self._gust = self._gust * decay + noise_std * self.rng.standard_normal(2)
        self.time_s += dt_s

    def wind_at(self, position_m: FloatArray) -> FloatArray:
        """(N, 2) wind velocity over ground (m/s) at positions (N, 2) m: mean plus the uniform gust."""
        wind = np.empty(_as_positions(position_m).shape)
        wind[...] = self._mean_wind + self._gust
        return wind

    def current_at(self, position_m: FloatArray) -> FloatArray:
        """(N, 2) water current over ground (m/s) at positions (N, 2) m: uniform plus the grid."""
        position_m = _as_positions(position_m)
        flow = np.empty(position_m.shape)
        flow[...] = self._uniform_current
        if self.current.grid is not None:
            flow += self.current.grid.sample(position_m)
        return flow
