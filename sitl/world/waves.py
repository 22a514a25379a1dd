"""Swell that rolls and pitches the hulls (physics fidelity), so that their IMUs and ATTITUDE carry the tilt a
real boat's do and the autonomy's levelling (bob_autonomy.estimation.tilt) is exercised end to end.

The model, as ArduPilot's SITL motorboat has it (libraries/SITL/SIM_Sailboat.cpp `update_wave`), is a travelling
sine wave whose surface slope the hull follows: at position x (m) and time t (s)

    slope(x, t) = A cos(k d.x - w t),     k = 2 pi / length,  w = 2 pi / period,  d the direction of travel,

and a hull heading along the unit vector f (right-hand unit vector r) is pitched nose up by slope (d.f) and rolled
right side down by -slope (d.r). The hulls' translation is not changed (the swell's orbital motion averages out
over a period); only their attitude, and so their sensors, are.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class WaveSpec:
    """tilt_deg: the largest slope of the water, deg (0: flat water, the default; a buoy in a moderate swell
    rolls 5-10 deg). period_s: wave period, s. length_m: wavelength, m. toward_deg: direction the waves travel
    towards, deg from east, counter-clockwise."""

    tilt_deg: float = 0.0
    period_s: float = 5.0
    length_m: float = 40.0
    toward_deg: float = 0.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.tilt_deg) and 0.0 <= self.tilt_deg <= 30.0):
            raise ValueError(f"wave tilt_deg must be within 0-30 deg; got {self.tilt_deg!r}")
        for name in ("period_s", "length_m"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f"wave {name} must be positive; got {value!r}")
        if not math.isfinite(self.toward_deg):
            raise ValueError(f"wave toward_deg must be finite; got {self.toward_deg!r}")

    @property
    def on(self) -> bool:
        return self.tilt_deg > 0.0


def hull_tilt(
    spec: WaveSpec, t_s: float, position_m: FloatArray, heading_rad: FloatArray, yaw_rate_radps: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """(roll (n,) rad right side down, pitch (n,) rad nose up, body rates (n, 3) rad/s about x forward, y right,
    z down) of hulls at positions (n, 2) m with headings (n,) rad (from east, counter-clockwise) turning at
    yaw_rate (n,) rad/s counter-clockwise, at time t_s (module docstring)."""
    amplitude = math.radians(spec.tilt_deg)
    k, w = 2.0 * math.pi / spec.length_m, 2.0 * math.pi / spec.period_s
    toward = math.radians(spec.toward_deg)
    d = np.array([math.cos(toward), math.sin(toward)])
    phase = k * (position_m @ d) - w * t_s
    slope, slope_rate = amplitude * np.cos(phase), amplitude * w * np.sin(phase)
    along = math.cos(toward) * np.cos(heading_rad) + math.sin(toward) * np.sin(heading_rad)  # d.f
    across = math.cos(toward) * np.sin(heading_rad) - math.sin(toward) * np.cos(heading_rad)  # d.r
    pitch, roll = slope * along, -slope * across
    # d/dt of d.f is yaw_rate (d.left) = -yaw_rate (d.r); of d.r, yaw_rate (d.f)
    pitch_rate = slope_rate * along - slope * yaw_rate_radps * across
    roll_rate = -slope_rate * across - slope * yaw_rate_radps * along
    yaw_rate_ned = -yaw_rate_radps
    sr, cr, sp, cp = np.sin(roll), np.cos(roll), np.sin(pitch), np.cos(pitch)
    body = np.column_stack(
        (
            roll_rate - yaw_rate_ned * sp,
            pitch_rate * cr + yaw_rate_ned * cp * sr,
            -pitch_rate * sr + yaw_rate_ned * cp * cr,
        )
    )
    return roll, pitch, body
