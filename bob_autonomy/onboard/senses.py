"""An eBot's range finders and light sensors, as its behaviour sees them, from decoded telemetry.

The latest DISTANCE_SENSOR of each sonar and the latest light readings are
kept with their reception times; `senses()` turns them into the behaviours'
`Senses`: obstacle offsets in the world-aligned frame (the sonar's bearing on
the body plus the estimated heading), NaN for no echo or a reading older than
`max_age_s`.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import numpy as np

from behaviors.base import Senses
from firmware_bridge.readings import LightReading, RangeReading


class EbotSenses:
    """Latest sonar ranges and light readings of one eBot. sonar_angles_rad: each sonar's bearing from the
    body's forward axis (counter-clockwise), indexed by DISTANCE_SENSOR id. max_age_s: readings older are NaN."""

    def __init__(self, sonar_angles_rad: Sequence[float], max_age_s: float = 1.0) -> None:
        self.angles = np.asarray(sonar_angles_rad, dtype=float)
        self.max_age_s = float(max_age_s)
        self.ranges_m = np.full(self.angles.size, np.nan)
        self.range_t_s = np.full(self.angles.size, -np.inf)
        self.light = np.full(2, np.nan)
        self.light_t_s = np.full(2, -np.inf)
        self.unknown_sensor = 0

    def feed(self, readings: Iterable[object]) -> None:
        """Keep the range and light readings among decoded readings (others are ignored)."""
        for reading in readings:
            if isinstance(reading, RangeReading):
                for sensor, distance, t in zip(reading.sensor, reading.distance_m, reading.t_s, strict=True):
                    if 0 <= sensor < self.angles.size:
                        self.ranges_m[sensor], self.range_t_s[sensor] = distance, t
                    else:
                        self.unknown_sensor += 1
            elif isinstance(reading, LightReading):
                for side, value, t in zip(reading.side, reading.intensity, reading.t_s, strict=True):
                    self.light[side], self.light_t_s[side] = value, t

    def senses(self, heading_rad: float, now_s: float) -> Senses:
        """One row of Senses: (1, sonars, 2) obstacle offsets m (world-aligned), (1, 2) light W/m^2."""
        fresh = now_s - self.range_t_s <= self.max_age_s
        distance = np.where(fresh, self.ranges_m, np.nan)
        axes = (heading_rad if np.isfinite(heading_rad) else np.nan) + self.angles
        offsets = np.stack((np.cos(axes), np.sin(axes)), axis=-1) * distance[:, None]
        light = np.where(now_s - self.light_t_s <= self.max_age_s, self.light, np.nan)
        return Senses(obstacles=offsets[None], light=light[None])
