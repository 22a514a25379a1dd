"""A simple pose estimator for a batch of vessels, until the EKF takes over.

Buoys: an alpha-beta tracker per axis on GPS fixes (taken at their own
measurement time, so latency is handled) gives position and velocity; the
compass gives heading, smoothed on the circle. eBots: dead reckoning from wheel
encoder ticks, the heading blended towards the compass. The autonomy acts on
these estimates, never on simulator truth.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from bob_autonomy.core.arrays import FloatArray, IntArray, wrap


@dataclass
class PoseEstimate:
    """Estimated position (N, 2) m, velocity (N, 2) m/s and heading (N,) rad at time t_s (N,)."""

    position: FloatArray
    velocity: FloatArray
    heading: FloatArray


class AlphaBetaBuoyEstimator:
    """Alpha-beta tracking of GPS positions and smoothed compass heading, for N buoys.

    alpha, beta: the tracker's position and velocity gains (per fix).
    heading_gain: fraction of the compass innovation taken per reading.
    """

    def __init__(self, n: int, alpha: float = 0.35, beta: float = 0.06, heading_gain: float = 0.5) -> None:
        self.alpha, self.beta, self.heading_gain = alpha, beta, heading_gain
        self.position = np.full((n, 2), np.nan)
        self.velocity = np.zeros((n, 2))
        self.heading = np.full(n, np.nan)
        self.t_fix = np.full(n, np.nan)
        self.rejected = 0

    def update_gps(
        self, agents: IntArray, t_s: FloatArray, xy_m: FloatArray, velocity_mps: FloatArray | None = None
    ) -> None:
        """Fuse position fixes (local frame, m) measured at t_s, and the receiver's ground velocity if given.

        A GPS receiver measures velocity (Doppler) far better than differencing
        positions can: when given, the velocity estimate moves halfway to it
        at each fix and the position residuals no longer feed the velocity.
        """
        good = np.isfinite(xy_m).all(axis=1) & np.isfinite(t_s)
        if velocity_mps is not None:
            good &= np.isfinite(velocity_mps).all(axis=1)
        self.rejected += int(np.count_nonzero(~good))
        agents, t_s, xy_m = agents[good], t_s[good], xy_m[good]
        measured_velocity = velocity_mps[good] if velocity_mps is not None else None
        fresh = np.isnan(self.t_fix[agents])
        late = ~fresh & (t_s <= self.t_fix[agents])
        self.rejected += int(np.count_nonzero(late))
        first = agents[fresh]
        self.position[first] = xy_m[fresh]
        self.t_fix[first] = t_s[fresh]
        use = ~fresh & ~late
        a, t, z = agents[use], t_s[use], xy_m[use]
        dt = (t - self.t_fix[a])[:, None]
        predicted = self.position[a] + self.velocity[a] * dt
        residual = z - predicted
        self.position[a] = predicted + self.alpha * residual
        if measured_velocity is None:
            self.velocity[a] += self.beta * residual / np.maximum(dt, 1e-3)
        else:
            # The receiver's Doppler velocity (~0.1 m/s noise) beats any velocity drawn from position
            # residuals (several m of noise over 0.2 s): use it alone, smoothed.
            self.velocity[a] += 0.5 * (measured_velocity[use] - self.velocity[a])
        self.t_fix[a] = t

    def update_compass(self, agents: IntArray, heading_rad: FloatArray) -> None:
        """Blend compass headings (rad) into the heading estimate."""
        good = np.isfinite(heading_rad)
        self.rejected += int(np.count_nonzero(~good))
        agents, heading_rad = agents[good], heading_rad[good]
        current = self.heading[agents]
        unset = np.isnan(current)
        innovation = wrap(heading_rad - np.where(unset, heading_rad, current))
        self.heading[agents] = wrap(np.where(unset, heading_rad, current + self.heading_gain * innovation))

    def estimate(self, t_s: float) -> PoseEstimate:
        """The pose extrapolated to t_s (s); NaN position until a first fix."""
        dt = np.where(np.isnan(self.t_fix), 0.0, t_s - self.t_fix)[:, None]
        return PoseEstimate(self.position + self.velocity * dt, self.velocity.copy(), self.heading.copy())


class OdometryEstimator:
    """Dead reckoning from wheel encoders for N differential-drive robots, heading tied to the compass.

    wheel_base_m: distance between the wheels. metres_per_tick: wheel travel per encoder tick.
    compass_gain: fraction of the compass innovation taken per reading (0 ignores the compass).
    """

    def __init__(
        self,
        position_m: FloatArray,
        heading_rad: FloatArray,
        wheel_base_m: float,
        metres_per_tick: float,
        compass_gain: float = 0.05,
    ) -> None:
        self.position = np.asarray(position_m, dtype=float).copy()
        self.heading = np.asarray(heading_rad, dtype=float).copy()
        self.velocity = np.zeros_like(self.position)
        self.wheel_base_m, self.metres_per_tick, self.compass_gain = wheel_base_m, metres_per_tick, compass_gain
        self.ticks = np.zeros((self.position.shape[0], 2), dtype=np.int64)
        self.has_ticks = np.zeros(self.position.shape[0], dtype=bool)  # cumulative ticks may be negative
        self.t_ticks = np.full(self.position.shape[0], np.nan)
        self.rejected = 0

    def update_encoders(self, agents: IntArray, t_s: FloatArray, ticks: NDArray[np.int64]) -> None:
        """Integrate the wheel travel since the last cumulative (left, right) tick counts."""
        first = ~self.has_ticks[agents]
        self.ticks[agents[first]] = ticks[first]
        self.t_ticks[agents[first]] = t_s[first]
        self.has_ticks[agents[first]] = True
        a, t, k = agents[~first], t_s[~first], ticks[~first]
        travel = (k - self.ticks[a]) * self.metres_per_tick
        forward = travel.mean(axis=1)
        turn = (travel[:, 1] - travel[:, 0]) / self.wheel_base_m
        middle = self.heading[a] + 0.5 * turn
        step = forward[:, None] * np.column_stack((np.cos(middle), np.sin(middle)))
        self.position[a] += step
        self.heading[a] = wrap(self.heading[a] + turn)
        dt = np.maximum(t - self.t_ticks[a], 1e-6)[:, None]
        self.velocity[a] = step / dt
        self.ticks[a], self.t_ticks[a] = k, t

    def update_compass(self, agents: IntArray, heading_rad: FloatArray) -> None:
        """Pull the dead-reckoned heading towards compass readings (rad)."""
        good = np.isfinite(heading_rad)
        self.rejected += int(np.count_nonzero(~good))
        a = agents[good]
        self.heading[a] = wrap(self.heading[a] + self.compass_gain * wrap(heading_rad[good] - self.heading[a]))

    def estimate(self, t_s: float) -> PoseEstimate:
        return PoseEstimate(self.position.copy(), self.velocity.copy(), self.heading.copy())
