"""Simple velocity controllers: from the behaviour's desired velocity to actuator commands.

Buoy: feed-forward of the nominal water drag at the desired velocity plus a
proportional correction on the estimated velocity; the world-frame thrust is
turned into the body frame with the estimated heading and limited to the
thruster's maximum. eBot: turn towards the wished heading (or the direction of
the desired velocity) and drive forward as the heading error allows; both
wheels scaled together to their speed limit. Commands never exceed the limits.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from bob_autonomy.core.arrays import FloatArray, wrap


@dataclass(frozen=True)
class BuoyModel:
    """The vessel's nominal model as the autonomy knows it (not the simulator's truth).

    mass_kg (including added mass), linear_drag_n_per_mps, quadratic_drag_n_per_mps2,
    max_thrust_n: nominal values for a BoB buoy (top speed 1 m/s at full thrust).
    """

    mass_kg: float = 35.0
    linear_drag_n_per_mps: float = 5.0
    quadratic_drag_n_per_mps2: float = 40.0
    max_thrust_n: float = 45.0

    @classmethod
    def for_top_speed(cls, top_speed_mps: float) -> BuoyModel:
        """The nominal model rescaled to reach `top_speed_mps` at full thrust, the split between linear and
        quadratic drag at top speed kept: drag(v) = T (a v / V + b (v / V)^2), a = 5/45, b = 40/45, V the top
        speed. For a vehicle that only says how fast full throttle goes (ArduPilot's SPEED_MAX)."""
        v = float(top_speed_mps)
        if not (math.isfinite(v) and 0.05 <= v <= 50.0):
            raise ValueError(f"top speed must be 0.05..50 m/s, got {top_speed_mps!r}")
        base = cls()
        linear_share = base.linear_drag_n_per_mps / base.max_thrust_n  # at the nominal 1 m/s top speed
        quadratic_share = base.quadratic_drag_n_per_mps2 / base.max_thrust_n
        return cls(
            mass_kg=base.mass_kg,
            linear_drag_n_per_mps=base.max_thrust_n * linear_share / v,
            quadratic_drag_n_per_mps2=base.max_thrust_n * quadratic_share / v**2,
            max_thrust_n=base.max_thrust_n,
        )


def rotate_to_body(vectors: FloatArray, heading_rad: FloatArray) -> FloatArray:
    """World-frame (N, 2) vectors in the body frame (x forward, y left) of headings (N,) rad."""
    c, s = np.cos(heading_rad), np.sin(heading_rad)
    return np.column_stack((c * vectors[:, 0] + s * vectors[:, 1], -s * vectors[:, 0] + c * vectors[:, 1]))


def clip_norm(vectors: FloatArray, limit: FloatArray | float) -> FloatArray:
    """Scale each (N, 2) row down to a norm of at most `limit`."""
    norm = np.hypot(vectors[:, 0], vectors[:, 1])
    return vectors * np.minimum(1.0, np.asarray(limit) / np.maximum(norm, 1e-12))[:, None]


@dataclass
class BuoyVelocityController:
    """Thrust (body frame, N) that drives the estimated velocity to the desired one.

    gain_per_s: proportional gain on the velocity error, as a fraction of mass per second.
    """

    model: BuoyModel = BuoyModel()
    gain_per_s: float = 1.5

    def thrust(
        self, desired_mps: FloatArray, velocity_mps: FloatArray, heading_rad: FloatArray, max_thrust_n: FloatArray
    ) -> FloatArray:
        """Body-frame thrust (N, 2) in N, at most `max_thrust_n` (N,) each."""
        m = self.model
        desired = np.nan_to_num(desired_mps)
        speed = np.hypot(desired[:, 0], desired[:, 1])[:, None]
        feed_forward = (m.linear_drag_n_per_mps + m.quadratic_drag_n_per_mps2 * speed) * desired
        correction = m.mass_kg * self.gain_per_s * (desired - np.nan_to_num(velocity_mps))
        world = clip_norm(feed_forward + correction, max_thrust_n)
        return rotate_to_body(world, np.nan_to_num(heading_rad))


@dataclass
class DiffDriveController:
    """Wheel speeds (left, right) in m/s towards a desired velocity and heading.

    wheel_base_m, max_wheel_speed_mps: the robot's geometry and limit.
    turn_gain_per_s: yaw rate commanded per radian of heading error.
    """

    wheel_base_m: float = 0.1
    max_wheel_speed_mps: float = 0.2
    turn_gain_per_s: float = 4.0

    def wheels(self, desired_mps: FloatArray, desired_heading_rad: FloatArray, heading_rad: FloatArray) -> FloatArray:
        """(N, 2) left and right wheel speeds, m/s, each within +-max_wheel_speed_mps."""
        desired = np.nan_to_num(desired_mps)
        speed = np.hypot(desired[:, 0], desired[:, 1])
        along = np.where(speed > 1e-6, np.arctan2(desired[:, 1], desired[:, 0]), heading_rad)
        target = np.where(np.isnan(desired_heading_rad), along, desired_heading_rad)
        error = wrap(target - heading_rad)
        forward = np.minimum(speed, self.max_wheel_speed_mps) * np.maximum(np.cos(error), 0.0)
        omega = self.turn_gain_per_s * error
        half = 0.5 * self.wheel_base_m
        wheels = np.column_stack((forward - omega * half, forward + omega * half))
        peak = np.abs(wheels).max(axis=1)
        return wheels * np.minimum(1.0, self.max_wheel_speed_mps / np.maximum(peak, 1e-12))[:, None]
